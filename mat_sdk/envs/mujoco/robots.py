"""The registry of multi-agent robots: which suite task, and which actuators each agent commands.

Environment ids are `<robot>-<layout>`. A layout is the decomposition itself (which actuators
form a team member); the joints each agent drives and observes are derived from the model
(`decomposition.py`). `swimmer-N` is a family: any N >= 3 links, N - 1 agents, one per joint.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from dm_control import suite
from dm_control.rl import control
from dm_control.suite import swimmer

from mat_sdk.envs.mujoco.sources import RobotSpec


@dataclass(frozen=True)
class SuiteTask:
    """A dm_control suite task as a picklable env factory: `SuiteTask("cheetah", "run")(seed)`."""

    domain: str
    task: str

    def __call__(self, seed: int | None) -> control.Environment:
        random = np.random.RandomState(seed)
        return suite.load(self.domain, self.task, task_kwargs={"random": random})

    def with_task(self, task: str) -> SuiteTask:
        return SuiteTask(self.domain, task)


@dataclass(frozen=True)
class SwimmerTask:
    """dm_control's swimmer with `links` links, as a picklable env factory."""

    links: int

    def __call__(self, seed: int | None) -> control.Environment:
        return swimmer.swimmer(n_links=self.links, random=np.random.RandomState(seed))


def _suite(env_id: str, domain: str, task: str, groups, **fields) -> RobotSpec:
    return RobotSpec(env_id, SuiteTask(domain, task), groups, **fields)


def _one_each(*names: str) -> tuple[tuple[str, ...], ...]:
    return tuple((name,) for name in names)


def _swimmer_features(physics: swimmer.Physics) -> np.ndarray:
    """Egocentric task features: the target in the head's frame and the head's velocity."""
    head_velocity = physics.data.sensordata[12:18][[0, 1, 5]]
    return np.concatenate([physics.nose_to_target(), head_velocity])


def _cheetah_run_reward(physics: control.Physics) -> float:
    """cheetah-run's `tolerance(speed, bounds=(10, inf), margin=10, sigmoid='linear')`."""
    speed = physics.data.sensordata[0]  # torso_subtreelinvel x
    return min(max(speed / 10.0, 0.0), 1.0)


_CHEETAH = ("bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot")
_WALKER = ("right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle")
_HOPPER = ("waist", "hip", "knee", "ankle")
_LEGS = ("front_left", "front_right", "back_right", "back_left")

_FIXED: dict[str, RobotSpec] = {
    spec.env_id: spec
    for spec in [
        _suite(
            "cheetah-6x1",
            "cheetah",
            "run",
            _one_each(*_CHEETAH),
            fast_reward=_cheetah_run_reward,
            description="one agent per joint",
        ),
        _suite(
            "cheetah-2x3",
            "cheetah",
            "run",
            (_CHEETAH[:3], _CHEETAH[3:]),
            fast_reward=_cheetah_run_reward,
            description="back leg, front leg",
        ),
        _suite(
            "walker-6x1", "walker", "walk", _one_each(*_WALKER), description="one agent per joint"
        ),
        _suite(
            "walker-2x3",
            "walker",
            "walk",
            (_WALKER[:3], _WALKER[3:]),
            description="right leg, left leg",
        ),
        _suite(
            "hopper-4x1", "hopper", "hop", _one_each(*_HOPPER), description="one agent per joint"
        ),
        _suite(
            "hopper-2x2",
            "hopper",
            "hop",
            (_HOPPER[:2], _HOPPER[2:]),
            description="waist+hip, knee+ankle",
        ),
        _suite(
            "quadruped-4x3",
            "quadruped",
            "walk",
            tuple((f"yaw_{leg}", f"lift_{leg}", f"extend_{leg}") for leg in _LEGS),
            description="one agent per leg (lift/extend are tendons over several joints)",
        ),
        _suite(
            "humanoid-limbs",
            "humanoid",
            "walk",
            (
                ("abdomen_y", "abdomen_z", "abdomen_x"),
                tuple(
                    f"right_{j}" for j in ("hip_x", "hip_z", "hip_y", "knee", "ankle_x", "ankle_y")
                ),
                tuple(
                    f"left_{j}" for j in ("hip_x", "hip_z", "hip_y", "knee", "ankle_x", "ankle_y")
                ),
                ("right_shoulder1", "right_shoulder2", "right_elbow"),
                ("left_shoulder1", "left_shoulder2", "left_elbow"),
            ),
            description="abdomen, two legs, two arms (action sizes 3/6/6/3/3, padded to 6)",
        ),
    ]
}

_SWIMMER = re.compile(r"swimmer-(\d+)$")
SWIMMER_EXAMPLES = ("swimmer-3", "swimmer-6", "swimmer-15")
FAMILIES = ("swimmer-N (N >= 3)",)


def swimmer_spec(links: int) -> RobotSpec:
    if links < 3:
        raise ValueError(f"swimmer-N needs N >= 3 links (N - 1 agents), got {links}")
    return RobotSpec(
        f"swimmer-{links}",
        SwimmerTask(links),
        _one_each(*(f"motor_{i}" for i in range(links - 1))),
        variable_count=True,
        root_features=False,
        task_features=_swimmer_features,
        description="N - 1 agents, one per joint, reach the target (any N >= 3)",
    )


def env_ids() -> list[str]:
    """The fixed ids, then examples of the swimmer family."""
    return [*_FIXED, *SWIMMER_EXAMPLES]


def spec_for(env_id: str) -> RobotSpec | None:
    """The built-in robot of that id, or None."""
    if env_id in _FIXED:
        return _FIXED[env_id]
    match = _SWIMMER.match(env_id)
    return swimmer_spec(int(match.group(1))) if match else None
