"""Checkpoints are data, not code: a damaged or edited one is refused naming what is wrong."""

import copy
import os
from pathlib import Path

import pytest
import torch
from helpers import make_checkpoint

from mat_export import export
from mat_sdk.evaluation.episodes import CheckpointPolicy
from mat_sdk.policy import checkpoint
from mat_sdk.policy.checkpoint import CheckpointError
from mat_sdk.training.trainer import Trainer


@pytest.fixture(scope="module")
def payload(tmp_path_factory):
    path = make_checkpoint(tmp_path_factory.mktemp("ckpt") / "good.pt", "coordination-3")
    return checkpoint.load(path)


def _edited(payload, tmp_path, name, edit):
    changed = copy.deepcopy(payload)
    edit(changed)
    path = tmp_path / f"{name}.pt"
    torch.save(changed, path)  # as an editor would: no validation on the way out
    return path


EDITS = {
    "string version": (lambda p: p.update(version="1"), "version must be an integer"),
    "list config": (lambda p: p.update(config=[1, 2]), "config must be a mapping"),
    "no weights": (lambda p: p.pop("model"), "model must map parameter names to tensors"),
    "extra model field": (
        lambda p: p["config"]["model"].update(colour="red"),
        r"config.model is invalid .*unknown field\(s\) \['colour'\]",
    ),
    "string model field": (
        lambda p: p["config"]["model"].update(n_embd="64"),
        "model n_embd must be an integer >= 1, got '64'",
    ),
    "no env id": (
        lambda p: p["config"]["train"]["env"].pop("id"),
        "config.train.env.id must be a string",
    ),
    "a list env id": (
        lambda p: p["config"]["train"]["env"].update(id=["x"]),
        "config.train.env.id must be",
    ),
    "no algo": (  # no default stands in for what the file trained
        lambda p: p["config"]["train"].pop("algo"),
        r"config.train is invalid \(names no algo\)",
    ),
    "no normaliser": (lambda p: p.pop("obs_norm"), "obs_norm must hold the tensors mean, var"),
    "bad progress": (lambda p: p.update(progress={"steps": -1}), "progress must hold"),
    "None fault": (  # a name MuJoCo's lookup would crash on
        lambda p: p["config"]["train"]["env"].update(faults={None: "zero"}),
        r"config.train is invalid \(a fault names an agent or joint by a non-empty string",
    ),
    "int fault": (
        lambda p: p["config"]["train"]["env"].update(faults={3: "zero"}),
        r"config.train is invalid \(a fault names an agent or joint by a non-empty string",
    ),
    "tuple fault": (
        lambda p: p["config"]["train"]["env"].update(faults={("a",): "zero"}),
        r"config.train is invalid \(a fault names an agent or joint by a non-empty string",
    ),
    "list options": (
        lambda p: p["config"]["train"]["env"].update(options=["x"]),
        r"config.train is invalid \(env_options must be a mapping",
    ),
    "seed option": (
        lambda p: p["config"]["train"]["env"].update(options={"seed": "x"}),
        "env_options cannot set seed",
    ),
    "two env ids": (
        lambda p: p["config"]["env"].update(id="coordination-4"),  # as written before 2026-12-03
        r"config.env.id differs from config.train.env \('coordination-3'\)",
    ),
    "unknown field": (
        lambda p: p["config"]["train"]["ppo"].update(colour="red"),
        r"config.train is invalid \(ppo has fields this SDK does not know \(\['colour'\]\)",
    ),
    "wrong weights": (
        lambda p: p["model"].update({"encoder.ln.weight": torch.zeros(3)}),
        "its weights do not fit the model",
    ),
}


@pytest.mark.parametrize("case", list(EDITS))
def test_an_edited_checkpoint_is_refused_by_every_reader(payload, tmp_path, case):
    edit, message = EDITS[case]
    path = _edited(payload, tmp_path, case.replace(" ", "_"), edit)
    readers = {
        "eval": CheckpointPolicy.from_checkpoint,
        "resume": Trainer.load,
        "finetune": Trainer.from_pretrained,
        "export": lambda p: export(p, tmp_path / "bundle"),
    }
    for reader, read in readers.items():
        with pytest.raises(CheckpointError, match=message):
            read(path)
        assert not (tmp_path / "bundle").exists(), reader


@pytest.mark.parametrize("lr", [float("nan"), 5.0, -1e-3, "3e-4"])
def test_resume_refuses_a_learning_rate_out_of_bounds(payload, tmp_path, lr):
    """An adaptive run's rate is read back from the file, so it is bounded there."""

    def edit(p):
        p["optimizer"]["param_groups"][0]["lr"] = lr

    path = _edited(payload, tmp_path, "bad_lr", edit)
    with pytest.raises(CheckpointError, match=r"learning rate must be in \(0, 1\]"):
        Trainer.load(path)


def test_resume_names_a_missing_training_state(payload, tmp_path):
    path = _edited(payload, tmp_path, "no_rng", lambda p: p.pop("rng"))
    with pytest.raises(CheckpointError, match="cannot resume from it.*KeyError: 'rng'"):
        Trainer.load(path)
    assert CheckpointPolicy.from_checkpoint(path) is not None  # evaluation needs no rng


def test_a_pickle_that_would_run_code_is_refused_with_the_reason(tmp_path):
    class RunsCode:
        def __reduce__(self):
            return (os.system, ("echo this must never run",))

    evil = tmp_path / "evil.pt"
    torch.save({"format": "mat-checkpoint", "version": 1, "x": RunsCode()}, evil)
    with pytest.raises(CheckpointError, match="unsupported GLOBAL posix.system") as refused:
        checkpoint.load(evil)
    message = str(refused.value)
    assert "weights_only" not in message and "\n" not in message


WRITTEN_BEFORE = sorted((Path(__file__).parent / "data").glob("*-5510455.pt"))


@pytest.mark.parametrize(
    "path",
    [
        pytest.param(p, marks=[pytest.mark.slow] if "hopper" in p.stem else [])
        for p in WRITTEN_BEFORE
    ],
    ids=lambda p: p.stem,
)
def test_checkpoints_written_by_earlier_versions_still_load_resume_and_export(path, tmp_path):
    """Files from commit 5510455 (before the model's action width was renamed, generators
    were saved with their device and TrainConfig gained options)."""
    from mat_runtime import Policy

    loaded = CheckpointPolicy.from_checkpoint(path)
    with Trainer.load(path, out_dir=tmp_path / "run") as trainer:
        assert trainer.model_config == loaded.policy.cfg
        start = trainer.progress.steps
        trainer.learn(start + 16, progress_bar=False)
        assert trainer.progress.steps == start + 16
    export(path, tmp_path / "bundle", agent_counts=(1, 2))
    policy = Policy.load(tmp_path / "bundle")
    assert policy.action_size == loaded.policy.cfg.action_size
