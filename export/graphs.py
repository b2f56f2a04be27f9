"""The torch modules that become the bundle's ONNX graphs.

They wrap a trained policy with what the runtime must not have to know: the observation
normaliser (folded into the encoder) and ValueNorm (values come out in return units).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from mat_sdk.policy.model import MAT, UNAVAILABLE_LOGIT, PolicyNetwork
from mat_sdk.policy.normalization import RunningMeanStd


def cache_names(n_block: int) -> list[tuple[str, str]]:
    """(past input, present output) names of every cache, Hugging Face Optimum style."""
    names = []
    for block in range(n_block):
        for attn in ("attn1", "attn2"):
            for part in ("key", "value"):
                names.append(
                    (f"past_key_values.{block}.{attn}.{part}", f"present.{block}.{attn}.{part}")
                )
    return names


class ObsNormalizer(nn.Module):
    """The training normaliser (`RunningMeanStd`, or none) as graph operations."""

    def __init__(self, running: RunningMeanStd | None, obs_dim: int):
        super().__init__()
        mean = torch.zeros(obs_dim) if running is None else torch.from_numpy(running.mean).float()
        scale = (
            torch.ones(obs_dim) if running is None else torch.from_numpy(running.scale()).float()
        )
        self.register_buffer("mean", mean)
        self.register_buffer("scale", scale)
        self.clip = None if running is None else running.clip

    def forward(self, obs: Tensor) -> Tensor:
        x = (obs - self.mean) * self.scale
        return x.clamp(-self.clip, self.clip) if self.clip is not None else x


class ValueScale(nn.Module):
    """ValueNorm's de-normalisation: value * std + mean."""

    def __init__(self, mean: float, std: float):
        super().__init__()
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32))

    def forward(self, values: Tensor) -> Tensor:
        return values * self.std + self.mean


class EncoderGraph(nn.Module):
    """obs [B, n, obs_dim] -> rep [B, n, C] (MAT) or normalised obs (decentralised), values."""

    def __init__(self, policy: PolicyNetwork, normalizer: ObsNormalizer, value_scale: ValueScale):
        super().__init__()
        self.policy, self.normalizer, self.value_scale = policy, normalizer, value_scale

    def forward(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        x = self.normalizer(obs)
        if self.policy.cfg.algorithm.autoregressive:
            rep, values = self.policy.encoder(x)
        else:
            rep, values = x, self.policy.values(x)
        return rep, self.value_scale(values)


class MATStepGraph(nn.Module):
    """One agent's decoder step with KV caches: (rep, token, past...) -> (params, present...)."""

    def __init__(self, policy: MAT):
        super().__init__()
        self.policy = policy
        self.discrete = policy.cfg.action_type == "discrete"

    def forward(self, rep: Tensor, token: Tensor, *past_and_mask: Tensor):
        n_cache = 4 * self.policy.cfg.n_block
        past, mask = past_and_mask[:n_cache], past_and_mask[n_cache:]
        blocks = [
            ((past[i], past[i + 1]), (past[i + 2], past[i + 3])) for i in range(0, n_cache, 4)
        ]
        params, present = self.policy.decode_step(token, rep, blocks)
        flat = [t for kv in present for pair in kv for t in pair]
        return (*self._head(params, mask), *flat)

    def _head(self, params: Tensor, mask: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
        if self.discrete:
            return (params.masked_fill(mask[0] == 0, UNAVAILABLE_LOGIT),)
        return params, self.policy.std().expand_as(params)


class DecentralisedStepGraph(nn.Module):
    """MAT-Dec / MAPPO: every agent's action parameters at once from normalised obs; no cache."""

    def __init__(self, policy: PolicyNetwork):
        super().__init__()
        self.policy = policy
        self.discrete = policy.cfg.action_type == "discrete"

    def forward(self, obs: Tensor, *mask: Tensor):
        params = self.policy.actor(obs)
        if self.discrete:
            return (params.masked_fill(mask[0] == 0, UNAVAILABLE_LOGIT),)
        return params, self.policy.std().expand_as(params)
