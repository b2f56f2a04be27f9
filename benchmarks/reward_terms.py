"""Each reward term's mean per step under random actions, per env: which term rules a task's
reward on a robot before any training (`mat_sdk.envs.tasks.reward_check`).

    PYTHONPATH=examples python -m benchmarks.reward_terms quadrupeds:go2 quadrupeds:a1 \\
        quadrupeds:spot --steps 1000 --seeds 3

Prints a Markdown table: a row per term, a column per env (mean over seeds of the mean per
step), and whether the trainer would warn that one penalty rules the reward.
"""

from __future__ import annotations

import click
import numpy as np

from mat_sdk import envs
from mat_sdk.envs.tasks.reward_check import random_breakdown, ruling_penalty


@click.command()
@click.argument("env_ids", nargs=-1, required=True)
@click.option("--steps", default=1000, show_default=True, help="random steps per seed")
@click.option("--seeds", default=3, show_default=True)
def main(env_ids: tuple[str, ...], steps: int, seeds: int) -> None:
    columns = {}
    for env_id in env_ids:
        runs = [
            random_breakdown(envs.make_team(env_id, seed=seed), steps, seed)
            for seed in range(seeds)
        ]
        columns[env_id] = {name: float(np.mean([r[name] for r in runs])) for name in runs[0]}
    names = list(dict.fromkeys(name for column in columns.values() for name in column))
    print("| term | " + " | ".join(env_ids) + " |")
    print("|---" * (len(env_ids) + 1) + "|")
    for name in names:
        cells = [f"{columns[e][name]:+.3f}" if name in columns[e] else "" for e in env_ids]
        print(f"| {name} | " + " | ".join(cells) + " |")
    warned = ["yes" if ruling_penalty(columns[e]) else "no" for e in env_ids]
    print("| one penalty rules (trainer warns) | " + " | ".join(warned) + " |")


if __name__ == "__main__":
    main()
