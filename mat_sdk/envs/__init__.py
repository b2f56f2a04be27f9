"""Multi-agent decompositions of dm_control robots, as PettingZoo envs and vectorised arrays.

    from mat_sdk import envs
    env = envs.make("cheetah-6x1", faults={"bfoot": "zero"})      # PettingZoo ParallelEnv
    vec = envs.make_vec("cheetah-6x1", num_envs=40, workers=2)      # obs [40, 6, obs_dim]

Options (keywords of `make`, `make_vec` and `make_team`):
    agent_id       append a one-hot agent id (default: on, except for variable-count families)
    hops           neighbourhood radius in the kinematic tree (default 1)
    episode_limit  truncate episodes after this many steps (default: the suite's, 1000)
    task           another task of the same robot, e.g. task="run" for walker
    seed           random stream of the env (initial pose, target)
Faults: `{"<agent name or joint name>": "zero" | "remove"}`. "zero" leaves the agent in the
team with its actuator(s) producing nothing; "remove" takes the agent out of the team (its
actuators produce nothing) so the agent count drops. Remaining agents keep their names and
their one-hot ids, so a policy trained on the full robot still recognises them.
Actions are in [-1, 1] (mapped onto each actuator's control range); finite values outside
are clipped; a wrong shape, a missing or unknown agent, NaN or inf raise `ValueError`.
`coordination-N`, a small discrete game, takes choices 0..N-1 instead (`Discrete(N)`).
"""

from __future__ import annotations

import inspect
import logging
import os
from collections.abc import Mapping
from typing import Any

# Headless by default: EGL renders without a display. Set MUJOCO_GL yourself to override.
os.environ.setdefault("MUJOCO_GL", "egl")


class _QuietSuiteModels(logging.Filter):
    """dm_control's own XML uses a deprecated MuJoCo attribute; users cannot act on that."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "settotalmass" not in record.getMessage()


logging.getLogger("absl").addFilter(_QuietSuiteModels())

from mat_sdk.envs.games import CoordinationGame
from mat_sdk.envs.mamujoco import PREFIX as _MAMUJOCO
from mat_sdk.envs.mamujoco import MaMuJoCoTeam
from mat_sdk.envs.parallel import TeamParallelEnv
from mat_sdk.envs.robots import env_ids, spec_for
from mat_sdk.envs.team import RobotTeam
from mat_sdk.envs.vector import TeamFactory, VecTeam

__all__ = [
    "RobotTeam",
    "TeamParallelEnv",
    "VecTeam",
    "list_envs",
    "make",
    "make_team",
    "make_vec",
]


def _build_team(env_id: str, faults: Mapping[str, str] | None = None, **options: Any):
    if env_id.startswith("coordination-"):
        kind, first = CoordinationGame, env_id
    elif env_id.startswith(_MAMUJOCO):
        kind, first = MaMuJoCoTeam, env_id
    else:
        kind, first = RobotTeam, spec_for(env_id)
    _check_options(kind, env_id, options)
    return kind(first, faults, **options)


def _check_options(kind: type, env_id: str, options: Mapping[str, Any]) -> None:
    """Refuse an option the env does not take, naming it and the ones it does."""
    valid = [
        name
        for name, p in inspect.signature(kind.__init__).parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    ]
    unknown = sorted(set(options) - set(valid))
    if unknown:
        raise ValueError(
            f"unknown env option(s) {unknown} for {env_id}; it takes {', '.join(valid)}"
        )


def make_team(env_id: str, faults: Mapping[str, str] | None = None, **options: Any):
    """The array-level team (`step(actions [n, action_width])`), the fastest single env."""
    return _build_team(env_id, faults, **options)


def make(
    env_id: str,
    faults: Mapping[str, str] | None = None,
    render_mode: str | None = None,
    **options: Any,
) -> TeamParallelEnv:
    """A PettingZoo `ParallelEnv` for `env_id` (see `list_envs()`)."""
    return TeamParallelEnv(_build_team(env_id, faults, **options), render_mode=render_mode)


def make_vec(
    env_id: str,
    num_envs: int,
    workers: int = 0,
    seed: int = 0,
    faults: Mapping[str, str] | None = None,
    **options: Any,
) -> VecTeam:
    """`num_envs` autoresetting copies stepped as arrays; `workers` > 0 uses processes."""
    factory = TeamFactory(_build_team, {"env_id": env_id, "faults": dict(faults or {}), **options})
    return VecTeam(factory, num_envs, workers=workers, seed=seed)


def list_envs() -> list[dict[str, Any]]:
    """One row per env id: agents, obs size, action size, episode limit, description."""
    rows = []
    for env_id in [*env_ids(), f"{_MAMUJOCO}HalfCheetah-6x1", "coordination-3"]:
        team = _build_team(env_id)
        spec = getattr(team, "spec", None)
        rows.append(
            {
                "id": env_id,
                "agents": team.n_agents,
                "obs": team.obs_dim,
                "act": team.action_size,  # discrete: the number of choices
                "episode_limit": team.episode_limit,
                "about": spec.description if spec else team.description,
            }
        )
    return rows
