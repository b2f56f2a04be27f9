"""Seed sets (`mat train --seeds`), the evaluation protocol and `mat report`."""

import json
import re

import numpy as np
import pytest
import torch
from helpers import mat

from mat_sdk.evaluation.protocol import (
    ABSOLUTE_FACTOR,
    env_and_task,
    interval_estimates,
    read_evaluations,
)
from mat_sdk.policy import checkpoint
from mat_sdk.training.multiseed import DONE_NAME, parse_seeds

# a run of a few seconds on the coordination game, evaluated every update
TINY = [
    "coordination-3", "--steps", "300", "--num-envs", "4", "--eval-every", "100",
    "--eval-episodes", "3", "--set", "rollout_length=25", "--set", "num_minibatches=1",
    "--set", "ppo_epochs=1", "--quiet",
]  # fmt: skip


@pytest.mark.parametrize(
    ("text", "seeds"), [("3", [0, 1, 2]), ("3-5", [3, 4, 5]), ("0,4,9", [0, 4, 9])]
)
def test_seeds_are_a_count_a_range_or_a_list(text, seeds):
    assert parse_seeds(text) == seeds


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("0", "--seeds 0 runs nothing"),
        ("5-3", "the range ends before it starts"),
        ("1,1", "names a seed twice"),
        ("two", "give a count (10), a range (3-7) or a list (0,4,9)"),
    ],
)
def test_bad_seed_sets_name_the_problem(text, problem):
    with pytest.raises(ValueError, match=problem.replace("(", r"\(").replace(")", r"\)")):
        parse_seeds(text)


def test_env_and_task_names_follow_marl_eval():
    assert env_and_task("mamujoco:HalfCheetah-6x1") == ("mamujoco", "HalfCheetah-6x1")
    assert env_and_task("cheetah-6x1") == ("mat_sdk", "cheetah-6x1")


@pytest.mark.slow
def test_a_seed_set_writes_one_ordinary_run_per_seed(tmp_path):
    run = mat("train", *TINY, "--steps", "100", "--seeds", "2", "--out", str(tmp_path))
    assert "2 seeds into" in run.stdout and "all 2 seeds finished" in run.stdout, run.stdout
    for seed in (0, 1):
        directory = tmp_path / f"seed_{seed}"
        assert (directory / DONE_NAME).exists() and (directory / "best.pt").exists()
        payload = checkpoint.load(directory / "checkpoint.pt")
        assert (
            payload["config"]["train"]["run"]["seed"] == seed
            and payload["progress"]["steps"] == 100
        )
    evaluations = read_evaluations([tmp_path])["mat_sdk"]["coordination-3"]["mat"]
    assert set(evaluations) == {"seed_0", "seed_1"}


def test_the_report_gives_intervals_curves_and_the_probability_of_improvement(tmp_path):
    pytest.importorskip("rliable")
    rng = np.random.default_rng(0)
    for algo, level in (("mat", 10.0), ("mappo", 5.0)):
        runs = {
            f"seed_{k}": {
                **{
                    f"step_{i}": {
                        "step_count": 1000 * i,
                        "return": list(level * i / 3 + rng.normal(size=4)),
                    }
                    for i in (1, 2, 3)
                },
                "absolute_metrics": {"return": list(level + rng.normal(size=40))},
            }
            for k in range(5)
        }
        run_dir = tmp_path / algo
        run_dir.mkdir()
        (run_dir / "evaluations.json").write_text(
            json.dumps({"mamujoco": {"Ant-4x2": {algo: runs}}})
        )
    report = mat(
        "report", str(tmp_path / "mat"), str(tmp_path / "mappo"), "--out", str(tmp_path / "r")
    )
    text = (tmp_path / "r" / "report.md").read_text()
    assert text in report.stdout and "## mamujoco: Ant-4x2" in text
    row = next(line for line in text.splitlines() if line.startswith("| mat | 5 |"))
    iqm, low, high = (float(x) for x in re.findall(r"-?\d+\.\d+", row)[:3])
    assert low <= iqm <= high and 9 < iqm < 11
    assert "| mat > mappo | 1.00 [1.00, 1.00] |" in text  # every MAT seed beats every MAPPO one
    # read off the curves: MAT's ~6.7 at step 2000 is the first to pass MAPPO's final ~5
    assert re.search(r"\| mat \| mappo \(\d\.\d\) \| 2,000 \|", text), text
    assert re.search(r"\| mappo \| mat \(\d+\.\d\) \| not by 3,000 \|", text), text
    assert (tmp_path / "r" / "mamujoco_Ant-4x2.png").stat().st_size > 1000


def test_an_interval_is_the_same_on_every_run_whatever_is_reported_beside_it():
    pytest.importorskip("rliable")
    from rliable import metrics

    rng = np.random.default_rng(0)
    mat_scores, mappo_scores = rng.normal(10, 1, (5, 1)), rng.normal(5, 1, (5, 1))
    alone = interval_estimates({"mat": mat_scores}, metrics.aggregate_mean)[1]["mat"]
    beside = interval_estimates({"mappo": mappo_scores, "mat": mat_scores}, metrics.aggregate_mean)
    assert np.array_equal(alone, beside[1]["mat"])


@pytest.mark.slow
def test_a_seed_set_equals_solo_runs_resumes_a_failed_seed_and_is_reported(tmp_path):
    out = tmp_path / "set"
    broken = out / "seed_1" / "checkpoint.pt"  # seed 1 will fail: a damaged checkpoint
    broken.parent.mkdir(parents=True)
    broken.write_bytes(b"not a checkpoint")
    failed = mat("train", *TINY, "--seeds", "0-1", "--out", str(out), check=False)
    assert failed.returncode == 1 and "seeds [1] failed" in failed.stderr, failed.stderr
    assert "Run the same command again to resume the failed seeds only" in failed.stderr
    assert (out / "seed_0" / DONE_NAME).exists() and not (out / "seed_1" / DONE_NAME).exists()
    assert "checkpoint" in (out / "seed_1" / "train.log").read_text()

    broken.unlink()
    finished = (out / "seed_0" / "checkpoint.pt").stat().st_mtime_ns
    again = mat("train", *TINY, "--seeds", "0-1", "--out", str(out))
    assert "1 of 2 seeds already finished" in again.stdout, again.stdout
    assert (out / "seed_0" / "checkpoint.pt").stat().st_mtime_ns == finished  # not rerun

    mat("train", *TINY, "--seed", "1", "--out", str(tmp_path / "solo"))
    ours = checkpoint.load(out / "seed_1" / "checkpoint.pt")["model"]
    solo = checkpoint.load(tmp_path / "solo" / "checkpoint.pt")["model"]
    assert all(torch.equal(ours[k], solo[k]) for k in solo)  # seed 1 of a set = a solo seed 1
    assert not all(
        torch.equal(ours[k], v)
        for k, v in checkpoint.load(out / "seed_0" / "checkpoint.pt")["model"].items()
    )

    # the protocol's record: evaluations every 100 steps, then the absolute metric
    log = json.loads((out / "seed_1" / "evaluations.json").read_text())
    run = log["mat_sdk"]["coordination-3"]["mat"]["seed_1"]
    assert [run[f"step_{i}"]["step_count"] for i in (1, 2, 3)] == [100, 200, 300]
    assert all(len(run[f"step_{i}"]["return"]) == 3 for i in (1, 2, 3))
    assert len(run["absolute_metrics"]["return"]) == 3 * ABSOLUTE_FACTOR
    assert (out / "seed_1" / "best.pt").exists()
    assert set(read_evaluations([out])["mat_sdk"]["coordination-3"]["mat"]) == {"seed_0", "seed_1"}

    pytest.importorskip("rliable")
    mat("train", *TINY, "--algo", "mat-dec", "--seeds", "2", "--out", str(tmp_path / "dec"))
    report = mat("report", str(out), str(tmp_path / "dec"), "--out", str(tmp_path / "report"))
    text = (tmp_path / "report" / "report.md").read_text()
    assert text in report.stdout and "## mat_sdk: coordination-3" in text
    assert "| mat | 2 |" in text and "| mat-dec | 2 |" in text and "| mat > mat-dec |" in text
    assert (tmp_path / "report" / "mat_sdk_coordination-3.png").stat().st_size > 1000


def test_a_seed_set_refuses_options_it_decides_itself(tmp_path):
    run = mat("train", *TINY, "--seeds", "2", "--seed", "3", "--out", str(tmp_path), check=False)
    assert run.returncode == 2 and "--seeds runs seed K as `--seed K`" in run.stderr
    assert "drop --seed" in run.stderr


def test_report_without_evaluations_says_how_to_get_them(tmp_path):
    pytest.importorskip("rliable")
    run = mat("report", str(tmp_path), "--out", str(tmp_path / "r"), check=False)
    assert run.returncode == 1 and "no evaluations.json under" in run.stderr
    assert "--eval-every" in run.stderr
