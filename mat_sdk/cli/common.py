"""What every `mat` command shares: one-line errors for a user's mistakes, the options that
recur, and how a command line's values become library arguments."""

from __future__ import annotations

import contextlib
import functools
import json
from collections.abc import Callable, Iterator
from pathlib import Path

import click

OUR_PACKAGES = ("mat_sdk", "mat_export", "mat_runtime")
# What our code raises on purpose for a user's mistake; raised from anywhere else, it is a bug.
EXPECTED = (ValueError, OSError, RuntimeError)
# The extra that brings each optional module.
EXTRAS = {"ray": "ray", **dict.fromkeys(
    ("torch", "onnx", "onnxscript", "mujoco", "dm_control", "pettingzoo", "gymnasium",
     "gymnasium_robotics", "tensorboard", "matplotlib", "tqdm", "imageio", "imageio_ffmpeg"),
    "train",
)}  # fmt: skip


def user_errors(command: Callable) -> Callable:
    """Turn a user's mistake into one line and exit code 1; keep the traceback of a bug.

    A mistake is an error our code raises on purpose (`EXPECTED`, raised in one of
    `OUR_PACKAGES`), an OS error about a path (permissions, a full disk), or a missing
    optional package; anything else is a bug, and its traceback is what a bug report needs.
    """

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except click.ClickException:
            raise
        except ModuleNotFoundError as error:
            extra = EXTRAS.get((error.name or "").split(".")[0])
            if extra is None:
                _report_bug()
            raise click.ClickException(
                f"{error}. This command needs the {extra} extra: pip install 'mat-sdk[{extra}]'"
            ) from None
        except EXPECTED as error:
            about_a_path = isinstance(error, OSError) and error.filename is not None
            if not (about_a_path or _raised_by_us(error)):
                _report_bug()
            raise click.ClickException(str(error)) from None
        except Exception:
            _report_bug()

    return wrapper


def _raised_by_us(error: BaseException) -> bool:
    """Whether the innermost frame of the error's traceback is in one of our packages."""
    frame = error.__traceback__
    while frame is not None and frame.tb_next is not None:
        frame = frame.tb_next
    module = frame.tb_frame.f_globals.get("__name__", "") if frame else ""
    return module.split(".")[0] in OUR_PACKAGES


def _report_bug() -> None:
    """Print the traceback of the exception being handled and ask for a report; exit 1."""
    import traceback

    traceback.print_exc()
    click.echo(
        "\nmat: this is an unexpected error, a bug in MAT SDK rather than a problem with your "
        "input. Please report it with the traceback above and the command you ran.",
        err=True,
    )
    raise SystemExit(1) from None


@contextlib.contextmanager
def resumable(checkpoint: Path, resume: str) -> Iterator[None]:
    """Ctrl-C: say what the last checkpoint holds and the command that continues from it."""
    try:
        yield
    except KeyboardInterrupt:
        from mat_sdk.policy import checkpoint as checkpoints

        if checkpoint.is_file():
            steps = checkpoints.load(checkpoint)["progress"]["steps"]
            where = f"{checkpoint} holds the run at {steps:,} steps; continue with:\n  {resume}"
        else:
            where = "no checkpoint was written yet; run the same command again to start over"
        click.echo(f"\ninterrupted; {where}", err=True)
        raise SystemExit(130) from None


def parse_faults(values: tuple[str, ...]) -> tuple:
    """`("bfoot=zero", "agent_2=remove", "FR_calf_joint=weak:0.5")` -> `Fault`s, each
    checked (`Fault.parse`); the env checks the names."""
    from mat_sdk.envs.core.faults import Fault, faults_of

    try:
        return faults_of(Fault.parse(value) for value in values)
    except ValueError as error:
        raise click.BadParameter(str(error), param_hint="--fault") from None


def fault_option(purpose: str) -> Callable:
    """`--fault NAME=zero|remove|weak:S`, repeatable: the command gets the `Fault`s
    (`parse_faults`; none: an empty tuple)."""
    return click.option(
        "--fault", "faults", multiple=True, metavar="NAME=zero|remove|weak:S", help=purpose,
        callback=lambda context, parameter, values: parse_faults(values),
    )  # fmt: skip


def set_option(purpose: str = "Any training option, e.g. lr=3e-4.") -> Callable:
    """`--set KEY=VALUE`, repeatable (see `parse_settings`)."""
    return click.option("--set", "settings", multiple=True, metavar="KEY=VALUE", help=purpose)


def trust_option(argument: str = "checkpoint") -> Callable:
    """`--trust-env-code`: the opt-in to import a `module:function` env id read from the file
    the command's `argument` names. The command gets that argument as `envs.Trusted` (the
    library's one way to vouch for a file), not the flag."""

    def decorate(command: Callable) -> Callable:
        @functools.wraps(command)
        def vouched(*args, trust_env_code: bool, **kwargs):
            if trust_env_code:
                from mat_sdk.envs.registry import Trusted

                kwargs[argument] = Trusted(kwargs[argument])
            return command(*args, **kwargs)

        return click.option(
            "--trust-env-code",
            is_flag=True,
            help="Import the module:function env id that the checkpoint records (it runs that "
            "module's code): only for files you trust. Built-in ids need no opt-in.",
        )(vouched)

    return decorate


def quiet_option() -> Callable:
    return click.option("--quiet", is_flag=True, help="No progress bar.")


def parse_counts(text: str, option: str) -> tuple[int, ...]:
    """`2,6,64` -> (2, 6, 64): positive integers, or a one-line error naming the option."""
    try:
        counts = tuple(int(part) for part in text.split(","))
    except ValueError:
        counts = ()
    if not counts or min(counts) < 1:
        raise click.BadParameter(f"{option} takes positive integers like 2,6,64, got {text!r}")
    return counts


def parse_settings(
    values: tuple[str, ...], own: dict[str, str] | None = None, param_hint: str = "--set"
) -> dict:
    """`("lr=3e-4", "shuffle_agents=true")` -> typed values (JSON, else the text).

    `own`: the fields this command sets through options of their own (field -> option); a
    `--set` of one of them is refused, since the two would contradict each other.
    """
    settings = {}
    for value in values:
        key, sep, raw = value.partition("=")
        if not sep:
            raise click.BadParameter(f"{value!r}: use KEY=VALUE", param_hint=param_hint)
        if own and key in own:
            raise click.BadParameter(
                f"{value!r}: {key} has an option of its own; use {own[key]} instead",
                param_hint=param_hint,
            )
        try:
            settings[key] = json.loads(raw)
        except json.JSONDecodeError:
            settings[key] = raw
    return settings
