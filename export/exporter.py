"""Checkpoint -> ONNX bundle, verified against torch before anything is written.

    mat_export.export("runs/cheetah/checkpoint.pt", "cheetah_onnx")

The bundle is built in a temporary directory beside the target and renamed into place only
after ORT matched torch on every agent count tried; a failed export leaves nothing behind,
and an existing bundle is replaced only with `force=True`.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import shutil
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from unittest import mock

import torch

from mat_export import parity
from mat_export.engines import ENGINES, openvino_parity
from mat_export.errors import ExportError
from mat_export.graphs import (
    DecentralisedStepGraph,
    EncoderGraph,
    MATStepGraph,
    ObsNormalizer,
    ValueScale,
    cache_names,
)
from mat_export.manifest import NORMALIZER_PLACE, finish_graph, manifest, sha256
from mat_export.parity import AGENT_COUNTS, measure_parity
from mat_export.target import check_target, staging
from mat_sdk import envs
from mat_sdk.common import files
from mat_sdk.policy import checkpoint
from mat_sdk.policy.control_graph import OPSET as DECODE_OPSET
from mat_sdk.policy.control_graph import build_decode
from mat_sdk.policy.model import ModelConfig, check_fits
from mat_sdk.policy.normalization import RunningMeanStd, ValueNorm

OPSET = 20  # encoder.onnx and decoder_step.onnx; decode*.onnx: DECODE_OPSET (24, Attention)


def export(
    checkpoint_path: str | os.PathLike,
    out_dir: str | Path,
    force: bool = False,
    agent_counts=AGENT_COUNTS,
    engines: tuple[str, ...] = (),
) -> dict[str, Any]:
    """Write the bundle and return its manifest.

    `encoder.onnx`, `decoder_step.onnx`, `decode.onnx` (any agent count) and, for MAT,
    `decode_n{N}.onnx`: the control step written out for the trained count N (no loop),
    which the runtime uses when it is given exactly N agents. The exporter builds the env
    the checkpoint records (its wiring goes into the manifest); a `module:function` env id is
    imported only for a checkpoint given as `envs.Trusted(path)`. `engines=("openvino",)`
    also runs every graph in OpenVINO against ONNX Runtime (`engines.openvino_parity`; the
    manifest's `parity.openvino`).
    """
    unknown = sorted(set(engines) - set(ENGINES))
    if unknown:
        raise ValueError(f"engines: {unknown} unknown; valid: {', '.join(ENGINES)}")
    given, out_dir = checkpoint_path, Path(out_dir)
    checkpoint_path = checkpoint.locate(checkpoint_path)  # or zoo:NAME
    check_target(out_dir, force, checkpoint_path)
    payload = checkpoint.load(checkpoint_path)
    envs.check_trusted([checkpoint.env_id(payload)], envs.trusted_as(checkpoint_path, given))
    built = staging(out_dir)  # before the work: an unwritable target fails in a moment
    try:
        with files.writing(out_dir):
            written = _build(payload, checkpoint_path, built, agent_counts, engines)
            umask = os.umask(0)
            os.umask(umask)
            built.chmod(0o777 & ~umask)  # mkdtemp makes 0700
            files.replace_directory(built, out_dir)
    finally:
        shutil.rmtree(built, ignore_errors=True)
    return written


def _build(
    payload: dict, checkpoint_path: Path, staging: Path, agent_counts, engines
) -> dict[str, Any]:
    """Every graph and the manifest into `staging`, held to torch's output; the manifest."""
    policy, normalizer, value_scale, obs_norm = _rebuild(payload)
    team = _check_env(payload, policy.cfg)
    cfg = policy.cfg
    counts = (cfg.n_agents,) if cfg.fixed_team else tuple(agent_counts)
    graphs = _export_graphs(policy, normalizer, value_scale, staging)
    written = manifest(payload, cfg, graphs, checkpoint_path)
    if hasattr(team, "wiring"):  # robots; PettingZoo envs and games have no actuators
        written["wiring"] = team.wiring().placed(NORMALIZER_PLACE).to_json()
    written["agents"]["action_widths"] = [int(w) for w in team.action_widths]
    if cfg.action_type == "discrete":  # an agent never takes its padding choices
        written["agents"]["choices"] = [int(c) for c in team.choices]
    folded = (
        normalizer.mean.numpy(),
        normalizer.scale.numpy(),
        normalizer.clip,
        float(value_scale.mean),
        float(value_scale.std),
    )
    bounds = (written["action"]["low"], written["action"]["high"])
    specialised = [cfg.n_agents] if cfg.algorithm.autoregressive else []
    for agents in [None, *specialised]:
        name = "decode.onnx" if agents is None else f"decode_n{agents}.onnx"
        decode = build_decode(policy, *folded, agents=agents, action_bounds=bounds)
        (staging / name).write_bytes(decode.SerializeToString())
        graphs[name] = {
            "inputs": [i.name for i in decode.graph.input],
            "outputs": [o.name for o in decode.graph.output],
            "opset": DECODE_OPSET,
            "agents": agents,  # None: any count
        }
    written["graphs"] = dict(graphs)
    measured = measure_parity(policy, obs_norm, value_scale, staging, counts, bounds)
    worst = max(measured["max_abs_diff"].values())
    if not worst <= parity.PARITY_LIMIT:
        raise ExportError(
            f"ONNX Runtime disagrees with torch by {worst:.3g} (> {parity.PARITY_LIMIT}); "
            "no bundle written"
        )
    written["parity"] = measured
    if "openvino" in engines:  # what a robot's Intel CPU would run, held to ORT
        second = openvino_parity(staging, sorted({int(n) for n in measured["max_abs_diff"]}))
        if second is None:
            raise ExportError(
                "engines=openvino: OpenVINO is not installed (pip install 'mat-sdk[openvino]'); "
                "no bundle written"
            )
        written["parity"]["openvino"] = second
    for name in graphs:
        finish_graph(staging / name, written)
    written["graphs"] = {
        name: {**io, "sha256": sha256(staging / name)} for name, io in graphs.items()
    }
    (staging / "manifest.json").write_text(json.dumps(written, indent=2) + "\n")
    return written


def _check_env(payload: dict, cfg: ModelConfig):
    """The bundle names the robot it drives: that env must exist and fit the model. Returns
    the team, for its wiring."""
    trained = checkpoint.recorded_config(payload).env
    env_id = trained.id
    try:
        team = envs.make_team(env_id, **trained.team_options)
    except (ValueError, TypeError) as error:
        raise ExportError(
            f"the checkpoint was trained on env {env_id!r}, which cannot be made here ({error}); "
            "no bundle written"
        ) from None
    try:
        check_fits(cfg, team, env_id)
    except ValueError as error:
        raise ExportError(f"{error}; no bundle written") from None
    return team


def _rebuild(payload: dict) -> tuple[Any, ObsNormalizer, ValueScale, RunningMeanStd | None]:
    """The checkpoint's policy, its observation normaliser as graph operations and as
    trained (parity is measured against the latter), and its value scale."""
    policy, obs_norm = checkpoint.restore_policy(payload, "the checkpoint")
    value_norm = ValueNorm()
    value_norm.load_state_dict(payload["value_norm"])
    mean, var = value_norm.mean_var()
    normalizer = ObsNormalizer(obs_norm, policy.cfg.obs_dim).eval()
    return policy, normalizer, ValueScale(float(mean), float(var.sqrt())).eval(), obs_norm


def _dims() -> dict[str, Any]:
    from torch.export import Dim

    return {
        "batch": Dim("batch", min=1, max=1 << 20),
        "agents": Dim("agents", min=1, max=1 << 16),
        "past": Dim("past", min=0, max=1 << 16),
    }


def _export_graphs(policy, normalizer, value_scale, directory: Path) -> dict[str, dict]:
    """Export both graphs; returns their input/output names."""
    cfg, dims = policy.cfg, _dims()
    batch, n = 3, cfg.n_agents if cfg.fixed_team else 5  # trace with sizes >= 2
    obs = torch.randn(batch, n, cfg.obs_dim)
    agents_dim = {} if cfg.fixed_team else {1: dims["agents"]}
    graphs = {}
    encoder = EncoderGraph(policy, normalizer, value_scale)
    graphs["encoder.onnx"] = _export(
        encoder,
        (obs,),
        {"obs": {0: dims["batch"], **agents_dim}},
        ["obs"],
        ["rep", "values"],
        directory / "encoder.onnx",
    )
    discrete = cfg.action_type == "discrete"
    head = ["logits"] if discrete else ["mean", "std"]
    mask = (
        [torch.ones(batch, 1 if cfg.algorithm.autoregressive else n, cfg.action_size)]
        if discrete
        else []
    )
    if cfg.algorithm.autoregressive:
        head_dim, n_cache = cfg.n_embd // cfg.n_head, 4 * cfg.n_block
        past = [torch.randn(batch, cfg.n_head, 4, head_dim) for _ in range(n_cache)]
        names = cache_names(cfg.n_block)
        token = torch.randn(batch, 1, policy.decoder.token_dim)
        rep = torch.randn(batch, 1, cfg.n_embd)
        inputs = ["rep", "token", *(p for p, _ in names), *(["available"] if discrete else [])]
        varargs = [{0: dims["batch"], 2: dims["past"]} for _ in names]
        varargs += [{0: dims["batch"]}] if discrete else []
        shapes = ({0: dims["batch"]}, {0: dims["batch"]}, tuple(varargs))  # rep, token, *rest
        graphs["decoder_step.onnx"] = _export(
            MATStepGraph(policy),
            (rep, token, *past, *mask),
            shapes,
            inputs,
            [*head, *(q for _, q in names)],
            directory / "decoder_step.onnx",
        )
    else:
        inputs = ["rep", *(["available"] if discrete else [])]
        per_agent = {0: dims["batch"], **agents_dim}
        shapes = (per_agent, (per_agent,)) if discrete else (per_agent,)  # obs, *mask
        graphs["decoder_step.onnx"] = _export(
            DecentralisedStepGraph(policy),
            (normalizer(obs), *mask),
            shapes,
            inputs,
            head,
            directory / "decoder_step.onnx",
        )
    return graphs


def _export(module, args, dynamic_shapes, inputs, outputs, path: Path) -> dict:
    registry_log = logging.getLogger("torch.onnx._internal.exporter._registration")
    level = registry_log.level
    registry_log.setLevel(logging.ERROR)  # "torchvision is not installed" is noise for us
    try:
        with warnings.catch_warnings(), torch.no_grad(), torchlib_registry_reused():
            warnings.simplefilter("ignore")
            program = torch.onnx.export(
                module,
                args,
                dynamo=True,
                opset_version=OPSET,
                dynamic_shapes=dynamic_shapes,
                input_names=inputs,
                output_names=outputs,
                verbose=False,
            )
    finally:
        registry_log.setLevel(level)
    program.save(str(path))
    return {"inputs": inputs, "outputs": outputs, "opset": OPSET}


@functools.cache
def _torchlib_registry(build, opset_version: int):
    return build(opset_version=opset_version)


@contextlib.contextmanager
def torchlib_registry_reused() -> Iterator[None]:
    """Build torchlib's operator registry once per process, not once per graph.

    torch.onnx.export rebuilds it (thousands of ATen overloads looked up) for every graph it
    exports and only reads it afterwards, so one registry per opset serves every export. This
    reaches into torch's exporter internals; where they differ from torch 2.13's, exports run
    as torch wrote them.
    """
    try:
        from torch.onnx._internal.exporter import _registration

        registry_class = _registration.ONNXRegistry
        original = registry_class.__dict__["from_torchlib"]
        assert isinstance(original, classmethod)
        build = original.__get__(None, registry_class)
    except (ImportError, AttributeError, KeyError, AssertionError):
        yield
        return

    def from_torchlib(cls, opset_version=_registration._constants.TORCHLIB_OPSET):
        return _torchlib_registry(build, opset_version)

    with mock.patch.object(registry_class, "from_torchlib", classmethod(from_torchlib)):
        yield
