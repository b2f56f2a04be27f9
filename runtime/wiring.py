"""A bundle's wiring: how the policy's arrays map onto the robot's sensors and actuators.

    policy = Policy.load("cheetah_onnx")
    print(policy.describe())                                  # agents, actuators, signals
    wiring = policy.wiring                                    # None for bundles without one
    obs = wiring.observe(data.qpos, data.qvel)                # [n, obs_dim], no torch, no env
    obs = wiring.observe(joint_pos=enc, joint_vel=vel, gravity=g, gyro=w, command=cmd, ...)
    index, values = wiring.commands(policy.act(obs))          # data.ctrl[index] = values

The manifest's `wiring` field (written by `mat export` for robots) holds, per agent, the
actuators and joints it drives and each action column's `ctrl = offset + scale * clip(a)`
(clipped to the column's low / high; for a torque motor, the joint target and the PD gains
that turn it into torque); the observation as an index table into the concatenated named
signals and constants, less an offset (the start pose of the joint positions), with the
name and columns of each feature; the control timestep; and where the observation
normaliser is (inside the graphs, which take raw observations). A robot built from joint
state has the signals qpos, qvel and task (its features); one built from its hardware's
signals (`mat_sdk.envs.Observation`) has joint_pos, joint_vel, gravity, gyro, contacts,
command, last_action, ... as `describe()` lists them. Every field is checked here before
use; a bundle without `wiring` still loads.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mat_runtime.manifest import _fail, integer, real, string, strings

CONTROL_TIMESTEP = (1e-5, 10.0)  # s: a controller ticks at 100 kHz at most, 0.1 Hz at least
MAX_ACTUATORS = 100_000  # a ctrl index past it is no robot's
MAX_COMMAND = 10.0  # m/s or rad/s: past it a velocity command is no robot's (as in training)


def check_wiring(wiring: Any, obs_dim: int, action_size: int, where: str) -> None:
    """Raise `BundleError` naming the first field of `wiring` that is malformed."""

    def need(field: str, problem: str | None) -> None:
        if problem:
            _fail(where, f"wiring.{field}", problem)

    need("", None if isinstance(wiring, dict) else f"must be an object, got {wiring!r}")
    need("control_timestep", real(wiring.get("control_timestep")))
    if not CONTROL_TIMESTEP[0] <= wiring["control_timestep"] <= CONTROL_TIMESTEP[1]:
        need(
            "control_timestep",
            f"must be in [{CONTROL_TIMESTEP[0]:g}, {CONTROL_TIMESTEP[1]:g}] s, "
            f"got {wiring['control_timestep']!r}",
        )
    need("normalizer", string(wiring.get("normalizer")))
    agents = wiring.get("agents")
    if not isinstance(agents, list) or not agents:
        need("agents", f"must be a non-empty list, got {agents!r}")
    for i, agent in enumerate(agents):
        need(f"agents[{i}]", None if isinstance(agent, dict) else "must be an object")
        need(f"agents[{i}].name", string(agent.get("name")))
        for key in ("actuators", "joints"):
            need(f"agents[{i}].{key}", strings(agent.get(key)))
        action = agent.get("action")
        if not isinstance(action, list) or len(action) != action_size:
            need(f"agents[{i}].action", f"must list {action_size} columns, got {action!r}")
        for j, column in enumerate(action):
            field = f"agents[{i}].action[{j}]"
            need(field, None if isinstance(column, dict) else "must be an object")
            for key in ("scale", "offset"):
                need(f"{field}.{key}", real(column.get(key)))
            if column.get("ctrl") is None:
                continue
            need(f"{field}.ctrl", integer(0)(column["ctrl"]))
            if column["ctrl"] >= MAX_ACTUATORS:
                need(f"{field}.ctrl", f"must be below {MAX_ACTUATORS}, got {column['ctrl']!r}")
            need(f"{field}.actuator", string(column.get("actuator")))
            for key in ("low", "high", "kp", "kd"):
                if column.get(key) is not None:
                    need(f"{field}.{key}", real(column[key]))
            low, high = column.get("low"), column.get("high")
            if low is not None and high is not None and low > high:
                need(field, f"has low {low!r} > high {high!r}")
            for key, problem in (("servo", "[kp, kd], two numbers >= 0"),
                                 ("range", "[low, high], low <= high")):  # fmt: skip
                pair = column.get(key)
                if pair is not None and not _pair(pair, nonnegative=key == "servo"):
                    need(f"{field}.{key}", f"must be {problem}, got {str(pair)[:80]}")
            if column.get("kp") is None and column.get("kd") is None:
                continue
            for key in ("kp", "kd"):  # a torque motor: its PD layer, fully
                need(f"{field}.{key}", real(column.get(key)))
                if column[key] < 0:
                    need(f"{field}.{key}", f"must be >= 0, got {column[key]!r}")
            need(f"{field}.target", string(column.get("target")))
            torque = column.get("torque")
            if not (isinstance(torque, list) and len(torque) == 2) or any(map(real, torque)):
                need(f"{field}.torque", f"must be [low, high], two finite numbers, got {torque!r}")
            if torque[0] > torque[1]:
                need(f"{field}.torque", f"must have low <= high, got {torque!r}")
    commands = wiring.get("commands", {})
    if not isinstance(commands, dict) or not all(
        isinstance(name, str) and _pair(span, limit=MAX_COMMAND) for name, span in commands.items()
    ):
        need("commands", f"must map names to [low, high] within +-{MAX_COMMAND:g}, got "
                         f"{str(commands)[:80]}")  # fmt: skip
    observation = wiring.get("observation")
    if observation is None:
        return
    need("observation", None if isinstance(observation, dict) else "must be an object")
    source = observation.get("source")
    if (
        not isinstance(source, dict)
        or list(source)[-1:] != ["constants"]
        or not all(isinstance(name, str) and name for name in source)
    ):
        need("observation.source", f"must give named signal ranges, constants last, got {source!r}")
    end = 0
    for name in source:
        span = source[name]
        valid = isinstance(span, list) and len(span) == 2 and all(not integer(0)(v) for v in span)
        if not valid or span[0] != end or span[1] < span[0]:
            need(f"observation.source.{name}", f"must be [{end}, stop >= {end}], got {span!r}")
        end = span[1]
    constants = observation.get("constants")
    width = source["constants"][1] - source["constants"][0]
    if not isinstance(constants, list) or len(constants) != width or any(map(real, constants)):
        need("observation.constants", f"must be {width} finite numbers, got {constants!r}")
    index = observation.get("index")
    rows_ok = isinstance(index, list) and len(index) == len(agents)
    if not rows_ok or not all(isinstance(row, list) and len(row) == obs_dim for row in index):
        need("observation.index", f"must be {len(agents)} rows of {obs_dim} source indices")
    flat = [v for row in index for v in row]
    if any(isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < end for v in flat):
        need("observation.index", f"must hold integers in 0..{end - 1}")
    offset = observation.get("offset")
    if offset is not None and (
        not isinstance(offset, list) or len(offset) != end or any(map(real, offset))
    ):
        need("observation.offset", f"must be {end} finite numbers, got {str(offset)[:80]}")
    signals = observation.get("signals", {})
    if not isinstance(signals, dict) or any(strings(labels) for labels in signals.values()):
        need("observation.signals", f"must map signal names to lists of labels, got {signals!r}")
    features = observation.get("features")
    if not isinstance(features, list):
        need("observation.features", f"must be a list, got {features!r}")
    for k, feature in enumerate(features):
        field = f"observation.features[{k}]"
        need(field, None if isinstance(feature, dict) else "must be an object")
        need(f"{field}.name", string(feature.get("name")))
        start, stop = feature.get("start"), feature.get("stop")
        if integer(0)(start) or integer(0)(stop) or not start < stop <= obs_dim:
            need(field, f"must have 0 <= start < stop <= {obs_dim}, got {start!r}..{stop!r}")


class Wiring:
    """A checked `wiring` field, ready for a controller: `observe` and `commands`."""

    def __init__(self, wiring: dict[str, Any]):
        self.raw = wiring
        self.control_timestep: float = float(wiring["control_timestep"])
        self.agents: list[dict[str, Any]] = wiring["agents"]
        self.normalizer: str = wiring["normalizer"]
        columns = [(i, j, c) for i, a in enumerate(self.agents) for j, c in enumerate(a["action"])]
        self.action_shape = (len(self.agents), len(self.agents[0]["action"]))
        driven = [(i, j, c) for i, j, c in columns if c.get("ctrl") is not None]
        self._action_rows = np.array([i for i, _, _ in driven], dtype=np.intp)
        self._action_cols = np.array([j for _, j, _ in driven], dtype=np.intp)
        self.ctrl_index = np.array([c["ctrl"] for _, _, c in driven], dtype=np.intp)
        self._scale = np.array([c["scale"] for _, _, c in driven])
        self._offset = np.array([c["offset"] for _, _, c in driven])
        self._low = np.array([_bound(c.get("low"), -np.inf) for _, _, c in driven])
        self._high = np.array([_bound(c.get("high"), np.inf) for _, _, c in driven])
        # torque motors: the PD gains that turn each column's joint target into torque
        self.gains = [
            (c["target"], c["kp"], c["kd"]) for _, _, c in driven if c.get("kp") is not None
        ]
        # per driven column: the joint it targets (None: a raw actuator control), the servo's
        # or PD layer's gains and the joint's range, where the bundle records them
        self.targets: list[str | None] = [c.get("target") for _, _, c in driven]
        self.servo: list[tuple[float, float] | None] = [
            tuple(c["servo"]) if "servo" in c else (c["kp"], c["kd"]) if "kp" in c else None
            for _, _, c in driven
        ]
        self.ranges: list[tuple[float, float] | None] = [
            tuple(c["range"]) if "range" in c else None for _, _, c in driven
        ]
        self.start_targets = self._offset.copy()  # each column's target at action 0
        self.command_ranges: dict[str, tuple[float, float]] = {
            name: (float(low), float(high))
            for name, (low, high) in wiring.get("commands", {}).items()
        }
        observation = wiring.get("observation")
        self.has_observation = observation is not None
        if self.has_observation:
            self.features: list[dict[str, Any]] = observation["features"]
            self.source: dict[str, list[int]] = observation["source"]
            self.signals: dict[str, list[str]] = observation.get("signals", {})
            self._inputs = [name for name in self.source if name != "constants"]
            self._index = np.array(observation["index"], dtype=np.intp)
            self._buffer = np.zeros(self.source["constants"][1])
            self._buffer[self.source["constants"][0] :] = observation["constants"]
            offset = observation.get("offset")
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
            columns = ", ".join(_column(c) for c in agent["action"])
            joints = ", ".join(agent["joints"]) or "none"
            lines.append(f"  {agent['name']}: joints {joints}; actions: {columns}")
        if self.has_observation:
            layout = ", ".join(f"{f['name']} [{f['start']}:{f['stop']}]" for f in self.features)
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


def _pair(value, nonnegative: bool = False, limit: float = np.inf) -> bool:
    """Whether `value` is two finite numbers within +-limit: both >= 0 (`nonnegative`, a
    servo's [kp, kd]), else [low, high] with low <= high."""
    return (
        isinstance(value, list)
        and len(value) == 2
        and not any(map(real, value))
        and all(abs(v) <= limit for v in value)
        and (min(value) >= 0 if nonnegative else value[0] <= value[1])
    )


def _bound(value, default: float) -> float:
    return default if value is None else float(value)


def _column(column: dict[str, Any]) -> str:
    if column.get("ctrl") is None:
        return "(none)"
    if column.get("kp") is not None:
        return (
            f"{column['actuator']}: target {column['target']} = {column['offset']:g} + "
            f"{column['scale']:g} a, torque = {column['kp']:g} (target - q) - {column['kd']:g} dq"
        )
    text = f"{column['actuator']} = {column['offset']:g} + {column['scale']:g} a"
    if column.get("low") is not None or column.get("high") is not None:
        text += f" in [{column.get('low')}, {column.get('high')}]"
    return text
