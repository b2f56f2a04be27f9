"""E copies of a team stepped as arrays, in this process or in worker processes.

Workers share every array with the parent through shared memory. A step crosses no pipe:
two semaphores say "go" and "done" (`mat_sdk.common.processes`). The pipe carries only errors and
the rare commands with arguments or results (reset, get and set state). Copy i is seeded with
`seed + i` and owns its random stream, so the same seed gives the same trajectories whatever
the worker count. Finished episodes reset automatically; the last observation of the
finished episode is in `info["final_obs"]` (for bootstrapping a truncated episode).
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mat_sdk.common import processes
from mat_sdk.common.processes import WorkerProcess, close_all, serve, wait_all
from mat_sdk.envs.core.base import as_array, invalid_action, real_actions

_FIELDS = {  # name: (shape after [num_envs], dtype)
    "actions": (("n", "act"), np.float64),
    "obs": (("n", "obs"), np.float32),
    "final_obs": (("n", "obs"), np.float32),
    "reward": ((), np.float64),
    "terminated": ((), np.bool_),
    "truncated": ((), np.bool_),
    "episode_return": ((), np.float64),
    "episode_length": ((), np.int64),
    "episode_travel": ((), np.float64),  # a floating base's forward distance (else NaN)
    "episode_tracking": (("track",), np.float64),  # its mean vx, vy, yaw rate (`tracking`)
    "reward_terms": (("terms",), np.float64),  # the step's reward by named term (`reward_terms`)
    "command_level": ((), np.float64),  # where a command curriculum stands (`command_level`)
    # teams with masks (`ArrayTeam.masks`): who is in the episode, and what each may choose
    "active": (("n",), np.float32),
    "left": (("n",), np.bool_),
    "available": (("n", "choices"), np.float32),
}


class _Buffers:
    """The step's arrays `[num_envs, ...]`, optionally in shared memory."""

    def __init__(self, sizes: dict[str, int], num_envs: int, raw: dict | None = None, shared=False):
        self.sizes, self.num_envs = sizes, num_envs
        self.raw = raw if raw is not None else {}
        for name, (dims, dtype) in _FIELDS.items():
            shape = (num_envs, *(sizes[d] for d in dims))
            if raw is None and shared:
                nbytes = max(1, int(np.prod(shape)) * np.dtype(dtype).itemsize)
                self.raw[name] = mp.RawArray("b", nbytes)
            if name in self.raw:
                array = np.frombuffer(self.raw[name], dtype=dtype, count=int(np.prod(shape)))
                setattr(self, name, array.reshape(shape))
            else:
                setattr(self, name, np.zeros(shape, dtype))


class _EnvSlice:
    """Steps copies `[start, start + len(teams))` of the buffers; autoresets finished ones."""

    def __init__(self, teams: list, start: int, buffers: _Buffers):
        self.teams, self.start, self.buffers = teams, start, buffers
        self._returns = np.zeros(len(teams))
        self._lengths = np.zeros(len(teams), dtype=np.int64)

    def reset(self, seeds: list[int | None]) -> None:
        for k, (team, seed) in enumerate(zip(self.teams, seeds, strict=True)):
            self.buffers.obs[self.start + k] = team.reset(seed=seed)
            self._read_masks(k, team)
        self._returns[:] = 0
        self._lengths[:] = 0

    def _read_masks(self, k: int, team) -> None:
        if team.masks:
            i = self.start + k
            self.buffers.left[i] = (self.buffers.active[i] > 0) & (team.active == 0)
            self.buffers.active[i] = team.active
            self.buffers.available[i] = team.available

    def step(self) -> None:
        b = self.buffers
        for k, team in enumerate(self.teams):
            i = self.start + k
            obs, reward, terminated, truncated = team.advance(b.actions[i])  # VecTeam.step checked
            self._returns[k] += reward
            self._lengths[k] += 1
            b.reward[i], b.terminated[i], b.truncated[i] = reward, terminated, truncated
            if b.sizes["terms"]:
                b.reward_terms[i] = team.term_values()
            b.command_level[i] = team.command_level()
            if terminated or truncated:
                b.final_obs[i] = obs
                b.episode_return[i], b.episode_length[i] = self._returns[k], self._lengths[k]
                b.episode_travel[i] = team.travelled()
                b.episode_tracking[i] = team.tracking()
                self._returns[k], self._lengths[k] = 0.0, 0
                obs = team.reset()
                b.active[i] = 1.0  # a new episode: nobody has left it
            else:
                b.episode_return[i], b.episode_length[i] = np.nan, 0
            b.obs[i] = obs
            self._read_masks(k, team)

    def get_state(self) -> list[dict]:
        return [
            {
                "team": team.get_state(),
                "return": float(self._returns[k]),
                "length": int(self._lengths[k]),
                "left": self.buffers.left[self.start + k].copy(),
            }
            for k, team in enumerate(self.teams)
        ]

    def set_state(self, states: list[dict]) -> None:
        for k, (team, state) in enumerate(zip(self.teams, states, strict=True)):
            team.set_state(state["team"])
            self._returns[k], self._lengths[k] = state["return"], state["length"]
            self._read_masks(k, team)
            self.buffers.left[self.start + k] = state.get("left", False)


def _worker(
    conn, handshake, make_team: Callable, seeds: list[int], start: int, sizes, num_envs, raw
):
    def setup() -> _EnvSlice:
        teams = [make_team(seed) for seed in seeds]
        return _EnvSlice(teams, start, _Buffers(sizes, num_envs, raw=raw))

    serve(conn, handshake, setup)


_TEAM_ATTRIBUTES = (
    "env_id",
    "reward_terms",
    "agents",
    "n_agents",
    "obs_dim",
    "action_width",
    "action_widths",
    "action_size",
    "action_type",
    "state_dim",
    "episode_limit",
    "masks",
    "control_timestep",
)


@dataclass(frozen=True)
class TeamFactory:
    """A picklable recipe for one team, so worker processes can build their own copies."""

    build: Callable[..., Any]
    kwargs: dict

    def __call__(self, seed: int | None) -> Any:
        return self.build(seed=seed, **self.kwargs)


class VecTeam:
    """`num_envs` copies of a team: `obs [E, n, obs_dim]`, `reward [E]`, `terminated [E]`...

    `workers=0` steps every copy in this process. `workers=W` splits the copies over this
    process and W worker processes when there is a core for each: the caller steps its own
    share while the workers step theirs, instead of idling while it waits for them. With
    fewer cores than W + 1, the workers step every copy and the caller only waits, since a
    third process on two cores slows every step (BENCHMARKS.md has the figures).
    """

    def __init__(self, make_team: TeamFactory, num_envs: int, workers: int = 0, seed: int = 0):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if not 0 <= workers < num_envs:
            raise ValueError(
                f"workers must be in [0, num_envs - 1 = {num_envs - 1}], got {workers}"
            )
        self.num_envs, self.workers, self.seed = num_envs, workers, seed
        probe = make_team(seed)
        for name in _TEAM_ATTRIBUTES:
            setattr(self, name, getattr(probe, name))
        self.randomization = getattr(probe, "randomization", None)  # robots' only
        sizes = {
            "n": self.n_agents,
            "obs": self.obs_dim,
            "act": self.action_width,
            "choices": self.action_size,
            "terms": len(self.reward_terms),
            "track": 3,
        }
        self._buffers = _Buffers(sizes, num_envs, shared=workers > 0)
        seeds = [seed + i for i in range(num_envs)]
        self._closed = False  # before the workers start: a failing one closes the rest
        self._workers: list[WorkerProcess] = []
        # This process steps a share too when it has a core for it.
        self.caller_steps = workers + 1 <= processes.usable_cores()
        parts = np.linspace(0, num_envs, workers + 1 + self.caller_steps).astype(int)
        bounds = parts if self.caller_steps else np.concatenate([[0], parts])  # its share first
        self._slices = bounds
        teams = [probe, *(make_team(s) for s in seeds[1 : bounds[1]])] if bounds[1] else []
        self._local = _EnvSlice(teams, 0, self._buffers)
        if workers:
            context = mp.get_context("spawn")
            spin = processes.SPIN_SECONDS if self.caller_steps else 0.0
            for lo, hi in itertools.pairwise(bounds[1:]):
                arguments = (make_team, seeds[lo:hi], int(lo), sizes, num_envs, self._buffers.raw)
                self._workers.append(WorkerProcess(context, _worker, arguments, spin))
            self._wait()

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Reset every copy; with a seed, copy i restarts its random stream at `seed + i`."""
        seeds = [None if seed is None else seed + i for i in range(self.num_envs)]
        self._run("reset", [(seeds[lo:hi],) for lo, hi in itertools.pairwise(self._slices)])
        return self._buffers.obs.copy()

    def step(self, actions: np.ndarray):
        """Step every copy; returns obs, reward, terminated, truncated, info (all arrays)."""
        expected = (self.num_envs, self.n_agents, self.action_width)
        actions = as_array(actions)
        if actions.shape != expected:
            raise ValueError(
                f"actions have shape {actions.shape}, expected (num_envs, n_agents, "
                f"action_width) = {expected}"
            )
        actions = real_actions(actions, lambda i: f"env {i[0]}, {self.agents[i[1]]}")
        invalid = invalid_action(actions, self.action_type, self.action_size)
        if invalid:
            (env, agent), problem = invalid
            raise ValueError(f"env {env}, {self.agents[agent]}: {problem}")
        b = self._buffers
        b.actions[:] = actions
        self._run("step", [()] * (self.workers + 1))
        done = b.terminated | b.truncated
        info = {
            "final_obs": b.final_obs.copy(),
            "episode_return": b.episode_return.copy(),
            "episode_length": b.episode_length.copy(),
            "episode_travel": b.episode_travel.copy(),
            "episode_tracking": b.episode_tracking.copy(),
            "reward_terms": b.reward_terms.copy(),
            "command_level": b.command_level.copy(),
            "done": done,
        }
        if self.masks:
            info["left"] = b.left.copy()  # agents that left the episode in this step
        return b.obs.copy(), b.reward.copy(), b.terminated.copy(), b.truncated.copy(), info

    def active(self) -> np.ndarray | None:
        """Which agents are in each copy's episode now, [E, n] (teams with masks), else None."""
        return self._buffers.active.copy() if self.masks else None

    def available(self) -> np.ndarray | None:
        """Which choices each agent may take now, [E, n, choices] (teams with masks)."""
        return self._buffers.available.copy() if self.masks else None

    def get_state(self) -> list[dict]:
        """Per copy: its full simulation state and episode progress (picklable numpy)."""
        return [s for part in self._run("get_state", [()] * (self.workers + 1)) for s in part]

    def set_state(self, states: list[dict]) -> None:
        if len(states) != self.num_envs:
            raise ValueError(f"{len(states)} env states for {self.num_envs} envs")
        self._run("set_state", [(states[lo:hi],) for lo, hi in itertools.pairwise(self._slices)])

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        close_all(self._workers)

    def __enter__(self) -> VecTeam:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        if hasattr(self, "_closed"):
            self.close()

    def _run(self, command: str, arguments: list) -> list:
        """Run `_EnvSlice.<command>(*arguments[k])` on every slice k; their results in order.

        A step needs no pipe: its actions are already in shared memory.
        """
        if self._closed:
            raise RuntimeError("this vectorised env is closed")
        for worker, argument in zip(self._workers, arguments[1:], strict=True):
            worker.go(None if command == "step" else command, argument)
        local = getattr(self._local, command)(*arguments[0])
        return [local, *self._wait()]

    def _wait(self) -> list:
        return wait_all(self._workers, "env worker failed", self.close)
