"""`mat zoo`: the trained models that ship with the project, and adding one."""

from __future__ import annotations

from pathlib import Path

import click

from mat_sdk.cli import main
from mat_sdk.cli.common import trust_option, user_errors


@main.group(invoke_without_command=True)
@click.pass_context
@user_errors
def zoo(context: click.Context) -> None:
    """The model zoo: trained policies that ship with the project, used as zoo:NAME.

    \b
    zoo:NAME works wherever a checkpoint or a bundle does:
      mat eval zoo:NAME --episodes 20        reproduces the card's return
      mat finetune zoo:NAME NEW_ENV_ID       adapts it
      mat export zoo:NAME -o DIR             re-exports it
      mat_runtime.Policy.load("zoo:NAME")    its bundle, without torch
    The zoo is zoo/ of a source checkout, or the directory MAT_ZOO names.
    """
    if context.invoked_subcommand is not None:
        return
    from mat_sdk.zoo import cards

    found, problems = cards()
    for problem in problems:
        click.echo(problem, err=True)
    if not found:
        from mat_runtime.zoo import zoo_dir

        click.echo(f"no models in {zoo_dir()}")
        return
    click.echo("| name | env | algo | steps | seed | return (95 % CI) | random team |")
    click.echo("|---|---|---|---|---|---|---|")
    for card in found:
        score = card["return"]
        low, high = score["ci95"]
        click.echo(
            f"| zoo:{card['name']} | {card['env_id']} | {card['algo']} | {card['steps']:,} | "
            f"{card['seed']} | {score['mean']:.1f} ({low:.1f} to {high:.1f}) | "
            f"{card['random_team_return']:.1f} |"
        )


@zoo.command("add")
@click.argument("run", type=click.Path(exists=True, path_type=Path))
@click.argument("name")
@click.option("--command", "made_by", required=True, help="The command that trained it.")
@click.option(
    "--episodes", default=20, show_default=True, type=click.IntRange(min=1),
    help="Episodes the card reports.",
)  # fmt: skip
@click.option("--force", is_flag=True, help="Replace a model of that name.")
@trust_option("run")
@user_errors
def zoo_add(run: Path, name: str, made_by: str, episodes: int, force: bool) -> None:
    """Add RUN (a run directory or checkpoint) to the zoo as NAME, with its card.

    NAME is letters, digits, '.', '_' and '-'. The model is exported, evaluated and written
    beside the zoo, then moved into place: a failure leaves the zoo as it was.
    """
    from mat_sdk.zoo import add, card_text

    card = add(run, name, made_by, episodes, force=force)
    click.echo(card_text(card))
