"""`StepPolicy`: a MAT bundle decoded agent by agent, through `encoder.onnx` and the KV-cached
`decoder_step.onnx`, with numpy and onnxruntime only.

    policy = Policy.load("cheetah_onnx", graph="step")    # or StepPolicy.load(...)
    actions = policy.act(obs)                             # equal to Policy.load(...).act(obs)
    for agent, action in policy.stream(obs):              # each agent's action as decoded
        send(agent, action)

This is the bundle's contract for anyone driving the decode step by step: the encoder once,
then one decoder step per agent, each agent's token (its predecessor's action as drawn: the
action itself, or a one-hot after a start slot for discrete choices) and the growing caches
`past_key_values.{block}.{attn}.{key,value}` -> `present...` fed back. A controller that
must act on the first agents before the last are decoded streams them; `decode.onnx`
(`Policy`) does the whole step in one call and is faster. Sampling draws the same noise as
`Policy.act` for the same seed, so both give the same actions.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from mat_runtime.bundle import read_bundle
from mat_runtime.errors import BundleError, InputError
from mat_runtime.policy import Policy, _deliver, _open_session

STEP_GRAPHS = ("encoder.onnx", "decoder_step.onnx")


class StepPolicy(Policy):
    """A loaded MAT bundle that decodes agent by agent (module docstring); the same input
    rules, checks and outputs as `Policy`."""

    def __init__(self, path: Path, manifest: dict[str, Any], encoder, step):
        super().__init__(path, manifest, {})
        self._encoder, self._step = encoder, step
        self._caches = [(c["past"], c["present"]) for c in manifest["caches"]]
        self._head_dim = manifest["model"]["n_embd"] // manifest["model"]["n_head"]
        self._heads = manifest["model"]["n_head"]
        self._token_size = manifest["action"].get("token_size", self.action_size)

    @classmethod
    def load(
        cls,
        path: str | Path,
        threads: int = 1,
        providers: list[str] | None = None,
        spin: bool = False,
        graph: str = "step",
    ) -> StepPolicy:
        """Verify the bundle and open its encoder and decoder-step graphs."""
        bundle = read_bundle(path, lambda manifest: list(STEP_GRAPHS))
        manifest = bundle.manifest
        if manifest.get("kind") != "autoregressive" or not manifest.get("caches"):
            raise BundleError(
                f"{bundle.path}: a {manifest['algo']} bundle's step graph acts for every agent "
                "at once; decoding agent by agent is for MAT bundles (use Policy.load)"
            )
        opened = [
            _open_session(bundle.path / name, manifest["graphs"][name]["opset"],
                          bundle.graphs[name], threads, providers, False, spin)
            for name in STEP_GRAPHS
        ]  # fmt: skip
        return cls(bundle.path, manifest, *opened)

    def act(
        self,
        obs,
        available=None,
        *,
        deterministic: bool = True,
        seed: int | np.random.Generator | None = None,
        return_values: bool = False,
        clip: bool = True,
        out: np.ndarray | None = None,
        out_extra: dict[str, np.ndarray] | None = None,
    ):
        """As `Policy.act`, decoded agent by agent (`out` and `out_extra` are written into)."""
        x = self._check_obs(obs)
        single = x.ndim == 2
        batch = x[None] if single else x
        decoded = list(self._decode(batch, available, deterministic, seed, clip))
        actions = np.stack([action for _, action, _ in decoded], axis=1)
        params = {
            key: np.concatenate([p[key] for _, _, p in decoded], axis=1) for key in decoded[0][2]
        }
        if self.discrete:
            actions = actions[..., 0]
        if single:
            actions, params = actions[0], {k: v[0] for k, v in params.items()}
        actions = _into(actions, out, "out", np.int64 if self.discrete else np.float32)
        if not return_values:
            return actions
        given = out_extra or {}
        return actions, {key: _into(value, given.get(key), f"out_extra[{key!r}]", np.float32)
                         for key, value in params.items()}  # fmt: skip

    def stream(
        self,
        obs,
        available=None,
        *,
        deterministic: bool = True,
        seed: int | np.random.Generator | None = None,
        clip: bool = True,
    ) -> Iterator[tuple[int, np.ndarray]]:
        """(agent, its action) for each agent in order, as soon as it is decoded: `[..,
        action_size]` floats or `[..]` int64 choices (`..`: B when obs has a batch)."""
        x = self._check_obs(obs)
        single = x.ndim == 2
        for agent, action, _ in self._decode(x[None] if single else x, available,
                                             deterministic, seed, clip):  # fmt: skip
            action = action[..., 0].astype(np.int64) if self.discrete else action
            yield agent, action[0] if single else action

    def _decode(self, obs: np.ndarray, available, deterministic, seed, clip):
        """(agent, action [B, A or 1], its outputs) per agent; obs [B, n, obs_dim]."""
        batch, n = obs.shape[:2]
        obs32 = np.asarray(obs, dtype=np.float32)
        if not np.isfinite(obs32).all():
            self._check_finite(obs32, None, False)
        noise = np.zeros((batch, n, self.action_size), np.float32)
        self._fill_noise(noise, deterministic, seed)
        mask = None
        if self.discrete:
            mask = np.zeros((batch, n, self.action_size), np.float32)
            self._fill_available(mask, None if available is None else _batched(available, obs))
        elif available is not None:
            raise InputError("`available` is for discrete policies; this one is continuous")
        rep, values = self._encoder.run(None, {"obs": obs32})
        bounds = (self._low, self._high) if clip else None
        layout = (self._caches, self._heads, self._head_dim, self._token_size)
        for agent, action, params in decode_agents(
            self._step, layout, rep, noise, mask, bounds=bounds
        ):
            params["values"] = values[:, agent : agent + 1, 0]
            yield agent, action, params


def decode_agents(step, layout, rep: np.ndarray, noise: np.ndarray, available=None, *,
                  forced: np.ndarray | None = None, bounds=None):  # fmt: skip
    """Drive `decoder_step.onnx` (session `step`) over the agents of `rep` [B, n, embd]:
    (agent, action [B, A or 1], its distribution's outputs) in order. `layout`: the caches'
    (past, present) names, heads, head size and token size; `noise` [B, n, A] (zero: the
    mean or argmax; Gaussian or Gumbel: a sample); `available` [B, n, A] for discrete
    choices; `forced` [B, n, A or 1]: condition each next agent on these actions instead of
    the ones decoded (teacher forcing); `bounds`: clip continuous actions to (low, high).
    The agent-by-agent reference that the runtime's step path and the exporter's parity use."""
    caches, heads, head_dim, token_size = layout
    batch, n = rep.shape[:2]
    discrete = available is not None
    past = {name: np.zeros((batch, heads, 0, head_dim), np.float32) for name, _ in caches}
    token = np.zeros((batch, 1, token_size), np.float32)
    if discrete:
        token[:, 0, 0] = 1.0  # the start slot
    for agent in range(n):
        feed = {"rep": np.ascontiguousarray(rep[:, agent : agent + 1]), "token": token, **past}
        if discrete:
            feed["available"] = np.ascontiguousarray(available[:, agent : agent + 1])
        outputs = step.run(None, feed)
        head = outputs[: -len(caches)]
        past = {name: value for (name, _), value in
                zip(caches, outputs[-len(caches):], strict=True)}  # fmt: skip
        drawn = noise[:, agent : agent + 1]
        if discrete:
            logits = head[0]
            choice = (logits + drawn).argmax(-1)
            action = choice[..., None].astype(np.float32)
            params = {"logits": logits}
        else:
            mean, std = head
            action = mean + std * drawn
            params = {"mean": mean, "std": std}
        given = action if forced is None else forced[:, agent : agent + 1]
        if discrete:
            token = np.zeros_like(token)
            token[np.arange(batch), 0, given[:, 0, 0].astype(np.int64) + 1] = 1.0
        else:
            token = np.ascontiguousarray(given, dtype=np.float32)
        if bounds is not None and not discrete:
            action = np.clip(action, *bounds)
        yield agent, action[:, 0], params


def _batched(available, obs: np.ndarray) -> np.ndarray:
    mask = np.asarray(available)
    return mask[None] if mask.ndim == obs.ndim - 1 else mask


def _into(value: np.ndarray, out: np.ndarray | None, name: str, dtype) -> np.ndarray:
    """`value` as `dtype`, or written into the caller's `out` (checked as `Policy.act` does)."""
    return _deliver(np.ascontiguousarray(value), out, name, dtype)
