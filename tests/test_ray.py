"""Ray rollout workers: optional (never imported without --ray), learn, survive a kill."""

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import GAME, mat

from mat_sdk.training.trainer import Trainer

TESTS = Path(__file__).parent


def test_training_without_ray_never_imports_it():
    script = """
import sys
from mat_sdk.training.trainer import Trainer
with Trainer("coordination-3", "mat", num_envs=2, rollout_length=2, num_minibatches=1) as t:
    t.learn(4, progress_bar=False)
assert "ray" not in sys.modules
print("ok")
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr


@pytest.mark.slow
def test_two_ray_workers_learn_the_game_and_a_killed_worker_is_replaced():
    ray = pytest.importorskip("ray")
    returns, killed = [], []

    def kill_one_worker_at_update_3(trainer, metrics):
        returns.append(metrics["return_mean"])
        if trainer.progress.updates == 3:
            pid = ray.get(trainer._remote.actors[1].pid.remote())
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    steps = 16_000
    with Trainer("coordination-3", "mat", ray="local", workers=2, **GAME) as trainer:
        trainer.learn(steps, callback=kill_one_worker_at_update_3, progress_bar=False)
        assert killed and trainer._remote.replacements == 1
        per_update = GAME["num_envs"] * GAME["rollout_length"]
        assert trainer.progress.updates == -(-steps // per_update)  # none lost
        assert len(returns) == trainer.progress.updates
        final = np.mean(trainer.evaluate(episodes=50))
    # as the local test asks of a local run; random play scores 2/27 = 0.07
    assert np.mean(returns[-5:]) >= 0.9 and final >= 0.9, (returns, final)


def _kill_plan(tmp_path, monkeypatch, **orders: str):
    """`killed_arm`'s plan: per process key, what its reward kills at the known step. Ray's
    processes inherit this process's environment: the plan, and `tests/` to import it from."""
    plan = tmp_path / "kill_plan"
    plan.mkdir()
    for key, target in orders.items():
        (plan / key).write_text(target)
    monkeypatch.setenv("KILL_PLAN", str(plan))
    path = os.environ.get("PYTHONPATH")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(TESTS), path])))
    return plan


def test_a_ray_worker_killed_mid_rollout_is_replaced_and_no_update_is_lost(tmp_path, monkeypatch):
    """One of two Ray workers kills itself at its 300th env step, inside the third update's
    rollout: a fresh worker collects that share again and the run ends on time."""
    pytest.importorskip("ray")
    plan = _kill_plan(tmp_path, monkeypatch, other="self")
    options = {"num_envs": 4, "rollout_length": 50, "ppo_epochs": 1, "num_minibatches": 1}
    with Trainer("killed_arm:arm", "mat", ray="local", workers=2, **options) as trainer:
        trainer.learn(600, progress_bar=False)
        assert (plan / "other.claimed").exists()  # the kill happened
        assert trainer._remote.replacements == 1
        assert trainer.progress.updates == 3 and trainer.progress.steps == 600


@pytest.mark.slow  # two minutes on 2 cores: a Ray cluster started, seeds killed and retried
def test_a_seed_set_on_ray_retries_killed_seeds_from_their_checkpoints(tmp_path, monkeypatch):
    """Seed 0's run and seed 1's Ray worker are killed at a known step of the third update;
    Ray retries both tasks, they resume from their checkpoints, and seed 1 ends equal to a
    solo run of seed 1."""
    pytest.importorskip("ray")
    from mat_sdk.policy import checkpoint

    plan = _kill_plan(tmp_path, monkeypatch, seed_0="self", seed_1="parent")
    args = ["killed_arm:arm", "--steps", "500", "--num-envs", "4", "--eval-every", "0",
            "--set", "rollout_length=25", "--set", "num_minibatches=1", "--set", "ppo_epochs=1",
            "--set", "checkpoint_every=1", "--quiet"]  # fmt: skip
    out = tmp_path / "set"
    run = mat("train", *args, "--seeds", "0-1", "--ray", "--out", str(out), check=False)
    assert run.returncode == 0 and "all 2 seeds finished" in run.stdout, run.stdout + run.stderr
    assert sorted(p.name for p in plan.iterdir()) == ["seed_0.claimed", "seed_1.claimed"]
    for seed in (0, 1):
        log = (out / f"seed_{seed}" / "train.log").read_text()
        assert "resuming" in log, log  # the retry continued from the checkpoint
        assert checkpoint.load(out / f"seed_{seed}" / "checkpoint.pt")["progress"]["steps"] == 500

    solo = tmp_path / "solo"
    mat("train", *args, "--seed", "1", "--out", str(solo))
    ours = checkpoint.load(out / "seed_1" / "checkpoint.pt")["model"]
    theirs = checkpoint.load(solo / "checkpoint.pt")["model"]
    assert all(torch.equal(ours[k], theirs[k]) for k in theirs)  # as if never killed


def test_a_seed_set_on_ray_without_ray_says_how_to_get_it(tmp_path):
    script = (
        "import sys; sys.modules['ray'] = None\n"  # as where Ray is not installed
        "from mat_sdk.cli import main\n"
        f"main(['train', 'coordination-3', '--steps', '100', '--seeds', '2', '--ray', "
        f"'--out', {str(tmp_path)!r}])\n"
    )
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert run.returncode == 1 and "--ray needs Ray: pip install 'mat-sdk[ray]'" in run.stderr
