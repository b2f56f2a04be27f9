"""The `mat` command line: tables, one-line errors, non-zero exit codes."""

import ast
import re
import sys
from pathlib import Path

import click
import numpy as np
from click.testing import CliRunner

from mat_sdk.cli import main
from mat_sdk.policy import checkpoint


def test_envs_table_lists_every_robot():
    result = CliRunner().invoke(main, ["envs"])
    assert result.exit_code == 0, result.output
    for env_id in (
        "cheetah-6x1",
        "quadruped-4x3",
        "humanoid-limbs",
        "swimmer-6",
        "mamujoco:HalfCheetah-6x1",
    ):
        assert env_id in result.output
    assert "episode" in result.output or "limit" in result.output


def test_rollout_runs_a_random_team_with_a_fault():
    result = CliRunner().invoke(
        main, ["rollout", "hopper-2x2", "--steps", "20", "--fault", "knee=zero"]
    )
    assert result.exit_code == 0, result.output
    assert "episode returns" in result.output


def test_rollout_plays_the_discrete_game_at_random():
    """Random choices: the leader is right 1/3 of the time and all differ 2/9 of those; a
    team whose actions are not choices, or whose leader shares the env's random stream, is
    off that rate."""
    result = CliRunner().invoke(main, ["rollout", "coordination-3", "--steps", "300"])
    assert result.exit_code == 0, result.output
    returns = ast.literal_eval(result.output.split("episode returns ")[1].strip())
    assert len(returns) == 300 and set(returns) <= {0.0, 1.0}
    assert 0.02 < np.mean(returns) < 0.15


def test_user_mistakes_give_one_line_and_exit_code():
    result = CliRunner().invoke(main, ["rollout", "cheetah-9x9"])
    assert result.exit_code != 0
    assert "unknown environment id 'cheetah-9x9'" in result.output
    assert "Traceback" not in result.output
    result = CliRunner().invoke(main, ["rollout", "cheetah-6x1", "--fault", "bfoot"])
    assert result.exit_code != 0 and "NAME=zero, NAME=remove or NAME=weak:S" in result.output
    result = CliRunner().invoke(main, ["rollout", "cheetah-6x1", "--fault", "bfoot=weak:2"])
    assert result.exit_code == 2 and "Traceback" not in result.output  # a usage error
    assert "fault bfoot='weak:2': a weak motor keeps a share of its force strictly" in result.output


TINY_TRAIN = [
    "--num-envs",
    "4",
    "--set",
    "rollout_length=10",
    "--set",
    "num_minibatches=2",
    "--set",
    "ppo_epochs=1",
    "--set",
    '{"episode_limit": 20}'.join(["env_options=", ""]),
    "--quiet",
]


def test_train_on_several_agent_counts_resume_and_eval_on_another(tmp_path):
    out, runner = tmp_path / "run", CliRunner()
    ids = ["swimmer-4", "swimmer-5"]
    first = runner.invoke(main, ["train", *ids, "--steps", "40", "--out", str(out), *TINY_TRAIN])
    assert first.exit_code == 0, first.output
    train = checkpoint.load(out / "checkpoint.pt")["config"]["train"]
    assert (train["env"]["id"], train["env"]["more"]) == ("swimmer-4", ["swimmer-5"])
    assert "swimmer-4 is a family: agents observe position='end-flags'" in first.output
    assert train["env"]["options"]["position"] == "end-flags"  # the measured best identity
    other = runner.invoke(main, ["train", "swimmer-4", "swimmer-7", "--out", str(out), "--resume"])
    assert other.exit_code != 0 and "more_envs=['swimmer-5']" in other.output
    resumed = runner.invoke(main, ["train", *ids, "--steps", "80", "--out", str(out), "--resume"])
    assert resumed.exit_code == 0 and "resuming" in resumed.output
    evaluated = runner.invoke(
        main, ["eval", str(out / "checkpoint.pt"), "--episodes", "2", "--env", "swimmer-9"]
    )
    assert evaluated.exit_code == 0 and "+-" in evaluated.output, evaluated.output


def test_train_resume_and_eval_from_the_command_line(tmp_path):
    out = tmp_path / "run"
    runner = CliRunner()
    result = runner.invoke(
        main, ["train", "hopper-2x2", "--steps", "80", "--out", str(out), *TINY_TRAIN]
    )
    assert result.exit_code == 0, result.output
    assert {p.name for p in out.iterdir()} >= {
        "checkpoint.pt",
        "metrics.csv",
        "tensorboard",
        "learning_curve.png",
    }
    again = runner.invoke(main, ["train", "hopper-2x2", "--steps", "40", "--out", str(out)])
    assert again.exit_code != 0 and "pass --resume" in again.output
    resumed = runner.invoke(
        main, ["train", "hopper-2x2", "--steps", "120", "--out", str(out), "--resume", "--quiet"]
    )
    assert resumed.exit_code == 0 and "resuming" in resumed.output
    assert len((out / "metrics.csv").read_text().splitlines()) == 1 + 3
    evaluated = runner.invoke(
        main, ["eval", str(out / "checkpoint.pt"), "--episodes", "2", "--fault", "knee=zero"]
    )
    assert evaluated.exit_code == 0, evaluated.output
    assert "return" in evaluated.output and "+-" in evaluated.output
    clobber = runner.invoke(
        main, ["eval", str(out / "checkpoint.pt"), "--video", str(out / "x.pt")]
    )
    assert clobber.exit_code != 0 and "name a .mp4 / .gif file" in clobber.output


def test_eval_and_train_refuse_bad_input_in_one_line(tmp_path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x00\x01")
    for args in (
        ["eval", str(junk)],
        ["train", "hopper-2x2", "--algo", "ppo"],
        ["train", "hopper-2x2", "--set", "lr"],
    ):
        result = CliRunner().invoke(main, args)
        assert result.exit_code != 0 and "Traceback" not in result.output, result.output
    assert "is not a MAT checkpoint" in CliRunner().invoke(main, ["eval", str(junk)]).output


def test_export_command_refuses_bad_input_in_one_line(tmp_path):
    junk = tmp_path / "junk.pt"
    junk.write_text("not a checkpoint")
    for args, message in (
        (["export", str(tmp_path / "missing.pt")], "no checkpoint at"),
        (["export", str(junk), "-o", str(tmp_path / "out")], "is not a MAT checkpoint"),
        (["export", str(tmp_path)], "is a directory, not a checkpoint; pass the checkpoint.pt"),
    ):
        result = CliRunner().invoke(main, args)
        assert (
            result.exit_code != 0 and message in result.output and "Traceback" not in result.output
        )
    assert not (tmp_path / "out").exists()


DOCUMENTED = (
    "README.md", "BENCHMARKS.md", "docs/RESULTS.md", "docs/FEWSHOT.md", "docs/GUIDE.md",
    "docs/REAL_ROBOTS.md", "docs/CUSTOM_ENVS.md",
)  # fmt: skip
INVOCATION = re.compile(r"(?:^|`|&& )\s*mat ([^`&#\n]*)", re.MULTILINE)


def documented_invocations() -> list[tuple[str, str]]:
    """Every `mat ...` command line the docs and the commands' help show, with where it was."""
    root = Path(__file__).resolve().parents[1]
    sources = {name: (root / name).read_text() for name in DOCUMENTED}
    groups = [("mat", main)]
    while groups:
        path, group = groups.pop()
        sources[f"{path} --help"] = group.help
        for name, command in group.commands.items():
            if isinstance(command, click.Group):
                groups.append((f"{path} {name}", command))
            else:
                sources[f"{path} {name} --help"] = command.help or ""
    return [
        (where, match.group(1).strip())
        for where, text in sources.items()
        for match in INVOCATION.finditer(text)
    ]


def test_every_documented_command_and_option_exists():
    invocations = documented_invocations()
    assert any(line.startswith("bench train") for _, line in invocations)
    for where, line in invocations:
        command, words = main, [word for word in line.split() if word != "..."]
        while words and isinstance(command, click.Group) and words[0] in command.commands:
            command = command.commands[words.pop(0)]
        runs_alone = getattr(command, "invoke_without_command", False)  # e.g. `mat zoo`
        named_none = command is main or (
            isinstance(command, click.Group) and words and not runs_alone
        )
        assert not named_none, f"{where}: `mat {line}` names no command"
        options = {opt for param in command.params for opt in (*param.opts, *param.secondary_opts)}
        for word in words:
            if word.startswith("--") and word not in ("--help",):
                assert word in options, f"{where}: `mat {line}`: {command.name} has no {word}"


def test_ctrl_c_says_what_the_checkpoint_holds_and_how_to_resume(tmp_path, monkeypatch):
    from mat_sdk.training.trainer import Trainer

    learn = Trainer.learn

    def interrupted_after_two_updates(self, total_steps, callback=None, progress_bar=True):
        def press_ctrl_c(trainer, metrics):
            if metrics["updates"] == 2:
                raise KeyboardInterrupt

        return learn(self, total_steps, callback=press_ctrl_c, progress_bar=progress_bar)

    monkeypatch.setattr(Trainer, "learn", interrupted_after_two_updates)
    out = tmp_path / "run"
    args = ["train", "hopper-2x2", "--steps", "400", "--out", str(out), *TINY_TRAIN]
    result = CliRunner().invoke(main, [*args, "--set", "checkpoint_every=1"])
    assert result.exit_code == 130, result.output
    assert f"{out / 'checkpoint.pt'} holds the run at 80 steps" in result.output
    assert f"mat train hopper-2x2 --out {out} --steps 400 --resume" in result.output
    monkeypatch.setattr(Trainer, "learn", learn)
    resumed = CliRunner().invoke(
        main, ["train", "hopper-2x2", "--out", str(out), "--steps", "400", "--resume", "--quiet"]
    )
    assert (
        resumed.exit_code == 0 and "resuming" in resumed.output and "at 80 steps" in resumed.output
    )


def test_a_bug_keeps_its_traceback_and_asks_for_a_report(monkeypatch):
    import mat_sdk.envs

    def broken(*args, **kwargs):
        return {}["no such key"]  # a bug, not the user's mistake

    monkeypatch.setattr(mat_sdk.envs, "make", broken)
    result = CliRunner().invoke(main, ["rollout", "hopper-2x2"])
    assert result.exit_code == 1
    assert "Traceback" in result.output and "KeyError" in result.output
    assert "a bug in MAT SDK" in result.output and "Please report it" in result.output

    def numpy_error(*args, **kwargs):  # a ValueError, but raised by a library, not by us
        return np.zeros(2).reshape(3)

    monkeypatch.setattr(mat_sdk.envs, "make", numpy_error)
    result = CliRunner().invoke(main, ["rollout", "hopper-2x2"])
    assert result.exit_code == 1 and "Traceback" in result.output and "a bug" in result.output


def test_contradicting_options_are_refused_in_one_line(tmp_path):
    cases = {
        ("train", "hopper-2x2", "--set", "num_envs=8"): "num_envs has an option of its own; "
        "use --num-envs",
        ("train", "hopper-2x2", "--set", "seed=3"): "use --seed",
        ("train", "hopper-2x2", "--set", "faults={}"): "use --fault",
        ("train", "hopper-2x2", "--set", "env=walker-6x1"): "use the ENV_ID argument",
        ("train", "hopper-2x2", "--set", "algo=mappo"): "use --algo",
        ("finetune", "x.pt", "--set", "lr=0.1"): "lr has an option of its own; use --lr",
        ("train", "hopper-2x2", "--steps", "-5"): "-5 is not in the range x>=1",
        ("train", "hopper-2x2", "--set", 'env_options={"bogus": 1}', "--quiet"): (
            "unknown env option(s) ['bogus'] for hopper-2x2"
        ),
        ("train", "hopper-2x2", "--set", "shuffle_agents=maybe"): (
            "shuffle_agents must be true or false, got 'maybe'"
        ),
        ("train", "hopper-2x2", "--seed", str(2**70)): "seed must be an integer in 0..2**31 - 1",
        ("train", "hopper-2x2", "--set", "attention_window=0"): (
            "attention_window must be an integer >= 2 or null, got 0"
        ),
    }
    for args, message in cases.items():
        result = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "never")])
        assert result.exit_code != 0, args
        assert message in result.output, (args, result.output)
        assert "Traceback" not in result.output
    assert not (tmp_path / "never" / "checkpoint.pt").exists()
    awake = CliRunner().invoke(main, ["bench", "jitter", "--keep-awake"])
    assert (
        awake.exit_code == 2
        and "--keep-awake keeps the loop's core awake: give it with --cpu" in awake.output
    )


def test_device_auto_trains_on_the_cpu_here(tmp_path):
    out = tmp_path / "auto"
    args = ["train", "hopper-2x2", "--steps", "40", "--out", str(out), "--device", "auto"]
    result = CliRunner().invoke(main, [*args, *TINY_TRAIN])
    assert result.exit_code == 0, result.output
    import torch

    from mat_sdk.policy import checkpoint

    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert checkpoint.load(out / "checkpoint.pt")["rng"]["device"] == expected


def test_ray_without_ray_names_the_ray_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # as where Ray is not installed
    result = CliRunner().invoke(
        main, ["train", "hopper-2x2", "--ray", "--out", str(tmp_path / "r"), *TINY_TRAIN]
    )
    assert result.exit_code == 1 and "pip install 'mat-sdk[ray]'" in result.output
    assert "Traceback" not in result.output


def test_resume_applies_how_to_run_and_refuses_what_to_train(tmp_path):
    out = tmp_path / "run"
    runner = CliRunner()
    first = runner.invoke(
        main, ["train", "hopper-2x2", "--steps", "40", "--out", str(out), *TINY_TRAIN]
    )
    assert first.exit_code == 0, first.output
    resume = ["train", "hopper-2x2", "--steps", "80", "--out", str(out), "--resume", "--quiet"]
    for extra, field in (
        (["--num-envs", "8"], "num_envs=4; got num_envs=8"),
        (["--set", "lr=0.1"], "lr=0.0003; got lr=0.1"),
        (["--recipe", "paper"], "recipe='fast'; got recipe='paper'"),
        (["--fault", "knee=zero"], "faults={}; got faults={'knee': 'zero'}"),
        (["--algo", "mat-dec"], "algo='mat'; got algo='mat-dec'"),
        (["--seed", "1"], "seed=0; got seed=1"),
    ):
        refused = runner.invoke(main, [*resume, *extra])
        assert refused.exit_code != 0 and field in refused.output, (extra, refused.output)
        assert "Traceback" not in refused.output
    other_env = runner.invoke(main, ["train", "walker-2x3", *resume[2:]])
    assert other_env.exit_code != 0 and "env='hopper-2x2'; got env='walker-2x3'" in other_env.output
    same = runner.invoke(main, [*resume, "--num-envs", "4", "--workers", "1"])
    assert same.exit_code == 0, same.output
    assert "at 40 steps (with workers=1)" in same.output  # applied, and said so


def test_trainer_and_mat_train_build_the_same_run_for_a_family(tmp_path):
    """The library decides the family identity where Trainer builds its env, so the Python API
    and the command line train the same policy from the same id, and record the same config
    in their checkpoints."""
    from mat_sdk.training.trainer import Trainer

    result = CliRunner().invoke(
        main, ["train", "swimmer-4", "--steps", "40", "--out", str(tmp_path), *TINY_TRAIN]
    )
    assert result.exit_code == 0, result.output
    cli = checkpoint.load(tmp_path / "checkpoint.pt")["config"]["train"]
    options = {"num_envs": 4, "rollout_length": 10, "num_minibatches": 2, "ppo_epochs": 1}
    with Trainer("swimmer-4", env_options={"episode_limit": 20}, **options) as trainer:
        assert trainer.notes and "is a family" in trainer.notes[0]
        trainer.learn(40, progress_bar=False)
        saved = trainer.save(tmp_path / "api.pt")
    api = checkpoint.load(saved)["config"]["train"]
    assert api["env"]["options"] == {"episode_limit": 20, "position": "end-flags"}
    assert api == cli
