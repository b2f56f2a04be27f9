"""Rendering's GL backend, set before any test module imports MuJoCo: the SDK defaults to
EGL when `mat_sdk.envs` is imported first, and a test module may import `mujoco` earlier.
And the fixtures several test modules share."""

import os

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(scope="session")
def go2_bundle(tmp_path_factory):
    """A Go2 bundle (`go2:walk`, a few updates, agent counts 1 and 4): its wiring, not its
    gait, is what the tests use."""
    from helpers import TINY

    from mat_export import export
    from mat_sdk.envs import Trusted
    from mat_sdk.training.trainer import Trainer
    from tests.recipes import with_examples

    with_examples()
    root = tmp_path_factory.mktemp("go2")
    with Trainer("go2:walk", **{**TINY, "rollout_length": 20}) as trainer:
        trainer.learn(40, progress_bar=False)
        ckpt = trainer.save(root / "go2.pt")
    export(Trusted(ckpt), root / "onnx", agent_counts=(1, 4))
    return root / "onnx"
