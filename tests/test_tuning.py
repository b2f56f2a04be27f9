"""Update settings measured on this machine before a long run (`mat train --tune`)."""

import json

import pytest
import torch
from helpers import mat

from mat_sdk.common.processes import usable_cores
from mat_sdk.policy import checkpoint
from mat_sdk.policy.config import TrainConfig
from mat_sdk.training.tuning import TUNE_FROM_STEPS, TUNED, TUNING_NAME, amortized, wanted

# a run of seconds; compile stays off (given), so only update workers and flushing are measured
TINY = [
    "coordination-3", "--steps", "200", "--num-envs", "4", "--set", "rollout_length=25",
    "--set", "num_minibatches=2", "--set", "ppo_epochs=2", "--set", "compile=false", "--quiet",
]  # fmt: skip


def _trained_with(path) -> dict:
    """A checkpoint's training settings by their flat names."""
    return TrainConfig.from_dict(checkpoint.load(path)["config"]["train"]).options()


def _flags(chosen: dict) -> list[str]:
    return ["--workers", str(chosen["workers"]), "--update-workers", str(chosen["update_workers"]),
            "--set", f"rollout_backend={chosen['rollout_backend']}",
            "--set", f"flush_denormal={json.dumps(chosen['flush_denormal'])}"]  # fmt: skip


def test_long_cpu_runs_tune_unless_told_and_the_given_settings_stay():
    assert wanted(None, TUNE_FROM_STEPS, on_cpu=True, fixed={})
    assert not wanted(None, TUNE_FROM_STEPS - 1, on_cpu=True, fixed={})
    assert not wanted(None, TUNE_FROM_STEPS, on_cpu=False, fixed={})
    assert not wanted(None, TUNE_FROM_STEPS, on_cpu=True, fixed=dict.fromkeys(TUNED, 0))
    assert not wanted(False, TUNE_FROM_STEPS, on_cpu=True, fixed={})
    assert wanted(True, 1, on_cpu=True, fixed={})
    assert not wanted(True, 1, on_cpu=True, fixed=dict.fromkeys(TUNED, 0))  # nothing to choose
    with pytest.raises(ValueError, match="--tune measures CPU update settings"):
        wanted(True, TUNE_FROM_STEPS, on_cpu=False, fixed={})


@pytest.mark.slow
def test_a_tuned_run_equals_a_run_given_the_chosen_settings(tmp_path):
    run = mat("train", *TINY, "--tune", "--out", str(tmp_path / "tuned"))
    assert "measuring the rollout and update settings" in run.stdout and "chosen: " in run.stdout
    record = json.loads((tmp_path / "tuned" / TUNING_NAME).read_text())
    chosen = record["chosen"]
    # compile was given
    assert set(chosen) == {"workers", "rollout_backend", "update_workers", "flush_denormal"}
    assert record["fixed"] == {"compile": False}
    # env workers and update workers (where a core is free), acting backend, flushing
    rounds = {row["round"] for row in record["measured"]}
    assert len(rounds) == (4 if usable_cores() > 1 else 2)
    per = {row["round"]: row["per"] for row in record["measured"]}
    assert sorted(per.values()).count("rollout") == (2 if usable_cores() > 1 else 1)
    for round_ in rounds:  # one winner per round, among candidates measured side by side
        assert [row["chosen"] for row in record["measured"] if row["round"] == round_].count(
            "yes"
        ) == 1
    last = [row for row in record["measured"] if row["round"] == max(rounds) and row["chosen"]]
    assert f"flush_denormal={json.dumps(chosen['flush_denormal'])}" in last[0]["candidate"]
    train = _trained_with(tmp_path / "tuned" / "checkpoint.pt")
    assert {name: train[name] for name in chosen} == chosen and train["compile"] is False

    mat("train", *TINY, *_flags(chosen), "--no-tune", "--out", str(tmp_path / "given"))
    tuned = checkpoint.load(tmp_path / "tuned" / "checkpoint.pt")["model"]
    given = checkpoint.load(tmp_path / "given" / "checkpoint.pt")["model"]
    assert all(torch.equal(tuned[k], given[k]) for k in given)  # the measurement left no trace
    assert not (tmp_path / "given" / TUNING_NAME).exists()


@pytest.mark.slow
def test_a_seed_set_is_tuned_once_and_a_rerun_keeps_the_settings(tmp_path):
    out = tmp_path / "set"
    run = mat("train", *TINY, "--steps", "100", "--seeds", "2", "--tune", "--out", str(out))
    assert "chosen: " in run.stdout, run.stdout
    chosen = json.loads((out / TUNING_NAME).read_text())["chosen"]
    for seed in (0, 1):
        assert not (out / f"seed_{seed}" / TUNING_NAME).exists()  # measured once, for all
        train = _trained_with(out / f"seed_{seed}" / "checkpoint.pt")
        assert {name: train[name] for name in chosen} == chosen

    again = mat("train", *TINY, "--steps", "100", "--seeds", "2", "--tune", "--out", str(out))
    assert "as measured before" in again.stdout and "measuring" not in again.stdout
    assert "2 of 2 seeds already finished" in again.stdout


def test_tuning_on_a_gpu_is_refused_with_what_to_do(tmp_path):
    run = mat("train", *TINY, "--tune", "--device", "cuda", "--out", str(tmp_path), check=False)
    assert run.returncode == 1 and "--tune measures CPU update settings" in run.stderr
    assert "drop it on CUDA" in run.stderr


def test_a_compile_is_chosen_only_where_the_run_pays_back_its_start_up():
    """torch.compile 4 % faster per step after a 30 s compile: worth it over a million
    optimizer steps, not over the 5,760 of a 921,600-step Go2 run (288 updates x 20)."""
    eager, compiled = (0.0203, 0.5), (0.0195, 30.0)  # seconds per step, warm-up seconds
    for run_steps, faster in ((5_760, eager), (1_000_000, compiled)):
        costs = {c: amortized(c[0], c[1], 40, run_steps) for c in (eager, compiled)}
        assert min(costs, key=costs.get) == faster
    assert amortized(0.02, 0.1, 40, 100) == 0.02  # a warm-up within its own steps adds nothing
