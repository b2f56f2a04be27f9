"""The bundle's manifest, and the metadata each graph carries of it."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import onnx

from mat_export.errors import ExportError
from mat_export.graphs import cache_names
from mat_sdk.envs.core.faults import as_mapping
from mat_sdk.policy import checkpoint
from mat_sdk.policy.model import ModelConfig

FORMAT = "mat-onnx"
VERSION = 1
STANDARD_DOMAINS = ("", "ai.onnx")
NORMALIZER_PLACE = (
    "inside the graphs: they take raw observations, normalise them with the training "
    "statistics and clip them"
)


def finish_graph(path: Path, manifest: dict) -> None:
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


def manifest(payload, cfg: ModelConfig, graphs, checkpoint_path) -> dict:
    env, train = payload["config"]["env"], checkpoint.recorded_config(payload)
    token = cfg.action_size + 1 if cfg.action_type == "discrete" else cfg.action_size
    return {
        "format": FORMAT,
        "version": VERSION,
        "algo": cfg.algo,
        "kind": cfg.algorithm.bundle_kind,
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
        "agents": {
            "min": cfg.n_agents if cfg.fixed_team else 1,
            "max": cfg.n_agents if cfg.fixed_team else None,
            "trained": cfg.n_agents,
            "trained_counts": env.get("counts") or [cfg.n_agents],  # every count trained on
            "names": env.get("agents"),
        },
        "env_id": train.env.id,  # with the faults and options the policy was trained under
        "env_faults": as_mapping(train.env.faults),
        "env_options": dict(train.env.options),
        "randomization": env.get("randomization"),  # null: trained without
        "caches": [{"past": p, "present": q} for p, q in cache_names(cfg.n_block)]
        if cfg.algorithm.autoregressive
        else [],
        "checkpoint": {
            "sha256": sha256(Path(checkpoint_path)),
            "steps": payload["progress"]["steps"],
        },
        "graphs": {name: io for name, io in graphs.items()},
    }


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
