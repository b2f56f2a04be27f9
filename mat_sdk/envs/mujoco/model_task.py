"""A bare MJCF model as a dm_control environment (`from_mjcf`): a start pose, a reward, an end.

Episodes start from the model's keyframe (`home` when it has one), or from a pose given by
joint angles (`start`, legged_gym's default_joint_angles) with the base lowered until the
robot touches the floor; a floating base with neither is refused, since qpos0 is rarely a
pose a robot can stand in. A model without a floating base may start from `qpos0`.
Noise respects each joint: a hinge or slide moves by up to `reset_noise` in its own units,
never more than `reset_noise` times half its range, and stays inside the range; a free
joint (a floating base) moves horizontally and turns only when asked (`root_noise`), its
quaternion staying a unit rotation; velocities of hinges and slides get normal noise of the
same scale. The reward is the user's function of the physics, or a list of `terms`; so is
the termination. A `VelocityCommand` is sampled per episode (or every few seconds), from
ranges that widen with the copy's curriculum level when it has one (`curriculum.py`).

Physics copies are compiled without visual assets (`compiler.discardvisual`): textures and
visual meshes cost hundreds of MB per copy on a Menagerie model and no physics reads them.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from dm_control import mujoco as dm_mujoco
from dm_control.rl import control
from dm_control.suite import base

from mat_sdk.envs.core.base import SETTLE_SECONDS, user_call
from mat_sdk.envs.core.checks import saved_array, saved_flag, saved_whole_number, short
from mat_sdk.envs.mujoco import terms
from mat_sdk.envs.mujoco.curriculum import CurriculumProgress
from mat_sdk.envs.mujoco.trunk import Trunk, geom_ids

HOME = "home"  # the keyframe a start defaults to, by Menagerie's convention
FLOOR = "floor"  # the reward's pseudo-term that lifts a negative step to 0 (logs)
_FREE, _BALL = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL)


@dataclass(frozen=True)
class ModelEnvironment:
    """A picklable recipe for a dm_control environment from an MJCF model and a reward."""

    model: str  # a path to the XML file, or the XML itself
    reward: Callable[[Any], float] | tuple[terms.Term, ...]
    terminate: Callable[[Any], bool] | tuple | None = None
    substeps: int = 1
    reset_noise: float = 0.1
    keyframe: str | None = None  # None: HOME when the model has it, else qpos0
    root_noise: tuple[float, float] = (0.0, 0.0)  # a free base's (position m, turn rad)
    commands: terms.VelocityCommand | None = None
    start: tuple[tuple[str, float], ...] | None = None  # joint angles by name
    only_positive_rewards: bool = False  # legged_gym's: a step's reward is at least 0
    visual: bool = False  # keep visual geoms, meshes and textures (rendering)

    def physics(self) -> dm_mujoco.Physics:
        """The compiled model, without visual assets unless `visual`; a path keeps its
        directory for included files and meshes. A process compiles a model once and
        gives each env copy its own copy of the compiled model."""
        # a copy of its own: randomization changes a copy's masses, friction and gains
        model = copy.copy(compiled_model(self.model, self.visual))
        return dm_mujoco.Physics.from_model(dm_mujoco.wrapper.MjModel(model))

    def __call__(self, seed: int | None) -> control.Environment:
        physics = self.physics()
        task = ModelTask(self, physics, np.random.RandomState(seed))
        return control.Environment(physics, task, n_sub_steps=self.substeps)  # no time limit


_COMPILED: dict[tuple[str, bool], mujoco.MjModel] = {}


def compiled_model(source: str, visual: bool) -> mujoco.MjModel:
    """`source` (a path or XML) compiled once per process, without visual assets unless
    `visual`; ValueError with MuJoCo's first line when it cannot be."""
    key = (source, visual)
    if key not in _COMPILED:
        xml = source.lstrip().startswith("<")
        try:
            spec = mujoco.MjSpec.from_string(source) if xml else mujoco.MjSpec.from_file(source)
            spec.compiler.discardvisual = not visual
            _COMPILED[key] = spec.compile()
        except Exception as error:  # MuJoCo's parser and compiler: ValueError, Error, ...
            first = (str(error).strip().splitlines() or [type(error).__name__])[0][:300]
            name = "the model XML" if xml else source
            raise ValueError(f"{name}: MuJoCo cannot load it as an MJCF model ({first})") from None
    return _COMPILED[key]


def start_pose(
    model: mujoco.MjModel, keyframe: str | None, start: Sequence[tuple[str, float]] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(qpos, ctrl) an episode starts from: the `start` joint angles, its base on the floor
    (`settled_pose`); else the keyframe's (by name; HOME by default when the model has one);
    else, for a model without a floating base, qpos0 and zero controls. Refuses a floating
    base with no pose to start from and a pose outside a joint's range."""
    if start is not None:
        if keyframe is not None:
            raise ValueError("give a start pose (start=) or a keyframe (keyframe=), not both")
        qpos = settled_pose(model, start)
        return qpos, _holding_controls(model, qpos)
    name = HOME if keyframe is None else keyframe
    key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, name)
    if key < 0 and keyframe is not None:
        keys = [model.key(i).name for i in range(model.nkey)]
        raise ValueError(
            f"the model has no keyframe named {keyframe!r}; its keyframes: "
            f"{', '.join(keys) or 'none'}"
        )
    if key < 0 and _FREE in model.jnt_type:
        raise ValueError(
            f"the model has a floating base but no {HOME!r} keyframe, so its episodes would "
            "start from qpos0 (straight legs, often in the floor); give a standing pose as "
            "joint angles, start={'FL_thigh_joint': 0.9, ...} (the base height is found by "
            "lowering it onto the floor), or name a keyframe (keyframe=...)"
        )
    if key >= 0:
        qpos, ctrl = model.key_qpos[key].copy(), model.key_ctrl[key].copy()
    else:
        qpos, ctrl = model.qpos0.copy(), np.zeros(model.nu)
    where = f"keyframe {name!r}" if key >= 0 else "qpos0 (the model has no home keyframe)"
    for joint in _ranged_joints(model):
        low, high = model.jnt_range[joint]
        value = qpos[model.jnt_qposadr[joint]]
        if not low - 1e-6 <= value <= high + 1e-6:
            raise ValueError(
                f"the start pose ({where}) puts joint {model.joint(joint).name!r} at {value:g}, "
                f"outside its range [{low:g}, {high:g}]; give a keyframe whose pose is in "
                "range (keyframe=...)"
            )
    return qpos, ctrl


def settled_pose(model: mujoco.MjModel, start: Sequence[tuple[str, float]]) -> np.ndarray:
    """qpos with the `start` joint angles (by joint name; the others at qpos0) and a level
    floating base at the height where the robot's lowest geom just touches the floor (found
    by bisection on MuJoCo's own collision detection, so meshes count exactly)."""
    qpos = model.qpos0.copy()
    for name, angle in start:
        joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if joint < 0 or model.jnt_type[joint] in (_FREE, _BALL):
            raise ValueError(
                f"start names {name!r}, which is not a hinge or slide joint of the model"
            )
        if not (isinstance(angle, int | float) and math.isfinite(angle)):
            raise ValueError(
                f"start angle of joint {name!r} must be a finite number, got {angle!r}"
            )
        qpos[model.jnt_qposadr[joint]] = angle
    free = [j for j in range(model.njnt) if model.jnt_type[j] == _FREE]
    if not free:
        return qpos
    base = model.jnt_qposadr[free[0]]
    qpos[base + 3 : base + 7] = (1.0, 0.0, 0.0, 0.0)
    data = mujoco.MjData(model)

    def touches(height: float) -> bool:
        data.qpos[:] = qpos
        data.qpos[base + 2] = height
        mujoco.mj_kinematics(model, data)
        mujoco.mj_collision(model, data)
        bodies = model.geom_bodyid[data.contact.geom[: data.ncon]]
        return bool(((bodies == 0).any(axis=1) & (bodies != 0).any(axis=1)).any())

    low, high = float(qpos[base + 2]) - 10.0, float(qpos[base + 2]) + 10.0
    if not touches(low) or touches(high):
        raise ValueError("start: cannot find the floor under the robot (does the model have one?)")
    for _ in range(50):
        middle = (low + high) / 2
        low, high = (middle, high) if touches(middle) else (low, middle)
    qpos[base + 2] = high
    return qpos


def _holding_controls(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """Controls that hold `qpos`: a position actuator's target is its joint's angle; others 0."""
    ctrl = np.zeros(model.nu)
    for actuator in range(model.nu):
        joint = int(model.actuator_trnid[actuator, 0])
        position = model.actuator_biastype[actuator] != int(mujoco.mjtBias.mjBIAS_NONE)
        if model.actuator_trntype[actuator] == int(mujoco.mjtTrn.mjTRN_JOINT) and position:
            ctrl[actuator] = qpos[model.jnt_qposadr[joint]]
    return ctrl


def couple_joints(model: mujoco.MjModel, qpos: np.ndarray) -> None:
    """Put every joint that an active joint equality couples to another (a gripper's second
    finger, a linkage) where the coupling has it, inside its range, in place: noise drawn
    per joint would pull coupled joints apart and jam them past their stops."""
    joint_equality = int(mujoco.mjtEq.mjEQ_JOINT)
    for k in range(model.neq):
        if model.eq_type[k] != joint_equality or not model.eq_active0[k]:
            continue
        first, second = int(model.eq_obj1id[k]), int(model.eq_obj2id[k])
        c = model.eq_data[k, :5]
        offset = 0.0
        if second >= 0:
            d = qpos[model.jnt_qposadr[second]] - model.qpos0[model.jnt_qposadr[second]]
            offset = c[1] * d + c[2] * d**2 + c[3] * d**3 + c[4] * d**4
        address = model.jnt_qposadr[first]
        value = model.qpos0[address] + c[0] + offset
        if model.jnt_limited[first]:
            value = np.clip(value, *model.jnt_range[first])
        qpos[address] = value


def _ranged_joints(model: mujoco.MjModel) -> list[int]:
    return [
        j
        for j in range(model.njnt)
        if model.jnt_limited[j] and model.jnt_type[j] not in (_FREE, _BALL)
    ]


class ModelTask(base.Task):
    """The task of a `ModelEnvironment`: start pose and noise, reward, termination, commands;
    it also keeps the actions of this step and the one before, for terms and observations."""

    MEMORY_ENTRIES, MEMORY_SIZE = 64, 4096  # bounds on a saved term memory: far past a robot's

    def __init__(self, recipe: ModelEnvironment, physics, random):
        super().__init__(random=random)
        self.recipe = recipe
        model, self._data = physics.model.ptr, physics.data.ptr
        check_terms(recipe.reward, recipe.terminate, model, recipe.commands)
        self.start_qpos, self.start_ctrl = start_pose(model, recipe.keyframe, recipe.start)
        self._noise_scale = _noise_scales(model, recipe.reset_noise)
        self.command = np.zeros(3 if recipe.commands else 0)
        self.fixed_command: np.ndarray | None = None
        control_timestep = physics.model.opt.timestep * recipe.substeps
        every = recipe.commands.resample_seconds if recipe.commands else None
        # control steps between commands (0: one per episode), and since the last one
        self._command_period = 0 if every is None else max(1, round(every / control_timestep))
        self._command_age = 0
        self.curriculum: CurriculumProgress | None = None  # `CommandCurriculum`'s level
        if recipe.commands is not None and recipe.commands.curriculum is not None:
            self.curriculum = CurriculumProgress(
                recipe.commands.curriculum, Trunk(model), round(SETTLE_SECONDS / control_timestep)
            )
        self._fell = False  # the last step ended the episode (the curriculum's judgement)
        # per actuator, in [-1, 1]: this step's action and the step's before
        self.action, self.previous_action = np.zeros(model.nu), np.zeros(model.nu)
        uses_terms = not callable(recipe.reward) or (
            recipe.terminate is not None and not callable(recipe.terminate)
        )
        self._step = None
        self.robot_scale: terms.RobotScale | None = None  # the units of relative terms
        # this step's reward by term, weighted (and what the floor added: `reward_terms`)
        self.term_values = np.zeros(len(self.reward_terms))
        if uses_terms:
            trunk = Trunk(model)
            self.robot_scale = terms.RobotScale.of(model, self.start_qpos[trunk.qpos + 2])
            self._step = terms.Step(
                physics.data.ptr, model, trunk, self.command, self.action, self.previous_action,
                control_timestep, self.robot_scale, self.start_qpos,
            )  # fmt: skip

    # ---------------------------------------------------------------- episodes
    def initialize_episode(self, physics) -> None:
        model, data = physics.model.ptr, physics.data.ptr
        position = self.random.uniform(-1.0, 1.0, model.nq)
        velocity = self.random.standard_normal(model.nv)
        scale_q, scale_v = self._noise_scale
        qpos = self.start_qpos + scale_q * position
        for joint in _ranged_joints(model):  # noise never leaves a joint's range
            address = model.jnt_qposadr[joint]
            qpos[address] = np.clip(qpos[address], *model.jnt_range[joint])
        couple_joints(model, qpos)
        data.qpos[:] = qpos
        data.qvel[:] = scale_v * velocity
        data.ctrl[:] = self.start_ctrl
        self._turn_free_joints(model, data)
        self.action[:] = 0.0
        self.previous_action[:] = 0.0
        if self._step is not None:
            self._step.memory.clear()
        if self.recipe.commands is not None:
            if self.curriculum is not None and self.fixed_command is None:
                self.curriculum.judge(fell=self._fell)
            command = self._new_command()
            self.command[:] = command if self.fixed_command is None else self.fixed_command
        self._command_age = 0
        self._fell = False
        super().initialize_episode(physics)

    def _turn_free_joints(self, model, data) -> None:
        """A floating base moves horizontally by up to root_noise[0] m and turns by up to
        root_noise[1] rad about a random axis; its quaternion stays a unit rotation."""
        shift, turn = self.recipe.root_noise
        if not (shift or turn):
            return
        for joint in range(model.njnt):
            if model.jnt_type[joint] != _FREE:
                continue
            address = model.jnt_qposadr[joint]
            data.qpos[address : address + 2] += self.random.uniform(-shift, shift, 2)
            axis = self.random.standard_normal(3)
            axis /= np.linalg.norm(axis)
            rotation = np.zeros(4)
            mujoco.mju_axisAngle2Quat(rotation, axis, self.random.uniform(-turn, turn))
            turned = np.zeros(4)
            mujoco.mju_mulQuat(turned, rotation, data.qpos[address + 3 : address + 7])
            mujoco.mju_normalize4(turned)
            data.qpos[address + 3 : address + 7] = turned

    def record_action(self, actuators: np.ndarray, actions: np.ndarray) -> None:
        """This step's actions of the driven `actuators` (clipped to [-1, 1]; the others 0)."""
        self.previous_action[:] = self.action
        self.action[:] = 0.0
        self.action[actuators] = actions

    def end_step(self) -> None:
        """After a step's reward, before its observation: a new command where its period
        has passed (`VelocityCommand.resample_seconds`), so the step is rewarded for the
        command its action followed and the next action sees the new one."""
        if self.fixed_command is not None:
            return
        if self.curriculum is not None:
            self.curriculum.follow(self._data, self.command)
        if self._command_period:
            self._command_age += 1
            if self._command_age >= self._command_period:
                if self.curriculum is not None:
                    self.curriculum.judge(fell=False)
                self.command[:] = self._new_command()
                self._command_age = 0

    def _new_command(self) -> np.ndarray:
        level = None if self.curriculum is None else self.curriculum.level
        return self.recipe.commands.sample(self.random, level)

    def set_command(self, command) -> None:
        """Hold the command at `command` (vx, vy, yaw_rate) in every episode (evaluation)."""
        if self.recipe.commands is None:
            raise ValueError("the command option is for envs with commands (from_mjcf commands=)")
        self.fixed_command = self.recipe.commands.check(command)
        self.command[:] = self.fixed_command

    def get_state(self) -> dict[str, Any]:
        memory = {} if self._step is None else self._step.memory
        state = {
            "command": self.command.copy(),
            "action": self.action.copy(),
            "previous_action": self.previous_action.copy(),
            "command_age": self._command_age,
            "fell": self._fell,
            "memory": {key: value.copy() for key, value in memory.items()},
        }
        if self.curriculum is not None:
            state["curriculum"] = self.curriculum.get_state()
        return state

    def set_state(self, state: dict[str, Any]) -> None:
        """The task's part of a saved episode, every value checked before any is used."""
        command = saved_array(
            state["command"], self.command.shape, "command", terms.VelocityCommand.LIMIT
        )
        actions = [
            saved_array(state[name], self.action.shape, name.replace("_", " "), 1.0)
            for name in ("action", "previous_action")
        ]
        # absent before commands were resampled within an episode
        age = saved_whole_number(state.get("command_age", 0), "command age (steps)")
        memory = self._checked_memory(state["memory"])
        fell = saved_flag(state.get("fell", False), "fall flag")
        if self.curriculum is not None and "curriculum" in state:
            self.curriculum.set_state(state["curriculum"])
        self.command[:] = command
        self.action[:], self.previous_action[:] = actions
        self._command_age = age
        self._fell = fell
        if self._step is not None:
            self._step.memory.clear()
            self._step.memory.update(memory)

    def _checked_memory(self, saved: Any) -> dict[str, np.ndarray]:
        """The terms' memory of the episode (a foot's time in the air, ...): named arrays of
        finite numbers, each the shape the term keeps where this env has kept it already."""
        own = {} if self._step is None else self._step.memory
        if not isinstance(saved, dict) or len(saved) > self.MEMORY_ENTRIES:
            raise ValueError(
                f"a saved term memory must be a mapping of at most {self.MEMORY_ENTRIES} "
                f"arrays, got {short(saved)}"
            )
        memory = {}
        for key, value in saved.items():
            if not isinstance(key, str):
                raise ValueError(f"a saved term memory is keyed by names, got {short(key)}")
            shape = own[key].shape if key in own else np.shape(value)
            if math.prod(shape) > self.MEMORY_SIZE:
                raise ValueError(
                    f"a saved term memory {short(key)} holds {math.prod(shape)} numbers, past "
                    f"the {self.MEMORY_SIZE} a term keeps"
                )
            memory[key] = saved_array(value, shape, f"term memory {short(key)}")
        return memory

    # ---------------------------------------------------------------- dm_control's Task
    def get_observation(self, physics) -> dict:
        return {"qpos": physics.data.qpos.copy(), "qvel": physics.data.qvel.copy()}

    @property
    def reward_terms(self) -> tuple[str, ...]:
        """The names of the reward's terms, as logged (empty for a reward function); with
        `only_positive_rewards`, last comes `floor`: what lifting a negative step to 0 added."""
        reward = self.recipe.reward
        if callable(reward):
            return ()
        names = tuple(term.name for term in reward)
        return (*names, FLOOR) if self.recipe.only_positive_rewards else names

    def get_reward(self, physics) -> float:
        reward = self.recipe.reward
        if callable(reward):
            return float(user_call(reward, "reward function", physics))
        values = self.term_values
        for k, term in enumerate(reward):
            values[k] = term.weight * term.value(self._step)
        total = float(values[: len(reward)].sum())
        if self.recipe.only_positive_rewards:
            values[-1] = max(0.0, -total)
            total = max(total, 0.0)
        return total

    def get_termination(self, physics) -> float | None:
        terminate = self.recipe.terminate
        if terminate is None:
            return None
        if callable(terminate):
            ended = user_call(terminate, "terminate", physics)
        else:
            ended = any(term.ends(self._step) for term in terminate)
        self._fell = bool(ended)
        return 0.0 if ended else None


def _noise_scales(model: mujoco.MjModel, noise: float) -> tuple[np.ndarray, np.ndarray]:
    """Per qpos and per dof: how far `reset_noise` moves each. Hinges and slides: `noise` in
    their units, at most `noise` x half their range; free and ball joints: not at all (their
    noise is `root_noise`)."""
    scale_q, scale_v = np.zeros(model.nq), np.zeros(model.nv)
    for joint in range(model.njnt):
        if model.jnt_type[joint] in (_FREE, _BALL):
            continue
        scale = noise
        if model.jnt_limited[joint]:
            low, high = model.jnt_range[joint]
            scale = noise * min(1.0, (high - low) / 2)
        scale_q[model.jnt_qposadr[joint]] = scale
        scale_v[model.jnt_dofadr[joint]] = scale
    return scale_q, scale_v


def check_terms(reward: Any, terminate: Any, model: mujoco.MjModel, commands: Any = None) -> None:
    """Refuse rewards and terminations that are neither functions nor lists of terms, terms
    that name what the model does not have, and terms that follow a command the task does
    not give, before any episode runs."""
    if not callable(reward):
        if not _terms_of(reward, terms.Term):
            raise ValueError(
                f"reward must be a function of the physics or a list of reward terms "
                f"(mat_sdk.envs.mujoco.terms), got {reward!r}"
            )
        weights = [term.weight for term in reward]
        if not all(isinstance(w, int | float) and math.isfinite(w) for w in weights):
            raise ValueError(f"reward terms' weights must be finite numbers, got {weights}")
    if (
        terminate is not None
        and not callable(terminate)
        and not _terms_of(terminate, terms.TERMINATIONS)
    ):
        raise ValueError(
            "terminate must be a function of the physics, a list of termination terms "
            f"(mat_sdk.envs.mujoco.terms), or None, got {terminate!r}"
        )
    uses_terms = not callable(reward) or (terminate is not None and not callable(terminate))
    if uses_terms:
        Trunk(model)  # terms read the floating base: it must exist
    for term in () if callable(reward) else reward:
        if getattr(term, "needs_commands", False) and commands is None:
            raise ValueError(
                f"reward term {type(term).__name__} follows a velocity command, and the task "
                "gives none: pass commands=envs.terms.VelocityCommand(vx=(low, high), ...)"
            )
    for term in () if terminate is None or callable(terminate) else terminate:
        if isinstance(term, terms.IllegalContact):
            geom_ids(model, term.names, "illegal contact")


def _terms_of(value: Any, kinds) -> bool:
    return (
        isinstance(value, Sequence)
        and not isinstance(value, str)
        and len(value) > 0
        and all(isinstance(term, kinds) for term in value)
    )
