"""The rollout and update settings a long run uses, measured on the machine it runs on
(`mat train`).

Which settings are fastest depends on the CPU and the env: env worker processes pay when a
step of the env costs more than the hand-off to a worker, acting through ONNX Runtime when
the policy's batch is large, and update worker processes on idle cores, torch.compile of the
loss and flushing subnormal floats to zero each win on some machines and lose on others
(BENCHMARKS.md). So before a long CPU run that sets none of them, the candidates are measured
side by side (`compare`, interleaved rounds) on the run's own env and recipe, in rounds of
choice: env workers (none, or one per free core), then the acting backend, each timed over
whole rollouts; then how many update workers (eager), with torch.compile or not, flushing
subnormals or not, each timed over optimizer steps on one rollout's data, its start-up (a
compile, a process) spread over the run's optimizer steps (`amortized`: a compile a short
run cannot pay back loses). A candidate that costs more to start must also beat the simpler
one by `MARGIN`. Env and
update workers may take the same free cores: the loop is synchronous, so the ones idle while
the others work.

The choice is printed and written to OUT/tuning.json, which a rerun of the same command
reuses (so a resumed run, or a seed set's unfinished seeds, keep their settings); the
checkpoint records it like any setting. Each candidate runs on a private copy of the trainer,
and the run itself starts from its seed afterwards, untouched: a tuned run equals a run
given the chosen settings on the command line.
"""

from __future__ import annotations

import copy
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from mat_sdk.common.files import write_text_atomic
from mat_sdk.common.timing import compare, print_table
from mat_sdk.policy.config import PPOConfig, TrainConfig
from mat_sdk.policy.normalization import ValueNorm
from mat_sdk.training.gradients import MinibatchGradients
from mat_sdk.training.trainer import Trainer

ROLLOUT = ("workers", "rollout_backend")  # timed over rollouts
TUNED = (*ROLLOUT, "update_workers", "compile", "flush_denormal")
TUNE_FROM_STEPS = 1_000_000  # a run this long pays for a minute of compiling many times over
MARGIN = 0.05  # a costlier candidate must be this much faster than the simpler one
MAX_UPDATE_WORKERS = 2
WARMUP_EPOCHS = 2  # subnormals appear as an update repeats its minibatches (BENCHMARKS.md)
TUNING_NAME = "tuning.json"


def wanted(tune: bool | None, steps: int, on_cpu: bool, fixed: dict) -> bool:
    """Whether a run measures its update settings: as asked (`tune`), else when it is a long
    CPU run that leaves one of them to us; ValueError for `tune` on a GPU."""
    if len(fixed) == len(TUNED):  # nothing left to choose
        return False
    if tune is None:
        return on_cpu and steps >= TUNE_FROM_STEPS
    if tune and not on_cpu:
        raise ValueError("--tune measures CPU update settings; drop it on CUDA")
    return tune


def twin(
    trainer: Trainer,
    batch: dict[str, torch.Tensor],
    update_workers: int = 0,
    compile_mode: str | None = None,
    **config_changes: Any,
) -> Trainer:
    """The trainer's own optimizer step on a private copy of its policy, with the chosen
    levers (`compile_mode`: torch.compile's mode for the loss, None for eager); its update
    workers get the config with `config_changes`."""
    copied = copy.copy(trainer)
    copied.config = trainer.config.with_options(**config_changes)
    copied.policy = copy.deepcopy(trainer.policy)
    copied.build_optimizer()
    copied.value_norm = ValueNorm(device=trainer.device)
    copied.gradients = MinibatchGradients(
        copied.policy, copied.params, copied.config, update_workers, compile_mode
    )
    copied.gradients.share(batch)
    return copied


def _epoch(trainer: Trainer, batch, minibatches) -> Callable[[], None]:
    """One pass over the minibatches, this process's subnormal mode set as the trainer's
    config has it (the mode is process-wide, and the candidates take turns)."""

    def run() -> None:
        torch.set_flush_denormal(trainer.config.run.flush_denormal)
        for idx in minibatches:
            trainer.optimizer_step(batch, idx)

    return run


def amortized(step_s: float, warmup_s: float, warmup_steps: int, run_steps: int) -> float:
    """Seconds per optimizer step over a run of `run_steps`: the step's own, and the
    warm-up's time beyond its `warmup_steps` steps (compiling, starting workers) spread over
    the run."""
    return step_s + max(0.0, warmup_s - warmup_steps * step_s) / run_steps


def _label(settings: dict) -> str:
    return ", ".join(f"{name}={json.dumps(settings[name])}" for name in TUNED if name in settings)


class _Measurements:
    """The rounds of choice so far, each a table of its candidates."""

    def __init__(self):
        self.table: list[dict] = []
        self.twins: list[Trainer] = []

    def update_on(self, trainer: Trainer, batch, minibatches) -> None:
        """The trainer, one rollout's rows and their minibatches the update rounds time."""
        self.trainer, self.batch, self.minibatches = trainer, batch, minibatches

    def race(self, candidates: list[dict], rounds: int, run_steps: int | None = None) -> dict:
        """Measure the candidates side by side; the fastest, unless a simpler one (earlier
        in the list) is within MARGIN of it. Given the run's optimizer steps, a candidate's
        start-up (compiling, starting workers: its warm-up's time beyond its steps) is
        spread over them: a compile the run is too short to pay back is not chosen."""
        epochs, warmups = {}, {}
        for settings in candidates:
            compile_mode = "default" if settings["compile"] else None
            started = time.perf_counter()
            copied = twin(self.trainer, self.batch, settings["update_workers"], compile_mode,
                          flush_denormal=settings["flush_denormal"])  # fmt: skip
            self.twins.append(copied)
            epoch = _epoch(copied, self.batch, self.minibatches)
            for _ in range(WARMUP_EPOCHS):  # compiles, starts the workers, makes subnormals
                epoch()  # (`compare` runs two more before it measures)
            epochs[_label(settings)] = epoch
            warmups[_label(settings)] = time.perf_counter() - started
        per_epoch = compare(epochs, seconds=0.0, rounds=rounds)  # one epoch per round
        self.close()
        steps = len(self.minibatches)
        seconds = {label: epoch_s / steps for label, epoch_s in per_epoch.items()}
        if run_steps:
            seconds = {
                label: amortized(step_s, warmups[label], WARMUP_EPOCHS * steps, run_steps)
                for label, step_s in seconds.items()
            }
        per = "optimizer step" + (f", start-up spread over {run_steps:,}" if run_steps else "")
        return self.choose(candidates, seconds, per)

    def choose(self, candidates: list[dict], seconds: dict[str, float], per: str) -> dict:
        """The fastest candidate, unless a simpler one (earlier in the list) is within
        MARGIN of it; the round's figures join the table."""
        chosen = candidates[0]
        for settings in candidates:
            if seconds[_label(settings)] < (1 - MARGIN) * seconds[_label(chosen)]:
                chosen = settings
        fastest, round_ = min(seconds.values()), len({row["round"] for row in self.table}) + 1
        self.table += [
            {
                "round": round_,
                "candidate": label,
                "ms": f"{value * 1e3:.2f}",
                "per": per,
                "vs fastest of the round": f"{value / fastest:.2f}x",
                "chosen": "yes" if label == _label(chosen) else "",
            }
            for label, value in seconds.items()
        ]
        return chosen

    def close(self) -> None:
        for copied in self.twins:
            copied.gradients.close()
        self.twins = []


def measure(
    config: dict, fixed: dict, free_cores: int, rounds: int = 3, steps: int | None = None
) -> tuple[dict, list[dict]]:
    """Choose `TUNED` settings for a run of `config` (Trainer options, `env` and `algo`
    included) on this machine; `fixed`: the ones the user set, kept as given; `free_cores`:
    cores the run's env and update workers may use beyond its own; `steps`: the run's env
    steps, over which the update's start-up costs are spread. -> (the chosen settings,
    a table of every candidate measured, round by round: each round's figures are comparable
    among themselves). A run on Ray keeps its rollout settings (its workers are Ray's)."""
    defaults = {name: TrainConfig().options()[name] for name in TUNED}
    if config.get("ray"):
        fixed = {**fixed, **{name: config.get(name, defaults[name]) for name in ROLLOUT}}
    base = {**defaults, **fixed}
    options = {k: v for k, v in config.items() if k not in ("env", "algo", "ray", *TUNED)}
    measurements = _Measurements()
    base = _rollout_rounds(config, options, base, fixed, free_cores, measurements, rounds)
    # the update is measured on one rollout collected here, whatever the run's rollout
    trainer = Trainer(config["env"], config["algo"], **options, workers=0, ray=None)
    try:
        batch = trainer.rollout().rows(trainer.config.ppo.advantage_std_floor)
        rows, count = len(batch), trainer.config.ppo.num_minibatches
        size = rows // count
        minibatches = [torch.arange(i * size, (i + 1) * size) for i in range(count)]
        measurements.update_on(trainer, batch, minibatches)
        ppo = trainer.config.ppo  # the run's optimizer steps: its updates' epochs x minibatches
        updates = None if steps is None else trainer.planned_steps(steps) // ppo.steps_per_update
        run_steps = None if updates is None else updates * ppo.ppo_epochs * count
        chosen = base
        if "update_workers" not in fixed:
            most = min(MAX_UPDATE_WORKERS, free_cores, size - 1)
            workers = [{**base, "update_workers": k} for k in range(most + 1)]
            chosen = measurements.race(workers, rounds, run_steps) if len(workers) > 1 else base
        for name in ("compile", "flush_denormal"):
            if name not in fixed:
                flipped = {**chosen, name: not chosen[name]}
                chosen = measurements.race([chosen, flipped], rounds, run_steps)
        return {name: chosen[name] for name in TUNED if name not in fixed}, measurements.table
    finally:
        measurements.close()
        trainer.close()
        torch.set_flush_denormal(False)  # as torch starts: the run sets its own


def _rollout_rounds(
    config: dict,
    options: dict,
    base: dict,
    fixed: dict,
    free_cores: int,
    measurements: _Measurements,
    rounds: int,
) -> dict:
    """`base` with the env workers (none, or one per free core) and then the acting backend
    that collect the run's rollouts fastest, each candidate a trainer of its own."""
    most = min(free_cores, options.get("num_envs", PPOConfig.num_envs) - 1)
    races = []
    if "workers" not in fixed and most > 0:
        races.append(("workers", [0, most]))
    if "rollout_backend" not in fixed:
        races.append(("rollout_backend", ["torch", "onnx"]))
    chosen = base
    for name, values in races:
        candidates = [{**chosen, name: value} for value in values]
        trainers = []
        try:
            for settings in candidates:
                trainers.append(
                    Trainer(config["env"], config["algo"], **options, ray=None,
                            **{k: settings[k] for k in ROLLOUT})
                )  # fmt: skip
            collects = {
                _label(settings): trainer.collector.collect
                for settings, trainer in zip(candidates, trainers, strict=True)
            }
            seconds = compare(collects, seconds=0.0, rounds=rounds)  # a rollout per round
        finally:
            for trainer in trainers:
                trainer.close()
        chosen = measurements.choose(candidates, seconds, "rollout")
    return chosen


def tuned_settings(
    out: Path,
    config: dict,
    fixed: dict,
    free_cores: int,
    echo: Callable[[str], None] = print,
    steps: int | None = None,
) -> dict:
    """The tuned settings for the run in `out` (of `steps` env steps): those of
    OUT/tuning.json when a run there measured them before, else measured now (and written
    there)."""
    path = out / TUNING_NAME
    if path.exists():
        recorded = json.loads(path.read_text())["chosen"]
        chosen = {name: recorded[name] for name in TUNED if name in recorded and name not in fixed}
        echo(f"settings as measured before ({path}): {_label({**fixed, **chosen})}")
        return chosen
    echo(
        "measuring the rollout and update settings on this machine before a long run: env "
        "workers, acting backend, update workers, torch.compile, subnormal flushing (about a "
        "minute or two; --no-tune skips it)"
    )
    chosen, table = measure(config, fixed, free_cores, steps=steps)
    if table:
        print_table(table, "rollout and update settings measured, round by round")
    else:  # e.g. only the update workers left open, and no core to give them
        echo("nothing left to measure here: no core is free for an update worker")
    echo(f"chosen: {_label({**fixed, **chosen})}")
    out.mkdir(parents=True, exist_ok=True)
    record = {"chosen": chosen, "fixed": fixed, "measured": table}
    write_text_atomic(path, json.dumps(record, indent=1) + "\n")
    return chosen
