"""A robot's observations as one gather: the named signals it reads, the index table that
picks every agent's observation out of them, and the layout a controller rebuilds it from.

By default the signals are MuJoCo's raw `qpos`, `qvel` and the task's features, and the
shared features are the root's height, orientation and velocities; with an `Observation`
(`features.py`) they are what a robot's hardware measures: `joint_pos` (relative to the start
pose), `joint_vel`, the IMU, sensors, contacts, the command and the previous action.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from mat_runtime.wiring_schema import Feature, ObservationLayout
from mat_sdk.envs.mujoco.action_map import ActionMap
from mat_sdk.envs.mujoco.decomposition import (
    actuator_joints,
    joint_dof_indices,
    joint_qpos_indices,
    root_feature_indices,
    root_joints,
)
from mat_sdk.envs.mujoco.features import Signal, robot_signals

if TYPE_CHECKING:
    from mat_sdk.envs.mujoco.sources import RobotSpec


class ObservationMap:
    """Every agent's observation from the concatenated signals and constants (0, 1, the
    agents' positions), less `offset` (the start pose): `observation(source())`."""

    def __init__(
        self,
        spec: RobotSpec,
        physics,
        task,
        members,
        active: list[int],
        agent_names: list[str],
        agent_id: bool,
        positions: np.ndarray,
        actions: ActionMap,
    ):
        self._spec, self._physics, self._task = spec, physics, task
        self._model, self._data = physics.model.ptr, physics.data.ptr
        width = actions.width
        if spec.observation is None:
            signals, joint_pos, joint_vel, shared = self._joint_state_signals()
            kinds = ("qpos", "qvel")
        else:
            signals, joint_pos, joint_vel, shared = self._hardware_signals()
            if spec.observation.last_action:
                signals.append(_last_action_signal(spec.env_id, task, actions, agent_names))
            kinds = ("pos", "vel")
        starts = np.cumsum([0, *(signal.size for signal in signals)])
        at = {signal.name: int(start) for signal, start in zip(signals, starts, strict=False)}
        end = int(starts[-1])
        zero, one = end, end + 1
        constants = [0.0, 1.0]  # then each agent's position features, if any

        def positions_of(joints):
            return [at[joint_pos[0]] + i for j in joints for i in joint_pos[1](j)]

        def velocities_of(joints):
            return [at[joint_vel[0]] + i for j in joints for i in joint_vel[1](j)]

        parts = {
            f"{field}.{kind}": [getter(getattr(member, field)) for member in members]
            for field in ("joints", "upstream", "downstream")
            for kind, getter in zip(kinds, (positions_of, velocities_of), strict=True)
        }
        widths = {name: max(len(entries) for entries in block) for name, block in parts.items()}
        shared_entries = {
            name: [at[signal] + i for i in index] for name, (signal, index) in shared.items()
        }
        widths |= {name: len(entries) for name, entries in shared_entries.items()}
        own = next((s for s in signals if s.per_agent), None)  # each agent's previous action
        widths |= {"last_action": width if own else 0}
        widths |= {"id": len(members) if agent_id else 0}
        widths |= {"position": positions.shape[1]}
        rows = []
        for agent in active:
            row = []
            for name, block in parts.items():
                row += block[agent] + [zero] * (widths[name] - len(block[agent]))
            for entries in shared_entries.values():
                row += entries
            if own:
                row += [at[own.name] + agent * width + k for k in range(width)]
            if agent_id:
                row += [one if i == agent else zero for i in range(len(members))]
            for value in positions[agent]:
                row.append(zero + len(constants))
                constants.append(float(value))
            rows.append(row)
        self.signals = signals
        self.index = np.array(rows, dtype=np.intp)
        self.obs_dim = self.index.shape[1]
        # the name and columns of each feature, in order (every agent's row has the same)
        columns = np.cumsum([0, *widths.values()])
        self.features = tuple(
            Feature(name, int(start), int(start + width))
            for (name, width), start in zip(widths.items(), columns, strict=False)
            if width
        )
        self.constants = np.array(constants)
        self.offset = None
        if spec.observation is not None:  # joint positions relative to the start pose
            self.offset = np.zeros(end + len(constants))
            self.offset[at["joint_pos"] : at["joint_pos"] + len(self._joints)] = (
                self._start_of_joints
            )
        model = self._model
        nq, nv, n_extra = model.nq, model.nv, len(self.task_features())
        root_qpos = {int(i) for j in root_joints(model) for i in joint_qpos_indices(model, j)}
        horizontal = root_qpos - set(root_feature_indices(model)[0].tolist())
        kept_qpos = [i for i in range(nq) if i not in horizontal]
        self._state_index = np.array(
            [*kept_qpos, *range(nq, nq + nv), *range(nq + nv, nq + nv + n_extra)], dtype=np.intp
        )
        self.state_dim = len(self._state_index)

    def task_features(self) -> np.ndarray:
        features = self._spec.task_features
        return np.zeros(0) if features is None else features(self._physics)

    def source(self) -> np.ndarray:
        """The signals and constants now, less the offset: what `observation` gathers from."""
        source = np.concatenate([signal.read() for signal in self.signals] + [self.constants])
        if self.offset is not None:
            source -= self.offset
        return source

    def observation(self, source: np.ndarray) -> np.ndarray:
        return source[self.index].astype(np.float32)

    def state(self) -> np.ndarray:
        """The global state: all joint positions (less horizontal root position) and
        velocities, and the task's features."""
        data = self._data
        source = np.concatenate((data.qpos, data.qvel, self.task_features()))
        return source[self._state_index].astype(np.float32)

    def layout(self) -> ObservationLayout:
        """The layout a controller on the hardware rebuilds the observation from."""
        source, start = {}, 0
        for signal in self.signals:
            source[signal.name] = (start, start + signal.size)
            start += signal.size
        source["constants"] = (start, start + len(self.constants))
        with_offset = self.offset is not None
        return ObservationLayout(
            source=source,
            constants=tuple(self.constants.tolist()),
            index=tuple(tuple(row) for row in self.index.tolist()),
            features=self.features,
            signals={s.name: tuple(s.labels) for s in self.signals} if with_offset else {},
            offset=tuple(self.offset.tolist()) if with_offset else None,
        )

    def _joint_state_signals(self):
        """MuJoCo's raw joint state: signals qpos, qvel and the task's features; the root's
        height, orientation and velocities shared (unless the spec leaves them out)."""
        model, data = self._model, self._data
        extra = len(self.task_features())
        signals = [
            Signal("qpos", model.nq, [], lambda: data.qpos),
            Signal("qvel", model.nv, [], lambda: data.qvel),
            Signal("task", extra, [], self.task_features),
        ]
        root_qpos, root_qvel = root_feature_indices(model)
        shared = {}
        if self._spec.root_features:
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
        (encoders), then the `Observation`'s whole-robot signals."""
        model, data, task = self._model, self._data, self._task
        # encoders: every hinge and slide but a floating base's (a fixed-base arm's first
        # joint hangs from the world too, and is measured like the others when it is driven)
        driven = {j for a in range(model.nu) for j in actuator_joints(model, a)}
        roots = set(root_joints(model)) - driven
        self._joints = [j for j in range(model.njnt) if j not in roots and model.jnt_type[j] >= 2]
        qpos_of = np.array([model.jnt_qposadr[j] for j in self._joints], dtype=np.intp)
        dof_of = np.array([model.jnt_dofadr[j] for j in self._joints], dtype=np.intp)
        start = getattr(task, "start_qpos", model.qpos0)
        self._start_of_joints = start[qpos_of]
        names = [model.joint(j).name for j in self._joints]
        slot = {joint: k for k, joint in enumerate(self._joints)}
        signals = [
            Signal("joint_pos", len(names), names, lambda: data.qpos[qpos_of]),
            Signal("joint_vel", len(names), names, lambda: data.qvel[dof_of]),
        ]
        command = getattr(task, "command", np.zeros(0))
        commands = getattr(getattr(task, "recipe", None), "commands", None)
        robot = robot_signals(
            self._spec.observation, self._physics, lambda: command,
            commands.names if commands else (),
        )  # fmt: skip
        signals += robot
        shared = {signal.name: (signal.name, list(range(signal.size))) for signal in robot}
        joint = ("joint_pos", lambda j: [slot[j]] if j in slot else [])  # no encoder: left out
        velocity = ("joint_vel", lambda j: [slot[j]] if j in slot else [])
        return signals, joint, velocity, shared


def _last_action_signal(env_id: str, task, actions: ActionMap, agents: list[str]) -> Signal:
    """Every agent's previous action, `[team agents x action width]` (a removed agent's and
    padding stay 0): each agent observes its own row."""
    width, rows = actions.width, len(agents)
    last = np.zeros(rows * width)
    source, ctrl = actions.driven_full, actions.ctrl_index

    def read() -> np.ndarray:
        last[source] = task.action[ctrl]
        return last

    if not hasattr(task, "action"):
        raise ValueError(f"{env_id}: last_action needs a task that records actions (from_mjcf's)")
    labels = [f"{agent}.{k}" for agent in agents for k in range(width)]
    return Signal("last_action", rows * width, labels, read, per_agent=True)
