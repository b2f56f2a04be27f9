"""Helpers shared by the tests."""

import subprocess
import sys

import torch
from torch import nn

from mat_sdk.training.trainer import Trainer
from tests.recipes import GAME  # noqa: F401  (the learning tests' recipe)

TINY = {"num_envs": 2, "rollout_length": 10, "ppo_epochs": 1, "num_minibatches": 1}


def trained_like(policy: nn.Module) -> nn.Module:
    """Replace the near-zero official init (gain 0.01) with unit-gain weights, as after training,
    so that every layer and every earlier action visibly matters."""
    with torch.no_grad():
        for module in policy.modules():
            if isinstance(module, nn.Linear):
                nn.init.orthogonal_(module.weight)
                if module.bias is not None:
                    nn.init.normal_(module.bias, std=0.1)
    return policy


def make_checkpoint(path, env_id="hopper-2x2", algo="mat", **options):
    """A briefly trained checkpoint (real normaliser statistics) with trained-scale weights."""
    with Trainer(env_id, algo, **TINY, **options) as trainer:
        trainer.learn(20, progress_bar=False)
        trained_like(trainer.policy)  # unit-gain weights: parity must hold on a real-scale net
        return trainer.save(path)


def mat(*args, check=True) -> subprocess.CompletedProcess:
    """`mat ARGS...` in a fresh process, as a user runs it; asserts success unless `check` is
    False."""
    run = subprocess.run(
        [sys.executable, "-m", "mat_sdk", *args], capture_output=True, text=True, timeout=300
    )
    if check:
        assert run.returncode == 0, run.stdout + run.stderr
    return run
