"""A downloaded checkpoint, bundle or zoo model never runs code: a `module:function` env id
read from a file is imported only when the user opts in for that run (`--trust-env-code`,
the path as `envs.Trusted`), and an id must name a plain function outside the standard library.

Each test puts a module `planted.py` in the working directory (the CLI imports typed
`module:function` ids from there) whose import leaves a marker file: the marker says whether
any code of the file's choosing ran.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mat_runtime import Policy
from mat_sdk import envs
from mat_sdk.envs import Trusted, UntrustedEnvError
from mat_sdk.evaluation.episodes import CheckpointPolicy, evaluate
from mat_sdk.policy import checkpoint
from mat_sdk.training.trainer import Trainer

REPO = Path(__file__).resolve().parents[1]
PLANTED = """
from pathlib import Path

Path(__file__).with_name("ran").write_text("imported")


def make():
    from mat_sdk.envs.mujoco.robots import spec_for

    return spec_for("hopper-2x2")
"""
HOSTILE = "planted:make"
REFUSED = "runs no code unless you opt in: pass --trust-env-code"


def _run(args, cwd):
    """`mat ARGS`, or `python SCRIPT.py ARGS`, in `cwd`, as a user runs it."""
    mat = str(Path(sys.executable).with_name("mat"))
    command = [sys.executable, *args] if args[0].endswith(".py") else [mat, *args]
    return subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def planted(tmp_path_factory):
    """A directory with `planted.py` and a checkpoint (hopper-2x2) whose recorded env id is
    `planted:make`; also its bundle, exported before the id was changed."""
    root = tmp_path_factory.mktemp("downloaded")
    (root / "planted.py").write_text(PLANTED)
    with Trainer("hopper-2x2", num_envs=2, rollout_length=10, ppo_epochs=1,
                 num_minibatches=1) as trainer:  # fmt: skip
        trainer.learn(20, progress_bar=False)
        honest = trainer.save(root / "honest.pt")
    from mat_export import export

    export(honest, root / "bundle")
    manifest = json.loads((root / "bundle" / "manifest.json").read_text())
    manifest["env_id"] = HOSTILE
    (root / "bundle" / "manifest.json").write_text(json.dumps(manifest))
    payload = torch.load(honest, weights_only=True)
    payload["config"]["train"]["env"]["id"] = HOSTILE
    checkpoint.save_atomic(payload, root / "hostile.pt")
    return root


@pytest.fixture(autouse=True)
def no_marker(planted):
    (planted / "ran").unlink(missing_ok=True)
    yield


def _refused(run, planted):
    assert run.returncode != 0, run.stdout
    assert REFUSED in run.stderr and "'planted:make'" in run.stderr, run.stderr
    assert "Traceback" not in run.stderr
    assert not (planted / "ran").exists(), "the planted module was imported"


@pytest.mark.parametrize(
    "args",
    [
        ["eval", "hostile.pt", "--episodes", "1"],
        ["export", "hostile.pt", "-o", "out_onnx"],
        ["finetune", "hostile.pt", "--steps", "20", "--out", "ft"],
        ["zoo", "add", "hostile.pt", "mine", "--command", "x"],
    ],
    ids=["eval", "export", "finetune", "zoo-add"],
)
def test_a_recorded_id_is_not_imported_without_the_opt_in(planted, args, monkeypatch):
    monkeypatch.setenv("MAT_ZOO", str(planted / "zoo"))
    _refused(_run(args, planted), planted)
    assert not (planted / "zoo" / "mine").exists() and not (planted / "out_onnx").exists()


def test_the_controller_does_not_import_a_bundles_id_without_the_opt_in(planted):
    run = _run([str(REPO / "examples" / "controller.py"), "bundle", "--seconds", "0.1"], planted)
    _refused(run, planted)


def test_a_zoo_models_id_is_not_imported_without_the_opt_in(planted, monkeypatch):
    model = planted / "zoo" / "shady"
    model.mkdir(parents=True, exist_ok=True)
    (model / "checkpoint.pt").write_bytes((planted / "hostile.pt").read_bytes())
    (model / "card.json").write_text("{}")
    monkeypatch.setenv("MAT_ZOO", str(planted / "zoo"))
    _refused(_run(["eval", "zoo:shady", "--episodes", "1"], planted), planted)
    listing = _run(["zoo"], planted)  # listing reads cards, imports nothing
    assert "shady/card.json: name is missing" in listing.stderr
    assert not (planted / "ran").exists()


def test_the_python_api_refuses_recorded_ids_without_the_opt_in(planted, monkeypatch):
    monkeypatch.chdir(planted)
    monkeypatch.syspath_prepend(str(planted))
    hostile = planted / "hostile.pt"
    for call in (
        lambda: Trainer.load(hostile),
        lambda: Trainer.from_pretrained(hostile),
        lambda: evaluate(CheckpointPolicy.from_checkpoint(hostile), 1),
    ):
        with pytest.raises(UntrustedEnvError, match="records the env id 'planted:make'"):
            call()
    from mat_sdk.training.finetune import finetune

    with pytest.raises(UntrustedEnvError, match=r"envs.Trusted\(path\)"):
        finetune(hostile, steps=20, out_dir=planted / "ft-api")
    assert not (planted / "ran").exists()


def test_what_imports_nothing_stays_so(planted):
    """Loading and describing a bundle, loading a checkpoint's policy, and acting on an env
    the user names never import the recorded id."""
    policy = Policy.load(planted / "bundle")
    assert policy.env_id == HOSTILE and "joints" in policy.describe()
    loaded = CheckpointPolicy.from_checkpoint(planted / "hostile.pt")
    assert len(evaluate(loaded, 1, env_id="hopper-2x2")) == 1
    run = _run(["eval", "hostile.pt", "--episodes", "1", "--env", "hopper-2x2"], planted)
    assert run.returncode == 0, run.stderr
    run = _run([str(REPO / "examples" / "controller.py"), "bundle", "--env", "hopper-2x2",
                "--seconds", "0.2", "--warmup", "0"], planted)  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert not (planted / "ran").exists()


def test_the_opt_in_imports_the_recorded_id(planted):
    """With --trust-env-code the file's id is honoured: here it names a real env."""
    run = _run(["eval", "hostile.pt", "--episodes", "1", "--trust-env-code"], planted)
    assert run.returncode == 0, run.stderr
    assert (planted / "ran").exists()


def test_a_trusted_path_is_the_python_opt_in(planted, monkeypatch):
    """In Python the path itself carries the opt-in (`Trusted`), through every layer below
    the call: the same file that is refused as a plain path is evaluated."""
    monkeypatch.chdir(planted)
    monkeypatch.syspath_prepend(str(planted))
    loaded = CheckpointPolicy.from_checkpoint(Trusted(planted / "hostile.pt"))
    assert len(evaluate(loaded, 1)) == 1
    assert (planted / "ran").exists()


@pytest.mark.parametrize(
    ("env_id", "problem"),
    [
        ("os:abort", "standard library module 'os'"),
        ("sys:exit", "standard library module 'sys'"),
        ("tempfile:mkdtemp", "standard library module 'tempfile'"),
        ("json.decoder:JSONDecoder", "standard library module 'json.decoder'"),
        ("torch:zeros", "not a Python function"),
        ("mat_sdk.zoo:tempfile.mkdtemp", "no dots"),
        ("click.testing:pdb.set_trace", "no dots"),
        ("mat_sdk.zoo:evaluate", "not defined in module 'mat_sdk.zoo'"),
        ("mat_sdk.zoo:shutil", "not defined in module 'mat_sdk.zoo'"),
        ("pathlib_not_there:x", "no module 'pathlib_not_there'"),
    ],
)
def test_even_a_trusted_id_must_name_a_plain_function_outside_the_standard_library(env_id, problem):
    with pytest.raises(ValueError, match=problem):
        envs.resolve(env_id)


def test_a_stdlib_id_in_a_checkpoint_is_refused_even_when_trusted(planted, tmp_path):
    payload = torch.load(planted / "honest.pt", weights_only=True)
    payload["config"]["train"]["env"]["id"] = "os:abort"
    checkpoint.save_atomic(payload, tmp_path / "abort.pt")
    run = _run(["eval", str(tmp_path / "abort.pt"), "--trust-env-code"], tmp_path)
    assert run.returncode == 1 and "standard library module 'os'" in run.stderr, run.stderr


def test_seed_children_do_not_import_modules_from_the_working_directory(tmp_path):
    """`mat train --seeds` starts each seed in a new interpreter: a `random.py` in the working
    directory must not shadow the standard library's there."""
    (tmp_path / "random.py").write_text(
        "from pathlib import Path\nPath(__file__).with_name('ran').write_text('x')\n"
        "raise SystemExit('the planted random.py ran')\n"
    )
    run = _run(
        ["train", "coordination-2", "--seeds", "1", "--steps", "16", "--num-envs", "4",
         "--set", "rollout_length=4", "--set", "num_minibatches=1", "--set", "ppo_epochs=1",
         "--out", "set", "--quiet"],
        tmp_path,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr
    assert not (tmp_path / "ran").exists()
    assert os.path.exists(tmp_path / "set" / "seed_0" / "checkpoint.pt")


def test_a_trusted_id_never_walks_attributes_into_other_modules(planted, tmp_path):
    """With the opt-in, the part after the colon is one function defined in that module: a
    recorded `module:other_module.function` is refused before anything is called."""
    payload = torch.load(planted / "honest.pt", weights_only=True)
    payload["config"]["train"]["env"]["id"] = "mat_sdk.zoo:tempfile.mkdtemp"
    checkpoint.save_atomic(payload, tmp_path / "walk.pt")
    run = _run(["eval", str(tmp_path / "walk.pt"), "--trust-env-code"], tmp_path)
    assert run.returncode == 1 and "no dots" in run.stderr and "Traceback" not in run.stderr


def test_a_tampered_best_checkpoint_is_not_evaluated_as_its_own_env(planted, monkeypatch):
    """The end-of-run absolute metric evaluates `best.pt` on the run's own env: a `best.pt`
    that records another module's id (with an evaluation log claiming a huge return) is
    refused, and the module is never imported."""
    from mat_sdk.evaluation.protocol import BEST_NAME, EvaluationLog

    monkeypatch.chdir(planted)
    monkeypatch.syspath_prepend(str(planted))
    run = planted / "tampered-run"
    run.mkdir(exist_ok=True)
    with Trainer("hopper-2x2", out_dir=run, num_envs=2, rollout_length=10, ppo_epochs=1,
                 num_minibatches=1) as trainer:  # fmt: skip
        log = EvaluationLog(run, every=10, episodes=1)
        trainer.learn(20, callback=log, progress_bar=False)
        (run / BEST_NAME).write_bytes((planted / "hostile.pt").read_bytes())
        with pytest.raises(UntrustedEnvError, match="best.pt records the env id 'planted:make'"):
            log.finish(trainer)
    assert not (planted / "ran").exists(), "the planted module was imported"


def test_a_resumed_finetune_does_not_trust_the_envs_its_checkpoint_adds(planted, monkeypatch):
    """`finetune(..., env=E, resume=True)` names E, and only E: a `more_envs` entry planted in
    the run's checkpoint is still refused."""
    from mat_sdk.training.finetune import finetune

    monkeypatch.chdir(planted)
    monkeypatch.syspath_prepend(str(planted))
    out = planted / "ft-resume"
    finetune(planted / "honest.pt", "hopper-2x2", steps=20, out_dir=out, eval_episodes=1,
             num_envs=2, rollout_length=10, ppo_epochs=1, num_minibatches=1,
             progress_bar=False)  # fmt: skip
    payload = torch.load(out / "checkpoint.pt", weights_only=True)
    payload["config"]["train"]["env"]["more"] = [HOSTILE]
    checkpoint.save_atomic(payload, out / "checkpoint.pt")
    with pytest.raises(UntrustedEnvError, match="records the env id 'planted:make'"):
        finetune(planted / "honest.pt", "hopper-2x2", steps=40, out_dir=out, resume=True,
                 progress_bar=False)  # fmt: skip
    run = _run(["finetune", "honest.pt", "hopper-2x2", "--resume", "--out", "ft-resume",
                "--steps", "40"], planted)  # fmt: skip
    _refused(run, planted)


def test_every_library_path_leaves_the_trust_decision_to_check_trusted():
    """The paths that load an env id from a file (eval, export, finetune, zoo, resume, the
    absolute metric) pass on the path the user gave (maybe `Trusted`) or the ids the user
    named; only the command line's --trust-env-code makes a `Trusted` path of its own (a
    library path vouching for a file itself is how the two holes above came about)."""
    import ast

    offenders = []
    vouchers = {Path("mat_sdk/envs/registry.py"), Path("mat_sdk/cli/common.py")}
    for path in [*(REPO / "mat_sdk").rglob("*.py"), *(REPO / "export").rglob("*.py")]:
        if path.relative_to(REPO) in vouchers:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            called = node.func if isinstance(node, ast.Call) else None
            name = getattr(called, "id", None) or getattr(called, "attr", None)
            if name == "Trusted":
                offenders.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert offenders == []
