"""An env for the fault tests: the example arm (`examples/my_robots.py`), whose reward kills the
process stepping it, or that process's parent, at a known env step, once.

The test names what to kill per process in a folder given by the `KILL_PLAN` environment
variable: a file `seed_S` holding `self` (seed S's run) or `parent` (the Ray worker that
started it), or a file `other` for any other process stepping the env (a Ray rollout
worker). At step `KILL_AT_STEP` of that process the reward claims the file (renames it, so
that the retried run is left alone) and sends SIGKILL: a kill at a known step, not a test
racing the run to find a process to kill.
"""

import os
import signal
import sys
from pathlib import Path

import numpy as np

from mat_sdk import envs

ARM = Path(__file__).resolve().parents[1] / "examples" / "robots" / "arm.xml"
LAYOUT = {"shoulder": ["shoulder"], "forearm": ["elbow", "wrist"]}
KILL_AT_STEP = 300  # env steps of one process: past the first updates and their checkpoints
_steps = 0


def _seed() -> str:
    """The seed of the seed-set child this runs in (its last argument: `seed_command`)."""
    return sys.argv[-1] if len(sys.argv) > 1 and sys.argv[-1].isdigit() else "other"


def reward_then_kill(physics) -> float:
    """The example arm's reward, after the kill the plan asks of this step."""
    global _steps
    _steps += 1
    plan = os.environ.get("KILL_PLAN")
    if plan and _steps == KILL_AT_STEP:
        seed = _seed()
        order = Path(plan) / ("other" if seed == "other" else f"seed_{seed}")
        claimed = order.with_suffix(".claimed")
        try:
            order.rename(claimed)
        except FileNotFoundError:
            pass  # nothing asked of this seed, or its first try already did it
        else:
            target = os.getpid() if claimed.read_text() == "self" else os.getppid()
            os.kill(target, signal.SIGKILL)
    tip = physics.named.data.site_xpos["tip"]
    target = physics.named.data.site_xpos["target"]
    return -float(np.linalg.norm(tip[:2] - target[:2]))


def arm() -> envs.RobotSpec:
    return envs.from_mjcf(ARM, LAYOUT, reward_then_kill, episode_limit=50, substeps=2)
