"""The KL-adaptive learning rate: it moves the rate towards the target KL, within bounds,
and a run that uses it logs the rate and KL it took."""

import pytest
import torch

from mat_sdk.training.adaptive_lr import BOUNDS, AdaptiveLR
from mat_sdk.training.run_log import read_metrics
from mat_sdk.training.trainer import Trainer


def _optimizer(*rates: float) -> torch.optim.Optimizer:
    groups = [{"params": [torch.nn.Parameter(torch.zeros(1))], "lr": lr} for lr in rates]
    return torch.optim.Adam(groups)


@pytest.mark.parametrize(
    ("kl", "factor"), [(0.05, 1 / 1.5), (0.021, 1 / 1.5), (0.01, 1.0), (0.006, 1.0), (0.004, 1.5)]
)
def test_the_rate_falls_past_twice_the_target_and_rises_under_half_of_it(kl, factor):
    optimizer = _optimizer(1e-3, 2e-4)  # a critic's own rate moves by the same factor
    AdaptiveLR(desired_kl=0.01).adapt(optimizer, kl)
    rates = [group["lr"] for group in optimizer.param_groups]
    assert rates == pytest.approx([1e-3 * factor, 2e-4 * factor])


def test_the_rate_stays_within_its_bounds():
    low, high = BOUNDS
    optimizer = _optimizer(high, low)
    schedule = AdaptiveLR(desired_kl=0.01)
    schedule.adapt(optimizer, 0.0)  # would rise: the first group is at the top already
    assert [g["lr"] for g in optimizer.param_groups] == pytest.approx([high, low * 1.5])
    for _ in range(40):
        schedule.adapt(optimizer, 1.0)
    assert [g["lr"] for g in optimizer.param_groups] == pytest.approx([low, low])


def test_a_run_with_a_target_kl_moves_its_rate_and_logs_it(tmp_path):
    """A target far below what a constant rate's steps reach: the rate falls every update
    (each update's first minibatch, still the rollout's policy, raises it once)."""
    options = {"num_envs": 2, "rollout_length": 10, "ppo_epochs": 2, "num_minibatches": 2}
    options |= {"lr": 1e-3, "desired_kl": 1e-6}
    with Trainer("hopper-2x2", "mat", out_dir=tmp_path, **options) as trainer:
        trainer.learn(60, progress_bar=False)
        final = trainer.optimizer.param_groups[0]["lr"]
    rows = read_metrics(tmp_path / "metrics.csv")
    rates = [float(row["lr"]) for row in rows]
    assert rates[0] < 1e-3 and rates[1] < rates[0] and rates[-1] == pytest.approx(final)
    assert all(float(row["kl"]) > 0 for row in rows)
