"""Rollouts acting through ONNX Runtime: the same distribution as torch, and it learns."""

import pytest
import torch
from helpers import trained_like

from mat_sdk.training.onnx_actor import OnnxActor
from mat_sdk.training.trainer import Trainer
from tests import recipes


@pytest.mark.parametrize("env_id", ["hopper-2x2", "coordination-3"])
def test_onnx_actor_log_probs_and_values_match_torch(env_id):
    with Trainer(env_id, "mat", num_envs=2, rollout_length=2, n_block=2, n_head=2) as trainer:
        policy = trained_like(trainer.policy).eval()
    actor = OnnxActor(policy)
    actor.refresh()
    obs = torch.randn(8, 5, policy.cfg.obs_dim)
    actions, log_probs, values = actor.act(obs, torch.Generator().manual_seed(0))
    with torch.no_grad():
        expected_log_probs, _, expected_values = policy.evaluate_actions(obs, actions)
    assert torch.allclose(log_probs, expected_log_probs, atol=1e-4)
    assert torch.allclose(values, expected_values, atol=1e-5)
    deterministic, _, _ = actor.act(obs, None, deterministic=True)
    with torch.no_grad():
        torch_deterministic, _, _ = policy.act(obs, deterministic=True)
    assert torch.allclose(deterministic, torch_deterministic, atol=1e-5)


@pytest.mark.slow
def test_onnx_rollouts_learn_the_coordination_game():
    """One seed is safe: `python -m benchmarks.seeds --recipe game-onnx`."""
    learned = recipes.onnx_game_return()
    assert learned >= 0.9, learned  # random play: 0.07
