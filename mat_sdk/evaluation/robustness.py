"""Robustness sweeps: a policy's episodes on its robot with one factor of the domain
randomization held at each of several values (friction 0.4-1.2, payload 0-2 kg, latency 0-2
steps, ...), everything else nominal.

    points = sweep(CheckpointPolicy.from_checkpoint("go2.pt"), "payload", [0, 1, 2])
    print(table(points, "payload"))
    plot({"randomized": [points]}, "payload", "payload.png")   # seeds' mean per label
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mat_sdk.envs.mujoco.randomization import setting
from mat_sdk.evaluation.episodes import CheckpointPolicy, Episodes, evaluate_episodes

Points = list[tuple[float, Episodes]]


def parse_values(text: str) -> list[float]:
    """`"0.4:1.2:5"` (low:high:count, evenly spaced) or `"0,1,2"` -> the values to sweep."""
    try:
        if ":" in text:
            low, high, count = text.split(":")
            if int(count) < 2:
                raise ValueError
            return [round(float(v), 10) for v in np.linspace(float(low), float(high), int(count))]
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(
            f"sweep values {text!r}: give low:high:count (count >= 2) or a comma-separated list"
        ) from None


def sweep(
    loaded: CheckpointPolicy,
    factor: str,
    values: Sequence[float],
    episodes: int = 10,
    seed: int = 10_000,
    **env_options: Any,
) -> Points:
    """Episodes at each value of `factor`, on the policy's robot with that factor alone (the
    randomization the policy trained under is replaced, so each point measures one factor)."""
    points = []
    for value in values:
        options = {**env_options, "randomize": setting(factor, value).to_dict()}
        result = evaluate_episodes(loaded, episodes, seed=seed, **options)
        points.append((float(value), result))
    return points


def table(points: Points, factor: str) -> str:
    """A Markdown table: per value, return mean +- std, falls, forward speed."""
    lines = [f"| {factor} | return | falls | forward speed (m/s) |", "|---|---|---|---|"]
    for value, result in points:
        speed = (
            "-"
            if np.isnan(result.speeds).all()
            else f"{np.nanmean(result.speeds):.3f} ± {np.nanstd(result.speeds):.3f}"
        )
        lines.append(
            f"| {value:g} | {np.mean(result.returns):,.1f} ± {np.std(result.returns):,.1f} "
            f"| {sum(result.ended)} / {len(result.ended)} | {speed} |"
        )
    return "\n".join(lines)


def plot(runs: Mapping[str, Sequence[Points]], factor: str, path: str | Path) -> Path:
    """Return, fall rate and forward speed against the factor's value: per label, the mean
    over its policies (seeds) with each seed's own curve faint."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    measures = {
        "return": lambda r: float(np.mean(r.returns)),
        "fall rate": lambda r: float(np.mean(r.ended)),
        "forward speed (m/s)": lambda r: (
            float(np.nanmean(r.speeds)) if not np.isnan(r.speeds).all() else np.nan
        ),
    }
    figure, axes = plt.subplots(1, len(measures), figsize=(4.2 * len(measures), 3.4))
    for (label, seeds), colour in zip(runs.items(), plt.rcParams["axes.prop_cycle"], strict=False):
        values = [value for value, _ in seeds[0]]
        for axis, (name, measure) in zip(axes, measures.items(), strict=True):
            curves = np.array([[measure(result) for _, result in points] for points in seeds])
            for curve in curves:
                axis.plot(values, curve, color=colour["color"], alpha=0.25, linewidth=1)
            axis.plot(values, curves.mean(axis=0), color=colour["color"], marker="o",
                      label=f"{label} ({len(seeds)} seed{'s' * (len(seeds) > 1)})")  # fmt: skip
            axis.set_xlabel(factor)
            axis.set_title(name)
    axes[0].legend(fontsize=8)
    figure.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path
