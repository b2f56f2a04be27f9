"""The MARL evaluation protocol: what a run records so results can be compared honestly.

Following Gorsane et al. (NeurIPS 2022) and their marl-eval tools (what Mava and BenchMARL
write): every `every` env steps the current policy plays `episodes` deterministic episodes
(their own fixed starts, independent of training's random streams, so an exact resume stays
exact); the best of those policies is kept (`best.pt`); at the end it is re-evaluated on 10x
the episodes, the "absolute metric". All of it goes to `evaluations.json`, in marl-eval's
layout, which `mat report` (and marl-eval itself) reads:

    {env: {task: {algo: {"seed_K": {"step_1": {"step_count": 50000, "return": [..]}, ...,
                                    "absolute_metrics": {"return": [..]}}}}}}
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from mat_sdk.evaluation import LoadedPolicy, evaluate
from mat_sdk.files import write_text_atomic

EVALUATIONS_NAME = "evaluations.json"
BEST_NAME = "best.pt"
ABSOLUTE_FACTOR = 10  # the absolute metric's episodes per evaluation episode
BUILT_IN = "mat_sdk"  # the env name of our own ids (`cheetah-6x1`), as marl-eval wants one
BOOTSTRAP_REPS = 2000  # rliable's default is 50,000; 2,000 keeps a report to seconds
CONFIDENCE = 0.95


def env_and_task(env_id: str) -> tuple[str, str]:
    """marl-eval's (environment, task) names of an id: `mamujoco:HalfCheetah-6x1` ->
    (mamujoco, HalfCheetah-6x1); `cheetah-6x1` -> (mat_sdk, cheetah-6x1)."""
    env, _, task = env_id.rpartition(":")
    return env or BUILT_IN, task


class EvaluationLog:
    """A `Trainer.learn` callback that evaluates every `every` steps into `evaluations.json`,
    keeping the best policy as `best.pt`; `finish` adds the absolute metric."""

    def __init__(self, out_dir: str | Path, every: int, episodes: int = 10):
        if every < 1 or episodes < 1:
            raise ValueError(f"every and episodes must be >= 1, got {every} and {episodes}")
        self.out_dir, self.every, self.episodes = Path(out_dir), every, episodes
        self.path = self.out_dir / EVALUATIONS_NAME
        self.data: dict[str, Any] = json.loads(self.path.read_text()) if self.path.exists() else {}

    def _run(self, trainer) -> dict[str, Any]:
        cfg = trainer.config
        env, task = env_and_task(cfg.env)
        algo = cfg.algo
        return (
            self.data.setdefault(env, {})
            .setdefault(task, {})
            .setdefault(algo, {})
            .setdefault(f"seed_{cfg.seed}", {})
        )

    def evaluations(self, trainer) -> list[dict[str, Any]]:
        """This run's evaluations so far, in order."""
        run = self._run(trainer)
        return [run[key] for key in sorted((k for k in run if k.startswith("step_")), key=_index)]

    def __call__(self, trainer, metrics: dict) -> None:
        done = self.evaluations(trainer)
        due = (done[-1]["step_count"] if done else 0) + self.every
        if trainer.progress["steps"] < due:
            return
        returns = trainer.evaluate(self.episodes)
        best = max((np.mean(e["return"]) for e in done), default=-np.inf)
        if np.mean(returns) > best:
            trainer.save(self.out_dir / BEST_NAME)
        run = self._run(trainer)
        run[f"step_{len(done) + 1}"] = {"step_count": trainer.progress["steps"], "return": returns}
        self._write()

    def finish(self, trainer) -> list[float] | None:
        """The absolute metric: the best evaluated policy on `ABSOLUTE_FACTOR` x the episodes
        (once; None if nothing was evaluated)."""
        run = self._run(trainer)
        if "absolute_metrics" in run:
            return run["absolute_metrics"]["return"]
        if not (self.out_dir / BEST_NAME).exists():
            return None
        best = LoadedPolicy.from_checkpoint(self.out_dir / BEST_NAME)
        # this run's own best policy, on the env the run was given
        returns = evaluate(best, self.episodes * ABSOLUTE_FACTOR, trust_env_code=True)
        run["absolute_metrics"] = {"return": returns}
        self._write()
        return returns

    def _write(self) -> None:
        write_text_atomic(self.path, json.dumps(self.data, indent=1) + "\n")


def _index(key: str) -> int:
    return int(key.split("_")[1])


def read_evaluations(paths: list[Path]) -> dict[str, Any]:
    """Every `evaluations.json` under `paths` (files or directories), merged; a seed found
    twice is refused, naming both files."""
    merged: dict[str, Any] = {}
    where: dict[tuple, Path] = {}
    files = [
        p for path in paths for p in ([path] if path.is_file() else path.rglob(EVALUATIONS_NAME))
    ]
    if not files:
        raise FileNotFoundError(
            f"no {EVALUATIONS_NAME} under {', '.join(map(str, paths))}; train with "
            "--eval-every (on by default for runs of 100,000 steps or more)"
        )
    for file in sorted(files):
        for env, tasks in json.loads(file.read_text()).items():
            for task, algos in tasks.items():
                for algo, seeds in algos.items():
                    for seed, run in seeds.items():
                        key = (env, task, algo, seed)
                        if key in where:
                            raise ValueError(
                                f"{env}/{task}/{algo}/{seed} is in both {where[key]} and {file}"
                            )
                        where[key] = file
                        merged.setdefault(env, {}).setdefault(task, {}).setdefault(algo, {})[
                            seed
                        ] = run
    return merged


def interval_estimates(
    scores: dict[str, Any], aggregate, confidence: float = CONFIDENCE, seed: int = 0
) -> tuple[dict, dict]:
    """rliable's point estimates and stratified-bootstrap CIs of `aggregate` over seeds:
    `scores` maps a name to [seeds, tasks] scores (or a tuple of such for a pairwise
    aggregate). The same resampling everywhere we report a CI; needs `mat-sdk[report]`."""
    import warnings

    from rliable import library as rly

    # arch (rliable's bootstrap) warns that RandomState is deprecated, which rliable passes
    warnings.filterwarnings("ignore", category=FutureWarning, module="arch")
    return rly.get_interval_estimates(
        scores, aggregate, reps=BOOTSTRAP_REPS, confidence_interval_size=confidence,
        random_state=np.random.RandomState(seed),
    )  # fmt: skip
