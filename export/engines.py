"""The bundle in a second inference engine: OpenVINO on the CPU, compiled as
`OPENVINO_CPU_CONFIG` says (`pip install 'mat-sdk[openvino]'`; `mat export --engine
openvino`), held to ONNX Runtime on the same inputs.

A robot computer with an Intel CPU may run OpenVINO rather than ONNX Runtime; this says which
graphs it runs as ONNX Runtime does. Each graph is compiled once and run on every agent count
the export measures (a specialised `decode_nN.onnx` on its own count). What the engine refuses
and where it computes something else are reported per graph and count (`refused`, `wrong`),
never hidden; one compiled model that serves a second agent count can give wrong outputs
(`reused`): compile one per count.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from mat_runtime.policy import session

ENGINES = ("openvino",)  # the engines an export can be checked in beside ONNX Runtime
BATCH = 2
TOLERANCE = 1e-4  # as the export holds ORT to torch
# How a robot should compile a bundle in OpenVINO, and how it is checked here. f32: the
# default precision (bf16 where the CPU has it) moves outputs by about 1e-2. No runtime
# cache: with the CPU plugin's cache of primitives by shape, `decode.onnx` computed 32, 48,
# 64 and 128 agents wrong (off by 1.3-2.2) on an AMD EPYC with AVX2 and no AVX-512, the
# other counts right (OpenVINO 2026.4.0 and .1); without it, every count at parity.
OPENVINO_CPU_CONFIG = {"INFERENCE_PRECISION_HINT": "f32", "CPU_RUNTIME_CACHE_CAPACITY": "0"}


def openvino_parity(directory: Path, counts) -> dict | None:
    """{"engine", "config" (how it was compiled), "max_abs_diff": {graph: |OpenVINO - ORT|
    over every output and count, each count on a model compiled for it}, "wrong": {"graph
    n=N": that difference, where it is past `TOLERANCE`}, "refused": {"graph n=N": the
    engine's reason}, "reused": {graph: |OpenVINO - ORT| where one compiled model served the
    counts in turn, when that differs}};
    None without OpenVINO."""
    try:
        import openvino
    except ImportError:
        return None
    core = openvino.Core()
    diffs: dict[str, float] = {}
    wrong: dict[str, float] = {}
    refused: dict[str, str] = {}
    reused: dict[str, float] = {}
    rng = np.random.default_rng(0)

    def compiled(path: Path):
        model = core.read_model(str(path))
        return core.compile_model(model, "CPU", OPENVINO_CPU_CONFIG)

    def worst(model, feeds, expected) -> float:
        got = model(feeds)
        return max(
            float(np.abs(np.asarray(got[model.outputs[k]]) - value).max(initial=0.0))
            for k, value in enumerate(expected)
        )

    for path in sorted(directory.glob("*.onnx")):
        reference = session(path.read_bytes())
        fixed = re.fullmatch(r"decode_n(\d+)", path.stem)
        try:
            shared = compiled(path)
        except RuntimeError as error:
            refused[path.name] = _reason(error)
            continue
        for n in [int(fixed.group(1))] if fixed else counts:
            feeds = {i.name: _input(i, n, rng) for i in reference.get_inputs()}
            expected = reference.run(None, feeds)
            try:
                diff = worst(compiled(path), feeds, expected)
                again = worst(shared, feeds, expected)
            except RuntimeError as error:
                refused[f"{path.name} n={n}"] = _reason(error)
                continue
            diffs[path.name] = max(diffs.get(path.name, 0.0), diff)
            if diff > TOLERANCE:
                wrong[f"{path.name} n={n}"] = diff
            elif again > TOLERANCE:
                reused[path.name] = max(reused.get(path.name, 0.0), again)
    return {
        "engine": f"openvino {openvino.__version__.split('-')[0]}",
        "config": dict(OPENVINO_CPU_CONFIG),
        "max_abs_diff": diffs,
        "wrong": wrong,
        "refused": refused,
        "reused": reused,
    }


def _input(spec, agents: int, rng: np.random.Generator) -> np.ndarray:
    """Random floats, or every choice available (a discrete policy's mask)."""
    shape = _shape(spec.shape, agents)
    if "float" in spec.type:
        return rng.standard_normal(shape).astype(np.float32)
    return np.ones(shape, dtype=bool if "bool" in spec.type else np.float32)


def _shape(dims, agents: int) -> list[int]:
    """An input's shape with its named dimensions given: a batch, the agents, 3 cached steps."""
    named = {"batch": BATCH, "agents": agents}
    return [d if isinstance(d, int) else named.get(d, 3) for d in dims]


def _reason(error: Exception) -> str:
    """The engine's own words, in one line."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    useful = [line for line in lines if not line.startswith("Exception from src/")]
    return " ".join(useful or lines)[:300]
