"""One task definition for any legged robot: terms, weights, command, termination,
randomization and training recipe written once, and a robot described by its names alone.

    go2 = LeggedRobot("go2/scene_mjx.xml", layout={"FL": ["FL_hip", ...], ...},
                      feet=("FL", "FR", "RL", "RR"), imu="imu", trunk=("base",))
    spec = WALK.spec(go2)                 # what from_mjcf returns: train, evaluate, export it

A task transfers across robots because every term is measured in the robot's own units
(`terms.RobotScale`: weight, standing height), the payload is a share of the robot's mass,
and a step's reward is never below 0 (`only_positive_rewards`: ending an episode early never
pays, whatever the penalties cost a heavy robot). Terms that name robot parts are written
without names (`FeetRhythm()`, `FeetAirTime()`, `FeetSlip()`, `IllegalContact()`) and take
the robot's `feet` and `trunk`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from mat_sdk.envs.core.recipe import TrainingRecipe
from mat_sdk.envs.mujoco import terms
from mat_sdk.envs.mujoco.actuation import JointTargets
from mat_sdk.envs.mujoco.features import Observation
from mat_sdk.envs.mujoco.model_task import compiled_model
from mat_sdk.envs.mujoco.sources import RobotSpec, from_mjcf


@dataclass(frozen=True)
class LeggedRobot:
    """What one legged robot brings to a task: its model and the names of its parts.

    - `layout`: agent name -> the actuator names it drives (a leg each, say);
    - `feet`: the geoms (or bodies, when the foot geoms are unnamed) that touch the floor;
    - `imu`: the site or body the IMU sits at (gravity and angular velocity in its frame);
    - `trunk`: geoms or bodies whose contact with anything ends the episode;
    - `start`: joint angles of a standing pose by joint name (the base height is found by
      lowering the robot onto the floor); None: the model's `home` keyframe (or `keyframe`)."""

    model: str | os.PathLike
    layout: Mapping[str, Sequence[str]]
    feet: tuple[str, ...]
    imu: str
    trunk: tuple[str, ...]
    start: Mapping[str, float] | None = None
    keyframe: str | None = None


@dataclass(frozen=True)
class LeggedTask:
    """A locomotion task for any `LeggedRobot` (the module docstring)."""

    reward: tuple[terms.Term, ...]
    terminate: tuple
    commands: terms.VelocityCommand
    recipe: TrainingRecipe
    randomize: bool | Mapping[str, Any] | None = True
    control_hz: float = 50.0
    episode_seconds: float = 20.0
    # joint target per unit of action, as the torque its stiffness turns it into, in units
    # of m g h: 0.62 is the Go2's 0.5 rad at kp 50; a stiffer or lighter robot moves less
    action_torque: float = 0.62
    root_noise: tuple[float, float] = (0.0, 0.05)
    only_positive_rewards: bool = True
    observation: Observation = field(
        default_factory=lambda: Observation(imu="imu", contacts=(), last_action=True)
    )

    def spec(self, robot: LeggedRobot, env_id: str | None = None) -> RobotSpec:
        """The task on `robot`, as `from_mjcf` builds it."""
        model = os.fspath(robot.model)
        if not model.lstrip().startswith("<"):
            model = str(Path(model).resolve())
        timestep = float(compiled_model(model, visual=False).opt.timestep)
        control_timestep = 1.0 / self.control_hz
        return from_mjcf(
            model,
            {name: list(actuators) for name, actuators in robot.layout.items()},
            [_named_parts(term, robot) for term in self.reward],
            terminate=[_named_parts(term, robot) for term in self.terminate],
            commands=self.commands,
            observation=replace(self.observation, imu=robot.imu, contacts=tuple(robot.feet)),
            actions=JointTargets(torque=self.action_torque),
            substeps=max(1, round(control_timestep / timestep)),
            episode_limit=round(self.episode_seconds * self.control_hz),
            root_noise=self.root_noise,
            start=robot.start,
            keyframe=robot.keyframe,
            randomize=self.randomize,
            only_positive_rewards=self.only_positive_rewards,
            recipe=self.recipe,
            env_id=env_id,
        )


def _named_parts(term: Any, robot: LeggedRobot) -> Any:
    """A term written without part names, given the robot's: feet for the feet's terms, the
    trunk for illegal contacts."""
    if isinstance(term, terms.FeetAirTime | terms.FeetRhythm | terms.FeetSlip) and not term.feet:
        return replace(term, feet=tuple(robot.feet))
    if isinstance(term, terms.IllegalContact) and not term.names:
        return replace(term, names=tuple(robot.trunk))
    return term


# Walking at a commanded velocity: the Go2's measured task (docs/REAL_ROBOTS.md), its
# penalties in robot-relative units so that robots of 12-50 kg learn it with the same weights.
WALK = LeggedTask(
    reward=(
        terms.TrackVelocity(1.0),  # follow the commanded vx, vy
        terms.TrackYawRate(0.5),  # and yaw rate
        terms.Alive(0.25),  # staying up pays
        terms.Upright(1.0),
        terms.VerticalVelocity(2.5),  # no bouncing (in units of sqrt(g h))
        terms.RollPitchRate(0.05),
        terms.ActionRate(0.01),  # smooth targets
        terms.Torque(0.3),  # effort, in units of m g h
        terms.JointLimits(1.0),  # off the mechanical stops
        # strides in the robot's own rhythm, not shuffles: each foot's phase paid up to
        # 1.3 sqrt(h/g) (FeetAirTime's fixed 0.5 s let Spot and the A1 slide their feet)
        terms.FeetRhythm(1.0),
    ),
    terminate=(terms.Tilt(60.0), terms.IllegalContact()),
    commands=terms.VelocityCommand(vx=(0.3, 1.0)),  # forward at 0.3-1 m/s
    recipe=TrainingRecipe(
        num_envs=32,
        rollout_length=100,
        lr=3e-4,  # where the rate starts: it follows a KL of 0.01 per leg
        desired_kl=0.01,
        ppo_epochs=5,
        num_minibatches=4,
        clip=0.2,
        entropy_coef=0.0,
        max_grad_norm=1.0,
        # 5 s training episodes (evaluations keep the task's 20 s): a policy that walks
        # still fell in the first second of 5-20 % of its episodes, a start it had met in
        # about one step in a thousand of its training. No push (every 5-10 s) lands in
        # them: pushed in training too, the policies took the evaluations' pushes no better
        train_episode_limit=250,
        # the machine's fastest rollout and update settings (both cores, where there are
        # two); returns under random commands select no better policy than the last, so no
        # evaluations during the run: `mat eval` the checkpoint at its command
        tune=True,
        eval_every=0,
    ),
)

# Following a joystick: any velocity in the ranges of Unitree's deployed Go2 policy (vx
# -0.5..1 m/s, vy +-0.5 m/s, yaw rate +-1 rad/s), a tenth of the commands zero (the stick at
# rest: the robot stands, its joints at the start pose), a new command every 5 s within an
# episode. WALK's terms otherwise, but tracking pays only what it gains over standing still
# (under these commands, most of them small, the plain kernels pay a standing robot about
# half of what tracking earns, and policies learnt to stand), and staying up pays what
# standing earned before (Alive 0.75: else a fall costs little, and policies that tried to
# move fell in half the episodes); docs/REAL_ROBOTS.md has the runs.
JOYSTICK = replace(
    WALK,
    reward=(
        terms.TrackVelocity(1.0, over_standing=True),
        terms.TrackYawRate(0.5, over_standing=True),
        terms.Alive(0.75),
        *WALK.reward[3:],
        terms.StandStill(0.5),
    ),
    commands=terms.VelocityCommand(
        vx=(-0.5, 1.0),
        vy=(-0.5, 0.5),
        yaw_rate=(-1.0, 1.0),
        standing=0.1,
        resample_seconds=5.0,
        # from WALK's forward band, each env copy widening towards the whole ranges as it
        # follows its commands: a gait first, then every direction as a small step from it
        curriculum=terms.CommandCurriculum(vx=WALK.commands.vx, levels=10),
    ),
    recipe=replace(WALK.recipe, train_episode_limit=None),  # 20 s: commands change within
)
