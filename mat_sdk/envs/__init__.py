"""Multi-agent decompositions of MuJoCo robots (ours or yours) and PettingZoo envs, as
PettingZoo envs and vectorised arrays.

    from mat_sdk import envs
    env = envs.make("cheetah-6x1", faults=[envs.Fault.zero("bfoot")])  # PettingZoo ParallelEnv
    vec = envs.make_vec("cheetah-6x1", num_envs=40, workers=2)      # obs [40, 6, obs_dim]
    arm = envs.from_mjcf("arm.xml", [["shoulder"], ["elbow", "wrist"]], reward)  # your robot
    vec = envs.make_vec("my_robots:arm", num_envs=8)                # by module:function id

Ids and what they build: `registry.py`; your own robots: `sources.py`; PettingZoo envs:
`pettingzoo_team.py`.

Options (keywords of `make`, `make_vec` and `make_team`):
    agent_id       append a one-hot agent id (default: on, except for variable-count families)
    position       append a count-independent identity: "fraction" (i / (N - 1)), "ends"
                   (1 / (1 + i), 1 / (N - i)), "near-ends" (min(i, 2) / 2, min(N - 1 - i, 2)
                   / 2) or "end-flags" (min(i, 1), min(N - 1 - i, 1)); robots and MaMuJoCo
    hops           neighbourhood radius in the kinematic tree (default 1)
    episode_limit  truncate episodes after this many steps (default: the suite's, 1000)
    task           another task of the same robot, e.g. task="run" for walker
    seed           random stream of the env (initial pose, target)
    randomize      domain randomization: true (every factor at its default range), or a
                   mapping of factors, e.g. {"payload": [0, 2], "push": null} (robots)
Faults (`envs.Fault`, from `mat_sdk.envs.core.faults`), each naming an agent or a joint:
`Fault.zero(name)` leaves the agent in the team with its actuator(s) taking no action (a
position actuator holds its start target); `Fault.remove(name)` takes the agent out of the
team (its actuators produce nothing) so the agent count drops; `Fault.weak(name, S)` leaves
the actuator(s) S of their force, 0 < S < 1. The mapping form `{name: "zero" | "remove" |
"weak:S"}` (as checkpoints store faults) is taken too. Remaining agents keep their names
and their one-hot ids, so a policy trained on the full robot still recognises them.
Actions are in [-1, 1] (mapped onto each actuator's control range); finite values outside
are clipped; a wrong shape, a missing or unknown agent, NaN or inf raise `ValueError`.
`coordination-N`, a small discrete game, takes choices 0..N-1 instead (`Discrete(N)`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import replace
from typing import Any

# Headless by default: EGL renders without a display. Set MUJOCO_GL yourself to override.
os.environ.setdefault("MUJOCO_GL", "egl")


class _QuietSuiteModels(logging.Filter):
    """dm_control's own XML uses a deprecated MuJoCo attribute; users cannot act on that."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "settotalmass" not in record.getMessage()


logging.getLogger("absl").addFilter(_QuietSuiteModels())

from mat_sdk.envs.core.faults import Fault, FaultsLike, as_mapping, faults_of
from mat_sdk.envs.core.recipe import TrainingRecipe
from mat_sdk.envs.core.vector import TeamFactory, VecTeam
from mat_sdk.envs.mujoco import terms
from mat_sdk.envs.mujoco.actuation import JointTargets
from mat_sdk.envs.mujoco.features import Observation
from mat_sdk.envs.mujoco.model_task import ModelEnvironment
from mat_sdk.envs.mujoco.randomization import Randomization
from mat_sdk.envs.mujoco.robots import env_ids
from mat_sdk.envs.mujoco.sources import RobotSpec, UnusedActuators, from_dm_control, from_mjcf
from mat_sdk.envs.mujoco.team import RobotTeam
from mat_sdk.envs.pettingzoo.parallel import TeamParallelEnv
from mat_sdk.envs.pettingzoo.team import PettingZooSpec, PettingZooTeam, from_pettingzoo
from mat_sdk.envs.registry import (
    ENTRY_POINT_GROUP,
    FAMILY_IDENTITY,
    EnvSpec,
    Trusted,
    UntrustedEnvError,
    build_team,
    check_trusted,
    family_identity,
    id_of,
    installed_ids,
    is_family,
    recipe_of,
    register,
    resolve,
    trusted_as,
)
from mat_sdk.envs.tasks import legged

__all__ = [
    "ENTRY_POINT_GROUP",
    "FAMILY_IDENTITY",
    "Env",
    "EnvSpec",
    "Fault",
    "FaultsLike",
    "JointTargets",
    "Observation",
    "PettingZooSpec",
    "PettingZooTeam",
    "Randomization",
    "RobotSpec",
    "RobotTeam",
    "TeamParallelEnv",
    "TrainingRecipe",
    "Trusted",
    "UntrustedEnvError",
    "UnusedActuators",
    "VecTeam",
    "as_mapping",
    "check_trusted",
    "family_identity",
    "faults_of",
    "from_dm_control",
    "from_mjcf",
    "from_pettingzoo",
    "id_of",
    "is_family",
    "legged",
    "list_envs",
    "make",
    "make_team",
    "make_vec",
    "random_rollout",
    "recipe_of",
    "register",
    "resolve",
    "terms",
    "trusted_as",
]

Env = str | EnvSpec


def make_team(env: Env, *, visual: bool = False, **options: Any):
    """The array-level team (`step(actions [n, action_width])`), the fastest single env.
    `options` are the env's own (`seed`, `faults`, `randomize`, ...: an unknown one is
    refused, naming those it takes). `visual`: to render, an MJCF model compiled with the
    visual assets (textures, visual meshes) that env copies leave out."""
    spec = resolve(env)
    factory = getattr(spec, "env_factory", None)
    if visual and isinstance(factory, ModelEnvironment):
        spec = replace(spec, env_factory=replace(factory, visual=True))
    return build_team(spec, **options)


def make(env: Env, *, render_mode: str | None = None, **options: Any) -> TeamParallelEnv:
    """A PettingZoo `ParallelEnv` for an env id (see `list_envs()`) or spec; `options` as
    `make_team` takes them."""
    return TeamParallelEnv(build_team(env, **options), render_mode=render_mode)


def make_vec(
    env: Env,
    num_envs: int,
    workers: int = 0,
    seed: int = 0,
    **options: Any,
) -> VecTeam:
    """`num_envs` autoresetting copies stepped as arrays; `workers` > 0 uses processes;
    `options` as `make_team` takes them, copy i seeded `seed + i`.

    Worker processes get the resolved spec (pickled), so an env registered only in this
    process works with workers as long as its functions are importable (module-level)."""
    spec = resolve(env)
    factory = TeamFactory(build_team, {"env": spec, **options})
    return VecTeam(factory, num_envs, workers=workers, seed=seed)


def list_envs() -> list[dict[str, Any]]:
    """One row per env id (built-in, then installed packages'): agents, obs size, action
    size, episode limit, description."""
    rows = []
    built_in = [
        *env_ids(),
        "mamujoco:HalfCheetah-6x1",
        "mamujoco:ManySegmentSwimmer-4x2",
        "mamujoco:ManySegmentAnt-3x2",
        "coordination-3",
    ]
    for env_id in [*built_in, *installed_ids()]:
        team = build_team(env_id)
        spec = getattr(team, "spec", None)
        rows.append(
            {
                "id": env_id,
                "agents": team.n_agents,
                "obs": team.obs_dim,
                "act": team.action_size,  # discrete: the number of choices
                "episode_limit": team.episode_limit,
                "about": getattr(spec, "description", "") or team.description,
                "family": team.variable_count,
            }
        )
        close = getattr(team, "close", None)
        if close:
            close()
    return rows


def random_rollout(
    env: Env, steps: int, seed: int = 0, **options: Any
) -> tuple[TeamParallelEnv, list[float]]:
    """`steps` env steps of a team acting uniformly at random over each agent's action space
    (from streams independent of the env's own); -> the env and its episodes' returns (the
    last one as far as it got)."""
    import numpy as np

    parallel = make(env, seed=seed, **options)
    streams = np.random.SeedSequence([seed, 1]).generate_state(len(parallel.possible_agents))
    for agent, stream in zip(parallel.possible_agents, streams, strict=True):
        parallel.action_space(agent).seed(int(stream))
    parallel.reset(seed=seed)
    episode_return, returns = 0.0, []
    for _ in range(steps):
        if not parallel.agents:
            returns.append(episode_return)
            episode_return = 0.0
            parallel.reset()
        actions = {a: parallel.action_space(a).sample() for a in parallel.agents}
        _, rewards, _, _, _ = parallel.step(actions)
        episode_return += next(iter(rewards.values()))
    returns.append(episode_return)
    return parallel, returns
