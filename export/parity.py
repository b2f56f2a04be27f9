"""ONNX Runtime held to torch: what the exporter measures before it writes a bundle."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from mat_export.graphs import cache_names
from mat_runtime.step import decode_agents

PARITY_LIMIT = 1e-4
AGENT_COUNTS = (1, 2, 6, 17, 64)


def measure_parity(
    policy, obs_norm, value_scale, directory: Path, counts, bounds=(-1.0, 1.0)
) -> dict:
    """Max |ORT - torch| per agent count: values, teacher-forced and autoregressive decoding
    (`decode*.onnx`: also sampled and clipped actions). The torch side normalises with the
    training normaliser itself (`obs_norm`, a `RunningMeanStd`, or None for raw
    observations), so a graph that drifted from training would show here."""
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
            x = torch.from_numpy(obs if obs_norm is None else obs_norm.normalize(obs))
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
        if not policy.cfg.algorithm.autoregressive:
            params = policy.actor(x)
            return sample(None, params), params
        return policy.decode(policy.encoder(x)[0], sample)


def decode_with_ort(policy, step, rep: np.ndarray, forced_actions: np.ndarray | None) -> dict:
    """Deterministic decode with the step graph (the runtime's own `decode_agents` for MAT);
    `forced_actions` conditions each agent on given actions instead."""
    cfg = policy.cfg
    discrete = cfg.action_type == "discrete"
    batch, n = rep.shape[:2]
    available = np.ones((batch, n, cfg.action_size), np.float32) if discrete else None
    if not cfg.algorithm.autoregressive:
        feed = {"rep": rep, **({"available": available} if discrete else {})}
        params = step.run(None, feed)[0]
        actions = params.argmax(-1)[..., None].astype(np.float32) if discrete else params
        return {"params": params, "actions": actions}
    layout = (cache_names(cfg.n_block), cfg.n_head, cfg.n_embd // cfg.n_head,
              policy.decoder.token_dim)  # fmt: skip
    noise = np.zeros((batch, n, cfg.action_size), np.float32)
    decoded = list(decode_agents(step, layout, rep, noise, available, forced=forced_actions))
    key = "logits" if discrete else "mean"
    return {
        "params": np.concatenate([params[key] for _, _, params in decoded], axis=1),
        "actions": np.stack([action for _, action, _ in decoded], axis=1),
    }
