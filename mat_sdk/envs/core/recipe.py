"""A task's training recipe: the PPO settings it trains well with, declared beside its terms.

    WALK_RECIPE = TrainingRecipe(num_envs=32, rollout_length=100, lr=3e-4, entropy_coef=0.0)
    envs.from_mjcf(..., recipe=WALK_RECIPE)

`mat train ENV` and `Trainer(ENV)` start from it: the algorithm's recipe first, the task's
over it, then what the user gives (`--set`, keyword options). A checkpoint records the
settings the run used, so a resume needs none of them again. Values are checked where they
are used, by the training config, with errors that name the field.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

RUN_SETTINGS = ("tune", "eval_every")  # `mat train`'s, not the training config's


@dataclass(frozen=True)
class TrainingRecipe:
    """PPO settings a task declares (None: the algorithm recipe's); how `mat train` runs it:
    `tune`, whether it measures the rollout and update settings on the machine first (None:
    for runs of 1e6 steps or more); `eval_every`, the env steps between the protocol's
    evaluations (0: none; None: 20 per run of 100,000 steps or more)."""

    num_envs: int | None = None
    rollout_length: int | None = None
    lr: float | None = None
    ppo_epochs: int | None = None
    num_minibatches: int | None = None
    clip: float | None = None
    entropy_coef: float | None = None
    max_grad_norm: float | None = None
    desired_kl: float | None = None
    train_episode_limit: int | None = None
    gamma: float | None = None
    gae_lambda: float | None = None
    tune: bool | None = None
    eval_every: int | None = None

    def settings(self) -> dict[str, Any]:
        """The training options it sets (`TrainConfig` fields): all but how the run goes."""
        return {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if f.name not in RUN_SETTINGS and getattr(self, f.name) is not None
        }
