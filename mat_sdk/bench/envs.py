"""Env stepping cost: our team step against dm_control's bare physics step, and vector rates."""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Sequence

import numpy as np

from mat_sdk import envs
from mat_sdk.common.processes import usable_cores
from mat_sdk.common.timing import compare, print_table

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
        actions = rng.uniform(-1, 1, (team.n_agents, team.action_width))
        env = envs.make(env_id, seed=0)
        env.reset(seed=0)
        per_agent = {name: actions[i, : team.action_widths[i]] for i, name in enumerate(env.agents)}
        times = compare(
            {
                "bare": lambda p=team.physics, k=team.substeps: p.step(k),
                "ours": lambda t=team, a=actions: _step_or_reset(t, a),
                "pz": lambda e=env, a=per_agent: _pz_step_or_reset(e, a),
            },
            seconds,
        )
        bare, ours, pz = times["bare"], times["ours"], times["pz"]
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


RANDOMIZED = ("cheetah-6x1", "quadruped-4x3", "mamujoco:Ant-4x2")


def randomization_table(robots=RANDOMIZED, seconds: float = 1.0) -> list[dict]:
    """Per robot: our array step (resets included) plain vs with every randomization factor
    at its default range, side by side."""
    rows = []
    for env_id in robots:
        plain, randomized = (envs.make_team(env_id, seed=0, randomize=r) for r in (False, True))
        rng = np.random.default_rng(0)
        actions = rng.uniform(-1, 1, (plain.n_agents, plain.action_width))
        for team in (plain, randomized):
            team.reset(seed=0)
        times = compare(
            {
                "off": lambda t=plain, a=actions: _step_or_reset(t, a),
                "on": lambda t=randomized, a=actions: _step_or_reset(t, a),
            },
            seconds,
        )
        rows.append(
            {
                "env": env_id,
                "randomization off (µs)": f"{times['off'] * 1e6:.1f}",
                "on (µs)": f"{times['on'] * 1e6:.1f}",
                "on / off": f"{times['on'] / times['off']:.2f}x",
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


def vector_table(env_id: str = "cheetah-6x1", num_envs: int = 40, seconds: float = 6.0):
    """Env-steps per second for `num_envs` copies: in-process, 1 and 2 worker processes.

    All three run side by side in interleaved rounds, together with the machine's own
    ceiling: two equal CPU-bound jobs in two processes vs one after the other in one.
    """
    vecs = {w: envs.make_vec(env_id, num_envs, workers=w, seed=0) for w in (0, 1, 2)}
    labels = {0: "in-process", **{w: _split_label(vecs[w]) for w in (1, 2)}}
    pool = mp.get_context("spawn").Pool(2)
    try:
        shape = (num_envs, vecs[0].n_agents, vecs[0].action_width)
        actions = np.random.default_rng(0).uniform(-1, 1, shape)
        for vec in vecs.values():
            vec.reset()
        variants = {w: (lambda v=vec: v.step(actions)) for w, vec in vecs.items()}
        work = 2_000_000  # ~0.1 s per job, so the pool's own overhead does not count
        variants["serial"] = lambda: (_burn(work), _burn(work))
        variants["parallel"] = lambda: pool.map(_burn, [work, work])
        times = compare(variants, seconds, rounds=7)
    finally:
        pool.terminate()
        for vec in vecs.values():
            vec.close()
    rows = [
        {
            "copies": f"{num_envs} x {env_id}",
            "stepping": label,
            "env-steps/s": f"{num_envs / times[w]:,.0f}",
            "vs in-process": f"{times[0] / times[w]:.2f}x",
        }
        for w, label in labels.items()
    ]
    rows.append(
        {
            "copies": "2 equal pure-CPU jobs",
            "stepping": "2 processes vs 1 (this machine's ceiling)",
            "env-steps/s": "-",
            "vs in-process": f"{times['serial'] / times['parallel']:.2f}x",
        }
    )
    return rows


def _split_label(vec: envs.VecTeam) -> str:
    workers = f"{vec.workers} worker process{'es' if vec.workers > 1 else ''}"
    if vec.caller_steps:
        return f"caller + {workers}"
    return f"{workers} (the caller waits: {usable_cores()} cores)"


def _burn(iterations: int) -> int:
    total = 0
    for i in range(iterations):
        total += i
    return total


def main(seconds: float = 1.0, robots: Sequence[str] = RANDOMIZED) -> None:
    print_table(single_step_table(seconds=seconds), "One control step, single process")
    print_table(
        randomization_table(robots, seconds=seconds),
        "One control step, domain randomization off vs on",
    )
    print_table(vector_table(seconds=6 * seconds), "Vectorised stepping, side by side")
