"""Torch-free runtime for exported MAT bundles: numpy + onnxruntime only.

    from mat_runtime import Policy
    policy = Policy.load("cheetah_onnx")
    actions = policy.act(obs)  # obs [n, obs_dim] -> actions [n, action_size]

See `mat_runtime.policy` for the input rules and thread-safety, `mat_runtime.loop` for a
fixed-rate control loop with its tick statistics, and `mat_runtime.controller` for the safe
state machine (damping -> stand -> policy) and guards a robot-side controller runs.
"""

from mat_runtime import loop
from mat_runtime.errors import BundleError, InputError, MatRuntimeError
from mat_runtime.policy import Policy
from mat_runtime.step import StepPolicy

__all__ = ["BundleError", "InputError", "MatRuntimeError", "Policy", "StepPolicy", "loop"]
