"""Running statistics: observation normalisation and the official ValueNorm."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

OBS_CLIP = 10.0  # normalised observations are clipped to +-this (the official code's)
OBS_EPSILON = 1e-8  # added to the variance before its square root


class RunningMeanStd:
    """Per-feature running mean/variance of observations (Welford's parallel update)."""

    def __init__(self, size: int, clip: float = OBS_CLIP):
        self.mean = np.zeros(size)
        self.var = np.ones(size)
        self.count = 1e-4
        self.clip = clip

    def update(self, batch: np.ndarray) -> None:
        batch = batch.reshape(-1, self.mean.shape[0])
        batch_mean, batch_var, n = batch.mean(0), batch.var(0), batch.shape[0]
        delta, total = batch_mean - self.mean, self.count + n
        self.mean = self.mean + delta * n / total
        self.var = (
            self.var * self.count + batch_var * n + delta**2 * self.count * n / total
        ) / total
        self.count = total

    def scale(self) -> np.ndarray:
        """What a centred observation is multiplied by: 1 / sqrt(var + epsilon)."""
        return 1.0 / np.sqrt(self.var + OBS_EPSILON)

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        scaled = (obs - self.mean) * self.scale()
        return np.clip(scaled, -self.clip, self.clip).astype(np.float32)

    def state_dict(self) -> dict:
        return {
            "mean": torch.from_numpy(self.mean),
            "var": torch.from_numpy(self.var),
            "count": self.count,
        }

    def load_state_dict(self, state: dict) -> None:
        self.mean, self.var = state["mean"].numpy().copy(), state["var"].numpy().copy()
        self.count = float(state["count"])


class ValueNorm:
    """The official code's value normaliser: one scalar, debiased EMA of mean and mean-square.

    beta 0.99999; the variance is floored at 1e-2.
    """

    def __init__(self, beta: float = 0.99999, epsilon: float = 1e-5, device: str = "cpu"):
        self.beta, self.epsilon = beta, epsilon
        self.running_mean = torch.zeros((), dtype=torch.float64, device=device)
        self.running_mean_sq = torch.zeros((), dtype=torch.float64, device=device)
        self.debiasing_term = torch.zeros((), dtype=torch.float64, device=device)

    def update(self, values: Tensor) -> None:
        values = values.detach().double()
        self.running_mean.mul_(self.beta).add_(values.mean() * (1 - self.beta))
        self.running_mean_sq.mul_(self.beta).add_((values**2).mean() * (1 - self.beta))
        self.debiasing_term.mul_(self.beta).add_(1 - self.beta)

    def mean_var(self) -> tuple[Tensor, Tensor]:
        debias = self.debiasing_term.clamp(min=self.epsilon)
        mean = self.running_mean / debias
        var = (self.running_mean_sq / debias - mean**2).clamp(min=1e-2)
        return mean, var

    def normalize(self, values: Tensor) -> Tensor:
        mean, var = self.mean_var()
        return ((values.double() - mean) / var.sqrt()).to(values.dtype)

    def denormalize(self, values: Tensor) -> Tensor:
        mean, var = self.mean_var()
        return (values.double() * var.sqrt() + mean).to(values.dtype)

    def state_dict(self) -> dict:
        return {
            "running_mean": self.running_mean.cpu(),
            "running_mean_sq": self.running_mean_sq.cpu(),
            "debiasing_term": self.debiasing_term.cpu(),
        }

    def load_state_dict(self, state: dict) -> None:
        for name, value in state.items():
            getattr(self, name).copy_(value)
