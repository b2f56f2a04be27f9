"""The MAT model: cached decoding equals teacher forcing; shapes; baselines."""

import pytest
import torch
from helpers import trained_like

from mat_sdk.policy.model import MAT, ModelConfig, build_policy


@pytest.mark.parametrize("window", [None, 3])
@pytest.mark.parametrize("action_type", ["continuous", "discrete"])
@pytest.mark.parametrize("n", [1, 2, 6, 17])
def test_cached_decoding_equals_teacher_forcing(action_type, n, window):
    torch.manual_seed(0)
    cfg = ModelConfig(
        obs_dim=11, action_size=4, n_agents=n, action_type=action_type, n_block=2, n_head=2,
        attention_window=window,
    )  # fmt: skip
    policy = trained_like(MAT(cfg))
    obs = torch.randn(5, n, 11)
    available = None
    if action_type == "discrete":
        available = (torch.rand(5, n, 4) > 0.3).float()
        available[..., 0] = 1.0
    generator = torch.Generator().manual_seed(1)
    actions, log_probs, values = policy.act(obs, available, generator=generator)
    forced_log_probs, _, forced_values = policy.evaluate_actions(obs, actions, available)
    assert (forced_log_probs - log_probs).abs().max() <= 1e-5
    assert (forced_values - values).abs().max() <= 1e-5
    if action_type == "discrete":
        assert available.gather(-1, actions.long()).all()  # never an unavailable action


def test_later_agents_depend_on_earlier_actions_only():
    torch.manual_seed(0)
    policy = trained_like(MAT(ModelConfig(obs_dim=5, action_size=2, n_agents=4)))
    obs = torch.randn(1, 4, 5)
    actions = torch.randn(1, 4, 2)
    mean, _ = policy.action_params(obs, actions)
    changed = actions.clone()
    changed[0, 2] += 1.0  # agent 2's action may affect agent 3 only
    mean2, _ = policy.action_params(obs, changed)
    assert torch.allclose(mean[0, :3], mean2[0, :3], atol=1e-6)
    assert not torch.allclose(mean[0, 3], mean2[0, 3], atol=1e-6)


def test_an_attention_window_limits_what_each_agent_sees():
    torch.manual_seed(0)
    cfg = ModelConfig(obs_dim=5, action_size=2, n_agents=9, attention_window=3)
    policy = trained_like(MAT(cfg))
    obs, actions = torch.randn(1, 9, 5), torch.randn(1, 9, 2)
    changed = obs.clone()
    changed[0, 4, 0] += 1.0  # one block: agents 2..6 (fewer than 3 places from agent 4) see it
    rep, rep2 = policy.encoder(obs)[0], policy.encoder(changed)[0]
    moved = (rep - rep2).abs().amax(-1)[0] > 1e-6
    assert moved.tolist() == [False, False, True, True, True, True, True, False, False]
    later = actions.clone()
    later[0, 1] += 1.0  # agent 2's token; the decoder's two attentions reach 2 * (3 - 1) on
    mean = policy.decoder(policy.shift_tokens(actions), rep)
    mean2 = policy.decoder(policy.shift_tokens(later), rep)
    moved = (mean - mean2).abs().amax(-1)[0] > 1e-6
    assert moved.tolist() == [False, False, True, True, True, True, True, False, False]
    full = trained_like(MAT(ModelConfig(obs_dim=5, action_size=2, n_agents=9)))
    assert ((full.encoder(obs)[0] - full.encoder(changed)[0]).abs().amax(-1) > 1e-6).all()
    with pytest.raises(ValueError, match="attention_window must be an integer >= 2"):
        ModelConfig(obs_dim=5, action_size=2, n_agents=9, attention_window=1)


@pytest.mark.parametrize("algo", ["mat", "mat-dec", "mappo", "happo"])
def test_every_algo_acts_and_evaluates(algo):
    policy = build_policy(ModelConfig(obs_dim=7, action_size=3, n_agents=3, algo=algo))
    obs = torch.randn(4, 3, 7)
    actions, log_probs, values = policy.act(obs)
    assert actions.shape == (4, 3, 3) and log_probs.shape == (4, 3, 3) and values.shape == (4, 3, 1)
    forced, entropy, _ = policy.evaluate_actions(obs, actions)
    assert torch.allclose(forced, log_probs, atol=1e-5) and entropy.shape == (4, 3, 3)
    deterministic, _, _ = policy.act(obs, deterministic=True)
    assert torch.equal(deterministic, policy.act(obs, deterministic=True)[0])


def test_official_std_parametrisation_and_bad_config():
    policy = MAT(ModelConfig(obs_dim=3, action_size=2, n_agents=2))
    assert torch.allclose(policy.std(), torch.sigmoid(torch.ones(2)) * 0.5)
    with pytest.raises(ValueError, match="unknown algo 'ppo'"):
        ModelConfig(obs_dim=3, action_size=2, n_agents=2, algo="ppo")


def test_every_algorithm_has_a_policy_and_the_registry_matches_the_runtimes_names():
    from mat_runtime.manifest import ALGOS, FIXED_TEAM
    from mat_sdk.policy.algorithms import ALGORITHMS, algorithm
    from mat_sdk.policy.model import POLICIES, build_policy

    assert tuple(ALGORITHMS) == ALGOS and set(POLICIES) == set(ALGOS)
    for name in ALGOS:
        cfg = ModelConfig(obs_dim=3, action_size=2, n_agents=2, algo=name)
        policy = build_policy(cfg)
        assert cfg.algorithm.name == name and cfg.fixed_team == (name in FIXED_TEAM)
        # what the registry says an algorithm does is what its policy has
        assert hasattr(policy, "decoder") == algorithm(name).autoregressive
        assert hasattr(policy, "actors") == algorithm(name).actor_per_agent
    with pytest.raises(ValueError, match="unknown algo 'ppo'; valid: mat, mat-dec"):
        algorithm("ppo")
