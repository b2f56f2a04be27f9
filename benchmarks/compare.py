"""MAT vs MAT-Dec vs MAPPO on one env at equal steps and settings, over seeds: a table and a plot.

    python -m benchmarks.compare mpe_envs:spread --steps 300000 --seeds 3 --out runs/spread

Each (algorithm, seed) trains with one set of PPO settings for all (`SPREAD` in
tests/recipes.py) in its own process (one per core), writes OUT/runs/ALGO-sK/ (metrics.csv,
checkpoint.pt), and is then evaluated on 32 deterministic episodes (`spread_return`). The
table gives every seed's evaluation and the mean and spread over seeds; the plot, the
per-update return of each algorithm averaged over its seeds, with the band between the
seeds' lowest and highest.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
from pathlib import Path

import numpy as np

from mat_sdk.bench import machine
from mat_sdk.common.processes import usable_cores
from mat_sdk.common.timing import print_table
from mat_sdk.training.run_log import METRICS_NAME, read_metrics
from tests.recipes import EVALUATION_SEED, SPREAD_EVALUATIONS, spread_return

COMPARED = ("mat", "mat-dec", "mappo")


def _train(job: tuple[str, str, int, int, str]) -> tuple[str, int, float]:
    import torch

    torch.set_num_threads(1)
    env_id, algo, seed, steps, out = job
    return algo, seed, spread_return(seed, env_id, steps, algo, Path(out) / f"{algo}-s{seed}")


def _curves(out: Path, seeds: list[int]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per algorithm: env steps and the per-update returns [seeds, updates]."""
    curves = {}
    for algo in COMPARED:
        runs = [read_metrics(out / f"{algo}-s{seed}" / METRICS_NAME) for seed in seeds]
        steps = np.array([int(r["steps"]) for r in runs[0]])
        returns = np.array([[float(r["return_mean"]) for r in rows] for rows in runs])
        curves[algo] = (steps, returns)
    return curves


def plot(curves, png: Path, title: str, window: int = 10) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    window = min(window, min(len(steps) for steps, _ in curves.values()))  # a short run
    kernel = np.ones(window) / window
    for algo, (steps, returns) in curves.items():
        smooth = np.array([np.convolve(r, kernel, mode="valid") for r in returns])
        x = steps[window - 1 :]
        ax.plot(x, smooth.mean(0), label=f"{algo} (mean of {len(returns)} seeds)")
        ax.fill_between(x, smooth.min(0), smooth.max(0), alpha=0.2)
    ax.set_xlabel("env steps")
    ax.set_ylabel(f"episode return (moving mean of {window} updates)")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return png


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("env_id")
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--out", type=Path, required=True, help="directory for runs and plot")
    args = parser.parse_args()
    runs = args.out / "runs"
    seeds = list(range(args.seeds))
    jobs = [(args.env_id, algo, seed, args.steps, str(runs)) for algo in COMPARED for seed in seeds]
    with mp.get_context("spawn").Pool(min(len(jobs), usable_cores())) as pool:
        results = pool.map(_train, jobs, chunksize=1)
    print(f"machine: {machine()}; {args.env_id}, {args.steps} steps, recipe tests.recipes.SPREAD")
    print(f"evaluation: {SPREAD_EVALUATIONS} deterministic episodes, seed {EVALUATION_SEED}\n")
    rows = []
    for algo in COMPARED:
        scores = [score for a, _, score in results if a == algo]
        rows.append(
            {
                "algorithm": algo,
                "per seed": ", ".join(f"{s:.2f}" for s in scores),
                "mean": f"{np.mean(scores):.2f}",
                "std": f"{np.std(scores):.2f}",
                "min": f"{np.min(scores):.2f}",
                "max": f"{np.max(scores):.2f}",
            }
        )
    print_table(rows, "final evaluation")
    png = args.out / f"{args.env_id.replace(':', '_')}_mat_matdec_mappo.png"
    print(plot(_curves(runs, seeds), png, f"{args.env_id}, {args.steps} steps, {len(seeds)} seeds"))


if __name__ == "__main__":
    main()
