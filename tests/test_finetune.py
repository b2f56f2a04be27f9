"""Few-shot fine-tuning: a pre-trained MAT adapts to a changed game faster than from scratch."""

import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from helpers import GAME, make_checkpoint

from mat_sdk.cli import main
from mat_sdk.training.trainer import Trainer
from tests import recipes

CHANGE = recipes.FINETUNE_CHANGE  # 3 agents -> 2; agent_2 now follows agent_0 directly


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory):
    return recipes.pretrain_game(tmp_path_factory.mktemp("pre") / "pre.pt")


def test_finetuning_adapts_faster_than_training_from_scratch(pretrained, tmp_path):
    """One seed is safe: `python -m benchmarks.seeds --recipe finetune --recipe finetune-gain`."""
    finetuned, scratch, final = recipes.finetune_against_scratch(pretrained, tmp_path / "ft")
    assert len(finetuned) == len(scratch) == recipes.FINETUNE_UPDATES
    assert np.mean(finetuned[-5:]) >= 0.95 and final >= 0.95, (finetuned, final)
    assert np.mean(finetuned[-5:]) >= np.mean(scratch[-5:]) + 0.15, (finetuned, scratch)
    summary = json.loads((tmp_path / "ft" / "finetune.json").read_text())
    assert summary["agents"] == ["agent_0", "agent_2"]
    assert summary["steps"] == recipes.FINETUNE_UPDATES * GAME["num_envs"] * GAME["rollout_length"]
    assert len(summary["zero_shot"]["returns"]) == 20 and summary["final"]["mean"] >= 0.95


def test_finetune_command_evaluates_trains_and_refuses_what_it_cannot_serve(pretrained, tmp_path):
    runner = CliRunner()
    out = tmp_path / "run"
    args = ["finetune", str(pretrained), "--fault", "agent_1=remove", "--steps", "512"]
    result = runner.invoke(main, [*args, "--out", str(out), "--episodes", "4", "--quiet"])
    assert result.exit_code == 0, result.output
    assert "zero-shot return" in result.output and (out / "checkpoint.pt").exists()
    assert json.loads((out / "finetune.json").read_text())["steps"] == 512

    again = runner.invoke(main, [*args, "--out", str(out), "--quiet"])
    assert again.exit_code == 1 and "exists" in again.output  # nothing overwritten
    resumed = runner.invoke(main, [*args[:-1], "1024", "--out", str(out), "--resume", "--quiet"])
    assert resumed.exit_code == 0, resumed.output
    assert json.loads((out / "finetune.json").read_text())["steps"] == 1024
    other_lr = runner.invoke(
        main, [*args[:-1], "1536", "--out", str(out), "--resume", "--lr", "0.1"]
    )
    assert (
        other_lr.exit_code != 0
        and "as it was trained, with lr=0.0005; got lr=0.1" in other_lr.output
    )

    other_size = runner.invoke(main, ["finetune", str(pretrained), "coordination-4", "--quiet"])
    assert other_size.exit_code == 1 and "observations of size 8" in other_size.output
    assert "Traceback" not in other_size.output


def test_mappo_refuses_a_different_agent_count(tmp_path):
    with Trainer("coordination-3", "mappo", **GAME) as trainer:
        path = trainer.save(tmp_path / "mappo.pt")
    with pytest.raises(ValueError, match="tied to 3 agents"):
        Trainer.from_pretrained(path, faults=CHANGE)


def test_a_swimmer_policy_finetunes_on_a_longer_swimmer(tmp_path):
    tiny = {"num_envs": 2, "rollout_length": 10, "ppo_epochs": 1, "num_minibatches": 1}
    with Trainer("swimmer-4", "mat", attention_window=2, **tiny) as trainer:
        trainer.learn(20, progress_bar=False)
        path = trainer.save(tmp_path / "swimmer4.pt")
        weights = {k: v.clone() for k, v in trainer.policy.state_dict().items()}
    with Trainer.from_pretrained(path, env="swimmer-6") as longer:
        assert longer.env.n_agents == 5 and longer.config.init_from == str(path)
        assert longer.policy.cfg.attention_window == 2  # the model as trained
        for name, value in longer.policy.state_dict().items():  # same weights, more agents
            assert (value == weights[name]).all(), name
        longer.learn(20, progress_bar=False)
        assert longer.predict(np.zeros((5, longer.env.obs_dim))).shape == (5, 1)


@pytest.mark.parametrize("algo", ["mat", "happo"])
def test_action_std_starts_fine_tuning_from_a_wider_std_and_nothing_else_changes(algo, tmp_path):
    path = make_checkpoint(tmp_path / f"{algo}.pt", algo=algo)
    with Trainer.from_pretrained(path) as kept:
        before = {k: v.clone() for k, v in kept.policy.state_dict().items()}
        assert not torch.allclose(kept.policy.std(), torch.tensor(0.2))
    with Trainer.from_pretrained(path, action_std=0.2) as widened:
        assert torch.allclose(widened.policy.std(), torch.tensor(0.2))  # every agent's
        for name, value in widened.policy.state_dict().items():
            assert name.endswith("log_std") or (value == before[name]).all(), name
    for bad in (0.5, 0.0, True):
        with pytest.raises(ValueError, match=r"action std must be in \(0, 0.5\)"):
            Trainer.from_pretrained(path, action_std=bad)


def test_action_std_is_refused_for_discrete_actions_and_on_resume(pretrained, tmp_path):
    with pytest.raises(ValueError, match="continuous actions; this policy's are discrete"):
        Trainer.from_pretrained(pretrained, faults=CHANGE, action_std=0.3)
    runner = CliRunner()
    args = ["finetune", str(pretrained), "--fault", "agent_1=remove", "--out", str(tmp_path)]
    result = runner.invoke(main, [*args, "--steps", "512", "--resume", "--action-std", "0.3"])
    assert result.exit_code == 1 and "resume without it" in result.output, result.output
    assert not any(tmp_path.iterdir())  # refused before the run directory was touched
