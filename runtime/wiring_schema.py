"""The wiring's schema: how a policy's arrays map onto a robot, as typed values.

An env that knows its robot (`RobotTeam.wiring()`, `MaMuJoCoTeam.wiring()`) builds a
`WiringSpec`; `mat export` writes it into the manifest (`to_json`); the runtime reads it back
(`WiringSpec.from_json`, every field checked before use) and acts through it
(`mat_runtime.wiring.Wiring`). One module holds the layout for both sides, so what the env
writes and what the runtime reads cannot drift apart; it needs nothing but the standard
library, as the runtime must.

The JSON layout (a manifest's `wiring` field):

- `control_timestep`, `physics_timestep` (s); `normalizer` (where the observation normaliser
  is: inside the graphs, which take raw observations);
- `agents`: per agent its `name`, the `actuators` and `joints` it drives and, per action
  column, the actuator it commands: `ctrl = offset + scale * clip(action, -1, 1)`, clipped to
  [low, high] where given (`ctrl` null: the column drives nothing). With joint targets the
  value is the `target` joint's position around the start pose; a torque motor's column also
  gives the PD gains `kp`, `kd` and its `torque` range, a position servo's its `servo` gains
  [kp, kd], and a limited joint its `range`;
- `observation` (absent where the env builds observations itself): `obs[i, j] = (source -
  offset)[index[i][j]]` with `source` the concatenation of the named signals and `constants`,
  at the ranges in `source`; `signals` names each signal's columns; `offset` (when present)
  holds the start pose under `joint_pos`; `features` the name and columns of each feature;
- `commands`: the velocity commands' trained ranges, for a robot that takes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from mat_runtime.manifest import _fail, integer, real, string, strings

CONTROL_TIMESTEP = (1e-5, 10.0)  # s: a controller ticks at 100 kHz at most, 0.1 Hz at least
MAX_ACTUATORS = 100_000  # a ctrl index past it is no robot's
MAX_COMMAND = 10.0  # m/s or rad/s: past it a velocity command is no robot's (as in training)

Pair = tuple[float, float]


@dataclass(frozen=True)
class ActionColumn:
    """One action column: the actuator it commands, `ctrl = offset + scale * clip(a, -1, 1)`
    within [low, high]; `ctrl` None: it drives nothing (a zeroed fault, a narrower agent's
    padding). `target`: the joint whose position the value is (joint targets); `kp`, `kd`,
    `torque`: a torque motor's PD layer; `servo`: a position servo's [kp, kd]; `range`: the
    target joint's limits."""

    scale: float = 0.0
    offset: float = 0.0
    ctrl: int | None = None
    actuator: str | None = None
    low: float | None = None
    high: float | None = None
    target: str | None = None
    kp: float | None = None
    kd: float | None = None
    torque: Pair | None = None
    servo: Pair | None = None
    range: Pair | None = None

    @property
    def drives(self) -> bool:
        return self.ctrl is not None

    @property
    def gains(self) -> Pair | None:
        """The gains a motor driver must be given: a servo's, or a torque motor's PD layer."""
        if self.servo is not None:
            return self.servo
        return None if self.kp is None else (self.kp, self.kd)

    def to_json(self) -> dict[str, Any]:
        data: dict[str, Any] = {"actuator": self.actuator, "ctrl": self.ctrl}
        data |= {"scale": self.scale, "offset": self.offset}
        for key in ("target", "kp", "kd", "low", "high"):
            if getattr(self, key) is not None:
                data[key] = getattr(self, key)
        for key in ("torque", "servo", "range"):
            if getattr(self, key) is not None:
                data[key] = list(getattr(self, key))
        return data


NO_ACTUATOR = ActionColumn()


@dataclass(frozen=True)
class AgentWiring:
    """One agent: its name, the actuators and joints it drives, its action columns."""

    name: str
    actuators: tuple[str, ...]
    joints: tuple[str, ...]
    action: tuple[ActionColumn, ...]

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "actuators": list(self.actuators),
            "joints": list(self.joints),
            "action": [column.to_json() for column in self.action],
        }


@dataclass(frozen=True)
class Feature:
    """A named part of every agent's observation: columns [start, stop)."""

    name: str
    start: int
    stop: int


@dataclass(frozen=True)
class ObservationLayout:
    """`obs[i, j] = (source - offset)[index[i][j]]`, `source` the named signals and the
    constants concatenated in `source`'s order (each a [start, stop) range)."""

    source: dict[str, tuple[int, int]]
    constants: tuple[float, ...]
    index: tuple[tuple[int, ...], ...]
    features: tuple[Feature, ...]
    signals: dict[str, tuple[str, ...]] = field(default_factory=dict)
    offset: tuple[float, ...] | None = None

    @property
    def inputs(self) -> list[str]:
        """The signals a controller gives, in the source's order."""
        return [name for name in self.source if name != "constants"]

    def to_json(self) -> dict[str, Any]:
        data: dict[str, Any] = {
            "features": [vars(feature).copy() for feature in self.features],
            "source": {name: list(span) for name, span in self.source.items()},
            "constants": list(self.constants),
            "index": [list(row) for row in self.index],
        }
        if self.offset is not None:
            data["offset"] = list(self.offset)
        if self.signals:
            data["signals"] = {name: list(labels) for name, labels in self.signals.items()}
        return data


@dataclass(frozen=True)
class WiringSpec:
    """How the policy's arrays map onto a robot (the module's docstring gives the layout)."""

    control_timestep: float
    agents: tuple[AgentWiring, ...]
    physics_timestep: float | None = None
    observation: ObservationLayout | None = None
    commands: dict[str, Pair] = field(default_factory=dict)
    normalizer: str | None = None

    def placed(self, normalizer: str) -> WiringSpec:
        """The same wiring, saying where the bundle keeps the observation normaliser."""
        return replace(self, normalizer=normalizer)

    def to_json(self) -> dict[str, Any]:
        data: dict[str, Any] = {"control_timestep": self.control_timestep}
        if self.physics_timestep is not None:
            data["physics_timestep"] = self.physics_timestep
        data["agents"] = [agent.to_json() for agent in self.agents]
        if self.observation is not None:
            data["observation"] = self.observation.to_json()
        if self.commands:
            data["commands"] = {name: list(span) for name, span in self.commands.items()}
        if self.normalizer is not None:
            data["normalizer"] = self.normalizer
        return data

    @classmethod
    def from_json(cls, data: Any, obs_dim: int, action_size: int, where: str) -> WiringSpec:
        """The wiring a manifest holds, every field checked first: `BundleError` naming the
        first malformed one."""
        check(data, obs_dim, action_size, where)
        observation = data.get("observation")
        return cls(
            control_timestep=float(data["control_timestep"]),
            physics_timestep=_optional_float(data.get("physics_timestep")),
            agents=tuple(
                AgentWiring(
                    name=agent["name"],
                    actuators=tuple(agent["actuators"]),
                    joints=tuple(agent["joints"]),
                    action=tuple(_column(column) for column in agent["action"]),
                )
                for agent in data["agents"]
            ),
            observation=None if observation is None else _layout(observation),
            commands={name: _pair_of(span) for name, span in data.get("commands", {}).items()},
            normalizer=data["normalizer"],
        )


def _optional_float(value) -> float | None:
    return None if value is None else float(value)


def _pair_of(value) -> Pair | None:
    return None if value is None else (float(value[0]), float(value[1]))


def _column(data: dict[str, Any]) -> ActionColumn:
    if data.get("ctrl") is None:
        return ActionColumn(scale=float(data["scale"]), offset=float(data["offset"]))
    return ActionColumn(
        scale=float(data["scale"]),
        offset=float(data["offset"]),
        ctrl=int(data["ctrl"]),
        actuator=data["actuator"],
        low=_optional_float(data.get("low")),
        high=_optional_float(data.get("high")),
        target=data.get("target"),
        kp=_optional_float(data.get("kp")),
        kd=_optional_float(data.get("kd")),
        torque=_pair_of(data.get("torque")),
        servo=_pair_of(data.get("servo")),
        range=_pair_of(data.get("range")),
    )


def _layout(data: dict[str, Any]) -> ObservationLayout:
    offset = data.get("offset")
    return ObservationLayout(
        source={name: (int(a), int(b)) for name, (a, b) in data["source"].items()},
        constants=tuple(float(v) for v in data["constants"]),
        index=tuple(tuple(row) for row in data["index"]),
        features=tuple(
            Feature(f["name"], int(f["start"]), int(f["stop"])) for f in data["features"]
        ),
        signals={name: tuple(labels) for name, labels in data.get("signals", {}).items()},
        offset=None if offset is None else tuple(float(v) for v in offset),
    )


def check(wiring: Any, obs_dim: int, action_size: int, where: str) -> None:
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
    physics = wiring.get("physics_timestep")
    if physics is not None:
        need("physics_timestep", real(physics))
        if not CONTROL_TIMESTEP[0] <= physics <= wiring["control_timestep"]:
            need(
                "physics_timestep",
                f"must be in [{CONTROL_TIMESTEP[0]:g} s, the control timestep], got {physics!r}",
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


def _pair(value, nonnegative: bool = False, limit: float = math.inf) -> bool:
    """Whether `value` is two finite numbers within +-limit: both >= 0 (`nonnegative`, a
    servo's [kp, kd]), else [low, high] with low <= high."""
    return (
        isinstance(value, list)
        and len(value) == 2
        and not any(map(real, value))
        and all(abs(v) <= limit for v in value)
        and (min(value) >= 0 if nonnegative else value[0] <= value[1])
    )
