"""The CUDA path: the same trainer code on a GPU (skipped where torch sees none)."""

import numpy as np
import pytest
import torch
from helpers import GAME

from mat_sdk.model import MAT, ModelConfig
from mat_sdk.trainer import Trainer

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]


def test_cached_decoding_equals_teacher_forcing_on_cuda():
    torch.manual_seed(0)
    policy = MAT(ModelConfig(obs_dim=9, action_dim=3, n_agents=17, n_block=2, n_head=2)).cuda()
    obs = torch.randn(8, 17, 9, device="cuda")
    actions, log_probs, values = policy.act(obs, generator=torch.Generator("cuda").manual_seed(0))
    forced, _, forced_values = policy.evaluate(obs, actions)
    assert (forced - log_probs).abs().max() <= 1e-5
    assert (forced_values - values).abs().max() <= 1e-5


def test_cuda_trainer_learns_the_coordination_game_and_checkpoints_load_on_cpu(tmp_path):
    options = {**GAME, "device": "cuda"}
    returns = []
    with Trainer("coordination-3", "mat", out_dir=tmp_path, **options) as trainer:
        assert next(trainer.policy.parameters()).is_cuda
        trainer.learn(
            16_000, progress_bar=False, callback=lambda t, m: returns.append(m["return_mean"])
        )
        obs = np.eye(3, 6, dtype=np.float32) + np.eye(3, 6, 3, dtype=np.float32)
        on_gpu = trainer.predict(obs)
    assert np.mean(returns[-5:]) >= 0.9
    with Trainer.load(tmp_path / "checkpoint.pt", device="cpu") as on_cpu:
        np.testing.assert_allclose(on_cpu.predict(obs), on_gpu)  # discrete: the same choices
