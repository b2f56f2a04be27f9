"""The learning tests' recipes (`tests/recipes.py`) swept over seeds, from the repository's root.

A learning test must hold on every seed and every CPU, not pass by one lucky trajectory; the
sweep runs a recipe on many seeds, one process per core, and prints the per-seed table.

    python -m benchmarks.seeds --recipe game-mat --seeds 16
    python -m benchmarks.seeds --seeds 4 --first 100      every recipe on seeds 100-103
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time
from collections.abc import Sequence

import numpy as np

from mat_sdk.bench import machine
from mat_sdk.common.processes import usable_cores
from mat_sdk.common.timing import print_table
from tests.recipes import RECIPES


def _score(job: tuple[str, int]) -> tuple[str, int, float, float]:
    import torch

    torch.set_num_threads(1)
    name, seed = job
    start = time.perf_counter()
    score = RECIPES[name].run(seed)
    return name, seed, score, time.perf_counter() - start


def sweep(names: Sequence[str], seeds: Sequence[int], processes: int | None = None) -> list[dict]:
    """Run every recipe on every seed, `processes` at a time (default: one per core)."""
    jobs = [(name, seed) for name in names for seed in seeds]
    processes = min(len(jobs), processes or usable_cores())
    with mp.get_context("spawn").Pool(processes) as pool:
        results = pool.map(_score, jobs, chunksize=1)
    rows = []
    for name in names:
        recipe = RECIPES[name]
        bound = recipe.bound()
        for _, seed, score, seconds in (r for r in results if r[0] == name):
            holds = score >= bound if recipe.above else score <= bound
            rows.append(
                {
                    "recipe": name,
                    "seed": seed,
                    "score": f"{score:.3f}",
                    "bound": f"{'>=' if recipe.above else '<='} {bound:.3f}",
                    "holds": "yes" if holds else "NO",
                    "seconds": f"{seconds:.0f}",
                }
            )
    return rows


def main(names: Sequence[str], seeds: Sequence[int], processes: int | None = None) -> list[dict]:
    print(f"machine: {machine()}, {usable_cores()} cores\n")
    rows = sweep(names, seeds, processes)
    print_table(rows, "per seed")
    summary = []
    for name in names:
        own = [r for r in rows if r["recipe"] == name]
        scores = np.array([float(r["score"]) for r in own])
        summary.append(
            {
                "recipe": name,
                "claim": RECIPES[name].claim,
                "holds": f"{sum(r['holds'] == 'yes' for r in own)}/{len(own)}",
                "min": f"{scores.min():.3f}",
                "median": f"{np.median(scores):.3f}",
                "max": f"{scores.max():.3f}",
            }
        )
    print_table(summary, "summary")
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--recipe", action="append", choices=list(RECIPES), help="repeatable [all]")
    parser.add_argument("--seeds", type=int, default=16, help="seeds 0..N-1 (or from --first)")
    parser.add_argument("--first", type=int, default=0, help="the first seed")
    parser.add_argument("--processes", type=int, help="runs at a time [one per core]")
    args = parser.parse_args()
    if args.seeds < 1 or args.first < 0:
        parser.error("--seeds must be >= 1 and --first >= 0")
    main(args.recipe or tuple(RECIPES), range(args.first, args.first + args.seeds), args.processes)
