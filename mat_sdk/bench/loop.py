"""The training loop's levers one by one, side by side (`mat bench loop`): where an update's
time goes, and what each lever `--tune` chooses from buys on this machine.

Variants, each adding one lever to the one before: the loop as it ran before tuning chose
rollout settings (envs stepped in this process, torch acting, the update in one process,
eager), then an env worker process, ONNX Runtime acting, an update worker process,
torch.compile. Each variant is a `Trainer` of the env's own recipe; they take turns, a few
updates each per round (after one warm-up update each: worker start, graph builds, the
compile), so a slow phase of a shared machine hits them alike. Per update: the rollout, the
share of it this process spends waiting for its env workers, the update, env-steps/s. A
first table gives the env alone: steps/s of the vectorised env with random actions, in this
process and with a worker.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from mat_sdk import envs
from mat_sdk.common.processes import usable_cores
from mat_sdk.common.timing import compare, print_table
from mat_sdk.training.trainer import Trainer

LEVERS = (
    ("before: envs in this process, torch acting, eager update", {}),
    ("+ 1 env worker process", {"workers": 1}),
    ("+ ONNX Runtime acting", {"rollout_backend": "onnx"}),
    ("+ 1 update worker process", {"update_workers": 1}),
    ("+ torch.compile", {"compile": True}),
)


def variants(cores: int) -> dict[str, dict]:
    """The levers, each on top of the ones before; the process levers only with a core free."""
    found, settings = {}, {"workers": 0, "rollout_backend": "torch", "update_workers": 0}
    for label, lever in LEVERS:
        if cores < 2 and ("workers" in lever or "update_workers" in lever):
            continue
        settings = {**settings, **lever}
        found[label] = settings
    return found


class _Waits:
    """Seconds the trainer's env spends waiting for its workers (its `_wait`), summed."""

    def __init__(self, trainer: Trainer):
        self.seconds = 0.0
        env = trainer.env
        wait = env._wait

        def timed():
            start = time.perf_counter()
            try:
                return wait()
            finally:
                self.seconds += time.perf_counter() - start

        env._wait = timed


def _env_table(env_id: str, num_envs: int, rounds: int) -> None:
    rows, vecs = [], {}
    try:
        for workers in (0, 1) if usable_cores() > 1 else (0,):
            vec = envs.make_vec(env_id, num_envs, workers=workers, seed=0)
            vec.reset(seed=0)
            actions = np.random.default_rng(0).uniform(
                -1, 1, (num_envs, vec.n_agents, vec.action_size)
            )
            vecs[f"{workers} worker{'s' if workers != 1 else ''}"] = (vec, actions)
        steps = {name: _stepper(vec, actions) for name, (vec, actions) in vecs.items()}
        seconds = compare(steps, seconds=2.0 * len(steps), rounds=rounds)
        base = next(iter(seconds.values()))
        for name, step_s in seconds.items():
            rows.append(
                {
                    "env copies stepped": f"{num_envs}, {name}",
                    "ms per vector step": f"{step_s * 1e3:.2f}",
                    "env-steps/s": f"{num_envs / step_s:,.0f}",
                    "vs in-process": f"{base / step_s:.2f}x",
                }
            )
    finally:
        for vec, _ in vecs.values():
            vec.close()
    print_table(rows, f"{env_id}: the env alone, random actions")


def _stepper(vec, actions) -> Callable[[], None]:
    return lambda: vec.step(actions)


def main(env_id: str = "go2:walk", updates: int = 3, rounds: int = 3) -> None:
    trainers: dict[str, Trainer] = {}
    try:
        for label, settings in variants(usable_cores()).items():
            trainers[label] = Trainer(env_id, "mat", **settings)
        first = next(iter(trainers.values()))
        per_update = first.config.ppo.steps_per_update
        _env_table(env_id, first.config.ppo.num_envs, rounds)
        waits = {label: _Waits(trainer) for label, trainer in trainers.items()}
        times: dict[str, list[dict]] = {label: [] for label in trainers}
        for trainer in trainers.values():  # warm-up: workers, ONNX graphs, the compile
            trainer.learn(per_update, progress_bar=False)
        waited = {label: 0.0 for label in trainers}
        for _ in range(rounds):
            for label, trainer in trainers.items():
                before = waits[label].seconds
                goal = trainer.progress.steps + per_update * updates
                trainer.learn(goal, progress_bar=False, callback=_into(times[label]))
                waited[label] += waits[label].seconds - before
        rows, base = [], None
        for label, measured in times.items():
            rollout = np.mean([m["rollout_s"] for m in measured])
            update = np.mean([m["update_s"] for m in measured])
            rate = per_update / (rollout + update)
            base = base or rate
            wait = waited[label] / len(measured)
            rows.append(
                {
                    "loop": label,
                    "rollout s": f"{rollout:.2f}",
                    "of it waiting for env workers": f"{wait / rollout:.0%}",
                    "update s": f"{update:.2f}",
                    "rollout / update share": f"{rollout / (rollout + update):.0%} / "
                    f"{update / (rollout + update):.0%}",
                    "env-steps/s": f"{rate:,.0f}",
                    "vs before": f"{rate / base:.2f}x",
                }
            )
        print_table(
            rows,
            f"{env_id}: one update of {per_update:,} env steps, each lever on top of the ones "
            f"above ({rounds} rounds of {updates} updates per variant, interleaved)",
        )
    finally:
        for trainer in trainers.values():
            trainer.close()


def _into(times: list[dict]) -> Callable[[Trainer, dict], None]:
    return lambda trainer, metrics: times.append(metrics)
