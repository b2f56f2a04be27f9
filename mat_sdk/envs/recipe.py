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


@dataclass(frozen=True)
class TrainingRecipe:
    """PPO settings a task declares (None: the algorithm recipe's); `tune`: whether
    `mat train` measures the update settings on the machine before a long run."""

    num_envs: int | None = None
    rollout_length: int | None = None
    lr: float | None = None
    ppo_epochs: int | None = None
    num_minibatches: int | None = None
    clip: float | None = None
    entropy_coef: float | None = None
    max_grad_norm: float | None = None
    gamma: float | None = None
    gae_lambda: float | None = None
    tune: bool | None = None

    def settings(self) -> dict[str, Any]:
        """The training options it sets (`TrainConfig` fields), without `tune`."""
        return {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if f.name != "tune" and getattr(self, f.name) is not None
        }
