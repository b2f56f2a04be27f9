"""Our optimised update computes exactly what the official-style reference computes."""

import copy

import pytest
import torch

from mat_sdk.bench.reference import OfficialStyleMAT, official_loss
from mat_sdk.policy.normalization import ValueNorm
from mat_sdk.training.ppo import Rows
from mat_sdk.training.trainer import Trainer


@pytest.mark.parametrize("update_workers", [0, 1], ids=["one-process", "split-with-a-worker"])
def test_losses_and_gradients_equal_the_official_style_reference(update_workers):
    with Trainer(
        "cheetah-6x1", "mat", num_envs=4, rollout_length=25, update_workers=update_workers
    ) as trainer:
        trajectory = trainer.rollout()
        names = ("obs", "actions", "log_probs", "values", "advantages", "returns")
        mb = Rows(**{name: getattr(trajectory, name).flatten(0, 1)[:50] for name in names})
        with torch.no_grad():  # trained-like weights: unit-gain layers and a moved policy
            for p in trainer.policy.parameters():
                p.add_(0.05 * torch.randn_like(p))
            mb.actions.add_(0.3 * torch.randn_like(mb.actions))
        reference = OfficialStyleMAT(copy.deepcopy(trainer.policy), trainer.env.n_agents)

        ours_norm, ref_norm = ValueNorm(), ValueNorm()
        ours_norm.update(mb.returns)
        trainer.gradients.share(mb)  # the trainer's own path: split over processes or not
        ours = trainer.gradients.backward(torch.arange(50), ours_norm.normalize(mb.returns))
        theirs = official_loss(reference, ref_norm, mb, trainer.config.ppo)
        ours_value, theirs_value = float(ours.total.detach()), float(theirs.detach())
        assert abs(ours_value - theirs_value) <= 1e-5 * max(1.0, abs(theirs_value))

        theirs.backward()
        ours_grads = dict(trainer.policy.named_parameters())
        checked = 0
        for name, param in reference.ours.named_parameters():
            mine = ours_grads[name].grad
            assert mine is not None and param.grad is not None, name
            assert torch.allclose(mine, param.grad, atol=1e-6, rtol=1e-4), name
            checked += 1
        assert checked == len(ours_grads)


def test_official_style_action_loop_matches_our_cached_decode():
    """`mat bench runtime`'s baseline chooses the actions our policy chooses."""
    with Trainer(
        "cheetah-6x1", "mat", num_envs=1, rollout_length=1, num_minibatches=1, seed=0
    ) as trainer:
        policy = trainer.policy.eval()
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.05 * torch.randn_like(p))
    for n in (1, 6, 17):
        obs = torch.randn(2, n, policy.cfg.obs_dim)
        reference = OfficialStyleMAT(copy.deepcopy(policy), n)
        theirs = reference.act(obs)
        ours = policy.act(obs, deterministic=True)
        for mine, official in zip(ours, theirs, strict=True):
            assert mine.shape == official.shape
            assert torch.allclose(mine, official, atol=1e-5), n
