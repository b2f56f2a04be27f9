"""PPO pieces, as the official MAT code computes them (with its known bugs fixed).

- GAE per agent on the shared team reward, on de-normalised values. Unlike the official code
  we bootstrap at truncation (the episode time limit) with the value of the final
  observation; only a real termination cuts the return.
- Continuous actions keep log-probs per action dimension: the ratio is per agent and per
  dimension, clipped surrogates are summed over dimensions, then averaged.
- Value loss: clipped by the same clip parameter, Huber (delta 10), max of clipped and
  unclipped. The official Huber is one-sided (a bug inherited from MAPPO); ours is the real one.
- Masks, where an env has them (PettingZoo envs): rows of agents that left the episode
  (`active` 0) weigh nothing in any term, as the official code's active masks; padded
  action dimensions (`action_dims` 0) are left out of the ratio, the surrogate and the
  entropy, so they get exactly zero gradient.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, fields, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from mat_sdk.policy.model import PolicyNetwork, in_agent_order


@dataclass(frozen=True)
class Rows:
    """An update's samples, one row per env step (`Trajectory.rows`): what the PPO and HAPPO
    losses read. Each tensor is [rows, n, ...]; the masks are None where the envs have none."""

    obs: Tensor
    actions: Tensor
    log_probs: Tensor
    values: Tensor
    advantages: Tensor  # normalised over the update
    returns: Tensor
    order: Tensor | None = None  # the agent order each row acted in (`shuffle_agents`)
    active: Tensor | None = None  # 1 for an agent in its episode, 0 after it left
    available: Tensor | None = None  # discrete: the choices each agent may take
    action_dims: Tensor | None = None  # 1 for an agent's real action dimensions, 0 padding

    def __len__(self) -> int:
        return self.obs.shape[0]

    def __getitem__(self, idx: Tensor) -> Rows:
        """The rows `idx` of every tensor: a minibatch."""
        return replace(self, **{name: tensor[idx] for name, tensor in self.tensors().items()})

    def tensors(self) -> dict[str, Tensor]:
        """Every tensor present, by name."""
        present = ((f.name, getattr(self, f.name)) for f in fields(self))
        return {name: tensor for name, tensor in present if tensor is not None}


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
    # The KL divergence from the rollout's policy, per agent (summed over its action
    # dimensions), estimated from the log-ratios: (r - 1) - log r, unbiased and >= 0.
    kl: Tensor


def minibatches(
    size: int,
    epochs: int,
    count: int,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
) -> Iterator[Tensor]:
    """An update's minibatches of row indices: `epochs` shuffles of `size` rows, each cut into
    `count` equal parts (the remainder of `size // count` is left out of that epoch).

    Shuffled on the CPU from `generator` (the trainer's stream, so a resume is exact) whatever
    the device the indices are used on."""
    per_minibatch = size // count
    for _ in range(epochs):
        order = torch.randperm(size, generator=generator).to(device)
        for k in range(count):
            yield order[k * per_minibatch : (k + 1) * per_minibatch]


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
    active: Tensor | None = None,
    action_dims: Tensor | None = None,
) -> LossTerms:
    """Shapes: log-probs/entropy [B, n, A], advantages/values/returns [B, n, 1] (normalised);
    the masks `active` [B, n, 1] and `action_dims` [B, n, A] (None: everything counts)."""
    log_ratio = log_prob - old_log_prob
    if action_dims is not None:  # where, not a product: no inf * 0 in the backward pass
        log_ratio = torch.where(action_dims > 0, log_ratio, torch.zeros_like(log_ratio))
    ratio = torch.exp(log_ratio)
    surrogate = torch.min(ratio * advantages, ratio.clamp(1 - clip, 1 + clip) * advantages)
    clipped = ((ratio - 1).abs() > clip).float()
    if action_dims is not None:
        surrogate = surrogate * action_dims
    policy_loss = -masked_mean(surrogate.sum(-1, keepdim=True), active)
    value = value_loss(values, old_values, returns, clip, huber_delta, active)
    counted = counted_entries(active, action_dims)
    entropy = masked_mean(entropy, counted)
    clip_fraction = masked_mean(clipped, counted)
    kl = masked_mean(((ratio - 1) - log_ratio).detach().sum(-1, keepdim=True), active)
    total = policy_loss - entropy_coef * entropy + value_coef * value
    return LossTerms(total, policy_loss, value, entropy, clip_fraction, kl)


def value_loss(
    values: Tensor,
    old_values: Tensor,
    returns: Tensor,
    clip: float,
    huber_delta: float,
    active: Tensor | None = None,
) -> Tensor:
    """The official value loss: Huber, the max of clipped and unclipped, over active rows."""
    clipped_values = old_values + (values - old_values).clamp(-clip, clip)
    return masked_mean(
        torch.max(
            F.huber_loss(values, returns, reduction="none", delta=huber_delta),
            F.huber_loss(clipped_values, returns, reduction="none", delta=huber_delta),
        ),
        active,
    )


def masked_mean(x: Tensor, weights: Tensor | None) -> Tensor:
    """The mean of `x` over the entries that `weights` (0 or 1) keep; None: over all."""
    if weights is None:
        return x.mean()
    weights = weights.expand_as(x)
    return (x * weights).sum() / weights.sum().clamp_min(1.0)


def counted_entries(active: Tensor | None, action_dims: Tensor | None) -> Tensor | None:
    """The weights of the entries that count: active agents' real action dimensions."""
    if active is None:
        return action_dims
    return active if action_dims is None else active * action_dims


@dataclass(frozen=True)
class LossCoefficients:
    """The numbers the PPO loss uses (`PPOConfig` fields of the same names)."""

    clip: float
    entropy_coef: float
    value_coef: float
    huber_delta: float

    @classmethod
    def of(cls, config) -> LossCoefficients:
        """The coefficients of anything with these fields, e.g. a `PPOConfig`."""
        return cls(config.clip, config.entropy_coef, config.value_coef, config.huber_delta)


def minibatch_loss(
    policy: PolicyNetwork, mb: Rows, targets: Tensor, coefficients: LossCoefficients
) -> LossTerms:
    """The PPO loss terms of one minibatch; `targets` are its normalised returns.

    Agents are evaluated in the order they acted in (`mb.order`, where the rollout shuffled
    them); the results come back in canonical order.
    """
    inputs = [mb.obs, mb.actions]
    if mb.available is not None:
        inputs.append(mb.available)
    log_prob, entropy, values = in_agent_order(mb.order, policy.evaluate_actions, *inputs)
    return ppo_loss(
        log_prob,
        mb.log_probs,
        mb.advantages,
        entropy,
        values,
        mb.values,
        targets,
        coefficients.clip,
        coefficients.entropy_coef,
        coefficients.value_coef,
        coefficients.huber_delta,
        mb.active,
        mb.action_dims,
    )
