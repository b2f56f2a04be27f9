"""PPO pieces, as the official MAT code computes them (with its known bugs fixed).

- GAE per agent on the shared team reward, on de-normalised values. Unlike the official code
  we bootstrap at truncation (the episode time limit) with the value of the final
  observation; only a real termination cuts the return.
- Continuous actions keep log-probs per action dimension: the ratio is per agent and per
  dimension, clipped surrogates are summed over dimensions, then averaged.
- Value loss: clipped by the same clip parameter, Huber (delta 10), max of clipped and
  unclipped. The official Huber is one-sided (a bug inherited from MAPPO); ours is the real one.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from mat_sdk.model import Policy, in_agent_order


def gae(
    rewards: Tensor,
    values: Tensor,
    next_values: Tensor,
    terminated: Tensor,
    done: Tensor,
    gamma: float,
    lam: float,
) -> Tensor:
    """Advantages [T, E, n] from rewards [T, E, 1], values and next-state values [T, E, n].

    `next_values[t]` is V(s_{t+1}), or V(final observation) where the episode ended at t;
    `terminated` zeroes the bootstrap, `done` (terminated or truncated) stops the trace.
    """
    advantages = torch.zeros_like(values)
    running = torch.zeros_like(values[0])
    for t in reversed(range(values.shape[0])):
        delta = rewards[t] + gamma * next_values[t] * (1.0 - terminated[t]) - values[t]
        running = delta + gamma * lam * (1.0 - done[t]) * running
        advantages[t] = running
    return advantages


@dataclass
class LossTerms:
    total: Tensor
    policy: Tensor
    value: Tensor
    entropy: Tensor
    clip_fraction: Tensor


def ppo_loss(
    log_prob: Tensor,
    old_log_prob: Tensor,
    advantages: Tensor,
    entropy: Tensor,
    values: Tensor,
    old_values: Tensor,
    returns: Tensor,
    clip: float,
    entropy_coef: float,
    value_coef: float,
    huber_delta: float,
) -> LossTerms:
    """Shapes: log-probs/entropy [B, n, A], advantages/values/returns [B, n, 1] (normalised)."""
    ratio = torch.exp(log_prob - old_log_prob)
    surrogate = torch.min(ratio * advantages, ratio.clamp(1 - clip, 1 + clip) * advantages)
    policy_loss = -surrogate.sum(-1, keepdim=True).mean()
    clipped_values = old_values + (values - old_values).clamp(-clip, clip)
    value_loss = torch.max(
        F.huber_loss(values, returns, reduction="none", delta=huber_delta),
        F.huber_loss(clipped_values, returns, reduction="none", delta=huber_delta),
    ).mean()
    entropy = entropy.mean()
    total = policy_loss - entropy_coef * entropy + value_coef * value_loss
    clip_fraction = ((ratio - 1).abs() > clip).float().mean()
    return LossTerms(total, policy_loss, value_loss, entropy, clip_fraction)


@dataclass(frozen=True)
class LossCoefficients:
    """The numbers the PPO loss uses (`TrainConfig` fields of the same names)."""

    clip: float
    entropy_coef: float
    value_coef: float
    huber_delta: float

    @classmethod
    def of(cls, config) -> LossCoefficients:
        """The coefficients of anything with these fields, e.g. a `TrainConfig`."""
        return cls(config.clip, config.entropy_coef, config.value_coef, config.huber_delta)


def minibatch_loss(
    policy: Policy, mb: dict[str, Tensor], targets: Tensor, coefficients: LossCoefficients
) -> LossTerms:
    """The PPO loss terms of one minibatch; `targets` are its normalised returns.

    Agents are evaluated in the order they acted in (`mb["order"]`, where the rollout
    shuffled them); the results come back in canonical order.
    """
    log_prob, entropy, values = in_agent_order(
        mb.get("order"), policy.evaluate, mb["obs"], mb["actions"]
    )
    return ppo_loss(
        log_prob,
        mb["log_probs"],
        mb["advantages"],
        entropy,
        values,
        mb["values"],
        targets,
        coefficients.clip,
        coefficients.entropy_coef,
        coefficients.value_coef,
        coefficients.huber_delta,
    )
