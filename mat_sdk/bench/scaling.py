"""Rollout scaling: env-steps/s of whole updates with local or Ray rollout workers
(`mat bench scaling`).

Each variant trains a fresh `Trainer` for a few updates of the chosen recipe and reports the
mean over the updates after the first (which includes start-up): env-steps/s, and the
rollout and update seconds per update. Variants run one after another, not interleaved
(each needs the whole machine), so compare them within one run only.
"""

from __future__ import annotations

import time

import numpy as np

from mat_sdk.bench import machine
from mat_sdk.common.timing import print_table
from mat_sdk.training.trainer import Trainer


def variants(workers: tuple[int, ...]) -> dict[str, dict]:
    """In-process rollouts, then local worker processes and Ray actors for each count."""
    found = {
        "local, in-process envs": {"workers": 0},
        "local, in-process envs, ONNX acting": {"workers": 0, "rollout_backend": "onnx"},
    }
    for count in workers:
        found[f"local, {_plural(count, 'worker process', 'es')}"] = {"workers": count}
    for count in workers:
        found[f"Ray, {_plural(count, 'actor')}"] = {"workers": count, "ray": "local"}
    most = max(workers)
    found[f"Ray, {_plural(most, 'actor')}, ONNX acting"] = {
        "workers": most,
        "ray": "local",
        "rollout_backend": "onnx",
    }
    return found


def _plural(count: int, noun: str, suffix: str = "s") -> str:
    return f"{count} {noun}{suffix if count != 1 else ''}"


def main(
    env_id: str = "cheetah-6x1", updates: int = 3, workers: tuple[int, ...] = (1, 2), **recipe
) -> None:
    rows = []
    for label, options in variants(workers).items():
        times: list[dict] = []
        with Trainer(env_id, "mat", **options, **recipe) as trainer:
            per_update = trainer.config.ppo.steps_per_update
            start = time.perf_counter()
            trainer.learn(per_update * updates, progress_bar=False, callback=_append_to(times))
            total = time.perf_counter() - start
        steady = times[1:] or times
        first = total - sum(m["rollout_s"] + m["update_s"] for m in steady)
        rollout = np.mean([m["rollout_s"] for m in steady])
        update = np.mean([m["update_s"] for m in steady])
        rows.append(
            {
                "rollouts": label,
                "env-steps/s": f"{per_update / (rollout + update):,.0f}",
                "rollout s/update": f"{rollout:.2f}",
                "update s/update": f"{update:.2f}",
                "first update incl. start-up (s)": f"{first:.1f}",
            }
        )
    print_table(rows, f"{env_id}, {updates} updates per variant — {machine()}")


def _append_to(metrics: list[dict]):
    return lambda trainer, m: metrics.append(m)
