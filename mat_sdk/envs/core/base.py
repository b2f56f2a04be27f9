"""`ArrayTeam`: the array API every env family implements (robots, games, MaMuJoCo)."""

from __future__ import annotations

import math
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mat_sdk.envs.core.checks import is_real, short

# Steps an episode may last at most: over half an hour of control at 50 Hz. A recorded
# limit beyond it would make an evaluation run for days.
MAX_EPISODE_LIMIT = 100_000


def checked_episode_limit(given: int | None, default: int) -> int:
    """The episode length to truncate at: `given` (1..MAX_EPISODE_LIMIT), or the env's own
    `default`."""
    if given is None:
        if not math.isfinite(default):
            raise ValueError("the environment has no time limit; set episode_limit")
        return int(default)
    if (
        isinstance(given, bool)
        or not isinstance(given, int | np.integer)
        or not 1 <= given <= MAX_EPISODE_LIMIT
    ):
        raise ValueError(
            f"episode_limit must be an integer in 1..{MAX_EPISODE_LIMIT:,}, got {short(given)}"
        )
    return int(given)


# Count-independent identities: an agent's place in the team's order (a chain's head first),
# as "fraction": i / (N - 1); "ends": 1 / (1 + i) and 1 / (N - i), closeness to each end;
# "near-ends": the agents before it and after it, each counted up to NEAR_ENDS and scaled to
# 1; or "end-flags", the same counted up to 1: whether any agent is before it, and after it.
# The last two make every agent farther inside look the same, in a long team as in a short
# one (end-flags transferred best to unseen counts, docs/TRANSFER.md). Unlike a one-hot id,
# none changes the observation size with N.
POSITIONS = ("fraction", "ends", "near-ends", "end-flags")
NEAR_ENDS = 2


def position_features(position: str | None, count: int) -> np.ndarray:
    """`[count, 0, 1 or 2]` features of each agent's place in a team of `count` agents."""
    if position is None:
        return np.zeros((count, 0))
    index = np.arange(count, dtype=np.float64)
    if position == "fraction":
        return (index / max(count - 1, 1))[:, None]
    if position == "ends":
        return np.stack([1.0 / (1 + index), 1.0 / (count - index)], axis=1)
    if position in ("near-ends", "end-flags"):
        cap = NEAR_ENDS if position == "near-ends" else 1
        return np.minimum(np.stack([index, count - 1 - index], axis=1), cap) / cap
    raise ValueError(f"position must be one of {POSITIONS} or None, got {position!r}")


def as_array(actions) -> np.ndarray:
    """`actions` as given, as an array (no conversion of its values), or ValueError."""
    try:
        return np.asarray(actions)
    except ValueError as error:  # ragged nesting
        raise ValueError(f"actions are not a rectangular array ({error})") from None


def real_actions(array: np.ndarray, where: Callable[[tuple[int, ...]], str]) -> np.ndarray:
    """An `as_array` of actions as float64, refusing what is not a real number (a string,
    None, a bool, a complex number) instead of letting numpy coerce it; `where(index)` names
    the agent of an element. Shapes are the caller's to check, first."""
    if array.dtype.kind in "fiu":
        return array.astype(np.float64, copy=False)
    if array.dtype.kind == "O":
        index = next((i for i in np.ndindex(array.shape) if not is_real(array[i])), None)
        if index is None:
            return array.astype(np.float64)
    else:
        index = (0,) * array.ndim
    value = array[index]
    value = value.item() if isinstance(value, np.generic) else value
    raise ValueError(
        f"{where(index)}: action must be a real number, got {value!r} ({type(value).__name__})"
    )


def invalid_action(
    actions: np.ndarray, action_type: str, action_size: int
) -> tuple[tuple[int, ...], str] | None:
    """The first invalid action in `actions [..., action_width]`: its index (all axes but the last)
    and the problem, or None. Invalid: NaN or inf; for discrete teams, anything but a whole
    choice 0..action_size - 1 (continuous values are clipped instead)."""
    valid = np.isfinite(actions).all(axis=-1)
    problem = "action contains NaN or inf"
    if valid.all() and action_type == "discrete":
        valid = ((actions == np.floor(actions)) & (actions >= 0) & (actions < action_size)).all(-1)
        problem = f"action must be a choice 0..{action_size - 1}"
    if valid.all():
        return None
    return tuple(int(i) for i in np.argwhere(~valid)[0]), problem


# tracking reports skip an episode's first second: the start from standing still
SETTLE_SECONDS = 1.0


class PhysicsDiverged(RuntimeWarning):
    """The simulation blew up (MuJoCo's unstable-acceleration reset, or NaN/inf state): the
    episode was truncated there, with reward 0 and non-finite observations zeroed."""


# MuJoCo's warnings for resetting a blown-up state; counted again after the reset
_RESET_WARNINGS = ("mjWARN_BADQACC", "mjWARN_BADQPOS", "mjWARN_BADQVEL")


def diverged(data, time_before: float, step: float, substep: float, reward: float) -> bool:
    """Whether a step of `data` (an `MjData`) must end the episode. MuJoCo resets a blown-up
    state silently (NaN or huge positions, velocities or accelerations: `mj_resetData`,
    simulated time included), so a step that advanced the time by less than its `step` (one
    `substep` less at most) was reset. On an episode's first step a reset at its start would
    not show in the time: there MuJoCo's warning counters (zero after the episode's reset)
    say it. A NaN or inf reward ends the episode too."""
    if not math.isfinite(reward) or data.time - time_before < step - 0.5 * substep:
        return True
    if time_before >= 0.5 * substep:
        return False
    import mujoco

    return any(data.warning[getattr(mujoco.mjtWarning, w)].number for w in _RESET_WARNINGS)


def end_diverged(env_id: str, step: int, obs: np.ndarray) -> tuple[np.ndarray, float]:
    """Warn, and what a diverged step returns instead: finite obs, reward 0."""
    warnings.warn(
        f"{env_id}: the physics diverged at step {step} (unstable accelerations or NaN state); "
        "the episode is truncated there with reward 0",
        PhysicsDiverged,
        stacklevel=3,
    )
    return np.nan_to_num(obs, nan=0.0, posinf=0.0, neginf=0.0), 0.0


class UserCodeError(RuntimeError):
    """A function the user gave (a reward, a termination, an env factory) raised."""


def user_call(function: Callable, role: str, *args: Any) -> Any:
    """`function(*args)`; what it raises becomes a `UserCodeError` naming the function, its
    role and where in it the error came from: the user's code, not a bug of the SDK."""
    try:
        return function(*args)
    except Exception as error:
        frame = traceback.extract_tb(error.__traceback__)[-1]
        where = f"{Path(frame.filename).name}:{frame.lineno}"
        name = getattr(function, "__name__", type(function).__name__)
        raise UserCodeError(
            f"your {role} {name} raised {type(error).__name__}: {error} (at {where}); fix it there"
        ) from error


def restore_whole(team: Any, state: dict, restore: Callable[[dict], None]) -> None:
    """`restore(state)` (a resumed run's env, from a checkpoint), or the team as it was and
    the error raised: a state refused part of the way leaves no env half restored."""
    before = team.get_state()
    try:
        restore(state)
    except Exception:
        restore(before)
        raise


def render_failed(error: Exception) -> RuntimeError:
    """The error for a frame MuJoCo could not render: what to install and set."""
    return RuntimeError(
        f"rendering failed ({error}); install a GL backend and set MUJOCO_GL=egl "
        "(GPU) or MUJOCO_GL=osmesa (CPU, Debian package libosmesa6)"
    )


class ArrayTeam:
    """A team stepped with arrays: actions `[n_agents, action_width]` in, obs `[n_agents, obs_dim]`,
    the shared reward and the episode flags out.

    `step` checks the actions and then calls `advance`, which trusts them. The wrappers that
    check a whole batch (`VecTeam`) or a dict of per-agent actions (the PettingZoo env)
    themselves call `advance`, so each env step checks its actions once.
    Subclasses set `n_agents`, `action_width`, `agents`, `env_id` and implement `advance`.
    """

    n_agents: int
    action_width: int  # columns of an agent's row in the action array (padded to the widest)
    action_widths: np.ndarray  # each agent's own action width
    agents: list[str]
    env_id: str
    action_type: str
    action_size: int  # continuous: action_width; discrete: the number of choices
    control_timestep: float = 1.0  # simulated seconds per env step (games: 1 step)
    # Teams whose agents may leave mid-episode or have unavailable choices set `masks` and
    # keep `active [n]` and `available [n, action_size]` up to date (PettingZoo envs).
    masks: bool = False
    variable_count: bool = False  # a family: one observation size for any agent count
    reward_terms: tuple[str, ...] = ()  # a reward built from named terms: their names

    def term_values(self) -> np.ndarray:
        """The last step's reward by term, weighted, in `reward_terms`' order (sums to it)."""
        return np.zeros(0)

    @property
    def choices(self) -> np.ndarray:
        """Discrete teams: each agent's own number of choices; the rest up to `action_size`
        is padding that an agent never takes."""
        return np.full(self.n_agents, self.action_size)

    def step(self, actions) -> tuple[np.ndarray, float, bool, bool]:
        """Apply `actions [n_agents, action_width]`; returns obs, reward, terminated, truncated.

        A wrong shape, NaN or inf, or (discrete) anything but a choice 0..action_size - 1
        raises `ValueError` naming the agent. Continuous teams clip finite values to [-1, 1]
        and ignore entries past an agent's own action size.
        """
        return self.advance(self.check_actions(actions))

    def check_actions(self, actions) -> np.ndarray:
        """`actions` as a float64 `[n_agents, action_width]` array of finite values, or
        ValueError."""
        array = as_array(actions)
        if array.shape != (self.n_agents, self.action_width):
            raise ValueError(
                f"actions have shape {array.shape}, expected (n_agents, action_width) = "
                f"({self.n_agents}, {self.action_width}) for {self.env_id}"
            )
        array = real_actions(array, lambda index: self.agents[index[0]])
        invalid = invalid_action(array, self.action_type, self.action_size)
        if invalid:
            (row,), problem = invalid
            raise ValueError(f"{self.agents[row]}: {problem}, got {array[row]}")
        return array

    def advance(self, actions: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        """`step` for actions already checked: a float64 `[n_agents, action_width]` array."""
        raise NotImplementedError

    def travelled(self) -> float:
        """How far a robot with a floating base moved forward in this episode (m, along its
        start heading); NaN for other envs."""
        return math.nan

    def tracking(self) -> np.ndarray:
        """A floating base's mean velocity in this episode after its first `SETTLE_SECONDS`,
        in its heading's frame, as a velocity command names it: (vx, vy in m/s, yaw rate in
        rad/s); NaN for other envs."""
        return np.full(3, math.nan)

    def command_level(self) -> float:
        """Where a command curriculum stands (`terms.CommandCurriculum`): 0 at its first
        ranges, 1 at the command's own; NaN for envs without one."""
        return math.nan

    def render(self, height: int = 240, width: int = 320, camera_id: int = 0) -> np.ndarray:
        """An RGB frame `[height, width, 3]`; the physics envs override this."""
        raise RuntimeError(f"{self.env_id} has no picture to render; record a robot's episode")
