"""Rendering's GL backend, set before any test module imports MuJoCo: the SDK defaults to
EGL when `mat_sdk.envs` is imported first, and a test module may import `mujoco` earlier."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
