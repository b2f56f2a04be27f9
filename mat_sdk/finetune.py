"""Few-shot fine-tuning: adapt a trained policy to a changed robot with little new data.

    from mat_sdk.finetune import finetune
    result = finetune("runs/cheetah/checkpoint.pt", faults={"bthigh": "zero"},
                      steps=20_000, out_dir="runs/cheetah-bthigh")
    print(result.zero_shot_mean, "->", result.final_mean)

The paper's claim (Sec. 5.3): a MAT pre-trained on the full robot adapts to a robot with a
disabled joint with a few percent of the pre-training data, and beats training from scratch.
First the pre-trained policy is evaluated on the changed robot as it is (zero-shot), then
PPO continues from it (`Trainer.from_pretrained`), logging and checkpointing like training.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mat_sdk.trainer import CHECKPOINT_NAME, Trainer

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
    checkpoint: str | Path,
    env: str | None = None,
    faults: dict[str, str] | None = None,
    steps: int = 20_000,
    out_dir: str | Path | None = None,
    eval_episodes: int = 10,
    reset_optimizer: bool = True,
    lr: float | None = None,
    resume: bool = False,
    callback: Callable[[Trainer, dict], bool | None] | None = None,
    progress_bar: bool = True,
    **options: Any,
) -> FinetuneResult:
    """Zero-shot evaluation, `steps` env steps of PPO from the pre-trained weights, evaluation.

    `env` defaults to the checkpoint's env; `faults` describe the change; `options` are any
    TrainConfig fields (num_envs, seed, ...). With `resume=True`, continues the run in
    `out_dir` after an interruption, as it was started (`options` then may only say how to
    run: device, workers, update_workers, checkpoint_every). Writes OUT/finetune.json with
    both evaluations.
    """
    out = Path(out_dir) if out_dir is not None else None
    summary_path = out / SUMMARY_NAME if out else None
    if resume:
        if out is None or not (out / CHECKPOINT_NAME).exists():
            raise FileNotFoundError(f"nothing to resume: {out}/{CHECKPOINT_NAME} does not exist")
        trainer = Trainer.load(out / CHECKPOINT_NAME, out_dir=out, **options)
        zero_shot = json.loads(summary_path.read_text())["zero_shot"]["returns"]
    else:
        if out is not None and (out / CHECKPOINT_NAME).exists():
            raise FileExistsError(
                f"{out / CHECKPOINT_NAME} exists; resume that run or choose another out_dir"
            )
        trainer = Trainer.from_pretrained(
            checkpoint, env, faults, reset_optimizer, lr, out_dir=out, **options
        )
        zero_shot = trainer.evaluate(eval_episodes)
        if summary_path:
            _write_summary(summary_path, trainer, checkpoint, zero_shot, None)
    trainer.learn(steps, callback=callback, progress_bar=progress_bar)
    final = trainer.evaluate(eval_episodes)
    if summary_path:
        _write_summary(summary_path, trainer, checkpoint, zero_shot, final)
    return FinetuneResult(trainer, zero_shot, final)


def _write_summary(path: Path, trainer: Trainer, checkpoint, zero_shot, final) -> None:
    def stats(returns):
        if returns is None:
            return None
        return {"mean": float(np.mean(returns)), "std": float(np.std(returns)), "returns": returns}

    cfg = trainer.config
    summary = {
        "pretrained": str(checkpoint),
        "env": cfg.env,
        "faults": cfg.faults,
        "agents": list(trainer.env.agents),
        "steps": trainer.progress["steps"],
        "zero_shot": stats(zero_shot),
        "final": stats(final),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(summary, indent=2) + "\n")
    tmp.replace(path)
