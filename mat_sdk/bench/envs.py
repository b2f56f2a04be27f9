"""Env stepping cost: our team step against dm_control's bare physics step, and vector rates."""

from __future__ import annotations

import multiprocessing as mp
import time

import numpy as np

from mat_sdk import envs
from mat_sdk.bench import print_table, time_per_call

ROBOTS = (
    "cheetah-6x1",
    "walker-6x1",
    "hopper-4x1",
    "quadruped-4x3",
    "humanoid-limbs",
    "swimmer-6",
)


def single_step_table(robots=ROBOTS, seconds: float = 1.0) -> list[dict]:
    """Per robot: bare `physics.step()` for one control step vs our array and PettingZoo steps."""
    rows = []
    for env_id in robots:
        team = envs.make_team(env_id, seed=0)
        team.reset(seed=0)
        rng = np.random.default_rng(0)
        actions = rng.uniform(-1, 1, (team.n_agents, team.act_dim))
        substeps = team._substeps
        bare = time_per_call(lambda p=team.physics, k=substeps: p.step(k), seconds)
        ours = time_per_call(lambda t=team, a=actions: _step_or_reset(t, a), seconds)
        env = envs.make(env_id, seed=0)
        env.reset(seed=0)
        per_agent = {name: actions[i, : team.act_dims[i]] for i, name in enumerate(env.agents)}
        pz = time_per_call(lambda e=env, a=per_agent: _pz_step_or_reset(e, a), seconds)
        rows.append(
            {
                "env": env_id,
                "bare physics.step (µs)": f"{bare * 1e6:.1f}",
                "our array step (µs)": f"{ours * 1e6:.1f}",
                "ratio": f"{ours / bare:.2f}x",
                "PettingZoo step (µs)": f"{pz * 1e6:.1f}",
                "PZ ratio": f"{pz / bare:.2f}x",
            }
        )
    return rows


def _step_or_reset(team, actions) -> None:
    _, _, terminated, truncated = team.step(actions)
    if terminated or truncated:
        team.reset()


def _pz_step_or_reset(env, actions) -> None:
    if not env.agents:
        env.reset()
    env.step(actions)


def vector_table(env_id: str = "cheetah-6x1", num_envs: int = 40, steps: int = 300) -> list[dict]:
    """Env-steps per second for `num_envs` copies: in-process, 1 and 2 worker processes."""
    rows, base = [], None
    for workers in (0, 1, 2):
        with envs.make_vec(env_id, num_envs, workers=workers, seed=0) as vec:
            vec.reset()
            actions = np.random.default_rng(0).uniform(-1, 1, (num_envs, vec.n_agents, vec.act_dim))
            for _ in range(20):
                vec.step(actions)
            start = time.perf_counter()
            for _ in range(steps):
                vec.step(actions)
            rate = num_envs * steps / (time.perf_counter() - start)
        base = base or rate
        label = "in-process" if workers == 0 else f"{workers} worker process(es)"
        rows.append(
            {
                "copies": f"{num_envs} x {env_id}",
                "stepping": label,
                "env-steps/s": f"{rate:,.0f}",
                "vs in-process": f"{rate / base:.2f}x",
            }
        )
    return rows


def _burn(iterations: int) -> float:
    start = time.perf_counter()
    total = 0
    for i in range(iterations):
        total += i
    return time.perf_counter() - start


def parallel_ceiling(iterations: int = 5_000_000) -> float:
    """How much faster two processes finish two equal CPU-bound jobs than one process does.

    On a machine with two free cores this is ~2.0; on shared virtual CPUs it is lower, and no
    worker scheme can beat it.
    """
    with mp.get_context("spawn").Pool(2) as pool:
        pool.map(_burn, [1000, 1000])
        start = time.perf_counter()
        pool.map(_burn, [iterations, iterations])
        parallel = time.perf_counter() - start
    serial = _burn(iterations) + _burn(iterations)
    return serial / parallel


def main(seconds: float = 1.0, vector_steps: int = 300) -> None:
    print_table(single_step_table(seconds=seconds), "One control step, single process")
    print_table(vector_table(steps=vector_steps), "Vectorised stepping")
    print(f"This machine's ceiling for 2 processes (pure-CPU jobs): {parallel_ceiling():.2f}x\n")
