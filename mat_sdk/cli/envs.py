"""`mat envs` and `mat rollout`: what envs there are, and one working at random."""

from __future__ import annotations

import click

from mat_sdk.cli import main
from mat_sdk.cli.common import fault_option, user_errors


@main.command()
@user_errors
def envs() -> None:
    """List the environment ids with their agents, observation and action sizes.

    \b
    swimmer-N works for any N >= 3 (N - 1 agents); MaMuJoCo scenarios are
    available as mamujoco:<Scenario>-<conf>, e.g. mamujoco:HalfCheetah-6x1;
    coordination-N (any N >= 2) is a one-step discrete game that MAT solves in
    seconds (act: its number of choices). Ids that installed packages register
    under the entry-point group mat_sdk.envs are listed too. [family]: one
    observation size for any agent count (swimmer-N, mamujoco:ManySegmentSwimmer-Kx2,
    mamujoco:ManySegmentAnt-Kx2), so one policy serves them all.
    """
    from mat_sdk.envs import list_envs

    rows = list_envs()
    click.echo(
        "Your own robot or PettingZoo env: an id module:function (e.g. my_robots:arm, "
        "imported from the current directory or PYTHONPATH), see docs/CUSTOM_ENVS.md.\n"
    )
    width = max(26, *(len(r["id"]) for r in rows))
    click.echo(f"{'id':<{width}} {'agents':>6} {'obs':>5} {'act':>4} {'limit':>6}  about")
    for r in rows:
        click.echo(
            f"{r['id']:<{width}} {r['agents']:>6} {r['obs']:>5} {r['act']:>4} "
            f"{r['episode_limit']:>6}  {'[family] ' if r['family'] else ''}{r['about']}"
        )


@main.command()
@click.argument("env_id")
@click.option("--steps", default=1000, show_default=True, help="Env steps to run.")
@click.option("--seed", default=0, show_default=True)
@fault_option("Break a joint or agent.")
@user_errors
def rollout(env_id: str, steps: int, seed: int, faults: tuple) -> None:
    """Roll out a random team on ENV_ID and print the episode returns.

    Example: mat rollout cheetah-6x1 --steps 2000 --fault bfoot=zero
    """
    from mat_sdk.envs import random_rollout

    env, returns = random_rollout(env_id, steps, seed, faults=faults)
    agents = env.possible_agents
    click.echo(f"{env_id}: agents {agents}, obs {env.observation_space(agents[0]).shape}")
    click.echo(f"random team, {steps} steps: episode returns {[round(r, 2) for r in returns]}")
