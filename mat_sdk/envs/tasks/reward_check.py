"""A check of a reward built from terms before training: under random actions, does one
penalty outweigh every positive term many times over? Then every vigorous motion is net
negative, and standing still (or, without `only_positive_rewards`, ending the episode) is
what the reward asks for: the weights were likely written for another robot's units.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from mat_sdk.envs.mujoco.model_task import FLOOR

RULING_FACTOR = 5.0  # a penalty this many times all positive terms together rules the reward
STEPS = 200


def random_breakdown(team, steps: int = STEPS, seed: int = 0) -> dict[str, float]:
    """Each reward term's mean per step over `steps` steps of uniform random actions."""
    random = np.random.default_rng(seed)
    team.reset(seed=seed)
    sums = np.zeros(len(team.reward_terms))
    shape = (team.n_agents, team.action_width)
    for _ in range(steps):
        _, _, terminated, truncated = team.advance(random.uniform(-1.0, 1.0, shape))
        sums += team.term_values()
        if terminated or truncated:
            team.reset()
    return dict(zip(team.reward_terms, (sums / steps).tolist(), strict=True))


def ruling_penalty(breakdown: dict[str, float]) -> str | None:
    """A warning naming the penalty that outweighs all positive terms `RULING_FACTOR` times
    over in `breakdown` (`random_breakdown`), or None."""
    terms = {name: value for name, value in breakdown.items() if name != FLOOR}
    positive = sum(value for value in terms.values() if value > 0)
    name, worst = min(terms.items(), key=lambda item: item[1], default=("", 0.0))
    if worst < 0 and -worst > RULING_FACTOR * max(positive, 1e-9):
        return (
            f"under random actions the reward term {name!r} costs {-worst:.3g} per step, more "
            f"than {RULING_FACTOR:g}x all positive terms together ({positive:.3g}): moving "
            "does not pay, and the policy may learn to stand still. Its weight may be in "
            "another robot's units; see the per-term logs (reward/... in metrics.csv)"
        )
    return None


class RewardWarning(UserWarning):
    """A reward whose terms make moving not pay."""


def check_reward(env_id: str, seed: int, **options: Any) -> list[str]:
    """Warn (RewardWarning) when one penalty rules `env_id`'s reward (built with `options`)
    under random actions; -> the warnings, for a trainer's notes."""
    from mat_sdk.envs.registry import build_team

    team = build_team(env_id, seed=seed, **options)
    warning = ruling_penalty(random_breakdown(team, seed=seed))
    if warning is None:
        return []
    warnings.warn(f"{env_id}: {warning}", RewardWarning, stacklevel=3)
    return [warning]
