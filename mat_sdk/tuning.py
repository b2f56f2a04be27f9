"""The update settings a long run uses, measured on the machine it runs on (`mat train`).

Which update step is fastest depends on the CPU: update worker processes on idle cores,
torch.compile of the loss, and flushing subnormal floats to zero each win on some machines
and lose on others (BENCHMARKS.md). So before a long CPU run that sets none of them, the
candidates are measured side by side (`compare`, interleaved rounds) on the run's own recipe
and one rollout of its own env, in three rounds of choice: how many update workers (eager),
then with torch.compile or not, then flushing subnormals or not. A candidate that costs more
to start (a compile, a process) must beat the simpler one by `MARGIN`.

The choice is printed and written to OUT/tuning.json, which a rerun of the same command
reuses (so a resumed run, or a seed set's unfinished seeds, keep their settings); the
checkpoint records it like any setting. Each twin updates a private copy of the policy, and
the run itself starts from its seed afterwards, untouched: a tuned run equals a run given
the chosen settings on the command line.
"""

from __future__ import annotations

import copy
import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from mat_sdk.config import TrainConfig
from mat_sdk.files import write_text_atomic
from mat_sdk.gradients import MinibatchGradients
from mat_sdk.normalization import ValueNorm
from mat_sdk.timing import compare, print_table
from mat_sdk.trainer import Trainer

TUNED = ("update_workers", "compile", "flush_denormal")
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
    copied.config = dataclasses.replace(trainer.config, **config_changes)
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
        torch.set_flush_denormal(trainer.config.flush_denormal)
        for idx in minibatches:
            trainer.optimizer_step(batch, idx)

    return run


def _label(settings: dict) -> str:
    return ", ".join(f"{name}={json.dumps(settings[name])}" for name in TUNED if name in settings)


class _Measurements:
    """The rounds of choice so far, each a table of its candidates."""

    def __init__(self, trainer: Trainer, batch, minibatches):
        self.trainer, self.batch, self.minibatches = trainer, batch, minibatches
        self.table: list[dict] = []
        self.twins: list[Trainer] = []

    def race(self, candidates: list[dict], rounds: int) -> dict:
        """Measure the candidates side by side; the fastest, unless a simpler one (earlier
        in the list) is within MARGIN of it."""
        epochs = {}
        for settings in candidates:
            compile_mode = "default" if settings["compile"] else None
            copied = twin(self.trainer, self.batch, settings["update_workers"], compile_mode,
                          flush_denormal=settings["flush_denormal"])  # fmt: skip
            self.twins.append(copied)
            epoch = _epoch(copied, self.batch, self.minibatches)
            for _ in range(WARMUP_EPOCHS):  # compiles, starts the workers, makes subnormals
                epoch()  # (`compare` runs two more before it measures)
            epochs[_label(settings)] = epoch
        per_epoch = compare(epochs, seconds=0.0, rounds=rounds)  # one epoch per round
        self.close()
        seconds = {label: epoch_s / len(self.minibatches) for label, epoch_s in per_epoch.items()}
        chosen = candidates[0]
        for settings in candidates:
            if seconds[_label(settings)] < (1 - MARGIN) * seconds[_label(chosen)]:
                chosen = settings
        fastest, round_ = min(seconds.values()), len({row["round"] for row in self.table}) + 1
        self.table += [
            {
                "round": round_,
                "candidate": label,
                "ms / optimizer step": f"{value * 1e3:.2f}",
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


def measure(config: dict, fixed: dict, free_cores: int, rounds: int = 3) -> tuple[dict, list[dict]]:
    """Choose `TUNED` settings for a run of `config` (Trainer options, `env` and `algo`
    included) on this machine; `fixed`: the ones the user set, kept as given; `free_cores`:
    cores the run's update may use beyond its own. -> (the chosen settings, a table of every
    candidate measured, round by round: each round's figures are comparable among
    themselves)."""
    defaults = {name: getattr(TrainConfig, name) for name in TUNED}
    base = {**defaults, **fixed}
    options = {k: v for k, v in config.items() if k not in ("env", "algo", *TUNED)}
    options |= {"workers": 0, "ray": None}  # the measurement steps its envs here
    trainer = Trainer(config["env"], config["algo"], **options)
    measurements = None
    try:
        trainer.config.check_batching()  # as the run would refuse it, before any work
        batch = trainer.rollout().rows(trainer.config.advantage_std_floor)
        rows = batch["obs"].shape[0]
        size = rows // trainer.config.num_minibatches
        minibatches = [torch.arange(i * size, (i + 1) * size)
                       for i in range(trainer.config.num_minibatches)]  # fmt: skip
        measurements = _Measurements(trainer, batch, minibatches)
        chosen = base
        if "update_workers" not in fixed:
            most = min(MAX_UPDATE_WORKERS, free_cores, size - 1)
            workers = [{**base, "update_workers": k} for k in range(most + 1)]
            chosen = measurements.race(workers, rounds) if len(workers) > 1 else base
        for name in ("compile", "flush_denormal"):
            if name not in fixed:
                chosen = measurements.race([chosen, {**chosen, name: not chosen[name]}], rounds)
        return {name: chosen[name] for name in TUNED if name not in fixed}, measurements.table
    finally:
        if measurements is not None:
            measurements.close()
        trainer.close()
        torch.set_flush_denormal(False)  # as torch starts: the run sets its own


def tuned_settings(
    out: Path, config: dict, fixed: dict, free_cores: int, echo: Callable[[str], None] = print
) -> dict:
    """The tuned settings for the run in `out`: those of OUT/tuning.json when a run there
    measured them before, else measured now (and written there)."""
    path = out / TUNING_NAME
    if path.exists():
        recorded = json.loads(path.read_text())["chosen"]
        chosen = {name: recorded[name] for name in TUNED if name in recorded and name not in fixed}
        echo(f"update settings as measured before ({path}): {_label({**fixed, **chosen})}")
        return chosen
    echo(
        "measuring the update settings on this machine before a long run: update workers, "
        "torch.compile, subnormal flushing (about a minute or two; --no-tune skips it)"
    )
    chosen, table = measure(config, fixed, free_cores)
    if table:
        print_table(table, "update settings measured, round by round")
    else:  # e.g. only the update workers left open, and no core to give them
        echo("nothing left to measure here: no core is free for an update worker")
    echo(f"chosen: {_label({**fixed, **chosen})}")
    out.mkdir(parents=True, exist_ok=True)
    record = {"chosen": chosen, "fixed": fixed, "measured": table}
    write_text_atomic(path, json.dumps(record, indent=1) + "\n")
    return chosen
