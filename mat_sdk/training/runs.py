"""A training run as `mat train` asks for it: started or resumed in its own directory, its
update settings tuned to the machine, evaluated to the protocol, every decision said.

    request = RunRequest(["cheetah-6x1"], steps=2_000_000, options={"seed": 0})
    result = train(request)                  # one run; seed sets: `multiseed.train_seeds`

`options` are `TrainConfig` fields; `given` names those the user chose (a resume refuses any
that differ from the checkpoint's; tuning keeps them as given). The Python API and the CLI
make the same call, so `Trainer`, `mat train` and each seed of a set train the same run.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mat_sdk.common import files
from mat_sdk.evaluation.protocol import EvaluationLog
from mat_sdk.policy.algorithms import algorithm
from mat_sdk.policy.checkpoint import CHECKPOINT_NAME
from mat_sdk.training.trainer import Trainer

Say = Callable[[str], None]
EVAL_FROM_STEPS = 100_000  # runs this long are evaluated to the protocol by default
EVALUATIONS_PER_RUN = 20


@dataclass
class RunRequest:
    """What a run is asked to do (the module docstring)."""

    env_ids: list[str]
    algo: str = "mat"
    steps: int = 1_000_000
    out: Path | None = None  # default: runs/ENV-ALGO-sSEED
    options: dict[str, Any] = field(default_factory=dict)  # training options (config.OPTIONS)
    given: list[str] = field(default_factory=list)  # the options the user chose
    resume: bool = False
    eval_every: int | None = None  # None: steps / 20 from EVAL_FROM_STEPS steps on, else off
    eval_episodes: int = 10
    tune: bool | None = None  # None: long CPU runs measure their update settings
    free_cores: int = 0  # cores the update may use beyond the run's own (tuning)

    def __post_init__(self):
        self.out = Path(self.out) if self.out is not None else self.default_out()

    @property
    def evaluation_interval(self) -> int:
        """Env steps between the protocol's evaluations (0: none): as asked, else 20 per run
        of EVAL_FROM_STEPS steps or more."""
        if self.eval_every is not None:
            return self.eval_every
        return self.steps // EVALUATIONS_PER_RUN if self.steps >= EVAL_FROM_STEPS else 0

    def default_out(self) -> Path:
        seed = self.options.get("seed", 0)
        return Path("runs") / f"{self.env_ids[0].replace(':', '_')}-{self.algo}-s{seed}"

    @property
    def checkpoint(self) -> Path:
        return self.out / CHECKPOINT_NAME

    def given_options(self) -> dict[str, Any]:
        """The options the user chose, with the env ids and algorithm (always chosen)."""
        chosen = {name: self.options[name] for name in self.given if name in self.options}
        return {"env": self.env_ids[0], "more_envs": self.env_ids[1:], "algo": self.algo, **chosen}

    def to_json(self) -> str:
        """As JSON, the faults in their mapping form (`envs.as_mapping`)."""
        from mat_sdk import envs

        options = dict(self.options)
        if "faults" in options:
            options["faults"] = envs.as_mapping(envs.faults_of(options["faults"]))
        asked = dataclasses.replace(self, options=options)
        return json.dumps({**dataclasses.asdict(asked), "out": str(self.out)})

    @classmethod
    def from_json(cls, text: str) -> RunRequest:
        return cls(**json.loads(text))


@dataclass
class RunResult:
    trainer: Trainer
    checkpoint: Path
    absolute: list[float] | None  # the best evaluated policy's returns (the protocol's)


def train(request: RunRequest, say: Say = print, progress_bar: bool = True) -> RunResult:
    """Start (or with `resume`, continue) the run in `request.out` and train it to
    `request.steps`; the directory is locked meanwhile (`files.RunLock`)."""
    request = with_task_recipe(request)
    with files.RunLock(request.out):
        trainer = start(request, say)
        with trainer:
            evaluations = None
            every = request.evaluation_interval
            if every:
                evaluations = EvaluationLog(request.out, every, request.eval_episodes)
                say(
                    f"evaluating every {every:,} steps on {request.eval_episodes} "
                    f"episodes into {evaluations.path} (--eval-every 0: off)"
                )
            trainer.learn(request.steps, callback=evaluations, progress_bar=progress_bar)
            absolute = None
            if evaluations is not None and trainer.progress.steps >= request.steps:
                absolute = evaluations.finish(trainer)
                if absolute is not None:
                    say(
                        f"absolute metric (best policy, {len(absolute)} episodes): "
                        f"{np.mean(absolute):.2f} ± {np.std(absolute):.2f}"
                    )
    return RunResult(trainer, request.checkpoint, absolute)


def with_task_recipe(request: RunRequest) -> RunRequest:
    """The request with its task's training recipe (`envs.TrainingRecipe`) under the
    options the user chose: `--set` and the flags override it, the CLI's defaults do not."""
    from mat_sdk import envs

    recipe = envs.recipe_of(request.env_ids[0])
    if recipe is None:
        return request
    settings = {k: v for k, v in recipe.settings().items() if k not in request.given}
    tune = request.tune if request.tune is not None else recipe.tune
    every = request.eval_every if request.eval_every is not None else recipe.eval_every
    return dataclasses.replace(
        request, options={**request.options, **settings}, tune=tune, eval_every=every
    )


def start(request: RunRequest, say: Say = print) -> Trainer:
    """The run's trainer: resumed from its checkpoint (refusing a changed task), or new (with
    the family identity and the tuned update settings), each decision said."""
    if request.resume:
        if not request.checkpoint.exists():
            raise FileNotFoundError(f"nothing to resume: {request.checkpoint} does not exist")
        # the ids given here are the user's, and must be the checkpoint's
        trainer = Trainer.load(request.checkpoint, out_dir=request.out, **request.given_options())
        changed = ", ".join(f"{k}={v}" for k, v in trainer.resumed_with.items())
        say(
            f"resuming {request.checkpoint} at {trainer.progress.steps:,} steps"
            + (f" (with {changed})" if changed else "")
        )
        return trainer
    if request.checkpoint.exists():
        raise FileExistsError(
            f"{request.checkpoint} exists; pass --resume to continue that run or choose another "
            "--out"
        )
    request = with_task_recipe(request)
    options = {**request.options, **tuned(request, say)}
    if len(request.env_ids) > 1:
        options["more_envs"] = list(request.env_ids[1:])
    trainer = Trainer(request.env_ids[0], request.algo, out_dir=request.out, **options)
    for note in trainer.notes:
        say(note)
    planned = trainer.planned_steps(request.steps)
    if planned != request.steps:
        per_update = trainer.config.ppo.steps_per_update
        say(
            f"--steps {request.steps:,}: training runs whole updates of {per_update:,} env "
            f"steps (num_envs x rollout_length), so this run ends at {planned:,} steps"
        )
    return trainer


def tuned(request: RunRequest, say: Say = print) -> dict[str, Any]:
    """The update settings measured fastest on this machine (`mat_sdk.training.tuning`), for a run
    that asks for them or a long CPU run by default; those the user chose stay as chosen.
    -> {field: value} to train with ({} when not tuning)."""
    from mat_sdk import envs
    from mat_sdk.training.tuning import TUNED, tuned_settings, wanted

    if algorithm(request.algo).sequential_update:  # no levers to measure
        return {}
    fixed = {name: request.options[name] for name in TUNED if name in request.given}
    device = request.options.get("device", "cpu")
    if not wanted(request.tune, request.steps, _on_cpu(device), fixed):
        return {}
    options = dict(request.options)
    options["env_options"] = envs.family_identity(
        request.env_ids[0], options.get("env_options") or {}
    )
    run = {**options, "env": request.env_ids[0], "algo": request.algo}
    free = max(0, request.free_cores)
    return tuned_settings(request.out, run, fixed, free, echo=say, steps=request.steps)


def _on_cpu(device: str) -> bool:
    if device != "auto":
        return device == "cpu"
    import torch

    return not torch.cuda.is_available()
