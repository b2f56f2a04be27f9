"""Ray rollout workers: optional (never imported without --ray), learn, survive a kill."""

import os
import signal
import subprocess
import sys

import numpy as np
import pytest
from helpers import GAME

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
