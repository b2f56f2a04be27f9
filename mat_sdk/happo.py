"""HAPPO's update (Kuba et al., ICLR 2022, as HARL implements it): the critic as MAPPO's, then
the agents' actors one after another in a random order, each on its own minibatches.

Agent i_m's surrogate weighs the advantage by the product of the probability ratios of the
agents updated before it, new over old policy, on the same samples (`factor`): it improves
the team's advantage given what those agents now do, not as if they had stayed put (the
paper's sequential update, with its monotonic improvement guarantee). Each agent's ratio is
the product over its action dimensions (HARL's "prod" aggregation), clipped as one.

Each agent's actor and the critic are groups of the flat Adam; an agent steps its own group
alone (`FlatParameters.only`), as with HARL's optimizer per agent.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from mat_sdk import ppo
from mat_sdk.flat_params import FlatParameters
from mat_sdk.model import HAPPO
from mat_sdk.normalization import ValueNorm
from mat_sdk.ppo import counted_entries, masked_mean, value_loss

if TYPE_CHECKING:
    from mat_sdk.config import TrainConfig


def update(
    policy: HAPPO,
    params: FlatParameters,
    optimizer: torch.optim.Optimizer,
    value_norm: ValueNorm,
    rows: dict[str, Tensor],
    config: TrainConfig,
    generator: torch.Generator,
) -> tuple[dict[str, float], bool]:
    """One HAPPO update on the rollout's `rows` (`Trajectory.rows`): its mean loss terms, and
    whether every loss was finite."""
    critic = [policy.cfg.n_agents]  # the critic's group comes after the actors'
    size, device = rows["obs"].shape[0], rows["obs"].device
    sums = dict.fromkeys(("policy_loss", "value_loss", "entropy", "clip_fraction"), 0.0)
    norms: list[Tensor] = []
    finite = torch.ones((), dtype=torch.bool, device=device)

    def minibatches():
        return ppo.minibatches(size, config.ppo_epochs, config.num_minibatches, generator, device)

    def step(loss: Tensor, groups: list[int]) -> None:
        nonlocal finite
        finite = finite & torch.isfinite(loss)
        params.zero_grad()
        loss.backward()
        norms.append(params.clip_grad_norm_(config.max_grad_norm, groups))
        with params.only(groups):
            optimizer.step()

    for idx in minibatches():
        returns = rows["returns"][idx]
        value_norm.update(returns)
        active = rows["active"][idx] if "active" in rows else None
        loss = value_loss(
            policy.values(rows["obs"][idx]), rows["values"][idx],
            value_norm.normalize(returns), config.clip, config.huber_delta, active,
        )  # fmt: skip
        step(config.value_coef * loss, critic)
        sums["value_loss"] += float(loss.detach()) / (config.ppo_epochs * config.num_minibatches)

    factor = torch.ones(size, 1, device=device)
    agents = torch.randperm(policy.cfg.n_agents, generator=generator).tolist()
    actor_steps = len(agents) * config.ppo_epochs * config.num_minibatches
    for agent in agents:
        for idx in minibatches():
            active = rows["active"][idx, agent] if "active" in rows else None
            log_ratio, entropy = _agent_terms(policy, agent, rows, idx, active)
            ratio = torch.exp(log_ratio)
            advantages = factor[idx] * rows["advantages"][idx, agent]
            surrogate = torch.min(
                ratio * advantages, ratio.clamp(1 - config.clip, 1 + config.clip) * advantages
            )
            policy_loss = -masked_mean(surrogate, active)
            step(policy_loss - config.entropy_coef * entropy, [agent])
            clipped = ((ratio - 1).abs() > config.clip).float()
            for key, value in (
                ("policy_loss", policy_loss),
                ("entropy", entropy),
                ("clip_fraction", masked_mean(clipped, active)),
            ):
                sums[key] += float(value.detach()) / actor_steps
        with torch.no_grad():  # this agent's new policy weighs the next agents' advantages
            log_ratio, _ = _agent_terms(policy, agent, rows, slice(None), None)
            factor = factor * torch.exp(log_ratio)
    metrics = {**sums, "grad_norm": float(torch.stack(norms).mean())}
    return metrics, bool(finite)


def _agent_terms(
    policy: HAPPO, agent: int, rows: dict[str, Tensor], idx, active: Tensor | None
) -> tuple[Tensor, Tensor]:
    """The agent's log(new / old probability) of its whole action [B, 1] (summed over its
    dimensions, padded ones left out) and its mean entropy over the counted entries."""
    available = rows["available"][idx] if "available" in rows else None
    log_prob, entropy = policy.agent_log_prob(
        agent, rows["obs"][idx], rows["actions"][idx], available
    )
    difference = log_prob - rows["log_probs"][idx, agent]
    dims = rows["action_dims"][idx, agent] if "action_dims" in rows else None
    if dims is not None:
        difference = torch.where(dims > 0, difference, torch.zeros_like(difference))
    return difference.sum(-1, keepdim=True), masked_mean(entropy, counted_entries(active, dims))
