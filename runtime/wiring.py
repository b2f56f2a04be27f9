"""A bundle's wiring: how the policy's arrays map onto the robot's sensors and actuators.

    policy = Policy.load("cheetah_onnx")
    print(policy.describe())                                  # agents, actuators, signals
    wiring = policy.wiring                                    # None for bundles without one
    obs = wiring.observe(data.qpos, data.qvel)                # [n, obs_dim], no torch, no env
    obs = wiring.observe(joint_pos=enc, joint_vel=vel, gravity=g, gyro=w, command=cmd, ...)
    index, values = wiring.commands(policy.act(obs))          # data.ctrl[index] = values

The manifest's `wiring` field (written by `mat export` for robots; its layout and checks in
`mat_runtime.wiring_schema`) holds, per agent, the actuators and joints it drives and each
action column's `ctrl = offset + scale * clip(a)`, and the observation as an index table into
the robot's named signals. A robot built from joint state has the signals qpos, qvel and task
(its features); one built from its hardware's signals (`mat_sdk.envs.Observation`) has
joint_pos, joint_vel, gravity, gyro, contacts, command, last_action, ... as `describe()`
lists them. A bundle without `wiring` still loads.
"""

from __future__ import annotations

import numpy as np

from mat_runtime.wiring_schema import ActionColumn, WiringSpec


class Wiring:
    """A checked `wiring` field, ready for a controller: `observe` and `commands`."""

    def __init__(self, spec: WiringSpec):
        self.spec = spec
        self.control_timestep = spec.control_timestep
        self.agents = spec.agents
        self.normalizer = spec.normalizer
        self.action_shape = (len(spec.agents), len(spec.agents[0].action))
        driven = [
            (i, j, column)
            for i, agent in enumerate(spec.agents)
            for j, column in enumerate(agent.action)
            if column.drives
        ]
        self._action_rows = np.array([i for i, _, _ in driven], dtype=np.intp)
        self._action_cols = np.array([j for _, j, _ in driven], dtype=np.intp)
        columns: list[ActionColumn] = [c for _, _, c in driven]
        self.ctrl_index = np.array([c.ctrl for c in columns], dtype=np.intp)
        self._scale = np.array([c.scale for c in columns])
        self._offset = np.array([c.offset for c in columns])
        self._low = np.array([-np.inf if c.low is None else c.low for c in columns])
        self._high = np.array([np.inf if c.high is None else c.high for c in columns])
        # torque motors: the PD gains that turn each column's joint target into torque
        self.gains = [(c.target, c.kp, c.kd) for c in columns if c.kp is not None]
        # per driven column: the joint it targets (None: a raw actuator control), the servo's
        # or PD layer's gains and the joint's range, where the bundle records them
        self.targets: list[str | None] = [c.target for c in columns]
        self.servo: list[tuple[float, float] | None] = [c.gains for c in columns]
        self.ranges: list[tuple[float, float] | None] = [c.range for c in columns]
        self.start_targets = self._offset.copy()  # each column's target at action 0
        self.command_ranges: dict[str, tuple[float, float]] = dict(spec.commands)
        layout = spec.observation
        self.has_observation = layout is not None
        if layout is not None:
            self.features = layout.features
            self.source = layout.source
            self.signals = layout.signals
            self._inputs = layout.inputs
            self._index = np.array(layout.index, dtype=np.intp)
            self._buffer = np.zeros(layout.source["constants"][1])
            self._buffer[layout.source["constants"][0] :] = layout.constants
            offset = layout.offset
            self._source_offset = None if offset is None else np.array(offset, dtype=np.float64)

    def observe(self, *values, **signals) -> np.ndarray:
        """Every agent's observation `[n, obs_dim]` (float32) from the robot's signals, by
        name or in `describe()`'s order: `observe(qpos, qvel, task)` for a robot built from
        its joint state (MuJoCo's qpos and qvel order, the task's features if any), or
        `observe(joint_pos=..., joint_vel=..., gravity=..., ...)` for one built from its
        hardware's signals (joint positions as the encoders read them: the start pose is
        subtracted here). A missing or misshapen signal raises ValueError naming it."""
        if not self.has_observation:
            raise ValueError(
                "this bundle's wiring has no observation layout (its env builds observations "
                "itself, e.g. MaMuJoCo); build them as the env does"
            )
        if len(values) > len(self._inputs):
            raise ValueError(f"observe takes at most {len(self._inputs)} signals: {self._inputs}")
        given = dict(zip(self._inputs, values, strict=False))
        twice = sorted(set(given) & set(signals))
        unknown = sorted(set(signals) - set(self._inputs))
        if twice or unknown:
            raise ValueError(
                f"signal(s) {twice or unknown} given {'twice' if twice else 'but unknown'}; "
                f"this bundle observes {self._inputs}"
            )
        given |= signals
        for name in self._inputs:
            start, stop = self.source[name]
            value = given.get(name)
            if value is None and not (name == "task" and stop == start):
                raise ValueError(f"signal {name} is missing; this bundle observes {self._inputs}")
            value = np.zeros(0) if value is None else _reading(value, name)
            if value.shape != (stop - start,):
                raise ValueError(f"{name} must have {stop - start} values, got shape {value.shape}")
            if not np.isfinite(value).all():
                raise ValueError(f"signal {name} holds NaN or infinite values: {value[:8]}")
            self._buffer[start:stop] = value
        source = self._buffer if self._source_offset is None else self._buffer - self._source_offset
        return source[self._index].astype(np.float32)

    def commands(self, actions) -> tuple[np.ndarray, np.ndarray]:
        """The MuJoCo ctrl indices and the values to write there for `actions` `[n, size]`:
        `ctrl = offset + scale * clip(action, -1, 1)`, clipped to each column's low / high,
        for every column that drives one. For a torque motor the value is the joint's
        target; `gains` gives the (joint, kp, kd) that the robot's PD loop turns into torque."""
        actions = _reading(actions, "actions")
        if actions.shape != self.action_shape:
            raise ValueError(
                f"actions must have shape [agents, width] = {list(self.action_shape)}, got "
                f"{list(actions.shape)}"
            )
        values = actions[self._action_rows, self._action_cols]
        if not np.isfinite(values).all():
            raise ValueError("actions hold NaN or infinite values: no command is sent from them")
        values = np.clip(values, -1.0, 1.0)
        return self.ctrl_index, np.clip(self._offset + self._scale * values, self._low, self._high)

    def describe(self) -> str:
        lines = [f"control timestep {self.control_timestep:g} s; normaliser {self.normalizer}"]
        for agent in self.agents:
            columns = ", ".join(_column(c) for c in agent.action)
            joints = ", ".join(agent.joints) or "none"
            lines.append(f"  {agent.name}: joints {joints}; actions: {columns}")
        if self.has_observation:
            layout = ", ".join(f"{f.name} [{f.start}:{f.stop}]" for f in self.features)
            lines.append(f"observation (every agent): {layout}")
            sources = ", ".join(f"{k} [{a}:{b}]" for k, (a, b) in self.source.items())
            lines.append(f"  gathered from the signals {sources}")
            for name, labels in self.signals.items():
                lines.append(f"  signal {name}: {', '.join(labels)}")
            if self._source_offset is not None:
                lines.append("  joint_pos: the encoders' angles; the start pose is subtracted")
        else:
            lines.append("observation: built by the env itself (no layout in the bundle)")
        return "\n".join(lines)


def _reading(value, name: str) -> np.ndarray:
    """`value` as real float64 numbers, or ValueError naming it (complex, text, objects)."""
    array = np.asarray(value)
    if array.dtype.kind not in "biuf":
        raise ValueError(f"{name} must be real numbers, got an array of {array.dtype}")
    return array.astype(np.float64)


def _column(column: ActionColumn) -> str:
    if not column.drives:
        return "(none)"
    if column.kp is not None:
        return (
            f"{column.actuator}: target {column.target} = {column.offset:g} + "
            f"{column.scale:g} a, torque = {column.kp:g} (target - q) - {column.kd:g} dq"
        )
    text = f"{column.actuator} = {column.offset:g} + {column.scale:g} a"
    if column.low is not None or column.high is not None:
        text += f" in [{column.low}, {column.high}]"
    return text
