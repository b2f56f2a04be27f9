"""The PPO update of the algorithms whose agents update together (MAT, MAT-Dec, MAPPO).

Epochs of shuffled minibatches over the rollout's rows; each minibatch's gradient is computed
in this process or split over update workers (`MinibatchGradients`), then one Adam step.
HAPPO updates its agents one after another instead (`mat_sdk.training.happo`); both return the
update's mean loss terms and whether every loss was finite.
"""

from __future__ import annotations

import torch

from mat_sdk.policy.config import PPOConfig
from mat_sdk.policy.normalization import ValueNorm
from mat_sdk.training import ppo
from mat_sdk.training.adaptive_lr import AdaptiveLR
from mat_sdk.training.flat_params import FlatParameters
from mat_sdk.training.gradients import MinibatchGradients
from mat_sdk.training.ppo import LossTerms, Rows

METRICS = ("policy_loss", "value_loss", "entropy", "clip_fraction", "kl", "grad_norm")


def update(
    params: FlatParameters,
    optimizer: torch.optim.Optimizer,
    value_norm: ValueNorm,
    gradients: MinibatchGradients,
    rows: Rows,
    config: PPOConfig,
    generator: torch.Generator,
) -> tuple[dict[str, float], bool]:
    """One update on the rollout's `rows`: its mean loss terms, and whether every loss was
    finite. Minibatches are drawn from `generator` (the run's own stream); with
    `config.desired_kl` each minibatch's KL sets the rate of its step (`AdaptiveLR`)."""
    gradients.share(rows)
    device = rows.obs.device
    # Accumulate on the device and read once per update: no host sync per minibatch.
    sums = dict.fromkeys(METRICS, torch.zeros((), device=device))
    finite = torch.ones((), dtype=torch.bool, device=device)
    indices = ppo.minibatches(
        len(rows), config.ppo_epochs, config.num_minibatches, generator, device
    )
    schedule = None if config.desired_kl is None else AdaptiveLR(config.desired_kl)
    count = 0
    for idx in indices:
        terms, grad_norm = optimizer_step(
            params, optimizer, value_norm, gradients, rows, idx, config.max_grad_norm, schedule
        )
        finite &= torch.isfinite(terms.total)
        values = (
            terms.policy, terms.value, terms.entropy, terms.clip_fraction, terms.kl, grad_norm
        )  # fmt: skip
        for key, value in zip(METRICS, values, strict=True):
            sums[key] = sums[key] + value.detach()
        count += 1
    metrics = {key: float(value) / count for key, value in sums.items()}
    return {**metrics, "lr": optimizer.param_groups[0]["lr"]}, bool(finite)


def optimizer_step(
    params: FlatParameters,
    optimizer: torch.optim.Optimizer,
    value_norm: ValueNorm,
    gradients: MinibatchGradients,
    rows: Rows,
    idx: torch.Tensor,
    max_grad_norm: float,
    schedule: AdaptiveLR | None = None,
) -> tuple[LossTerms, torch.Tensor]:
    """One PPO step on the minibatch `idx` of `rows` (already shared with `gradients`): its
    loss terms and the gradient norm before clipping. A `schedule` sets the step's learning
    rate from the minibatch's KL first."""
    returns = rows.returns[idx]
    value_norm.update(returns)
    params.zero_grad()
    terms = gradients.backward(idx, value_norm.normalize(returns))
    grad_norm = params.clip_grad_norm_(max_grad_norm)
    if schedule is not None:
        schedule.adapt(optimizer, float(terms.kl))
    optimizer.step()
    return terms, grad_norm
