"""The bundle manifest's schema: every field the runtime reads, checked before any is used.

A manifest is data from a file, so nothing in it is trusted: each field must have its type
and range, graph names must be plain file names inside the bundle, and the numbers must
agree with each other. A violation raises `BundleError` naming the field. The schema is a
few lines of plain Python rather than a JSON-Schema library, so that a robot's controller
process needs nothing beyond numpy and onnxruntime.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from typing import Any

from mat_runtime.errors import BundleError

ALGOS = ("mat", "mat-dec", "mappo", "happo")
FIXED_TEAM = ("mappo", "happo")  # policies for exactly the agent count they were trained on
ACTION_TYPES = ("continuous", "discrete")
GRAPH_NAME = re.compile(r"(encoder|decoder_step|decode|decode_n(\d+))\.onnx$")
_LARGEST = 2**31 - 1  # sizes beyond this are not a policy, and overflow numpy and ORT

# A check returns the problem with the value (a phrase), or None when it is fine.
Check = Callable[[Any], str | None]


def integer(low: int = 1) -> Check:
    def check(value):
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= _LARGEST:
            return f"must be an integer in {low}..{_LARGEST}, got {value!r}"
        return None

    return check


def real(value) -> str | None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return f"must be a finite number, got {value!r}"
    return None


def one_of(*choices: str) -> Check:
    def check(value):
        return None if value in choices else f"must be one of {list(choices)}, got {value!r}"

    return check


def optional(inner: Check) -> Check:
    def check(value):
        return None if value is None else inner(value)

    return check


def string(value) -> str | None:
    return None if isinstance(value, str) else f"must be a string, got {value!r}"


def strings(value) -> str | None:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        return f"must be a list of strings, got {value!r}"
    return None


def mapping(value) -> str | None:
    return None if isinstance(value, dict) else f"must be an object, got {value!r}"


def sha256(value) -> str | None:
    if not isinstance(value, str) or not re.fullmatch(r"[0-9a-f]{64}", value):
        return f"must be a sha256 hex digest, got {value!r}"
    return None


SCHEMA: dict[str, Any] = {
    "algo": one_of(*ALGOS),
    "obs_dim": integer(),
    "action": {
        "type": one_of(*ACTION_TYPES),
        "size": integer(),
        "low": real,
        "high": real,
    },
    "agents": {"min": integer(), "max": optional(integer())},
    "env_id": optional(string),
    "env_faults": optional(mapping),
    "env_options": optional(mapping),
    "randomization": optional(mapping),
    "graphs": mapping,
}
GRAPH_SCHEMA: dict[str, Any] = {
    "sha256": sha256,
    "inputs": strings,
    "outputs": strings,
    "opset": integer(),
    "agents": optional(integer()),
}
OPTIONAL = {
    "env_id",
    "env_faults",
    "env_options",
    "randomization",
}  # absent from bundles of early versions
GRAPH_OPTIONAL = {"agents"}


def check_manifest(manifest: dict[str, Any], where: str) -> None:
    """Raise `BundleError` for the first field of `manifest` that is missing, of the wrong
    type or out of range, or that disagrees with another; `where` names the file."""
    _check(manifest, SCHEMA, "", where, OPTIONAL)
    action, agents = manifest["action"], manifest["agents"]
    if manifest["algo"] in FIXED_TEAM and agents["max"] != agents["min"]:
        _fail(where, "agents", f"of a {manifest['algo']} bundle must be one count, got {agents!r}")
    choices = agents.get("choices")  # discrete agents' own numbers of choices
    if choices is not None and (
        action["type"] != "discrete"
        or not isinstance(choices, list)
        or any(integer()(c) or c > action["size"] for c in choices)
    ):
        _fail(where, "agents.choices", f"must list integers in 1..action.size, got {choices!r}")
    if not action["low"] < action["high"]:
        _fail(where, "action.low", f"must be below action.high, got {action['low']!r}")
    if agents["max"] is not None and agents["max"] < agents["min"]:
        _fail(where, "agents.max", f"must be >= agents.min, got {agents['max']!r}")
    for name, entry in manifest["graphs"].items():
        field = f"graphs.{name}"
        match = GRAPH_NAME.fullmatch(name) if isinstance(name, str) else None
        if match is None:
            _fail(
                where, field, "is not a graph name of a bundle (encoder.onnx, decoder_step.onnx, "
                "decode.onnx, decode_nN.onnx): a graph must be a file in the bundle directory",
            )  # fmt: skip
        _check(entry, GRAPH_SCHEMA, f"{field}.", where, GRAPH_OPTIONAL)
        count = match.group(2)
        agents = entry.get("agents")
        if count is not None and agents != int(count):
            _fail(where, f"{field}.agents", f"must be {count}, got {agents!r}")
        if name == "decode.onnx" and agents is not None:
            _fail(where, f"{field}.agents", f"must be null (any count), got {agents!r}")


def _check(
    values: Any,
    schema: Mapping[str, Any],
    prefix: str,
    where: str,
    optional: set[str] = frozenset(),
) -> None:
    if not isinstance(values, dict):
        _fail(where, prefix.rstrip(".") or "manifest", f"must be an object, got {values!r}")
    for key, rule in schema.items():
        field = f"{prefix}{key}"
        if key not in values:
            if key in optional:
                continue
            _fail(where, field, "is missing")
        if isinstance(rule, dict):
            _check(values[key], rule, f"{field}.", where)
            continue
        problem = rule(values[key])
        if problem:
            _fail(where, field, problem)


def _fail(where: str, field: str, problem: str) -> None:
    if len(problem) > 200:
        problem = problem[:200] + "..."
    raise BundleError(f"{where}: {field} {problem}; re-export the bundle with `mat export`")
