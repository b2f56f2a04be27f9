"""Robustness sweeps of groups of policies (e.g. trained with and without randomization, a few
seeds each): per factor, a Markdown table of each group's seed means and a plot.

    PYTHONPATH=examples python -m benchmarks.robustness \\
        --group plain='runs/go2-mat/seed_*/checkpoint.pt' \\
        --group randomized='runs/go2-mat-rand/seed_*/checkpoint.pt' \\
        --sweep friction=0.4:1.2:5 --sweep payload=0:2:5 --sweep latency=0,1,2 \\
        --episodes 10 --env-option 'command=[0.7,0,0]' --out docs/real-robots/robustness

Each (checkpoint, factor, value) is evaluated once and kept in OUT/results.json, so a rerun
after more policies finish only evaluates what is new.
"""

from __future__ import annotations

import glob
import json
from pathlib import Path

import click
import numpy as np

from mat_sdk.cli.common import parse_settings
from mat_sdk.common.files import write_text_atomic
from mat_sdk.envs import Trusted
from mat_sdk.evaluation import robustness
from mat_sdk.evaluation.episodes import CheckpointPolicy, Episodes


@click.command()
@click.option(
    "--group",
    "groups",
    multiple=True,
    required=True,
    metavar="LABEL=GLOB",
    help="Checkpoints of one group (its seeds); repeat a LABEL to add more.",
)
@click.option("--sweep", "sweeps", multiple=True, required=True, metavar="FACTOR=VALUES")
@click.option("--episodes", default=10, show_default=True)
@click.option("--env-option", "env_options", multiple=True, metavar="KEY=VALUE")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True)
def main(groups, sweeps, episodes, env_options, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    store = out / "results.json"
    results = json.loads(store.read_text()) if store.exists() else {}
    options = parse_settings(env_options, param_hint="--env-option")
    paths = {}
    for group in groups:
        label, _, pattern = group.partition("=")
        matched = sorted(glob.glob(pattern))
        if not matched:
            raise click.BadParameter(f"{pattern!r} matches no checkpoint", param_hint="--group")
        paths.setdefault(label, []).extend(matched)  # a label given twice gathers both
    lines = [f"{episodes} episodes per point, env options {options or 'none'}; per group the "
             "mean over its seeds, the seeds' range in brackets, then each checkpoint's own "
             "speed / falls.", ""]  # fmt: skip
    lines += [f"- {label}: {', '.join(checkpoints)}" for label, checkpoints in paths.items()]
    for text in sweeps:
        factor, _, values = text.partition("=")
        values = robustness.parse_values(values)
        runs: dict[str, list[robustness.Points]] = {}
        for label, checkpoints in paths.items():
            runs[label] = []
            for path in checkpoints:
                key = f"{path} {factor} {episodes} {json.dumps(options, sort_keys=True)}"
                done = {float(v): e for v, e in results.get(key, [])}
                todo = [v for v in values if v not in done]
                if todo:
                    # the user named these files
                    loaded = CheckpointPolicy.from_checkpoint(Trusted(path))
                    for value, result in robustness.sweep(
                        loaded, factor, todo, episodes, **options
                    ):
                        done[value] = result.__dict__
                        click.echo(f"{path} {factor}={value:g}: {result.summary()}", err=True)
                    results[key] = sorted(done.items())
                    write_text_atomic(store, json.dumps(results, indent=1))
                runs[label].append([(v, Episodes(**done[v])) for v in values])
        lines += _table(runs, factor, values) + _per_checkpoint(runs, paths, factor, values)
        robustness.plot(runs, factor, out / f"{factor}.png")
    report = "\n".join(lines) + "\n"
    write_text_atomic(out / "README.md", report)
    click.echo(report)


def _table(runs, factor: str, values) -> list[str]:
    labels = list(runs)
    head = " | ".join(f"{label}: speed (m/s) / falls / return" for label in labels)
    lines = ["", f"### {factor}", "", f"| {factor} | {head} |", "|---" * (1 + len(labels)) + "|"]
    for k, value in enumerate(values):
        cells = []
        for label in labels:
            points = [seed[k][1] for seed in runs[label]]
            speed = [np.nanmean(p.speeds) for p in points]
            falls = [sum(p.ended) for p in points]
            ret = [np.mean(p.returns) for p in points]
            cells.append(
                f"{np.mean(speed):.3f} [{min(speed):.2f}, {max(speed):.2f}] / "
                f"{sum(falls)} of {sum(len(p.ended) for p in points)} / {np.mean(ret):,.0f}"
            )
        lines.append(f"| {value:g} | " + " | ".join(cells) + " |")
    return lines


def _per_checkpoint(runs, paths, factor: str, values) -> list[str]:
    names = [f"{label} {Path(path).parent.name}" for label in runs for path in paths[label]]
    lines = ["", f"| {factor} | " + " | ".join(names) + " |", "|---" * (1 + len(names)) + "|"]
    for k, value in enumerate(values):
        points = [seed[k][1] for label in runs for seed in runs[label]]
        cells = [f"{np.nanmean(p.speeds):.2f} / {sum(p.ended)}" for p in points]
        lines.append(f"| {value:g} | " + " | ".join(cells) + " |")
    return lines


if __name__ == "__main__":
    main()
