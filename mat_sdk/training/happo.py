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

from mat_sdk.policy.model import HAPPO
from mat_sdk.policy.normalization import ValueNorm
from mat_sdk.training import ppo
from mat_sdk.training.flat_params import FlatParameters
from mat_sdk.training.ppo import Rows, counted_entries, masked_mean, value_loss

if TYPE_CHECKING:
    from mat_sdk.policy.config import PPOConfig


def update(
    policy: HAPPO,
    params: FlatParameters,
    optimizer: torch.optim.Optimizer,
    value_norm: ValueNorm,
    rows: Rows,
    config: PPOConfig,
    generator: torch.Generator,
) -> tuple[dict[str, float], bool]:
    """One HAPPO update on the rollout's `rows` (`Trajectory.rows`): its mean loss terms, and
    whether every loss was finite."""
    critic = [policy.cfg.n_agents]  # the critic's group comes after the actors'
    size, device = len(rows), rows.obs.device
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
        mb = rows[idx]
        value_norm.update(mb.returns)
        loss = value_loss(
            policy.values(mb.obs), mb.values,
            value_norm.normalize(mb.returns), config.clip, config.huber_delta, mb.active,
        )  # fmt: skip
        step(config.value_coef * loss, critic)
        sums["value_loss"] += float(loss.detach()) / (config.ppo_epochs * config.num_minibatches)

    factor = torch.ones(size, 1, device=device)
    agents = torch.randperm(policy.cfg.n_agents, generator=generator).tolist()
    actor_steps = len(agents) * config.ppo_epochs * config.num_minibatches
    for agent in agents:
        for idx in minibatches():
            mb = rows[idx]
            active = None if mb.active is None else mb.active[:, agent]
            log_ratio, entropy = _agent_terms(policy, agent, mb, active)
            ratio = torch.exp(log_ratio)
            advantages = factor[idx] * mb.advantages[:, agent]
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
            log_ratio, _ = _agent_terms(policy, agent, rows, None)
            factor = factor * torch.exp(log_ratio)
    metrics = {**sums, "grad_norm": float(torch.stack(norms).mean())}
    return metrics, bool(finite)


def _agent_terms(
    policy: HAPPO, agent: int, mb: Rows, active: Tensor | None
) -> tuple[Tensor, Tensor]:
    """The agent's log(new / old probability) of its whole action [B, 1] (summed over its
    dimensions, padded ones left out) and its mean entropy over the counted entries."""
    log_prob, entropy = policy.agent_log_prob(agent, mb.obs, mb.actions, mb.available)
    difference = log_prob - mb.log_probs[:, agent]
    dims = None if mb.action_dims is None else mb.action_dims[:, agent]
    if dims is not None:
        difference = torch.where(dims > 0, difference, torch.zeros_like(difference))
    return difference.sum(-1, keepdim=True), masked_mean(entropy, counted_entries(active, dims))
