"""A robot as a team of agents, stepped with arrays: the fast core under every env API.

`RobotTeam.step` takes actions `[n_agents, action_width]` and returns observations
`[n_agents, obs_dim]`. It steps MuJoCo directly (the way dm_control's `Physics.step` does)
and builds every observation with one gather from a precomputed index table, so the team
costs little more than the physics itself.

Observation of an agent, in order (each block zero-padded to the widest agent's):
own joints' positions | velocities | upstream neighbours' positions | velocities |
downstream positions | velocities | shared features | own previous action (when observed) |
one-hot agent id | position (`base.POSITIONS`, when asked for).

The observation is gathered from named signals. By default they are MuJoCo's raw `qpos`,
`qvel` and the task's features, and the shared features are the root's height, orientation
and velocities; with an `Observation` (`features.py`) they are what a robot's hardware
measures: `joint_pos` (relative to the start pose), `joint_vel`, the IMU, sensors, contacts,
the command and the previous action. `wiring()` describes the signals for a controller.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from mat_runtime.wiring_schema import (
    NO_ACTUATOR,
    ActionColumn,
    AgentWiring,
    Feature,
    ObservationLayout,
    WiringSpec,
)
from mat_sdk.envs.core.base import (
    SETTLE_SECONDS,
    ArrayTeam,
    checked_episode_limit,
    diverged,
    end_diverged,
    position_features,
    render_failed,
)
from mat_sdk.envs.core.faults import Fault, faults_of
from mat_sdk.envs.mujoco.actuation import target_map, weaken
from mat_sdk.envs.mujoco.decomposition import (
    actuator_joints,
    decompose,
    joint_dof_indices,
    joint_qpos_indices,
    root_feature_indices,
    root_joints,
)
from mat_sdk.envs.mujoco.features import Signal, robot_signals
from mat_sdk.envs.mujoco.randomization import Randomization, Randomizer
from mat_sdk.envs.mujoco.trunk import Trunk

if TYPE_CHECKING:
    from mat_sdk.envs.mujoco.sources import RobotSpec

_FULL_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # includes ctrl and the solver's warmstart


def _actuator_name(model, actuator: int) -> str:
    """An actuator's name, or `#index` for an unnamed one."""
    return model.actuator(actuator).name or f"#{actuator}"


class RobotTeam(ArrayTeam):
    """A multi-agent robot with the array API. See `mat_sdk.envs.make` for the options."""

    action_type = "continuous"

    def __init__(
        self,
        spec: RobotSpec,
        faults: Iterable[Fault] | Mapping[str, str] | None = None,
        *,
        seed: int | None = None,
        agent_id: bool | None = None,
        hops: int | None = None,
        episode_limit: int | None = None,
        task: str | None = None,
        position: str | None = None,
        command: list[float] | None = None,
        randomize: bool | Mapping | Randomization | None = None,
    ):
        """Options left as None take the spec's (`RobotSpec.hops`, ...). `position` appends
        an identity that does not depend on the agent count (`base.POSITIONS`); `command`
        holds a robot with velocity commands at (vx, vy, yaw_rate) in every episode;
        `randomize` varies the robot per episode and step (`randomization.py`; false: off)."""
        self.spec = spec
        self.env_id = spec.env_id
        self._env = spec.load(seed, task)
        self.physics = self._env.physics
        self._task = self._env.task
        if command is not None:
            if not hasattr(self._task, "set_command"):
                raise ValueError(f"{spec.env_id} takes no command: it has no velocity commands")
            self._task.set_command(command)
        self._model, self._data = self.physics.model.ptr, self.physics.data.ptr
        self.control_timestep = self._env.control_timestep()
        self.substeps = round(self.control_timestep / self._model.opt.timestep)
        limit = spec.episode_limit if episode_limit is None else episode_limit
        self.episode_limit = checked_episode_limit(limit, self._env._step_limit)
        agent_id = spec.agent_id if agent_id is None else agent_id
        self.agent_id = (not spec.variable_count) if agent_id is None else bool(agent_id)

        self.variable_count = spec.variable_count
        self._positions = position_features(position, len(spec.groups))
        self.team = decompose(self._model, spec.groups, spec.hops if hops is None else hops)
        self.possible_agents = spec.names()
        self.faults = faults_of(faults)
        zeroed, removed, weakened = self._resolve_faults(self.faults)
        weaken(self._model, weakened)
        self.active = [i for i in range(len(self.team)) if i not in removed]
        self.agents = [self.possible_agents[i] for i in self.active]
        self.n_agents = len(self.active)
        self.action_widths = np.array([len(self.team[i].actuators) for i in self.active])
        self.action_width = max(len(a.actuators) for a in self.team)
        self.action_size = self.action_width  # the policy's action size
        self._reward = (
            spec.fast_reward if task is None and spec.fast_reward else self._task.get_reward
        )
        self.reward_terms = tuple(getattr(self._task, "reward_terms", ()))
        self._build_action_map(zeroed)
        self._build_observation_map()
        given = spec.randomize if randomize is None else randomize
        self.randomization = Randomization.parse(given)
        self._randomizer = None
        if self.randomization is not None:
            sources = [(signal.name, signal.size) for signal in self._signals]
            self._randomizer = Randomizer(
                self.randomization, self._model, self._data, self.control_timestep, sources,
                spec.env_id,
            )  # fmt: skip
        self._steps = 0
        try:  # a floating base, whose forward travel `travelled` measures
            self._base = Trunk(self._model)
        except ValueError:
            self._base = None
        self._start = self._base_position()
        self._tracked = np.zeros(4)  # sums of vx, vy, yaw rate and their count (`tracking`)
        self._settle_steps = round(SETTLE_SECONDS / self.control_timestep)

    # ---------------------------------------------------------------- set-up
    def joint_names(self, agent: int) -> list[str]:
        """MuJoCo names of the joints an agent drives."""
        return [self._model.joint(j).name for j in self.team[agent].joints]

    def _resolve_faults(
        self, faults: tuple[Fault, ...]
    ) -> tuple[set[int], set[int], dict[int, float]]:
        """Zeroed actuators, removed agents and weak actuators (with the force each keeps)."""
        zeroed: set[int] = set()
        removed: set[int] = set()
        weakened: dict[int, float] = {}
        for fault in faults:
            agents, actuators = self._fault_target(fault.target)
            if fault.kind == "remove":
                removed.update(agents)
            elif fault.kind == "zero":
                zeroed.update(actuators)
            else:
                weakened.update(dict.fromkeys(actuators, fault.strength))
        if len(removed) == len(self.team):
            raise ValueError("faults remove every agent; at least one must stay")
        for agent in removed:
            zeroed.update(self.team[agent].actuators)
        return zeroed, removed, weakened

    def _fault_target(self, name: str) -> tuple[list[int], list[int]]:
        if name in self.possible_agents:
            agent = self.possible_agents.index(name)
            return [agent], list(self.team[agent].actuators)
        joint = mujoco.mj_name2id(self._model, mujoco.mjtObj.mjOBJ_JOINT, name)
        hits = [
            (i, a)
            for i, member in enumerate(self.team)
            for a in member.actuators
            if joint >= 0 and joint in actuator_joints(self._model, a)
        ]
        if not hits:
            joints = [n for i in range(len(self.team)) for n in self.joint_names(i)]
            raise ValueError(
                f"fault names {name!r}, which is neither an agent nor an actuated joint of "
                f"{self.spec.env_id}; agents: {', '.join(self.possible_agents)}; "
                f"joints: {', '.join(joints)}"
            )
        return sorted({i for i, _ in hits}), [a for _, a in hits]

    def _build_action_map(self, zeroed: set[int]) -> None:
        """Which entries of the `[n, action_width]` action array drive which actuator."""
        driven, full, actuators = [], [], []
        for row, agent in enumerate(self.active):
            for col, actuator in enumerate(self.team[agent].actuators):
                if actuator not in zeroed:
                    driven.append(row * self.action_width + col)
                    full.append(agent * self.action_width + col)
                    actuators.append(actuator)
        self._action_driven = np.array(driven, dtype=np.intp)
        self._action_driven_full = np.array(full, dtype=np.intp)  # in [team agents, width]
        self._ctrl_index = np.array(actuators, dtype=np.intp)
        low, high = self._model.actuator_ctrlrange[self._ctrl_index].T
        self._ctrl_low, self._ctrl_half = low, (high - low) / 2
        self._targets = None  # actions as joint targets around the start pose
        if self.spec.actions is not None:
            start = getattr(self._task, "start_qpos", self._model.qpos0)
            scale = getattr(self._task, "robot_scale", None)  # from_mjcf tasks with terms
            moment = None if scale is None else scale.torque
            self._targets = target_map(
                self._model, self._ctrl_index, start, self.spec.actions, moment
            )
        # every driven actuator's action, as the task's terms and observations see it
        self._record = getattr(self._task, "record_action", None)
        self._end_step = getattr(self._task, "end_step", None)

    def _build_observation_map(self) -> None:
        """One index table that gathers every observation from the concatenated signals and
        constants (0, 1, the agents' positions), less `offset` (the start pose)."""
        model = self._model
        if self.spec.observation is None:
            signals, joint_pos, joint_vel, shared = self._joint_state_signals()
            kinds = ("qpos", "qvel")
        else:
            signals, joint_pos, joint_vel, shared = self._hardware_signals()
            kinds = ("pos", "vel")
        starts = np.cumsum([0, *(signal.size for signal in signals)])
        at = {signal.name: int(start) for signal, start in zip(signals, starts, strict=False)}
        end = int(starts[-1])
        zero, one = end, end + 1
        constants = [0.0, 1.0]  # then each agent's position features, if any

        def positions(joints):
            return [at[joint_pos[0]] + i for j in joints for i in joint_pos[1](j)]

        def velocities(joints):
            return [at[joint_vel[0]] + i for j in joints for i in joint_vel[1](j)]

        parts = {
            f"{field}.{kind}": [getter(getattr(member, field)) for member in self.team]
            for field in ("joints", "upstream", "downstream")
            for kind, getter in zip(kinds, (positions, velocities), strict=True)
        }
        widths = {name: max(len(entries) for entries in block) for name, block in parts.items()}
        shared_entries = {
            name: [at[signal] + i for i in index] for name, (signal, index) in shared.items()
        }
        widths |= {name: len(entries) for name, entries in shared_entries.items()}
        own = next((s for s in signals if s.per_agent), None)  # each agent's previous action
        widths |= {"last_action": self.action_width if own else 0}
        widths |= {"id": len(self.team) if self.agent_id else 0}
        widths |= {"position": self._positions.shape[1]}
        rows = []
        for agent in self.active:
            row = []
            for name, block in parts.items():
                row += block[agent] + [zero] * (widths[name] - len(block[agent]))
            for entries in shared_entries.values():
                row += entries
            if own:
                row += [
                    at[own.name] + agent * self.action_width + k for k in range(self.action_width)
                ]
            if self.agent_id:
                row += [one if i == agent else zero for i in range(len(self.team))]
            for value in self._positions[agent]:
                row.append(zero + len(constants))
                constants.append(float(value))
            rows.append(row)
        self._signals = signals
        self._obs_index = np.array(rows, dtype=np.intp)
        self.obs_dim = self._obs_index.shape[1]
        # the name and columns of each feature, in order (every agent's row has the same)
        columns = np.cumsum([0, *widths.values()])
        self._features = tuple(
            Feature(name, int(start), int(start + width))
            for (name, width), start in zip(widths.items(), columns, strict=False)
            if width
        )
        self._constants = np.array(constants)
        self._offset = None
        if self.spec.observation is not None:  # joint positions relative to the start pose
            self._offset = np.zeros(end + len(constants))
            self._offset[at["joint_pos"] : at["joint_pos"] + len(self._joints)] = (
                self._start_of_joints
            )
        nq, nv, n_extra = model.nq, model.nv, len(self._extra_features())
        root_qpos = {int(i) for j in root_joints(model) for i in joint_qpos_indices(model, j)}
        horizontal = root_qpos - set(root_feature_indices(model)[0].tolist())
        kept_qpos = [i for i in range(nq) if i not in horizontal]
        self._state_index = np.array(
            [*kept_qpos, *range(nq, nq + nv), *range(nq + nv, nq + nv + n_extra)], dtype=np.intp
        )
        self.state_dim = len(self._state_index)

    def _joint_state_signals(self):
        """MuJoCo's raw joint state: signals qpos, qvel and the task's features; the root's
        height, orientation and velocities shared (unless the spec leaves them out)."""
        model, data = self._model, self._data
        extra = len(self._extra_features())
        signals = [
            Signal("qpos", model.nq, [], lambda: data.qpos),
            Signal("qvel", model.nv, [], lambda: data.qvel),
            Signal("task", extra, [], self._extra_features),
        ]
        root_qpos, root_qvel = root_feature_indices(model)
        shared = {}
        if self.spec.root_features:
            shared = {
                "root.qpos": ("qpos", root_qpos.tolist()),
                "root.qvel": ("qvel", root_qvel.tolist()),
            }
        shared["task"] = ("task", list(range(extra)))
        joint_pos = ("qpos", lambda j: [int(i) for i in joint_qpos_indices(model, j)])
        joint_vel = ("qvel", lambda j: [int(i) for i in joint_dof_indices(model, j)])
        return signals, joint_pos, joint_vel, shared

    def _hardware_signals(self):
        """What the robot's hardware measures: every non-root joint's position and velocity
        (encoders), then the `Observation`'s whole-robot signals, then the previous action."""
        model, data = self._model, self._data
        # encoders: every hinge and slide but a floating base's (a fixed-base arm's first
        # joint hangs from the world too, and is measured like the others when it is driven)
        driven = {j for a in range(model.nu) for j in actuator_joints(model, a)}
        roots = set(root_joints(model)) - driven
        self._joints = [j for j in range(model.njnt) if j not in roots and model.jnt_type[j] >= 2]
        qpos_of = np.array([model.jnt_qposadr[j] for j in self._joints], dtype=np.intp)
        dof_of = np.array([model.jnt_dofadr[j] for j in self._joints], dtype=np.intp)
        start = getattr(self._task, "start_qpos", model.qpos0)
        self._start_of_joints = start[qpos_of]
        names = [model.joint(j).name for j in self._joints]
        slot = {joint: k for k, joint in enumerate(self._joints)}
        signals = [
            Signal("joint_pos", len(names), names, lambda: data.qpos[qpos_of]),
            Signal("joint_vel", len(names), names, lambda: data.qvel[dof_of]),
        ]
        command = getattr(self._task, "command", np.zeros(0))
        commands = getattr(getattr(self._task, "recipe", None), "commands", None)
        robot = robot_signals(
            self.spec.observation, self.physics, lambda: command, commands.names if commands else ()
        )
        signals += robot
        shared = {signal.name: (signal.name, list(range(signal.size))) for signal in robot}
        if self.spec.observation.last_action:
            signals.append(self._last_action_signal())
        joint = ("joint_pos", lambda j: [slot[j]] if j in slot else [])  # no encoder: left out
        velocity = ("joint_vel", lambda j: [slot[j]] if j in slot else [])
        return signals, joint, velocity, shared

    def _last_action_signal(self) -> Signal:
        """Every agent's previous action, `[team agents x action width]` (a removed agent's
        and padding stay 0): each agent observes its own row."""
        width, rows = self.action_width, len(self.team)
        last = np.zeros(rows * width)
        source = self._action_driven_full  # driven entries of the [team agents, width] array
        task, actuators = self._task, self._ctrl_index

        def read():
            last[source] = task.action[actuators]
            return last

        if not hasattr(task, "action"):
            raise ValueError(
                f"{self.env_id}: last_action needs a task that records actions (from_mjcf's)"
            )
        labels = [f"{agent}.{k}" for agent in self.possible_agents for k in range(width)]
        return Signal("last_action", rows * width, labels, read, per_agent=True)

    def _extra_features(self) -> np.ndarray:
        features = self.spec.task_features
        return np.zeros(0) if features is None else features(self.physics)

    def task_features(self) -> np.ndarray:
        """The task's features now (e.g. a target's position), the `task` part of the
        observation source in `wiring()`; empty for tasks without them."""
        return np.asarray(self._extra_features(), dtype=np.float64)

    def wiring(self) -> WiringSpec:
        """How the policy's arrays map onto this robot, for a controller on the hardware
        (`mat_runtime.wiring_schema` gives the layout):

        - per agent, the actuators and joints it drives and, per action column, the actuator
          it commands (its name and index in MuJoCo's ctrl) with
          `ctrl = offset + scale * clip(action, -1, 1)`, clipped to [low, high] where given
          (`NO_ACTUATOR`: none). With joint targets the value is the joint's target around
          the start pose; a torque motor's column also gives the PD gains kp, kd that turn
          the target into its torque on the robot;
        - the observation: `obs[i, j] = (source - offset)[index[i][j]]` with `source` the
          concatenation of the named signals and `constants` (0, 1, positions), at the
          ranges in `source`; `signals` names each signal's columns; `offset` (when present)
          holds the start pose under `joint_pos`; the name and columns of each feature;
        - per joint-target column, the joint's range and, for a position servo, its gains
          [kp, kd] (what a robot's motor driver must be given to act as the model did);
        - the velocity commands' trained ranges, for a robot that takes them;
        - the control timestep, and where the observation normaliser is."""
        model = self._model
        drives = dict(zip(self._action_driven.tolist(), range(len(self._ctrl_index)), strict=True))
        agents = []
        for row, agent in enumerate(self.active):
            action = []
            for col in range(self.action_width):
                k = drives.get(row * self.action_width + col)
                action.append(NO_ACTUATOR if k is None else self._action_column(k))
            agents.append(
                AgentWiring(
                    name=self.agents[row],
                    actuators=tuple(_actuator_name(model, a) for a in self.team[agent].actuators),
                    joints=tuple(self.joint_names(agent)),
                    action=tuple(action),
                )
            )
        source, start = {}, 0
        for signal in self._signals:
            source[signal.name] = (start, start + signal.size)
            start += signal.size
        source["constants"] = (start, start + len(self._constants))
        with_offset = self._offset is not None
        observation = ObservationLayout(
            source=source,
            constants=tuple(self._constants.tolist()),
            index=tuple(tuple(row) for row in self._obs_index.tolist()),
            features=self._features,
            signals={s.name: tuple(s.labels) for s in self._signals} if with_offset else {},
            offset=tuple(self._offset.tolist()) if with_offset else None,
        )
        commands = getattr(getattr(self._task, "recipe", None), "commands", None)
        return WiringSpec(
            control_timestep=float(self.control_timestep),
            physics_timestep=float(model.opt.timestep),
            agents=tuple(agents),
            observation=observation,
            # the ranges the policy was trained on, for a controller
            commands={}
            if commands is None
            else {name: tuple(getattr(commands, name)) for name in commands.names},
        )

    def _action_column(self, k: int) -> ActionColumn:
        """The wiring of driven actuator k (`wiring`)."""
        model, ctrl = self._model, int(self._ctrl_index[k])
        named = {"actuator": _actuator_name(model, ctrl), "ctrl": ctrl}
        if self._targets is None:
            half = float(self._ctrl_half[k])
            return ActionColumn(scale=half, offset=float(self._ctrl_low[k]) + half, **named)
        targets = self._targets
        joint = int(model.actuator_trnid[ctrl, 0])
        named |= {"scale": float(targets.scale[k]), "offset": float(targets.offset[k])}
        named["target"] = model.joint(joint).name
        if targets.pd:
            torque = (float(targets.low[k]), float(targets.high[k]))
            return ActionColumn(kp=targets.kp, kd=targets.kd, torque=torque, **named)
        low, high = (
            float(v) if np.isfinite(v) else None for v in (targets.low[k], targets.high[k])
        )
        servo = None
        if model.actuator_biastype[ctrl] == mujoco.mjtBias.mjBIAS_AFFINE:
            # a position servo: the gains the robot's motor driver must be given for it
            servo = (
                float(model.actuator_gainprm[ctrl, 0]),
                float(-model.actuator_biasprm[ctrl, 2]),
            )
        joint_range = None
        if model.jnt_limited[joint]:
            joint_range = (float(model.jnt_range[joint, 0]), float(model.jnt_range[joint, 1]))
        return ActionColumn(low=low, high=high, servo=servo, range=joint_range, **named)

    # ---------------------------------------------------------------- episode
    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start an episode; a seed restarts the task's random stream (initial pose, target)."""
        if seed is not None and hasattr(self._task, "_random"):  # suite tasks' random stream
            self._task._random = np.random.RandomState(seed)
        randomizer, random = self._randomizer, self._task._random
        if randomizer is not None:
            randomizer.new_episode(random)
        with self.physics.reset_context():
            self._task.initialize_episode(self.physics)
            if randomizer is not None:
                randomizer.perturb_start(random)
        self._steps = 0
        self._start = self._base_position()
        self._tracked[:] = 0.0
        return self._sensed()

    def _base_position(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A floating base's horizontal position and heading (unit vector), else None."""
        if self._base is None:
            return None
        heading = self._data.xmat[self._base.body].reshape(3, 3)[:2, 0]
        position = self._data.qpos[self._base.qpos : self._base.qpos + 2].copy()
        return position, heading / max(float(np.linalg.norm(heading)), 1e-9)

    def term_values(self) -> np.ndarray:
        return self._task.term_values if self.reward_terms else np.zeros(0)

    def travelled(self) -> float:
        if self._start is None:
            return math.nan
        position, heading = self._start
        return float((self._data.qpos[self._base.qpos : self._base.qpos + 2] - position) @ heading)

    def tracking(self) -> np.ndarray:
        count = self._tracked[3]
        return self._tracked[:3] / count if count else np.full(3, math.nan)

    def _track(self) -> None:
        """Add this step's velocity in the heading's frame to `tracking`'s sums."""
        base, data = self._base, self._data
        r = data.xmat[base.body].tolist()  # row-major 3 x 3; plain floats: a per-step cost
        vx, vy, _, wx, wy, wz = data.qvel[base.qvel : base.qvel + 6].tolist()
        hx, hy = r[0], r[3]  # the base's x axis, horizontal part
        norm = max(math.hypot(hx, hy), 1e-9)
        tracked = self._tracked
        tracked[0] += (vx * hx + vy * hy) / norm
        tracked[1] += (vy * hx - vx * hy) / norm
        tracked[2] += r[6] * wx + r[7] * wy + r[8] * wz  # the world z of the body's rates
        tracked[3] += 1.0

    def advance(self, actions: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        flat = actions.reshape(-1)[self._action_driven]  # a copy: clipped in place below
        np.minimum(flat, 1.0, out=flat)
        np.maximum(flat, -1.0, out=flat)
        if self._record is not None:
            self._record(self._ctrl_index, flat)
        if self._randomizer is not None:  # a push now; the motors get a late action
            self._randomizer.push(self._task._random)
            flat = self._randomizer.delay(flat)
        time_before = self._data.time
        if self._targets is None:
            self._data.ctrl[self._ctrl_index] = self._ctrl_low + (flat + 1.0) * self._ctrl_half
            self._physics_step()
        elif not self._targets.pd:
            targets = self._targets.targets(flat)
            self._data.ctrl[self._ctrl_index] = np.clip(
                targets, self._targets.low, self._targets.high
            )
            self._physics_step()
        else:  # a PD layer at the physics rate turns the targets into torques
            targets = self._targets.targets(flat)
            for substep in range(self.substeps):
                self._data.ctrl[self._ctrl_index] = self._targets.torques(self._data, targets)
                self._physics_step(1, first=substep == 0, last=substep == self.substeps - 1)
        self._steps += 1
        if self._base is not None and self._steps > self._settle_steps:
            self._track()
        reward = float(self._reward(self.physics))
        if self._end_step is not None:  # e.g. a new velocity command, seen in this obs
            self._end_step()
        obs = self._sensed()
        step, substep = self.control_timestep, self._model.opt.timestep
        if diverged(self._data, time_before, step, substep, reward):
            obs, reward = end_diverged(self.env_id, self._steps, obs)
            return obs, reward, False, True
        terminated = self._task.get_termination(self.physics) is not None
        return obs, reward, terminated, self._steps >= self.episode_limit

    def _physics_step(self, substeps: int | None = None, first=True, last=True) -> None:
        """`substeps` physics steps the way dm_control's legacy step takes them: the first
        finishes the step the last `mj_step1` began, and the last begins the next one, so
        positions and sensors are up to date for the reward."""
        substeps = self.substeps if substeps is None else substeps
        if first:
            mujoco.mj_step2(self._model, self._data)
            substeps -= 1
        if substeps > 0:
            mujoco.mj_step(self._model, self._data, substeps)
        if last:
            mujoco.mj_step1(self._model, self._data)

    def observe(self) -> np.ndarray:
        """The observation of the state now, `[n_agents, obs_dim]` (without sensor noise)."""
        return self._observation(self._source())

    def _source(self) -> np.ndarray:
        source = np.concatenate([signal.read() for signal in self._signals] + [self._constants])
        if self._offset is not None:
            source -= self._offset
        return source

    def _observation(self, source: np.ndarray) -> np.ndarray:
        return source[self._obs_index].astype(np.float32)

    def _sensed(self) -> np.ndarray:
        """The observation as the agents sense it: with this step's noise, when randomized."""
        source = self._source()
        if self._randomizer is not None:
            self._randomizer.noise(source, self._task._random)
        return self._observation(source)

    def get_state(self) -> dict:
        """Everything that decides the rest of the episode, to resume it exactly."""
        physics = np.empty(mujoco.mj_stateSize(self._model, _FULL_STATE))
        mujoco.mj_getState(self._model, self._data, physics, _FULL_STATE)
        return {
            "physics": physics,
            "geom_pos": self._model.geom_pos.copy(),  # tasks place targets here at reset
            "random": self._task._random.get_state(),
            "steps": self._steps,
            **({"task": self._task.get_state()} if hasattr(self._task, "get_state") else {}),
            **({"start": list(self._start)} if self._start is not None else {}),
            **({"randomizer": self._randomizer.get_state()} if self._randomizer else {}),
        }

    def set_state(self, state: dict) -> None:
        mujoco.mj_setState(self._model, self._data, np.asarray(state["physics"]), _FULL_STATE)
        self._model.geom_pos[:] = state["geom_pos"]
        self._task._random.set_state(state["random"])
        self._steps = int(state["steps"])
        if "task" in state:
            self._task.set_state(state["task"])
        if "start" in state:
            self._start = tuple(np.asarray(v, dtype=np.float64) for v in state["start"])
        if self._randomizer is not None:
            self._randomizer.set_state(state["randomizer"])
        mujoco.mj_forward(self._model, self._data)

    def state(self) -> np.ndarray:
        """The global state: all joint positions (less horizontal root position) and velocities."""
        source = np.concatenate((self._data.qpos, self._data.qvel, self._extra_features()))
        return source[self._state_index].astype(np.float32)

    def render(self, height: int = 240, width: int = 320, camera_id: int = 0) -> np.ndarray:
        """An RGB frame `[height, width, 3]`; needs a GL backend (set MUJOCO_GL=egl or osmesa).
        A model without cameras is filmed by a free camera that follows the robot."""
        try:
            if self._model.ncam == 0:
                return self._follow(height, width)
            return self.physics.render(height=height, width=width, camera_id=camera_id)
        except Exception as error:
            raise render_failed(error) from error

    def _follow(self, height: int, width: int) -> np.ndarray:
        """A frame from a camera that tracks the robot's root body from the side and above."""
        renderer = getattr(self, "_renderer", None)
        if renderer is None or (renderer.height, renderer.width) != (height, width):
            renderer = self._renderer = mujoco.Renderer(self._model, height, width)
        camera = mujoco.MjvCamera()
        camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        camera.trackbodyid = self._base.body if self._base is not None else 1
        camera.distance = 1.2 * float(self._model.stat.extent)
        camera.azimuth, camera.elevation = 120.0, -15.0
        renderer.update_scene(self._data, camera)
        return renderer.render()
