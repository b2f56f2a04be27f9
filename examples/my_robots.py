"""Your own robot as a MAT SDK env: a model file, a reward, and which actuators each agent drives.

    PYTHONPATH=examples mat train my_robots:arm --steps 20000 --out runs/arm

`my_robots:arm` is a `module:function` env id: every tool (`mat train`, `mat eval`,
`mat export`, `examples/controller.py`) imports this module and calls `arm()` to rebuild the
same env. The reward and termination are module-level functions, so env worker processes
can rebuild it too. docs/CUSTOM_ENVS.md walks through it.
"""

from pathlib import Path

import numpy as np

from mat_sdk import envs

MODEL = Path(__file__).parent / "robots" / "arm.xml"
LAYOUT = {"shoulder": ["shoulder"], "forearm": ["elbow", "wrist"]}


def reach_reward(physics) -> float:
    """Closer is better: minus the fingertip's distance to the target, in metres."""
    tip = physics.named.data.site_xpos["tip"]
    target = physics.named.data.site_xpos["target"]
    return -float(np.linalg.norm(tip[:2] - target[:2]))


def arm() -> envs.RobotSpec:
    """Two agents: the shoulder (one action) and the forearm (elbow and wrist, two)."""
    return envs.from_mjcf(MODEL, LAYOUT, reach_reward, episode_limit=50, substeps=2)
