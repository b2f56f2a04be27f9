"""E copies of a team stepped as arrays, in this process or in worker processes.

Workers share every array with the parent through shared memory. A step crosses no pipe:
two semaphores say "go" and "done" (`_Handshake`). The pipe carries only errors and the rare
commands with arguments or results (reset, get and set state). Copy i is seeded with
`seed + i` and owns its random stream, so the same seed gives the same trajectories whatever
the worker count. Finished episodes reset automatically; the last observation of the
finished episode is in `info["final_obs"]` (for bootstrapping a truncated episode).
"""

from __future__ import annotations

import contextlib
import itertools
import multiprocessing as mp
import os
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from mat_sdk.envs.base import invalid_action

_FIELDS = {  # name: (shape after [num_envs], dtype)
    "actions": (("n", "act"), np.float64),
    "obs": (("n", "obs"), np.float32),
    "final_obs": (("n", "obs"), np.float32),
    "state": (("state",), np.float32),
    "reward": ((), np.float64),
    "terminated": ((), np.bool_),
    "truncated": ((), np.bool_),
    "episode_return": ((), np.float64),
    "episode_length": ((), np.int64),
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
        self._returns[:] = 0
        self._lengths[:] = 0

    def step(self) -> None:
        b = self.buffers
        for k, team in enumerate(self.teams):
            i = self.start + k
            obs, reward, terminated, truncated = team.advance(b.actions[i])  # VecTeam.step checked
            self._returns[k] += reward
            self._lengths[k] += 1
            b.reward[i], b.terminated[i], b.truncated[i] = reward, terminated, truncated
            if terminated or truncated:
                b.final_obs[i] = obs
                b.episode_return[i], b.episode_length[i] = self._returns[k], self._lengths[k]
                self._returns[k], self._lengths[k] = 0.0, 0
                obs = team.reset()
            else:
                b.episode_return[i], b.episode_length[i] = np.nan, 0
            b.obs[i] = obs

    def state(self) -> None:
        for k, team in enumerate(self.teams):
            self.buffers.state[self.start + k] = team.state()

    def get_state(self) -> list[dict]:
        return [
            {
                "team": team.get_state(),
                "return": float(self._returns[k]),
                "length": int(self._lengths[k]),
            }
            for k, team in enumerate(self.teams)
        ]

    def set_state(self, states: list[dict]) -> None:
        for k, (team, state) in enumerate(zip(self.teams, states, strict=True)):
            team.set_state(state["team"])
            self._returns[k], self._lengths[k] = state["return"], state["length"]


_SPIN_SECONDS = 0.002
_MESSAGE, _FAILED = 0, 1  # the handshake's flags


def usable_cores() -> int:
    """The cores this process may run on (its affinity), which decides how copies are split."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


class _Handshake:
    """The per-step signal between the caller and one worker, without the pipe.

    The caller releases `go`, the worker releases `done`; a semaphore's release and acquire
    also order the shared-memory writes around them, on every architecture. A waiting side
    polls its semaphore for `spin_seconds` before it sleeps: waking a sleeping process costs
    ~20 µs each way plus a cold core, ~15 % of a 20-copy cheetah step (BENCHMARKS.md). Spin
    only when every process has a core of its own, or the spinning steals the stepping.
    """

    def __init__(self, context, spin_seconds: float):
        self.go, self.done = context.Semaphore(0), context.Semaphore(0)
        self.flags = context.RawArray("b", 2)  # [_MESSAGE]: a command waits on the pipe
        self.spin_seconds = spin_seconds

    def wait(self, semaphore, alive: Callable[[], bool]) -> bool:
        """Take `semaphore`; False if the other side died while we waited."""
        deadline = time.perf_counter() + self.spin_seconds
        while time.perf_counter() < deadline:
            if semaphore.acquire(False):
                return True
        while not semaphore.acquire(timeout=1.0):
            if not alive():
                return False
        return True


def _worker(
    conn: Connection,
    handshake: _Handshake,
    make_team: Callable,
    seeds: list[int],
    start: int,
    sizes,
    num_envs,
    raw,
):
    parent_alive = mp.parent_process().is_alive  # an orphaned worker exits
    flags = handshake.flags
    try:
        teams = [make_team(seed) for seed in seeds]
        envs = _EnvSlice(teams, start, _Buffers(sizes, num_envs, raw=raw))
        conn.send(("ok", None))
        handshake.done.release()
        while handshake.wait(handshake.go, parent_alive):
            if flags[_MESSAGE]:
                command, argument = conn.recv()
                if command == "close":
                    break
                conn.send(("ok", getattr(envs, command)(*argument)))
            else:
                envs.step()
            handshake.done.release()
    except KeyboardInterrupt:
        pass
    except Exception:
        flags[_FAILED] = 1
        conn.send(("error", traceback.format_exc()))
        handshake.done.release()
    finally:
        conn.close()


_TEAM_ATTRIBUTES = (
    "env_id",
    "agents",
    "n_agents",
    "obs_dim",
    "act_dim",
    "act_dims",
    "n_actions",
    "action_type",
    "state_dim",
    "episode_limit",
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
    third process on two cores slows every step (1.25x against 1.68x, BENCHMARKS.md).
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
        sizes = {
            "n": self.n_agents,
            "obs": self.obs_dim,
            "act": self.act_dim,
            "state": self.state_dim,
        }
        self._buffers = _Buffers(sizes, num_envs, shared=workers > 0)
        seeds = [seed + i for i in range(num_envs)]
        self._closed = False  # before the workers start: a failing one closes the rest
        self._pipes: list[Connection] = []
        self._handshakes: list[_Handshake] = []
        self._processes: list[mp.Process] = []
        # This process steps a share too when it has a core for it.
        self.caller_steps = workers + 1 <= usable_cores()
        parts = np.linspace(0, num_envs, workers + 1 + self.caller_steps).astype(int)
        bounds = parts if self.caller_steps else np.concatenate([[0], parts])  # its share first
        self._slices = bounds
        teams = [probe, *(make_team(s) for s in seeds[1 : bounds[1]])] if bounds[1] else []
        self._local = _EnvSlice(teams, 0, self._buffers)
        if workers:
            context = mp.get_context("spawn")
            spin = _SPIN_SECONDS if self.caller_steps else 0.0
            for lo, hi in itertools.pairwise(bounds[1:]):
                parent, child = context.Pipe()
                handshake = _Handshake(context, spin)
                process = context.Process(
                    target=_worker,
                    args=(
                        child,
                        handshake,
                        make_team,
                        seeds[lo:hi],
                        int(lo),
                        sizes,
                        num_envs,
                        self._buffers.raw,
                    ),
                    daemon=True,
                )
                process.start()
                child.close()
                self._pipes.append(parent)
                self._handshakes.append(handshake)
                self._processes.append(process)
            self._wait(message=True)

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Reset every copy; with a seed, copy i restarts its random stream at `seed + i`."""
        seeds = [None if seed is None else seed + i for i in range(self.num_envs)]
        self._run("reset", [(seeds[lo:hi],) for lo, hi in itertools.pairwise(self._slices)])
        return self._buffers.obs.copy()

    def step(self, actions: np.ndarray):
        """Step every copy; returns obs, reward, terminated, truncated, info (all arrays)."""
        actions = np.asarray(actions, dtype=np.float64)
        expected = (self.num_envs, self.n_agents, self.act_dim)
        if actions.shape != expected:
            raise ValueError(
                f"actions have shape {actions.shape}, expected (num_envs, n_agents, act_dim) = "
                f"{expected}"
            )
        invalid = invalid_action(actions, self.action_type, self.n_actions)
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
            "done": done,
        }
        return b.obs.copy(), b.reward.copy(), b.terminated.copy(), b.truncated.copy(), info

    def state(self) -> np.ndarray:
        self._run("state", [()] * (self.workers + 1))
        return self._buffers.state.copy()

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
        for pipe, handshake in zip(self._pipes, self._handshakes, strict=True):
            handshake.flags[_MESSAGE] = 1
            with contextlib.suppress(BrokenPipeError, OSError):
                pipe.send(("close", ()))
            handshake.go.release()
        for process in self._processes:
            process.join(timeout=5)
            if process.is_alive():
                process.terminate()

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
        message = command != "step"
        for pipe, handshake, argument in zip(
            self._pipes, self._handshakes, arguments[1:], strict=True
        ):
            handshake.flags[_MESSAGE] = message
            if message:
                pipe.send((command, argument))
            handshake.go.release()
        local = getattr(self._local, command)(*arguments[0])
        return [local, *self._wait(message)]

    def _wait(self, message: bool) -> list:
        """Wait for every worker; with `message`, collect the results from their pipes."""
        results, errors = [], []
        for pipe, handshake, process in zip(
            self._pipes, self._handshakes, self._processes, strict=True
        ):
            if not handshake.wait(handshake.done, process.is_alive):
                errors.append("a worker process died")
            elif message or handshake.flags[_FAILED]:
                status, detail = pipe.recv()
                (errors if status == "error" else results).append(detail)
        if errors:
            self.close()
            raise RuntimeError("env worker failed:\n" + errors[0])
        return results
