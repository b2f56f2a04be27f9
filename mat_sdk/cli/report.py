"""`mat report`: runs compared the way the field asks."""

from __future__ import annotations

from pathlib import Path

import click

from mat_sdk.cli import main
from mat_sdk.cli.common import user_errors


@main.command()
@click.argument("runs", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
    help="Directory for report.md and the curves.",
)  # fmt: skip
@user_errors
def report(runs, out_dir) -> None:
    """Compare runs the way the field asks: IQM and mean with 95 % bootstrap CIs.

    RUNS are run directories (or their parents, e.g. the OUT of `mat train --seeds`) holding
    evaluations.json. Per task: IQM and mean over seeds of each seed's absolute metric, with
    stratified-bootstrap confidence intervals (rliable), sample-efficiency curves with CI
    bands, and the probability of improvement between algorithms. Needs
    pip install 'mat-sdk[report]'.

    \b
    Example:
      mat train cheetah-6x1 --seeds 5 --steps 2000000 --out runs/cheetah-mat
      mat train cheetah-6x1 --seeds 5 --steps 2000000 --algo mappo --out runs/cheetah-mappo
      mat report runs/cheetah-mat runs/cheetah-mappo --out docs/cheetah
    """
    try:
        import rliable  # noqa: F401
    except ImportError:
        raise click.ClickException(
            "mat report needs rliable: pip install 'mat-sdk[report]'"
        ) from None
    from mat_sdk.evaluation.report import write_report

    click.echo(write_report(list(runs), out_dir))
    click.echo(f"written: {out_dir / 'report.md'}")
