"""`mat report RUN_DIR... --out DIR`: runs' evaluations, compared the way the field asks.

From every `evaluations.json` under the given directories (`mat_sdk.evaluation.protocol`), per task:
the interquartile mean (IQM) and the mean over seeds, each with a 95 % stratified-bootstrap
confidence interval (rliable, Agarwal et al. 2021), of each seed's absolute metric (or its
last evaluation, for runs without one); sample-efficiency curves (IQM over seeds at each
evaluation, with its CI band); the env steps at which each algorithm's curve reaches each
other's final value, read off the plotted curve itself (so a crossing quoted in docs uses the
figure's own smoothing); and the probability that one algorithm improves on another.
Writes DIR/report.md and one PNG of curves per task.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np

from mat_sdk.evaluation.protocol import (
    BOOTSTRAP_REPS,
    CONFIDENCE,
    interval_estimates,
    read_evaluations,
)


def _final(run: dict[str, Any]) -> tuple[float, str]:
    """A seed's score: the mean of its absolute metric, else of its last evaluation."""
    if "absolute_metrics" in run:
        return float(np.mean(run["absolute_metrics"]["return"])), "absolute"
    steps = sorted((k for k in run if k.startswith("step_")), key=lambda k: int(k[5:]))
    if not steps:
        return float("nan"), "none"
    return float(np.mean(run[steps[-1]]["return"])), "last evaluation"


def _curve(runs: list[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    """(step counts, [seeds, evaluations] mean returns) over the evaluations all seeds have."""
    series = []
    for run in runs:
        steps = sorted((k for k in run if k.startswith("step_")), key=lambda k: int(k[5:]))
        series.append([(run[k]["step_count"], float(np.mean(run[k]["return"]))) for k in steps])
    length = min(len(s) for s in series)
    counts = np.array([step for step, _ in series[0][:length]])
    return counts, np.array([[value for _, value in s[:length]] for s in series])


def _iqm_and_mean(scores: np.ndarray) -> np.ndarray:
    from rliable import metrics

    return np.array([metrics.aggregate_iqm(scores), metrics.aggregate_mean(scores)])


def _iqm_per_evaluation(scores: np.ndarray) -> np.ndarray:
    """[seeds, 1 task, evaluations] -> the IQM at each evaluation."""
    from rliable import metrics

    return np.array([metrics.aggregate_iqm(scores[..., i]) for i in range(scores.shape[-1])])


def _reaching(centres: dict[str, tuple[np.ndarray, np.ndarray]]) -> list[str]:
    """Sample efficiency off the plotted IQM curves: the first evaluation at which each
    algorithm's curve reaches the last point of each other algorithm's."""
    lines = ["", "| IQM curve of | reaches the final IQM of | at env steps |", "|---|---|---|"]
    for x, y in itertools.permutations(centres, 2):
        steps, curve = centres[x]
        target = centres[y][1][-1]
        reached = np.flatnonzero(curve >= target)
        at = f"{steps[reached[0]]:,}" if reached.size else f"not by {steps[-1]:,}"
        lines.append(f"| {x} | {y} ({target:.1f}) | {at} |")
    return lines


def write_report(paths: list[Path], out: Path) -> str:
    """Write `out`/report.md and the curves; returns the Markdown."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from rliable import metrics

    data = read_evaluations(paths)
    out.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Results",
        "",
        f"IQM and mean over seeds with {CONFIDENCE:.0%} stratified-bootstrap confidence "
        f"intervals (rliable, {BOOTSTRAP_REPS} resamples). A seed's score is its absolute "
        "metric (its best evaluated policy on 10x the episodes) where it has one, else its "
        "last evaluation.",
    ]
    for env, tasks in sorted(data.items()):
        for task, algos in sorted(tasks.items()):
            scores, kinds, curves = {}, {}, {}
            for algo, seeds in sorted(algos.items()):
                finals = [_final(run) for _, run in sorted(seeds.items())]
                scores[algo] = np.array([[score] for score, _ in finals])  # [seeds, 1 task]
                kinds[algo] = sorted({kind for _, kind in finals})
                curves[algo] = _curve(list(seeds.values()))
            point, interval = interval_estimates(scores, _iqm_and_mean)
            lines += ["", f"## {env}: {task}", "",
                      "| algorithm | seeds | IQM [95 % CI] | mean [95 % CI] | score |",
                      "|---|---|---|---|---|"]  # fmt: skip
            for algo in scores:
                (iqm, mean), (low, high) = point[algo], interval[algo]
                lines.append(
                    f"| {algo} | {len(scores[algo])} | {iqm:.1f} [{low[0]:.1f}, {high[0]:.1f}] "
                    f"| {mean:.1f} [{low[1]:.1f}, {high[1]:.1f}] | {', '.join(kinds[algo])} |"
                )
            pairs = list(itertools.permutations(scores, 2))
            if pairs:
                pair_scores = {f"{x} > {y}": (scores[x], scores[y]) for x, y in pairs}
                improve, improve_ci = interval_estimates(
                    pair_scores, metrics.probability_of_improvement
                )
                lines += ["", "| probability of improvement | P [95 % CI] |", "|---|---|"]
                for pair in pair_scores:
                    low, high = np.ravel(improve_ci[pair])[:2]
                    lines.append(f"| {pair} | {float(np.ravel(improve[pair])[0]):.2f} "
                                 f"[{low:.2f}, {high:.2f}] |")  # fmt: skip
            figure, axis = plt.subplots(figsize=(6.5, 4))
            centres = {}
            for algo, (steps, values) in curves.items():
                if not len(steps):
                    continue
                per_step = {algo: values[:, None, :]}  # [seeds, 1 task, evaluations]
                centre, band = interval_estimates(per_step, _iqm_per_evaluation)
                centres[algo] = (steps, centre[algo])
                (line,) = axis.plot(
                    steps,
                    centre[algo],
                    label=f"{algo} ({len(values)} seed{'s' if len(values) > 1 else ''})",
                )
                axis.fill_between(steps, band[algo][0], band[algo][1], alpha=0.2,
                                  color=line.get_color())  # fmt: skip
            if len(centres) > 1:
                lines += _reaching(centres)
            axis.set_xlabel("env steps")
            axis.set_ylabel("return (IQM over seeds, 95 % CI)")
            axis.set_title(f"{env}: {task}")
            axis.grid(alpha=0.3)
            axis.legend()
            figure.tight_layout()
            picture = out / f"{env}_{task}.png".replace(":", "_")
            figure.savefig(picture, dpi=120)
            plt.close(figure)
            lines += ["", f"![{task}]({picture.name})"]
    text = "\n".join(lines) + "\n"
    (out / "report.md").write_text(text)
    return text
