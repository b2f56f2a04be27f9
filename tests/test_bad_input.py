"""Hostile or broken input gets a clear error naming the problem, and loses nothing: your own
robots and envs, full disks, foreign files in a run, evaluations for the report, the zoo,
two runs in one directory. (Checkpoints: test_checkpoint.py; bundles: test_runtime.py;
recorded env ids: test_trust.py.)"""

from __future__ import annotations

import errno
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
from gymnasium import spaces
from helpers import TINY, make_checkpoint
from pettingzoo import ParallelEnv

from mat_sdk import envs
from mat_sdk.common import files
from mat_sdk.envs.core.base import UserCodeError
from mat_sdk.envs.mujoco.sources import MAX_SUBSTEPS
from mat_sdk.policy import checkpoint
from mat_sdk.training.trainer import Trainer

ARM = """
<mujoco>
  <worldbody>
    <body name="upper"><joint name="shoulder" axis="0 1 0"/><geom size=".05 .2" type="capsule"/>
      <body name="lower" pos="0 0 .4"><joint name="elbow" axis="0 1 0"/>
        <geom size=".04 .2" type="capsule"/></body></body>
  </worldbody>
  <actuator><motor name="shoulder" joint="shoulder"/><motor name="elbow" joint="elbow"/></actuator>
</mujoco>
"""
LAYOUT = [["shoulder"], ["elbow"]]


def still(physics) -> float:
    return -float(np.square(physics.data.qvel).sum())


# ------------------------------------------------------------------ your own robot
@pytest.mark.parametrize(
    ("model", "layout", "options", "message"),
    [
        (None, LAYOUT, {}, "model must be an MJCF file path or an XML string, got None"),
        (ARM, None, {}, "layout lists each agent's actuator names"),
        (ARM, [[None]], {}, "names an actuator by None"),
        (ARM, [[3]], {}, "names an actuator by 3"),
        (ARM, {None: ["shoulder"]}, {}, "agent names must be distinct strings"),
        (ARM, "shoulder", {}, "layout lists each agent's actuator names"),
        ("<mujoco><worldbody>", LAYOUT, {}, "MuJoCo cannot load it as an MJCF model"),
        (ARM.replace('joint="elbow"/>', 'site="nowhere"/>'), LAYOUT, {}, "cannot load it"),
        (ARM, LAYOUT, {"terminate": "yes"}, "terminate must be a function"),
        (ARM, LAYOUT, {"reset_noise": -1}, "reset_noise must be a finite number >= 0"),
        (ARM, LAYOUT, {"reset_noise": math.inf}, "reset_noise must be a finite number >= 0"),
        (ARM, LAYOUT, {"reset_noise": math.nan}, "reset_noise must be a finite number >= 0"),
        (ARM, LAYOUT, {"substeps": 10**9}, f"substeps must be an integer in 1..{MAX_SUBSTEPS}"),
    ],
)
def test_a_model_or_layout_that_cannot_work_is_refused(model, layout, options, message):
    with pytest.raises(ValueError, match=message):
        envs.from_mjcf(model, layout, still, **options)


def test_files_that_are_not_models_are_refused(tmp_path):
    (tmp_path / "notes.txt").write_text("not a model")
    with pytest.raises(ValueError, match="MuJoCo cannot load it as an MJCF model"):
        envs.from_mjcf(tmp_path / "notes.txt", LAYOUT, still)
    including = ARM.replace("<worldbody>", '<include file="notes.txt"/><worldbody>')
    (tmp_path / "robot.xml").write_text(including)
    with pytest.raises(ValueError, match="robot.xml: MuJoCo cannot load it"):
        envs.from_mjcf(tmp_path / "robot.xml", LAYOUT, still)
    meshed = ARM.replace(  # a mesh that collides: physics copies load it too
        "<worldbody>",
        '<asset><mesh file="notes.txt"/></asset><worldbody><geom mesh="notes" type="mesh"/>',
    )
    (tmp_path / "meshed.xml").write_text(meshed)
    with pytest.raises(ValueError, match="meshed.xml: MuJoCo cannot load it"):
        envs.from_mjcf(tmp_path / "meshed.xml", LAYOUT, still)


@pytest.mark.parametrize("returned", ["robot", None])
def test_a_factory_must_return_a_dm_control_environment(returned):
    with pytest.raises(ValueError, match="must return a dm_control control.Environment, got"):
        envs.from_dm_control(lambda seed: returned, LAYOUT)


def test_an_error_in_the_users_own_function_names_it(tmp_path):
    def needs_root(physics) -> float:
        return float(physics.named.data.qpos["root"][0])

    team = envs.from_mjcf(ARM, LAYOUT, needs_root).build()
    team.reset(seed=0)
    with pytest.raises(UserCodeError, match=r"your reward function needs_root raised KeyError"):
        team.step(np.zeros((2, 1)))

    def broken_factory(seed):
        raise OSError("no robot here")

    with pytest.raises(UserCodeError, match="your environment factory broken_factory raised"):
        envs.from_dm_control(broken_factory, LAYOUT)


@pytest.mark.parametrize(
    ("faults", "message"),
    [
        ({None: "zero"}, "names an agent or joint by a non-empty string, got None"),
        ({3: "zero"}, "got 3"),
        ({("a",): "zero"}, r"got \('a',\)"),
        (["bfoot"], r"faults must be envs.Fault values \(Fault.zero\(name\), ...\), got 'bfoot'"),
        ("bfoot=zero", "faults are a list of envs.Fault"),
        ({"bfoot": "half"}, "mode must be one of"),
        ({"bfoot": "weak:2"}, "strictly between 0 and 1"),
        ([envs.Fault.zero("bfoot"), envs.Fault.weak("bfoot", 0.5)], "one fault per agent or joint"),
    ],
)
def test_fault_names_are_checked_before_mujoco_sees_them(faults, message):
    """A None name crashed MuJoCo's name lookup (a segfault): refused before any lookup."""
    with pytest.raises(ValueError, match=message):
        envs.make_team("cheetah-6x1", faults=faults)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"seed": "x"}, "env option seed must be an integer"),
        ({"seed": 1.5}, "env option seed must be an integer"),
        ({"agent_id": 1}, "env option agent_id must be true or false"),
        ({"hops": "2"}, "env option hops must be an integer"),
        ({"position": 3}, "env option position must be a string"),
    ],
)
def test_env_option_values_are_checked(options, message):
    with pytest.raises(ValueError, match=message):
        envs.make_team("swimmer-4", **options)


def test_a_checkpoint_with_a_none_fault_is_refused_by_eval_and_resume(tmp_path):
    """Once a segfault (signal 11) in eval, export and --resume; now a one-line refusal."""
    good = make_checkpoint(tmp_path / "good.pt", "cheetah-2x3")
    payload = checkpoint.load(good)
    payload["config"]["train"]["env"]["faults"] = {None: "zero"}
    bad = checkpoint.save_atomic(payload, tmp_path / "bad.pt")
    for args in (["eval", str(bad), "--episodes", "1"], ["export", str(bad), "-o", "b"]):
        run = _mat(args, tmp_path)
        assert run.returncode == 1, run.stderr
        assert "a fault names an agent or joint by a non-empty string" in run.stderr
        assert "Traceback" not in run.stderr


# ------------------------------------------------------------------ PettingZoo envs
class Twins(ParallelEnv):
    """Two agents; `flaw` makes it misbehave in one way."""

    metadata: ClassVar[dict] = {"name": "twins"}

    def __init__(self, seed=None, flaw=None):
        self.flaw = flaw
        self.possible_agents = ["a", "a"] if flaw == "duplicate" else ["a", "b"]
        if flaw == "collide":
            self.possible_agents = [1, "1"]
        self._space = spaces.Box(-1, 1, (2,), np.float32)

    def observation_space(self, agent):
        return self._space

    def action_space(self, agent):
        return self._space

    def _obs(self):
        value = np.nan if self.flaw == "nan obs" else 0.0
        return {a: np.full(2, value, np.float32) for a in self.agents}

    def reset(self, seed=None, options=None):
        self.agents = ["a", "ghost"] if self.flaw == "ghost" else list(self.possible_agents)
        if self.flaw == "renamed":
            self.agents = ["a", "c"]
        return self._obs(), {a: {} for a in self.agents}

    def step(self, actions):
        reward = math.inf if self.flaw == "inf reward" else 1.0
        rewards = {a: reward for a in self.agents}
        flags = {a: False for a in self.agents}
        return self._obs(), rewards, flags, dict(flags), {a: {} for a in self.agents}


@pytest.mark.parametrize(
    ("flaw", "message"),
    [
        ("duplicate", "possible_agents must be distinct names"),
        ("collide", r"possible_agents must be distinct names \(also as text\)"),
        ("nan obs", "a's observation holds NaN or inf"),
        ("inf reward", "a's reward is inf"),
        ("ghost", r"the env's agents \['a', 'ghost'\] are not distinct members"),
        ("renamed", r"the env's agents \['a', 'c'\] are not distinct members"),
    ],
)
def test_a_pettingzoo_env_that_breaks_its_contract_is_refused(flaw, message):
    with pytest.raises(ValueError, match=message):
        team = envs.from_pettingzoo(lambda seed: Twins(seed, flaw)).build()
        team.reset(seed=0)
        team.step(np.zeros((2, 2)))


# ------------------------------------------------------------------ full disks
def _mat(args, cwd):
    mat = str(Path(sys.executable).with_name("mat"))
    return subprocess.run([mat, *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def _full(monkeypatch, after: int = 0):
    """Every write through `torch.save` fails with ENOSPC after `after` successful ones, as on
    a disk that fills up."""
    import torch

    real, calls = torch.save, {"n": 0}

    def save(obj, f, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] > after:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", save)


@pytest.mark.parametrize("after", [0, 1], ids=["from the start", "after a checkpoint"])
def test_a_full_disk_during_training_is_one_line_and_keeps_the_last_checkpoint(
    tmp_path, monkeypatch, after
):
    trainer = Trainer("cheetah-2x3", out_dir=tmp_path, checkpoint_every=1, **TINY)
    _full(monkeypatch, after)
    with trainer, pytest.raises(files.WriteFailed) as failed:
        trainer.learn(200, progress_bar=False)
    assert (
        str(failed.value) == f"cannot write {tmp_path / 'checkpoint.pt'}: no space left on device"
    )
    if after:  # the checkpoint of the first update survives, whole
        assert checkpoint.load(tmp_path / "checkpoint.pt")["progress"]["updates"] == 1
    assert not list(tmp_path.glob(".*.tmp"))


def test_a_full_disk_during_export_keeps_the_old_bundle(tmp_path, monkeypatch):
    from mat_export import export, exporter

    ckpt = make_checkpoint(tmp_path / "c.pt", "cheetah-2x3")
    export(ckpt, tmp_path / "bundle", agent_counts=(1,))
    before = {p.name: p.read_bytes() for p in (tmp_path / "bundle").iterdir()}

    def no_room(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(exporter, "finish_graph", no_room)
    with pytest.raises(files.WriteFailed, match=r"cannot write .*bundle: no space left on device"):
        export(ckpt, tmp_path / "bundle", force=True, agent_counts=(1,))
    assert {p.name: p.read_bytes() for p in (tmp_path / "bundle").iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bundle", "c.pt"]


def test_a_read_only_directory_is_named(tmp_path):
    import os

    if os.geteuid() == 0:
        pytest.skip("root writes into read-only directories")
    (tmp_path / "locked").mkdir(mode=0o500)
    with pytest.raises(files.WriteFailed, match="locked/x.json: permission denied"):
        files.write_text_atomic(tmp_path / "locked" / "x.json", "{}")


# ------------------------------------------------------------------ foreign files in a run
@pytest.mark.parametrize(
    "content", [b"\x00\xff\xfe binary garbage", b"when,who\n1,2\n"], ids=["binary", "foreign"]
)
def test_a_foreign_metrics_file_is_set_aside_on_resume(tmp_path, content):
    with Trainer("cheetah-2x3", out_dir=tmp_path, **TINY) as trainer:
        trainer.learn(20, progress_bar=False)
    (tmp_path / "metrics.csv").write_bytes(content)
    with (
        pytest.warns(UserWarning, match="not a metrics file of this SDK"),
        Trainer.load(tmp_path / "checkpoint.pt", out_dir=tmp_path) as trainer,
    ):
        trainer.learn(40, progress_bar=False)
    assert (tmp_path / "metrics.csv.unreadable").read_bytes() == content
    rows = (tmp_path / "metrics.csv").read_text().splitlines()
    assert rows[0].startswith("steps,updates") and len(rows) == 2


# ------------------------------------------------------------------ mat report
def _evaluations(run: dict) -> dict:
    return {"mat_sdk": {"cheetah-6x1": {"mat": {"seed_0": run}}}}


GOOD = {"step_1": {"step_count": 100, "return": [1.0, 2.0]}}
NAN = {"step_1": {"step_count": 100, "return": ["NAN"]}}  # written as JSON's NaN below


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{", "is not JSON"),
        ("", "is not JSON"),
        ("[" * 100_000 + "]" * 100_000, "nested too deeply|must be an object"),
        ("[]", "the file must be an object of env names"),
        (json.dumps({"mat_sdk": {}}), "mat_sdk names no task"),
        (json.dumps({"mat_sdk": {"t": {"mat": {}}}}), "mat_sdk/t/mat names no seed"),
        (json.dumps(_evaluations({"step_1": {"return": [1]}})), "step_count must be an integer"),
        (json.dumps(_evaluations({"step_1": {"step_count": 5}})), "return must be a non-empty"),
        (json.dumps(_evaluations({"step_1": {"step_count": 5, "return": ["1"]}})), "finite"),
        (json.dumps(_evaluations({})), "has no evaluation"),
        (json.dumps(_evaluations({"notes": 1})), "neither step_K nor absolute_metrics"),
        (json.dumps(_evaluations(NAN)).replace('"NAN"', "NaN"), "is NaN"),
        (json.dumps(_evaluations(NAN)).replace('"NAN"', "Infinity"), "is Infinity"),
        (json.dumps({"../../x": {"t": {"mat": {"seed_0": GOOD}}}}), "not a plain name"),
        (json.dumps({"/tmp/x": {"t": {"mat": {"seed_0": GOOD}}}}), "not a plain name"),
        (json.dumps({"e": {"t": {"mat |x|\n| y": {"seed_0": GOOD}}}}), "not a plain name"),
    ],
)
def test_report_refuses_hostile_evaluations_naming_the_file(tmp_path, text, message):
    from mat_sdk.evaluation.report import write_report

    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "evaluations.json").write_text(text)
    with pytest.raises(ValueError, match=message) as refused:
        write_report([tmp_path / "run"], tmp_path / "out")
    assert "evaluations.json" in str(refused.value)
    assert not (tmp_path / "out").exists() and sorted(tmp_path.iterdir()) == [tmp_path / "run"]


def test_report_does_not_follow_a_symlink_out_of_the_run(tmp_path):
    from mat_sdk.evaluation.report import write_report

    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "evaluations.json").symlink_to("/etc/passwd")
    with pytest.raises(ValueError, match="resolves outside"):
        write_report([tmp_path / "run"], tmp_path / "out")
    run = _mat(["report", "run", "--out", "out"], tmp_path)
    assert (
        run.returncode == 1 and "resolves outside" in run.stderr and "Traceback" not in run.stderr
    )


# ------------------------------------------------------------------ the zoo
@pytest.fixture
def zoo(tmp_path, monkeypatch):
    monkeypatch.setenv("MAT_ZOO", str(tmp_path / "zoo"))
    return tmp_path


@pytest.mark.parametrize("name", ["../x", "/tmp/abs", "", "with space", ".hidden"])
def test_zoo_add_refuses_names_that_are_not_names(zoo, name):
    from mat_sdk.zoo import add

    ckpt = make_checkpoint(zoo / "c.pt", "coordination-3")
    with pytest.raises(ValueError, match="zoo name"):
        add(ckpt, name, "x")
    assert not (zoo / "zoo").exists() or not any((zoo / "zoo").iterdir())
    assert sorted(p.name for p in zoo.iterdir()) == ["c.pt", "zoo"] or sorted(
        p.name for p in zoo.iterdir()
    ) == ["c.pt"]


def test_zoo_add_replaces_only_with_force_and_leaves_nothing_when_refused(zoo):
    from mat_sdk.zoo import add

    ckpt = make_checkpoint(zoo / "c.pt", "coordination-3")
    with pytest.raises(ValueError, match="episodes must be an integer >= 1"):
        add(ckpt, "game", "x", episodes=0)
    assert not (zoo / "zoo" / "game").exists()
    card = add(ckpt, "game", "mat train ...", episodes=2)
    assert card["name"] == "game" and (zoo / "zoo" / "game" / "onnx" / "manifest.json").exists()
    with pytest.raises(FileExistsError, match="pass --force"):
        add(ckpt, "game", "again", episodes=2)
    assert add(ckpt, "game", "again", episodes=2, force=True)["made_by"] == "again"
    assert [p.name for p in (zoo / "zoo").iterdir()] == ["game"]  # no staging left


@pytest.mark.parametrize(
    "card",
    [
        pytest.param("{", marks=pytest.mark.slow),
        pytest.param("[1, 2]", marks=pytest.mark.slow),
        '{"name": "x"}',
    ],
    ids=["invalid", "list", "keys"],
)
def test_a_broken_card_is_named_and_the_others_still_list(zoo, card):
    from mat_sdk.zoo import add

    add(make_checkpoint(zoo / "c.pt", "coordination-3"), "good", "x", episodes=2)
    (zoo / "zoo" / "broken").mkdir()
    (zoo / "zoo" / "broken" / "card.json").write_text(card)
    run = _mat(["zoo"], zoo)
    assert run.returncode == 0, run.stderr
    assert "| zoo:good |" in run.stdout
    assert "broken/card.json:" in run.stderr and "skipped" in run.stderr


# ------------------------------------------------------------------ one run per directory
def test_a_second_run_in_the_same_directory_is_refused_naming_the_first(tmp_path):
    """The lock is the OS's: a second process is refused; the lock dies with its holder."""
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import sys, time\nfrom mat_sdk.common import files\n"
         f"with files.RunLock({str(tmp_path)!r}):\n    print('held', flush=True)\n"
         "    time.sleep(60)\n"],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(files.RunLocked, match=rf"in use by another run \(pid {holder.pid}\)"):
            Trainer("cheetah-2x3", out_dir=tmp_path, **TINY).learn(20, progress_bar=False)
        run = _mat(["train", "cheetah-2x3", "--steps", "20", "--out", str(tmp_path)], tmp_path)
        assert run.returncode == 1 and f"pid {holder.pid}" in run.stderr, run.stderr
        assert not (tmp_path / "checkpoint.pt").exists()
    finally:
        holder.kill()
        holder.wait()
    with Trainer("cheetah-2x3", out_dir=tmp_path, **TINY) as trainer:  # free again
        trainer.learn(20, progress_bar=False)


# ------------------------------------------------------------------ packaging
def test_the_report_extra_pins_what_its_statistics_need():
    """rliable's bootstrap (arch) breaks with pandas 3: the extra itself must keep it out, for
    a user who installs without our constraints file."""
    import tomllib

    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert "pandas<3" in project["project"]["optional-dependencies"]["report"]


@pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")
@pytest.mark.parametrize("after", [0, 3], ids=["from the start", "mid-run"])
def test_a_disk_that_fills_under_tensorboard_is_one_line_and_no_thread_traceback(
    tmp_path, monkeypatch, capfd, after
):
    """TensorBoard's writer thread meets the full disk first: the run stops with the one-line
    error, and the thread prints no traceback of its own."""
    from tensorboard.summary.writer import record_writer

    real, calls = record_writer.RecordWriter.write, {"n": 0}

    def no_room(self, data):
        calls["n"] += 1
        if calls["n"] > after:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, data)

    trainer = Trainer("cheetah-2x3", out_dir=tmp_path, **TINY)
    monkeypatch.setattr(record_writer.RecordWriter, "write", no_room)
    with trainer, pytest.raises(files.WriteFailed, match="no space left on device"):
        trainer.learn(2000, progress_bar=False)
    assert "Traceback" not in capfd.readouterr().err


def test_faults_are_values_parsed_once_and_their_mapping_form_loads_the_same():
    """`--fault` strings, the mapping form checkpoints store and `Fault` values are one thing;
    the env acts on the typed list."""
    from mat_sdk.envs.core.faults import Fault, as_mapping, faults_of

    typed = (Fault.zero("bfoot"), Fault.weak("fthigh", 0.5), Fault.remove("agent_2"))
    parsed = tuple(
        Fault.parse(text) for text in ("bfoot=zero", "fthigh=weak:0.5", "agent_2=remove")
    )
    assert parsed == typed == faults_of(as_mapping(typed))
    assert [str(fault) for fault in typed] == ["bfoot=zero", "fthigh=weak:0.5", "agent_2=remove"]
    with pytest.raises(
        ValueError, match="'bfoot': a fault is NAME=zero, NAME=remove or NAME=weak:S"
    ):
        Fault.parse("bfoot")
    team = envs.make_team("cheetah-6x1", faults=[Fault.remove("agent_2")])
    same = envs.make_team("cheetah-6x1", faults={"agent_2": "remove"})
    assert team.faults == same.faults == (Fault.remove("agent_2"),) and team.n_agents == 5
