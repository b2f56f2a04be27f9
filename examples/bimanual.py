"""Two arms, two agents: PR2 arms (Gymnasium's Pusher arm, twice) each reaching a target.

    PYTHONPATH=examples mat train bimanual:reach --steps 1000000 --out runs/bimanual

Each arm is an agent that drives its seven joints through a PD layer on the arm's torque
motors (joint targets around the start pose). Every episode places a target in front of each
arm; an agent observes its own joints (encoders) and where both hands and both targets are
(world positions: the arms' kinematics give the hands, a camera the targets). The reward
is minus the two hands' distances to their targets, in metres, plus a bonus that grows
steeply in the last few centimetres (`PRECISION`); a reach succeeds when the hand ends the
episode within 2 cm of its target (`SUCCESS`).

`robots/pr2_arms/` holds the model, built from Gymnasium's MIT-licensed pusher_v5.xml (its
license beside it).
"""

from pathlib import Path

import numpy as np
from dm_control import mujoco
from dm_control.rl import control
from dm_control.suite import base

from mat_sdk import envs

MODEL = Path(__file__).parent / "robots" / "pr2_arms" / "pr2_arms.xml"
JOINTS = ("shoulder_pan", "shoulder_lift", "upper_arm_roll", "elbow_flex", "forearm_roll",
          "wrist_flex", "wrist_roll")  # fmt: skip
ARMS = {"left": 0.6, "right": -0.6}  # each arm's shoulder, y in metres
LAYOUT = {arm: [f"{arm}_{joint}" for joint in JOINTS] for arm in ARMS}
SENSORS = ("left_hand", "left_target", "right_hand", "right_target")  # MJCF framepos
HOME = {"shoulder_lift": 0.3, "elbow_flex": -1.3, "wrist_flex": -0.5}  # rad; hand at x 0.66, z 0.25
TARGETS = {"x": (0.5, 0.8), "y": (-0.2, 0.2), "z": (0.1, 0.4)}  # m; y around each shoulder
SUCCESS = 0.02  # m
PRECISION = (0.2, 0.02)  # weight, m: + weight * (1 - tanh(distance / m)) per hand
START_NOISE = 0.1  # rad on each joint at the start, inside its range
SUBSTEPS = 5  # 10 ms physics steps: 20 Hz control


class Reach(base.Task):
    """Episodes start from HOME (elbows bent, hands in front of the shoulders) with noise;
    targets placed per episode in front of each arm; reward: minus the hands' distances."""

    def __init__(self, model, random=None):
        super().__init__(random=random)
        names = [model.joint(j).name for j in range(model.njnt)]
        # the pose joint targets are around (`RobotTeam` reads `start_qpos`)
        self.start_qpos = np.array(
            [HOME.get(name.split("_", 1)[1].removesuffix("_joint"), 0.0) for name in names]
        )

    def initialize_episode(self, physics) -> None:
        model, data = physics.model.ptr, physics.data.ptr
        noise = self.random.uniform(-START_NOISE, START_NOISE, model.nq)
        start = self.start_qpos + noise
        data.qpos[:] = np.clip(start, model.jnt_range[:, 0], model.jnt_range[:, 1])
        data.qvel[:] = 0.0
        for arm, shoulder in ARMS.items():
            x, y, z = (self.random.uniform(*TARGETS[axis]) for axis in "xyz")
            physics.named.model.geom_pos[f"{arm}_target"] = (x, shoulder + y, z)
        super().initialize_episode(physics)

    def get_observation(self, physics) -> dict:
        return {"distances": distances(physics)}

    def get_reward(self, physics) -> float:
        """Minus the distances (m), with a bonus within a few cm: -d alone pulls as hard at
        5 cm as at 50, and policies trained on it stopped 4-8 cm short."""
        gap = distances(physics)
        weight, scale = PRECISION
        return float(np.sum(-gap + weight * (1.0 - np.tanh(gap / scale))))


def distances(physics) -> np.ndarray:
    """Each hand's distance to its target (m), left then right."""
    sensed = physics.named.data.sensordata
    return np.array(
        [np.linalg.norm(sensed[f"{arm}_target"] - sensed[f"{arm}_hand"]) for arm in ARMS]
    )


def environment(seed: int | None) -> control.Environment:
    physics = mujoco.Physics.from_xml_path(str(MODEL))
    task = Reach(physics.model.ptr, random=seed)
    return control.Environment(physics, task, n_sub_steps=SUBSTEPS)


def reach() -> envs.RobotSpec:
    """Two seven-joint arms reaching targets, 100 steps (5 s) per episode."""
    return envs.from_dm_control(
        environment,
        LAYOUT,
        observation=envs.Observation(sensors=SENSORS, last_action=False),
        actions=envs.JointTargets(scale=1.0, kp=10.0, kd=1.0),
        episode_limit=100,
        env_id="bimanual:reach",
        description="two PR2 arms, one agent each, reaching a target per arm",
    )
