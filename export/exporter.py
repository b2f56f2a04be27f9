"""Checkpoint -> ONNX bundle, verified against torch before anything is written.

    mat_export.export("runs/cheetah/checkpoint.pt", "cheetah_onnx")

The bundle is built in a temporary directory beside the target and renamed into place only
after ORT matched torch on every agent count tried; a failed export leaves nothing behind,
and an existing bundle is replaced only with `force=True`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import torch

from mat_export.graphs import (
    DecentralisedStepGraph,
    EncoderGraph,
    MATStepGraph,
    ObsNormalizer,
    ValueScale,
    cache_names,
)
from mat_runtime.manifest import GRAPH_NAME
from mat_sdk import checkpoint, envs, files
from mat_sdk.control_graph import OPSET as DECODE_OPSET
from mat_sdk.control_graph import build_decode
from mat_sdk.model import MAT, ModelConfig, build_policy
from mat_sdk.normalization import ValueNorm

FORMAT = "mat-onnx"
VERSION = 1
OPSET = 20
PARITY_LIMIT = 1e-4
AGENT_COUNTS = (1, 2, 6, 17, 64)
STANDARD_DOMAINS = ("", "ai.onnx")
NORMALIZER_PLACE = (
    "inside the graphs: they take raw observations, normalise them with the training "
    "statistics and clip them"
)


class ExportError(ValueError):
    """The export was refused or failed; nothing was written."""


def export(
    checkpoint_path: str | Path,
    out_dir: str | Path,
    force: bool = False,
    agent_counts=AGENT_COUNTS,
    trust_env_code: bool = False,
) -> dict[str, Any]:
    """Write the bundle and return its manifest.

    `encoder.onnx`, `decoder_step.onnx`, `decode.onnx` (any agent count) and, for MAT,
    `decode_n{N}.onnx`: the control step written out for the trained count N (no loop),
    which the runtime uses when it is given exactly N agents. The exporter builds the env
    the checkpoint records (its wiring goes into the manifest); a `module:function` env id is
    imported only with `trust_env_code=True`.
    """
    out_dir, checkpoint_path = Path(out_dir), checkpoint.locate(checkpoint_path)  # or zoo:NAME
    _check_target(out_dir, force, checkpoint_path)
    payload = checkpoint.load(checkpoint_path)
    envs.check_trusted([payload["config"]["env"]["id"]], trust_env_code, str(checkpoint_path))
    staging = _staging(out_dir)  # before the work: an unwritable target fails in a moment
    try:
        with files.writing(out_dir):
            manifest = _build(payload, checkpoint_path, staging, agent_counts)
            umask = os.umask(0)
            os.umask(umask)
            staging.chmod(0o777 & ~umask)  # mkdtemp makes 0700
            files.replace_directory(staging, out_dir)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return manifest


def _build(payload: dict, checkpoint_path: Path, staging: Path, agent_counts) -> dict[str, Any]:
    """Every graph and the manifest into `staging`, held to torch's output; the manifest."""
    policy, normalizer, value_scale = _rebuild(payload)
    team = _check_env(payload, policy.cfg)
    cfg = policy.cfg
    counts = (cfg.n_agents,) if cfg.algo == "mappo" else tuple(agent_counts)
    graphs = _export_graphs(policy, normalizer, value_scale, staging)
    manifest = _manifest(payload, cfg, graphs, checkpoint_path)
    if hasattr(team, "wiring"):  # robots; PettingZoo envs and games have no actuators
        manifest["wiring"] = {**team.wiring(), "normalizer": NORMALIZER_PLACE}
    manifest["agents"]["action_widths"] = [int(w) for w in team.action_widths]
    if cfg.action_type == "discrete":  # an agent never takes its padding choices
        manifest["agents"]["choices"] = [int(c) for c in team.choices]
    folded = (
        normalizer.mean.numpy(),
        normalizer.scale.numpy(),
        normalizer.clip,
        float(value_scale.mean),
        float(value_scale.std),
    )
    bounds = (manifest["action"]["low"], manifest["action"]["high"])
    specialised = [cfg.n_agents] if cfg.algo == "mat" else []
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
    manifest["graphs"] = dict(graphs)
    parity = measure_parity(policy, normalizer, value_scale, staging, counts, bounds)
    worst = max(parity["max_abs_diff"].values())
    if not worst <= PARITY_LIMIT:
        raise ExportError(
            f"ONNX Runtime disagrees with torch by {worst:.3g} (> {PARITY_LIMIT}); "
            "no bundle written"
        )
    manifest["parity"] = parity
    for name in graphs:
        _finish_graph(staging / name, manifest)
    manifest["graphs"] = {
        name: {**io, "sha256": _sha256(staging / name)} for name, io in graphs.items()
    }
    (staging / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def _check_target(out_dir: Path, force: bool, checkpoint_path: Path) -> None:
    """Refuse, before any work, to write where it would lose something: over anything but a
    bundle, over a bundle unless `force`, over a bundle that also holds other files (notes,
    the checkpoint itself), or through a symlink."""
    if out_dir.is_symlink():
        raise ExportError(
            f"{out_dir} is a symlink; not replacing it or what it points to; "
            "choose a real directory for the bundle"
        )
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportError(f"{out_dir} is a file; choose a directory for the bundle")
    source = Path(checkpoint_path).resolve()
    if out_dir.exists() and source.is_relative_to(out_dir.resolve()):
        raise ExportError(
            f"{out_dir} holds the checkpoint being exported ({checkpoint_path}); "
            "choose another directory for the bundle"
        )
    if not out_dir.exists() or not any(out_dir.iterdir()):
        return
    manifest = out_dir / "manifest.json"
    try:
        listed = json.loads(manifest.read_text())
        is_bundle = listed.get("format") == FORMAT
        # only the files an exporter writes: a doctored manifest cannot list others as its own
        own = {"manifest.json", *(g for g in listed.get("graphs", {}) if GRAPH_NAME.fullmatch(g))}
    except (OSError, ValueError, AttributeError, TypeError):
        is_bundle, own = False, set()
    if not is_bundle:
        raise ExportError(
            f"{out_dir} exists and is not a MAT bundle (no {FORMAT} manifest.json); "
            "not replacing it, even with --force; choose a new directory"
        )
    foreign = sorted(p.name for p in out_dir.iterdir() if p.name not in own)
    if foreign:
        raise ExportError(
            f"{out_dir} holds files that are not the bundle's ({', '.join(foreign[:5])}"
            f"{', ...' if len(foreign) > 5 else ''}); not replacing it, even with --force; "
            "move them out or choose a new directory"
        )
    if not force:
        raise ExportError(f"{out_dir} exists; pass --force (force=True) to replace it")


def _staging(out_dir: Path) -> Path:
    """The empty directory beside `out_dir` that the bundle is built in."""
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    except OSError as error:
        raise ExportError(
            f"cannot write the bundle {out_dir} ({error.strerror or error}: "
            f"{error.filename or out_dir.parent}); choose a directory you can write to"
        ) from None


def _check_env(payload: dict, cfg: ModelConfig):
    """The bundle names the robot it drives: that env must exist and fit the model. Returns
    the team, for its wiring."""
    env_id, train = payload["config"]["env"]["id"], payload["config"]["train"]
    try:
        team = envs.make_team(env_id, train.get("faults") or {}, **(train.get("env_options") or {}))
    except (ValueError, TypeError) as error:
        raise ExportError(
            f"the checkpoint was trained on env {env_id!r}, which cannot be made here ({error}); "
            "no bundle written"
        ) from None
    if (team.obs_dim, team.action_size) != (cfg.obs_dim, cfg.action_size):
        raise ExportError(
            f"env {env_id} gives observations of size {team.obs_dim} and actions of size "
            f"{team.action_size}, but the checkpoint's model takes {cfg.obs_dim} and "
            f"{cfg.action_size}; no bundle written"
        )
    return team


def _rebuild(payload: dict) -> tuple[Any, ObsNormalizer, ValueScale]:
    cfg = ModelConfig.from_dict(payload["config"]["model"])
    policy = build_policy(cfg)
    checkpoint.load_weights(policy, payload["model"], "the checkpoint")
    policy.eval()
    norm = payload["obs_norm"] if payload["config"]["train"]["normalize_obs"] else None
    normalizer = ObsNormalizer(
        None if norm is None else norm["mean"], None if norm is None else norm["var"], cfg.obs_dim
    )
    value_norm = ValueNorm()
    value_norm.load_state_dict(payload["value_norm"])
    mean, var = value_norm.mean_var()
    return policy, normalizer.eval(), ValueScale(float(mean), float(var.sqrt())).eval()


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
    batch, n = 3, cfg.n_agents if cfg.algo == "mappo" else 5  # trace with sizes >= 2
    obs = torch.randn(batch, n, cfg.obs_dim)
    agents_dim = {} if cfg.algo == "mappo" else {1: dims["agents"]}
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
        [torch.ones(batch, 1 if isinstance(policy, MAT) else n, cfg.action_size)]
        if discrete
        else []
    )
    if isinstance(policy, MAT):
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
        with warnings.catch_warnings(), torch.no_grad():
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


def _finish_graph(path: Path, manifest: dict) -> None:
    """Self-describing metadata, full checker, standard ops only; saved deterministically."""
    model = onnx.load(str(path))
    del model.metadata_props[:]
    for key, value in manifest.items():  # every field; the hashes cannot describe themselves
        entry = model.metadata_props.add()
        entry.key, entry.value = key, json.dumps(value)
    model.producer_name, model.producer_version = "mat-sdk", str(manifest["version"])
    onnx.checker.check_model(model, full_check=True)
    foreign = {node.domain for node in model.graph.node} - set(STANDARD_DOMAINS)
    if foreign:
        raise ExportError(f"{path.name} uses non-standard op domains {sorted(foreign)}")
    path.write_bytes(model.SerializeToString(deterministic=True))


def _manifest(payload, cfg: ModelConfig, graphs, checkpoint_path) -> dict:
    env, train = payload["config"]["env"], payload["config"]["train"]
    token = cfg.action_size + 1 if cfg.action_type == "discrete" else cfg.action_size
    return {
        "format": FORMAT,
        "version": VERSION,
        "algo": cfg.algo,
        "kind": "autoregressive" if cfg.algo == "mat" else "decentralised",
        "obs_dim": cfg.obs_dim,
        "action": {
            "type": cfg.action_type,
            "size": cfg.action_size,
            "low": env.get("action_low", -1.0),
            "high": env.get("action_high", 1.0),
            "token_size": token,
        },
        "model": {
            "n_embd": cfg.n_embd,
            "n_head": cfg.n_head,
            "n_block": cfg.n_block,
            "attention_window": cfg.attention_window,
        },
        "opset": OPSET,
        "agents": {
            "min": cfg.n_agents if cfg.algo == "mappo" else 1,
            "max": cfg.n_agents if cfg.algo == "mappo" else None,
            "trained": cfg.n_agents,
            "trained_counts": env.get("counts") or [cfg.n_agents],  # every count trained on
            "names": env.get("agents"),
        },
        "env_id": env.get("id"),  # with the faults and options the policy was trained under
        "env_faults": dict(train.get("faults") or {}),
        "env_options": dict(train.get("env_options") or {}),
        "caches": [{"past": p, "present": q} for p, q in cache_names(cfg.n_block)]
        if cfg.algo == "mat"
        else [],
        "checkpoint": {
            "sha256": _sha256(Path(checkpoint_path)),
            "steps": payload["progress"]["steps"],
        },
        "graphs": {name: io for name, io in graphs.items()},
    }


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def measure_parity(
    policy, normalizer, value_scale, directory: Path, counts, bounds=(-1.0, 1.0)
) -> dict:
    """Max |ORT - torch| per agent count: values, teacher-forced and autoregressive decoding
    (`decode*.onnx`: also sampled and clipped actions)."""
    from mat_runtime.policy import session  # the runtime's own session settings

    encoder = session((directory / "encoder.onnx").read_bytes())
    step = session((directory / "decoder_step.onnx").read_bytes())
    decoders = {None: session((directory / "decode.onnx").read_bytes())}
    for path in directory.glob("decode_n*.onnx"):  # specialised to one agent count
        decoders[int(path.stem.removeprefix("decode_n"))] = session(path.read_bytes())
    cfg, rng = policy.cfg, np.random.default_rng(0)
    counts = sorted({*counts, *(n for n in decoders if n is not None)})
    result: dict[str, float] = {}
    for n in counts:
        obs = (2.0 * rng.standard_normal((2, n, cfg.obs_dim))).astype(np.float32)
        with torch.no_grad():
            x = normalizer(torch.from_numpy(obs))
            actions, _, values = policy.act(x, deterministic=True)
            params, _ = policy.action_params(x, actions)
            torch_values = value_scale(values).numpy()
        rep, ort_values = encoder.run(None, {"obs": obs})
        forced = decode_with_ort(policy, step, rep, actions.numpy())
        free = decode_with_ort(policy, step, rep, None)
        diffs = [
            _value_diff(ort_values, torch_values),
            np.abs(forced["params"] - params.numpy()).max(),
            np.abs(free["params"] - params.numpy()).max(),
        ]
        noise = rng.standard_normal((2, n, cfg.action_size)).astype(np.float32)
        if cfg.action_type == "discrete":
            noise = -np.log(-np.log(rng.uniform(1e-9, 1.0, noise.shape))).astype(np.float32)
        sampled, sampled_params = torch_decode(policy, x, torch.from_numpy(noise))
        pairs = [(free["actions"], actions.numpy())]
        runs = [
            (decode, given, expected)
            for count, decode in decoders.items()
            if count in (None, n)
            for given, expected in (
                (np.zeros_like(noise), (actions.numpy(), params.numpy())),
                (noise, (sampled.numpy(), sampled_params.numpy())),
            )
        ]
        for decode, given, (expected, expected_params) in runs:
            feed = {"obs": obs, "noise": given}
            if cfg.action_type == "discrete":
                feed["available"] = np.ones_like(noise)
            got = dict(
                zip([o.name for o in decode.get_outputs()], decode.run(None, feed), strict=True)
            )
            diffs.append(
                np.abs(
                    got["logits" if cfg.action_type == "discrete" else "mean"] - expected_params
                ).max()
            )
            diffs.append(_value_diff(got["values"], torch_values))
            pairs.append((got["actions"], expected))
            if cfg.action_type == "continuous":
                pairs.append((got["clipped_actions"], np.clip(expected, *bounds)))
        for got, expected in pairs:
            if cfg.action_type == "continuous":
                diffs.append(np.abs(got - expected).max())
            elif not np.array_equal(got, expected):
                diffs.append(float("inf"))  # a different discrete choice
        result[str(n)] = float(max(diffs))
    return {
        "max_abs_diff": result,
        "limit": PARITY_LIMIT,
        "agent_counts": list(counts),
        "measures": "actions and distribution parameters: absolute; values (return units): "
        "relative to max(1, |value|), as float32 cannot hold large returns to 1e-5",
    }


def _value_diff(got: np.ndarray, expected: np.ndarray) -> float:
    return float(np.abs(got - expected).max() / max(1.0, float(np.abs(expected).max())))


def torch_decode(policy, x: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The torch policy sampling with given noise, as `decode.onnx` does: (actions, params)."""
    discrete = policy.cfg.action_type == "discrete"

    def sample(i: int | None, params: torch.Tensor) -> torch.Tensor:
        agent_noise = noise if i is None else noise[:, i : i + 1]
        if discrete:
            return (params + agent_noise).argmax(-1, keepdim=True).float()
        return params + policy.std() * agent_noise

    with torch.no_grad():
        if not isinstance(policy, MAT):
            params = policy.actor(x)
            return sample(None, params), params
        return policy.decode(policy.encoder(x)[0], sample)


def decode_with_ort(policy, step, rep: np.ndarray, forced_actions: np.ndarray | None) -> dict:
    """Deterministic decode with the step graph; `forced_actions` feeds given actions instead."""
    cfg = policy.cfg
    discrete = cfg.action_type == "discrete"
    batch, n = rep.shape[:2]
    if not isinstance(policy, MAT):
        feed = {"rep": rep}
        if discrete:
            feed["available"] = np.ones((batch, n, cfg.action_size), np.float32)
        params = step.run(None, feed)[0]
        actions = params.argmax(-1)[..., None].astype(np.float32) if discrete else params
        return {"params": params, "actions": actions}
    head_dim = cfg.n_embd // cfg.n_head
    names = cache_names(cfg.n_block)
    past = {p: np.zeros((batch, cfg.n_head, 0, head_dim), np.float32) for p, _ in names}
    token = policy.start_token(batch).numpy()
    all_params, all_actions = [], []
    for i in range(n):
        feed = {"rep": rep[:, i : i + 1], "token": token, **past}
        if discrete:
            feed["available"] = np.ones((batch, 1, cfg.action_size), np.float32)
        out = step.run(None, feed)
        params = out[0]
        past = {p: value for (p, _), value in zip(names, out[-len(names) :], strict=True)}
        action = params.argmax(-1)[..., None].astype(np.float32) if discrete else params
        chosen = action if forced_actions is None else forced_actions[:, i : i + 1]
        all_params.append(params)
        all_actions.append(action)
        token = policy.action_token(torch.from_numpy(chosen.astype(np.float32))).numpy()
    return {"params": np.concatenate(all_params, 1), "actions": np.concatenate(all_actions, 1)}
