"""Few-shot fine-tuning: adapt a trained policy to a changed robot with little new data.

    from mat_sdk.envs import Fault
    from mat_sdk.training.finetune import finetune
    result = finetune("runs/cheetah/checkpoint.pt", faults=[Fault.zero("bthigh")],
                      steps=20_000, out_dir="runs/cheetah-bthigh")
    print(result.zero_shot_mean, "->", result.final_mean)

The paper's claim (Sec. 5.3): a MAT pre-trained on the full robot adapts to a robot with a
disabled joint with a few percent of the pre-training data, and beats training from scratch.
First the pre-trained policy is evaluated on the changed robot as it is (zero-shot), then
PPO continues from it (`Trainer.from_pretrained`), logging and checkpointing like training.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mat_sdk import envs
from mat_sdk.common import files
from mat_sdk.policy import checkpoint as checkpoints
from mat_sdk.training.trainer import CHECKPOINT_NAME, Trainer

SUMMARY_NAME = "finetune.json"


@dataclass
class FinetuneResult:
    trainer: Trainer
    zero_shot: list[float]  # episode returns of the pre-trained policy on the changed robot
    final: list[float]  # the same episodes after fine-tuning

    @property
    def zero_shot_mean(self) -> float:
        return float(np.mean(self.zero_shot))

    @property
    def final_mean(self) -> float:
        return float(np.mean(self.final))


def finetune(
    checkpoint: str | os.PathLike,
    env: str | None = None,
    steps: int = 20_000,
    out_dir: str | Path | None = None,
    eval_episodes: int = 10,
    reset_optimizer: bool = True,
    lr: float | None = None,
    action_std: float | None = None,
    resume: bool = False,
    callback: Callable[[Trainer, dict], bool | None] | None = None,
    progress_bar: bool = True,
    **options: Any,
) -> FinetuneResult:
    """Zero-shot evaluation, `steps` env steps of PPO from the pre-trained weights, evaluation.

    `env` defaults to the checkpoint's env; `options` are any training options: `faults`
    describe the change, num_envs, seed, .... `action_std` re-opens exploration (a continuous
    policy's action std set afresh, e.g. 0.3, where a long training left it near 0.1). With
    `resume=True`, continues the run in `out_dir` after an interruption, as it was started
    (`options` then may only say how to run: device, workers, update_workers,
    checkpoint_every). Writes OUT/finetune.json with both evaluations. Without `env`, a
    `module:function` env id that the checkpoint records is imported only for a checkpoint
    given as `envs.Trusted(path)`.
    """
    if resume and action_std is not None:
        raise ValueError(
            "action_std sets the std where a fine-tuning run starts; a resumed run goes on "
            "with the std it has learned: resume without it"
        )
    out = Path(out_dir) if out_dir is not None else None
    with files.RunLock(out) if out else contextlib.nullcontext():
        if resume:  # as it was started: what is given again must be what it was
            given = {**options, "lr": lr}
            given = {k: v for k, v in given.items() if v is not None}
            if not given.get("faults", True):  # no change given: not a change to check
                del given["faults"]
            trainer, zero_shot = _resumed(out, env, checkpoint, given)
        else:
            trainer = _started(checkpoint, env, reset_optimizer, lr, action_std, out, options)
            zero_shot = trainer.evaluate(eval_episodes)
            if out:
                _write_summary(out / SUMMARY_NAME, trainer, checkpoint, zero_shot, None)
        trainer.learn(steps, callback=callback, progress_bar=progress_bar)
        final = trainer.evaluate(eval_episodes)
        if out:
            _write_summary(out / SUMMARY_NAME, trainer, checkpoint, zero_shot, final)
    return FinetuneResult(trainer, zero_shot, final)


def default_out(env: str | None, changes: tuple[envs.Fault, ...]) -> Path:
    """runs/finetune-<the change>: its faults, else the env."""
    label = "-".join(f"{f.target}_{f.mode}" for f in changes) or (env or "same")
    return Path("runs") / f"finetune-{label.replace(':', '_')}"


def _started(checkpoint, env, reset_optimizer, lr, action_std, out, options) -> Trainer:
    if out is not None and (out / CHECKPOINT_NAME).exists():
        raise FileExistsError(
            f"{out / CHECKPOINT_NAME} exists; resume that run or choose another out_dir"
        )
    return Trainer.from_pretrained(
        checkpoint, env, reset_optimizer, lr, out_dir=out, action_std=action_std, **options
    )


def _resumed(out, env, started_from, options) -> tuple[Trainer, list[float]]:
    """The interrupted run in `out`, as it was started, and its zero-shot returns; its
    checkpoint is trusted as the one it started from is (`envs.trusted_as`)."""
    resumed = None if out is None else out / CHECKPOINT_NAME
    if resumed is None or not resumed.exists():
        raise FileNotFoundError(f"nothing to resume: {out}/{CHECKPOINT_NAME} does not exist")
    if env is not None:  # the run goes on on the env it records
        recorded = checkpoints.env_id(checkpoints.load(resumed))
        if envs.id_of(env) != recorded:
            raise ValueError(
                f"{resumed} fine-tunes on {recorded!r}, not {env!r}; resume it without "
                "another env, or start a new run with another out_dir"
            )
        options = {**options, "env": recorded}  # typed by the user: trusted as named
    trainer = Trainer.load(envs.trusted_as(resumed, started_from), out_dir=out, **options)
    zero_shot = json.loads((out / SUMMARY_NAME).read_text())["zero_shot"]["returns"]
    return trainer, zero_shot


def _write_summary(path: Path, trainer: Trainer, checkpoint, zero_shot, final) -> None:
    def stats(returns):
        if returns is None:
            return None
        return {"mean": float(np.mean(returns)), "std": float(np.std(returns)), "returns": returns}

    cfg = trainer.config
    summary = {
        "pretrained": str(checkpoint),
        "env": cfg.env.id,
        "faults": envs.as_mapping(cfg.env.faults),
        "agents": list(trainer.env.agents),
        "steps": trainer.progress.steps,
        "zero_shot": stats(zero_shot),
        "final": stats(final),
    }
    files.write_text_atomic(path, json.dumps(summary, indent=2) + "\n")
