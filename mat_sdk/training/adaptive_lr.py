"""A learning rate that follows the policy's step size: rsl_rl's KL-adaptive schedule.

PPO's clip bounds how far one update moves the policy only loosely; a fixed rate that is safe
late in training is slow early, and one fast early overshoots later. Measuring each
minibatch's KL divergence from the rollout's policy and scaling the rate to keep it near a
target (`desired_kl`) takes large steps while they are small in the policy's own terms. The
rate lives in the optimizer's parameter groups, so a checkpoint keeps it and a resume
continues from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

BOUNDS = (1e-5, 1e-2)  # rsl_rl's: the rate never stalls, nor leaves Adam's useful range


@dataclass(frozen=True)
class AdaptiveLR:
    """Scale every group's learning rate by `factor` towards a KL of `desired_kl`: down when a
    minibatch's KL is over twice the target, up when under half of it, within `BOUNDS`."""

    desired_kl: float
    factor: float = 1.5

    def adapt(self, optimizer: torch.optim.Optimizer, kl: float) -> None:
        if kl > 2.0 * self.desired_kl:
            scale = 1.0 / self.factor
        elif kl < 0.5 * self.desired_kl:
            scale = self.factor
        else:
            return
        low, high = BOUNDS
        for group in optimizer.param_groups:
            group["lr"] = min(max(group["lr"] * scale, low), high)
