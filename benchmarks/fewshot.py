"""The paper's few-shot protocol on a HalfCheetah (results in docs/FEWSHOT.md).

For each of the six joints disabled ("zero"): the pre-trained policy's zero-shot return,
then fine-tuning from it and MAT from scratch (on the checkpoint's env, with its recipe) with
the same env steps, each evaluated after budgets given as fractions of the pre-training
steps, or of `--of` steps (the paper: 1e7). One run per method passes through every
budget, so the smaller budgets are nested in the larger. With `--seeds 0 1 2` every
fine-tuning and from-scratch run is repeated per seed, and a cell reports the mean over
seeds with its 95 % bootstrap CI (`mat_sdk.evaluation.protocol.interval_estimates`, as
`mat report`).

    python -m benchmarks.fewshot runs/curve-mat/checkpoint.pt --budgets 0.01 0.05
    python -m benchmarks.fewshot runs/hc6x1-mat/checkpoint.pt --budgets 0.01 --of 10000000 \
        --seeds 0 1 2 --out docs/fewshot-mamujoco

Rows are appended to OUT/fewshot.csv as they finish; re-running skips finished rows, so an
interrupted experiment continues where it stopped.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from mat_sdk.common.files import write_text_atomic
from mat_sdk.evaluation.protocol import interval_estimates
from mat_sdk.policy import checkpoint as checkpoints
from mat_sdk.training.finetune import finetune
from mat_sdk.training.trainer import Trainer

JOINTS = ("bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot")
FIELDS = ["joint", "method", "budget", "steps", "return_mean", "return_std", "seed"]


def _read(table: Path) -> list[dict]:
    """The CSV's rows; a table from before seeds were repeated is seed 0's."""
    with table.open() as f:
        return [{**row, "seed": row.get("seed") or "0"} for row in csv.DictReader(f)]


def _evaluate_at(budget_steps: dict[int, float], episodes: int, rows: list, joint, method, seed):
    """A `learn` callback that evaluates once the run passes each budget."""
    pending = sorted(budget_steps)

    def callback(trainer: Trainer, metrics: dict) -> bool:
        while pending and trainer.progress.steps >= pending[0]:
            steps = pending.pop(0)
            returns = trainer.evaluate(episodes)
            rows.append(
                [joint, method, budget_steps[steps], steps, np.mean(returns), np.std(returns), seed]
            )
        return bool(pending)

    return callback


def _cells(rows: list[dict]) -> dict[tuple, tuple[float, str]]:
    """(joint, method, budget) -> (mean, its text): one seed's `mean ± std` over episodes,
    or several seeds' mean with its 95 % bootstrap CI over seeds."""
    from rliable import metrics

    by_cell: dict[tuple, list[dict]] = {}
    for r in rows:
        by_cell.setdefault((r["joint"], r["method"], float(r["budget"])), []).append(r)
    cells = {}
    for key, runs in by_cell.items():
        means = np.array([float(r["return_mean"]) for r in runs])
        if len(runs) == 1:
            cells[key] = (means[0], f"{means[0]:.0f} ± {float(runs[0]['return_std']):.0f}")
            continue
        point, interval = interval_estimates({"cell": means[:, None]}, metrics.aggregate_mean)
        low, high = np.ravel(interval["cell"])
        cells[key] = (float(point["cell"]), f"{float(point['cell']):.0f} [{low:.0f}, {high:.0f}]")
    return cells


def report(table: Path, plot: Path, env_id: str) -> str:
    """A Markdown table (joint x method/budget) and a bar chart of the CSV: one seed's
    mean ± std over episodes, or the mean over seeds [95 % CI]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = _read(table)
    seeds = sorted({int(r["seed"]) for r in rows if r["method"] != "zero-shot"})
    budgets = sorted({float(r["budget"]) for r in rows if r["method"] != "zero-shot"})
    joints = list(dict.fromkeys(r["joint"] for r in rows))
    # the zero-shot policy is the same for every seed: one evaluation
    rows = [r for r in rows if r["method"] != "zero-shot" or int(r["seed"]) == seeds[0]]
    cell = _cells(rows)
    columns = [("zero-shot", 0.0)] + [(m, b) for b in budgets for m in ("finetune", "scratch")]
    header = ["joint disabled"] + [
        "zero-shot" if m == "zero-shot" else f"{m} {b:.0%} ({int(float(_steps(rows, b))):,} steps)"
        for m, b in columns
    ]
    spread = "mean ± std over episodes" if len(seeds) == 1 else "mean over seeds [95 % CI]"
    lines = [f"Seeds {', '.join(map(str, seeds))}; each cell: {spread}.", ""]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for joint in joints:
        values = [cell[(joint, *key)][1] if (joint, *key) in cell else "" for key in columns]
        lines.append(f"| {joint} | " + " | ".join(values) + " |")
    figure, axis = plt.subplots(figsize=(9, 4))
    width = 0.8 / len(columns)
    for k, key in enumerate(columns):
        heights = [cell[(j, *key)][0] if (j, *key) in cell else 0 for j in joints]
        label = key[0] if key[0] == "zero-shot" else f"{key[0]} {key[1]:.0%}"
        axis.bar(np.arange(len(joints)) + k * width, heights, width, label=label)
    axis.set_xticks(np.arange(len(joints)) + 0.4 - width / 2, joints)
    axis.set_ylabel("episode return")
    axis.set_title(f"{env_id}, one joint disabled: fine-tuned MAT vs MAT from scratch")
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(plot, dpi=120)
    text = "\n".join(lines) + "\n"
    print(text)
    return text


def _steps(rows: list[dict], budget: float) -> str:
    return next(r["steps"] for r in rows if float(r["budget"]) == budget)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("checkpoint", help="MAT pre-trained on a HalfCheetah with six agents")
    parser.add_argument("--budgets", type=float, nargs="+", default=[0.01, 0.05, 0.1])
    parser.add_argument(
        "--of", type=int, help="steps the budgets are fractions of [the pre-training's]"
    )
    parser.add_argument("--joints", nargs="+", default=list(JOINTS))
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="[0]")
    parser.add_argument("--out", type=Path, default=Path("docs/fewshot"))
    parser.add_argument("--report", action="store_true", help="Only print the table and plot.")
    args = parser.parse_args()
    table = args.out / "fewshot.csv"
    if args.report and not table.exists():
        parser.error(f"--report: no results in {table}; run without --report")
    pretrained = checkpoints.load(args.checkpoint)
    env_id = checkpoints.env_id(pretrained)
    recipe = checkpoints.recorded_training(pretrained)["recipe"]  # scratch trains as it did
    if args.report:
        report(table, args.out / "fewshot.png", env_id)
        return

    reference_steps = args.of or pretrained["progress"]["steps"]
    budget_steps = {round(b * reference_steps): b for b in args.budgets}
    args.out.mkdir(parents=True, exist_ok=True)
    done = set()
    if table.exists():
        old = _read(table)
        done = {(r["joint"], r["method"], int(r["seed"])) for r in old}
        if "seed" not in table.open().readline():  # a table from before seeds: say seed 0
            lines = [",".join(FIELDS)] + [",".join(str(r[f]) for f in FIELDS) for r in old]
            write_text_atomic(table, "\n".join(lines) + "\n")
    else:
        table.write_text(",".join(FIELDS) + "\n")
    for seed in args.seeds:
        for joint in args.joints:
            _run_cells(args, joint, seed, env_id, recipe, budget_steps, done, table)
    report(table, args.out / "fewshot.png", env_id)


def _run_cells(
    args, joint: str, seed: int, env_id: str, recipe: str, budget_steps, done: set, table: Path
):
    """Fine-tune and train from scratch with `joint` disabled, one seed, appending rows."""
    faults = {joint: "zero"}
    total = max(budget_steps)
    for method in ("finetune", "scratch"):
        if (joint, method, seed) in done:
            continue
        rows: list = []
        callback = _evaluate_at(budget_steps, args.episodes, rows, joint, method, seed)
        if method == "finetune":
            result = finetune(
                args.checkpoint, faults=faults, steps=total, eval_episodes=args.episodes,
                callback=callback, progress_bar=False, seed=seed,
            )  # fmt: skip
            result.trainer.close()
            zero = result.zero_shot
            rows.insert(0, [joint, "zero-shot", 0.0, 0, np.mean(zero), np.std(zero), seed])
        else:
            with Trainer(env_id, "mat", recipe=recipe, faults=faults, seed=seed) as trainer:
                trainer.learn(total, callback=callback, progress_bar=False)
        with table.open("a") as f:
            csv.writer(f).writerows(rows)
        for row in rows:
            print(", ".join(str(round(v, 3)) if isinstance(v, float) else str(v) for v in row))


if __name__ == "__main__":
    main()
