"""A bundle's wiring: how the policy's arrays map onto the robot's sensors and actuators.

    policy = Policy.load("cheetah_onnx")
    print(policy.describe())                                  # agents, actuators, layout
    wiring = policy.wiring                                    # None for bundles without one
    obs = wiring.observe(data.qpos, data.qvel)                # [n, obs_dim], no torch, no env
    index, values = wiring.commands(policy.act(obs))          # data.ctrl[index] = values

The manifest's `wiring` field (written by `mat export` for robots) holds, per agent, the
actuators and joints it drives and each action column's `ctrl = offset + scale * clip(a)`;
the observation as an index table into qpos | qvel | task features | constants, with the
name and columns of each feature; the control timestep; and where the observation
normaliser is (inside the graphs, which take raw observations). Every field is checked here
before use; a bundle without `wiring` still loads.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mat_runtime.manifest import _fail, integer, real, string, strings

_SOURCES = ("qpos", "qvel", "task", "constants")


def check_wiring(wiring: Any, obs_dim: int, action_size: int, where: str) -> None:
    """Raise `BundleError` naming the first field of `wiring` that is malformed."""

    def need(field: str, problem: str | None) -> None:
        if problem:
            _fail(where, f"wiring.{field}", problem)

    need("", None if isinstance(wiring, dict) else f"must be an object, got {wiring!r}")
    need("control_timestep", real(wiring.get("control_timestep")))
    if wiring["control_timestep"] <= 0:
        need("control_timestep", f"must be > 0, got {wiring['control_timestep']!r}")
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
            if column.get("ctrl") is not None:
                need(f"{field}.ctrl", integer(0)(column["ctrl"]))
    observation = wiring.get("observation")
    if observation is None:
        return
    need("observation", None if isinstance(observation, dict) else "must be an object")
    source = observation.get("source")
    if not isinstance(source, dict) or set(source) != set(_SOURCES):
        need("observation.source", f"must give the ranges of {list(_SOURCES)}, got {source!r}")
    end = 0
    for name in _SOURCES:
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
        driven = [(i, j, c) for i, j, c in columns if c.get("ctrl") is not None]
        self._action_rows = np.array([i for i, _, _ in driven], dtype=np.intp)
        self._action_cols = np.array([j for _, j, _ in driven], dtype=np.intp)
        self.ctrl_index = np.array([c["ctrl"] for _, _, c in driven], dtype=np.intp)
        self._scale = np.array([c["scale"] for _, _, c in driven])
        self._offset = np.array([c["offset"] for _, _, c in driven])
        observation = wiring.get("observation")
        self.has_observation = observation is not None
        if self.has_observation:
            self.features: list[dict[str, Any]] = observation["features"]
            self.source: dict[str, list[int]] = observation["source"]
            self._index = np.array(observation["index"], dtype=np.intp)
            self._buffer = np.zeros(self.source["constants"][1])
            self._buffer[self.source["constants"][0] :] = observation["constants"]

    def observe(self, qpos, qvel, task=None) -> np.ndarray:
        """Every agent's observation `[n, obs_dim]` (float32) from the robot's joint positions
        and velocities (MuJoCo's qpos and qvel order) and the task's features (if any)."""
        if not self.has_observation:
            raise ValueError(
                "this bundle's wiring has no observation layout (its env builds observations "
                "itself, e.g. MaMuJoCo); build them as the env does"
            )
        for name, values in (("qpos", qpos), ("qvel", qvel), ("task", task)):
            start, stop = self.source[name]
            values = np.zeros(0) if values is None else np.asarray(values, dtype=np.float64)
            if values.shape != (stop - start,):
                raise ValueError(
                    f"{name} must have {stop - start} values, got shape {values.shape}"
                )
            self._buffer[start:stop] = values
        return self._buffer[self._index].astype(np.float32)

    def commands(self, actions) -> tuple[np.ndarray, np.ndarray]:
        """The MuJoCo ctrl indices and the values to write there for `actions` `[n, size]`:
        `ctrl = offset + scale * clip(action, -1, 1)`, for every column that drives one."""
        values = np.clip(np.asarray(actions)[self._action_rows, self._action_cols], -1.0, 1.0)
        return self.ctrl_index, self._offset + self._scale * values

    def describe(self) -> str:
        lines = [f"control timestep {self.control_timestep:g} s; normaliser {self.normalizer}"]
        for agent in self.agents:
            columns = ", ".join(
                f"{c['actuator']} = {c['offset']:g} + {c['scale']:g} a"
                if c.get("ctrl") is not None
                else "(none)"
                for c in agent["action"]
            )
            joints = ", ".join(agent["joints"]) or "none"
            lines.append(f"  {agent['name']}: joints {joints}; actions: {columns}")
        if self.has_observation:
            layout = ", ".join(f"{f['name']} [{f['start']}:{f['stop']}]" for f in self.features)
            sources = ", ".join(f"{k} [{a}:{b}]" for k, (a, b) in self.source.items())
            lines.append(f"observation (every agent): {layout}")
            lines.append(f"  gathered from qpos | qvel | task | constants: {sources}")
        else:
            lines.append("observation: built by the env itself (no layout in the bundle)")
        return "\n".join(lines)
