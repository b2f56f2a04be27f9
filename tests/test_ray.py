"""Ray rollout workers: optional (never imported without --ray), learn, survive a kill."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from helpers import GAME, mat

from mat_sdk.trainer import Trainer


def test_training_without_ray_never_imports_it():
    script = """
import sys
from mat_sdk.trainer import Trainer
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
        if trainer.progress["updates"] == 3:
            pid = ray.get(trainer._remote.actors[1].pid.remote())
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    steps = 16_000
    with Trainer("coordination-3", "mat", ray="local", workers=2, **GAME) as trainer:
        trainer.learn(steps, callback=kill_one_worker_at_update_3, progress_bar=False)
        assert killed and trainer._remote.replacements == 1
        per_update = GAME["num_envs"] * GAME["rollout_length"]
        assert trainer.progress["updates"] == -(-steps // per_update)  # none lost
        assert len(returns) == trainer.progress["updates"]
        final = np.mean(trainer.evaluate(episodes=50))
    # as the local test asks of a local run; random play scores 2/27 = 0.07
    assert np.mean(returns[-5:]) >= 0.9 and final >= 0.9, (returns, final)


def _seed_child(run) -> int | None:
    """The pid of the `mat train` process writing into `run`, if one runs."""
    for entry in os.listdir("/proc"):
        try:
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                argv = f.read().split(b"\0")
        except OSError:
            continue
        if b"mat_sdk" in argv and b"train" in argv and str(run).encode() in argv:
            return int(entry)
    return None


def _parent(pid: int) -> int:
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[1])


@pytest.mark.slow
def test_a_seed_set_on_ray_retries_killed_seeds_from_their_checkpoints(tmp_path):
    """Seed 0's run and seed 1's Ray worker are killed mid-run; Ray retries both tasks, they
    resume from their checkpoints, and seed 1 ends equal to a solo run of seed 1."""
    pytest.importorskip("ray")
    from mat_sdk import checkpoint

    args = ["coordination-3", "--steps", "6000", "--num-envs", "4", "--eval-every", "0",
            "--set", "rollout_length=25", "--set", "num_minibatches=1", "--set", "ppo_epochs=1",
            "--set", "checkpoint_every=1", "--quiet"]  # fmt: skip
    out = tmp_path / "set"
    command = [sys.executable, "-m", "mat_sdk", "train", *args, "--seeds", "0-1", "--ray"]
    run = subprocess.Popen([*command, "--out", str(out)], stdout=subprocess.PIPE, text=True)
    killed = {}
    try:
        deadline = time.monotonic() + 300
        while len(killed) < 2 and time.monotonic() < deadline and run.poll() is None:
            for seed in (0, 1):
                directory = out / f"seed_{seed}"
                child = _seed_child(directory)
                if seed in killed or child is None or not (directory / "checkpoint.pt").exists():
                    continue
                target = child if seed == 0 else _parent(child)  # its Ray worker
                os.kill(target, signal.SIGKILL)
                killed[seed] = target
            time.sleep(0.2)
        stdout, _ = run.communicate(timeout=600)
    finally:
        run.kill()
    assert len(killed) == 2, f"the seeds finished before they could be killed: {stdout}"
    assert run.returncode == 0 and "all 2 seeds finished" in stdout, stdout
    for seed in (0, 1):
        log = (out / f"seed_{seed}" / "train.log").read_text()
        assert "resuming" in log, log  # the retry continued from the checkpoint
        assert checkpoint.load(out / f"seed_{seed}" / "checkpoint.pt")["progress"]["steps"] == 6000

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
