"""The `mat` command line. Heavy imports happen inside commands, so `--help` stays instant."""

from __future__ import annotations

import functools
from collections.abc import Callable

import click


def user_errors(command: Callable) -> Callable:
    """Turn a user's mistake (ValueError, FileNotFoundError) into one line and exit code 1."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except (ValueError, FileNotFoundError, FileExistsError) as error:
            raise click.ClickException(str(error)) from None
        except ImportError as error:
            raise click.ClickException(
                f"{error}. This command needs the training extra: pip install 'mat-sdk[train]'"
            ) from None

    return wrapper


def parse_faults(values: tuple[str, ...]) -> dict[str, str]:
    """`("bfoot=zero", "agent_2=remove")` -> `{"bfoot": "zero", "agent_2": "remove"}`."""
    faults = {}
    for value in values:
        name, sep, mode = value.partition("=")
        if not sep or not name or mode not in ("zero", "remove"):
            raise click.BadParameter(
                f"{value!r}: use NAME=zero or NAME=remove", param_hint="--fault"
            )
        faults[name] = mode
    return faults


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mat-sdk")
def main() -> None:
    """MAT SDK: train Multi-Agent Transformer policies on multi-agent MuJoCo robots,
    export them to ONNX, and run them without torch.

    \b
    Start here:
      mat envs                          the robots and their agent decompositions
      mat rollout cheetah-6x1           a random team, to see an env work
      mat bench envs                    env stepping speed
    """


@main.command()
@user_errors
def envs() -> None:
    """List the environment ids with their agents, observation and action sizes.

    \b
    swimmer-N works for any N >= 3 (N - 1 agents); MaMuJoCo scenarios are
    available as mamujoco:<Scenario>-<conf>, e.g. mamujoco:HalfCheetah-6x1.
    """
    from mat_sdk.envs import list_envs

    rows = list_envs()
    click.echo(f"{'id':<26} {'agents':>6} {'obs':>5} {'act':>4} {'limit':>6}  about")
    for r in rows:
        click.echo(
            f"{r['id']:<26} {r['agents']:>6} {r['obs']:>5} {r['act']:>4} "
            f"{r['episode_limit']:>6}  {r['about']}"
        )


@main.command()
@click.argument("env_id")
@click.option("--steps", default=1000, show_default=True, help="Env steps to run.")
@click.option("--seed", default=0, show_default=True)
@click.option(
    "--fault", "faults", multiple=True, metavar="NAME=zero|remove", help="Break a joint or agent."
)
@user_errors
def rollout(env_id: str, steps: int, seed: int, faults: tuple[str, ...]) -> None:
    """Roll out a random team on ENV_ID and print the episode returns.

    Example: mat rollout cheetah-6x1 --steps 2000 --fault bfoot=zero
    """
    import numpy as np

    from mat_sdk.envs import make

    env = make(env_id, faults=parse_faults(faults), seed=seed)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    click.echo(f"{env_id}: agents {env.agents}, obs {env.observation_space(env.agents[0]).shape}")
    episode_return, returns = 0.0, []
    for _ in range(steps):
        if not env.agents:
            returns.append(episode_return)
            episode_return = 0.0
            env.reset()
        actions = {a: rng.uniform(-1, 1, env.action_space(a).shape) for a in env.agents}
        _, rewards, _, _, _ = env.step(actions)
        episode_return += next(iter(rewards.values()))
    returns.append(episode_return)
    click.echo(f"random team, {steps} steps: episode returns {[round(r, 2) for r in returns]}")


@main.group()
def bench() -> None:
    """Benchmarks that print Markdown tables (paste them into BENCHMARKS.md)."""


@bench.command("envs")
@click.option("--seconds", default=1.0, show_default=True, help="Time per measured variant.")
@user_errors
def bench_envs(seconds: float) -> None:
    """Our env step vs dm_control's bare physics step, and vectorised rates."""
    from mat_sdk.bench.envs import main as run

    run(seconds=seconds)
