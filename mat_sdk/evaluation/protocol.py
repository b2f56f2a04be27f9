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
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from mat_sdk import envs
from mat_sdk.common.files import write_text_atomic
from mat_sdk.evaluation.episodes import CheckpointPolicy, evaluate

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
        env, task = env_and_task(cfg.env.id)
        algo = cfg.algo
        return (
            self.data.setdefault(env, {})
            .setdefault(task, {})
            .setdefault(algo, {})
            .setdefault(f"seed_{cfg.run.seed}", {})
        )

    def evaluations(self, trainer) -> list[dict[str, Any]]:
        """This run's evaluations so far, in order."""
        run = self._run(trainer)
        return [run[key] for key in sorted((k for k in run if k.startswith("step_")), key=_index)]

    def __call__(self, trainer, metrics: dict) -> None:
        done = self.evaluations(trainer)
        due = (done[-1]["step_count"] if done else 0) + self.every
        if trainer.progress.steps < due:
            return
        returns = trainer.evaluate(self.episodes)
        best = max((np.mean(e["return"]) for e in done), default=-np.inf)
        if np.mean(returns) > best:
            trainer.save(self.out_dir / BEST_NAME)
        run = self._run(trainer)
        run[f"step_{len(done) + 1}"] = {"step_count": trainer.progress.steps, "return": returns}
        self._write()

    def finish(self, trainer) -> list[float] | None:
        """The absolute metric: the best evaluated policy on `ABSOLUTE_FACTOR` x the episodes
        (once; None if nothing was evaluated)."""
        run = self._run(trainer)
        if "absolute_metrics" in run:
            return run["absolute_metrics"]["return"]
        if not (self.out_dir / BEST_NAME).exists():
            return None
        path = self.out_dir / BEST_NAME
        best = CheckpointPolicy.from_checkpoint(path)
        # this run's own best policy: a file that records another env is refused
        named = trainer.config.env.ids
        envs.check_trusted([best.training.env.id], path, named=named)
        returns = evaluate(best, self.episodes * ABSOLUTE_FACTOR, env_id=trainer.config.env.id)
        run["absolute_metrics"] = {"return": returns}
        self._write()
        return returns

    def _write(self) -> None:
        write_text_atomic(self.path, json.dumps(self.data, indent=1) + "\n")


def _index(key: str) -> int:
    return int(key.split("_")[1])


def read_evaluations(paths: list[Path]) -> dict[str, Any]:
    """Every `evaluations.json` under `paths` (files or directories), checked and merged; a
    seed found twice is refused, naming both files. A file that is not of marl-eval's layout,
    holds a non-finite or missing return, a name that is not a plain name (a path, Markdown),
    or lies outside the directory it was found under (a symlink) is refused, naming it."""
    merged: dict[str, Any] = {}
    where: dict[tuple, Path] = {}
    files = []
    for path in paths:
        if path.is_file():
            files.append(path)
            continue
        root = path.resolve()
        for found in path.rglob(EVALUATIONS_NAME):
            if not found.resolve().is_relative_to(root):
                raise ValueError(f"{found}: resolves outside {path} ({found.resolve()}); not read")
            files.append(found)
    if not files:
        raise FileNotFoundError(
            f"no {EVALUATIONS_NAME} under {', '.join(map(str, paths))}; train with "
            "--eval-every (on by default for runs of 100,000 steps or more)"
        )
    for file in sorted(files):
        for (env, task, algo, seed), run in _runs(file):
            key = (env, task, algo, seed)
            if key in where:
                raise ValueError(f"{env}/{task}/{algo}/{seed} is in both {where[key]} and {file}")
            where[key] = file
            merged.setdefault(env, {}).setdefault(task, {}).setdefault(algo, {})[seed] = run
    return merged


# env, task, algorithm and seed names: they become file names and Markdown table cells
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,99}")
STEP = re.compile(r"step_(\d{1,9})")


def _runs(file: Path) -> list[tuple[tuple[str, str, str, str], dict[str, Any]]]:
    """The seeds' runs of one evaluations file, each checked, or ValueError naming the file
    and the first field that is wrong."""

    def fail(field: str, problem: str) -> None:
        raise ValueError(f"{file}: {field} {problem}; is it an evaluations.json of `mat train`?")

    def refuse_constant(name: str) -> None:
        fail("a return", f"is {name}; returns must be finite numbers")

    try:
        data = json.loads(file.read_text(), parse_constant=refuse_constant)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        fail("the file", f"is not JSON ({type(error).__name__})")
    except RecursionError:
        fail("the file", "is nested too deeply")
    runs = []
    for path, value in _levels(data, ("env", "task", "algorithm", "seed"), fail):
        field = "/".join(path)
        steps = [key for key in value if STEP.fullmatch(key)]
        unknown = set(value) - set(steps) - {"absolute_metrics"}
        if unknown:
            fail(
                field,
                f"has entries that are neither step_K nor absolute_metrics ({sorted(unknown)[:3]})",
            )
        if not steps and "absolute_metrics" not in value:
            fail(field, "has no evaluation")
        for key in [*steps, *(["absolute_metrics"] if "absolute_metrics" in value else [])]:
            entry = value[key]
            if not isinstance(entry, dict):
                fail(f"{field}/{key}", "is not an object")
            returns = entry.get("return")
            if (
                not isinstance(returns, list)
                or not returns
                or not all(
                    isinstance(r, int | float) and not isinstance(r, bool) and math.isfinite(r)
                    for r in returns
                )
            ):
                fail(f"{field}/{key}/return", "must be a non-empty list of finite numbers")
            count = entry.get("step_count")
            if key != "absolute_metrics" and (
                isinstance(count, bool) or not isinstance(count, int) or count < 0
            ):
                fail(f"{field}/{key}/step_count", f"must be an integer >= 0, got {count!r}")
        runs.append((path, value))
    return runs


def _levels(data: Any, levels: tuple[str, ...], fail, path: tuple[str, ...] = ()):
    """(names, value) at the depth of `levels` in nested objects whose keys are plain names."""
    if not isinstance(data, dict):
        fail("/".join(path) or "the file", f"must be an object of {levels[0]} names")
    if not data:
        fail("/".join(path) or "the file", f"names no {levels[0]}")
    for name, value in data.items():
        if not NAME.fullmatch(name):
            fail("/".join(path) or "the file", f"has the {levels[0]} name {name[:40]!r}, not a "
                 "plain name (letters, digits, '_', '.', '+', '-')")  # fmt: skip
        if len(levels) == 1:
            if not isinstance(value, dict):
                fail("/".join((*path, name)), "must be an object of evaluations")
            yield (*path, name), value
        else:
            yield from _levels(value, levels[1:], fail, (*path, name))


def interval_estimates(
    scores: dict[str, Any], aggregate, confidence: float = CONFIDENCE, seed: int = 0
) -> tuple[dict, dict]:
    """rliable's point estimates and stratified-bootstrap CIs of `aggregate` over seeds:
    `scores` maps a name to [seeds, tasks] scores (or a tuple of such for a pairwise
    aggregate). The same resampling everywhere we report a CI; needs `mat-sdk[report]`.

    Reproducible: rliable 1.2's bootstraps draw their resamples from NumPy's global stream
    (its `random_state` argument is not used for them), so that stream is seeded `seed` for
    each name in turn, and restored after. Each name's CI is then the same on every run and
    whatever else is reported beside it."""
    from rliable import library as rly

    points, intervals = {}, {}
    outside = np.random.get_state()
    try:
        for name, score in scores.items():
            np.random.seed(seed)
            point, interval = rly.get_interval_estimates(
                {name: score}, aggregate, reps=BOOTSTRAP_REPS, confidence_interval_size=confidence
            )
            points[name], intervals[name] = point[name], interval[name]
    finally:
        np.random.set_state(outside)
    return points, intervals
