"""Any PettingZoo `ParallelEnv` as a team: padded to one shape, with masks for what padding adds.

    spec = envs.from_pettingzoo(lambda seed: simple_spread_v3.parallel_env(), team_reward="sum")

MAT reads every agent through one embedding and writes every action through one head, so
agents must share one observation size and one action size. Here they are padded to the
largest, and the padding is masked so that it changes nothing the policy learns:

- observations: zero-padded (plus a one-hot agent id, by default);
- Box actions: padded to the widest agent; the padded dimensions are ignored by the env and
  masked out of log-probs and entropy (`action_widths`), so they get exactly zero gradient;
- Discrete actions: padded to the most choices; an agent's extra choices are unavailable, as
  are those its `action_mask` forbids (in its observation dict or its info, PettingZoo's
  convention), through `available` [n, choices];
- agents that leave mid-episode (PettingZoo's shrinking `agents`) keep their row, zeroed,
  and are inactive (`active` [n]) until the episode ends: the loss skips inactive rows.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from gymnasium import spaces

from mat_sdk.envs.core.base import ArrayTeam, checked_episode_limit
from mat_sdk.envs.core.faults import Fault

TEAM_REWARDS = ("sum", "mean")
SUPPORTED = (
    "every agent's observation a 1-D Box (or a Dict of 'observation' and 'action_mask'), and "
    "every agent's action a 1-D Box, or every agent's a Discrete"
)


@dataclass(frozen=True)
class PettingZooSpec:
    """How to build a team over a PettingZoo env (`from_pettingzoo`)."""

    env_id: str
    env_factory: Callable[[int | None], Any]
    team_reward: str = "sum"
    agent_id: bool = True
    episode_limit: int | None = None
    description: str = ""

    def build(self, **options: Any) -> PettingZooTeam:
        return PettingZooTeam(self, **options)

    def renamed(self, env_id: str) -> PettingZooSpec:
        return replace(self, env_id=env_id)


def from_pettingzoo(
    env_factory: Callable[[int | None], Any],
    *,
    team_reward: str = "sum",
    agent_id: bool = True,
    episode_limit: int | None = None,
    env_id: str | None = None,
) -> PettingZooSpec:
    """A team over `env_factory(seed)`, a PettingZoo `ParallelEnv` of Box or Discrete agents.

    `team_reward` ("sum" or "mean") turns the agents' rewards into the team's. Episodes end
    when the env has no agents left, or after `episode_limit` steps. The env is built once now
    to check its spaces: an unsupported one raises `ValueError` saying what is supported.
    """
    if team_reward not in TEAM_REWARDS:
        raise ValueError(f"team_reward must be one of {TEAM_REWARDS}, got {team_reward!r}")
    name = getattr(env_factory, "__name__", type(env_factory).__name__)
    spec = PettingZooSpec(
        env_id or f"pettingzoo:{name}",
        env_factory,
        team_reward,
        bool(agent_id),
        episode_limit,
        f"PettingZoo env from {name}",
    )
    spec.build().close()  # refuse unsupported spaces now, not in a worker
    return spec


def _check_names(agents: list, env_id: str) -> None:
    """Agent names must be distinct, also as text (1 and "1" would be one agent in a
    checkpoint, a manifest or a log)."""
    texts = [str(a) for a in agents]
    if not agents or len(set(texts)) != len(texts):
        raise ValueError(
            f"{env_id}: possible_agents must be distinct names (also as text), got {agents!r}"
        )


def _observation_box(space, agent: str) -> spaces.Box:
    """The agent's observation Box (inside a Dict that also holds its `action_mask`)."""
    if isinstance(space, spaces.Dict) and set(space.spaces) in (
        {"observation"},
        {"observation", "action_mask"},
    ):
        return _observation_box(space["observation"], agent)
    if isinstance(space, spaces.Box) and len(space.shape) == 1:
        return space
    raise ValueError(f"{agent}: observation space {space} is not supported; supported: {SUPPORTED}")


class PettingZooTeam(ArrayTeam):
    """A PettingZoo `ParallelEnv` with the array API (see the module docstring)."""

    masks = True

    def __init__(
        self,
        spec: PettingZooSpec,
        *,
        faults: Iterable[Fault] | Mapping[str, str] | None = None,
        seed: int | None = None,
        agent_id: bool | None = None,
        episode_limit: int | None = None,
    ):
        if faults:
            raise ValueError(
                f"{spec.env_id}: faults act on robot actuators; a PettingZoo env takes none"
            )
        self.spec, self.env_id, self.description = spec, spec.env_id, spec.description
        self._env = spec.env_factory(seed)
        self.possible_agents = list(self._env.possible_agents)
        _check_names(self.possible_agents, spec.env_id)
        self.agents = self.possible_agents
        self.n_agents = len(self.agents)
        self.agent_id = spec.agent_id if agent_id is None else bool(agent_id)
        observed = [_observation_box(self._env.observation_space(a), a) for a in self.agents]
        self._obs_sizes = [box.shape[0] for box in observed]
        self.obs_dim = max(self._obs_sizes) + (self.n_agents if self.agent_id else 0)
        self._set_up_actions([self._env.action_space(a) for a in self.agents])
        self.state_dim = self._state_size()
        limit = spec.episode_limit if episode_limit is None else episode_limit
        own = getattr(self._env, "max_cycles", getattr(self._env.unwrapped, "max_cycles", 1000))
        self.episode_limit = checked_episode_limit(limit, own)
        self.control_timestep = 1.0 / float(self._env.metadata.get("render_fps", 1) or 1)
        self.active = np.ones(self.n_agents, dtype=np.float32)
        self.available = np.ones((self.n_agents, self.action_size), dtype=np.float32)
        self._rng = np.random.default_rng(seed)
        self._episode_seed = 0
        self._taken: list[np.ndarray] = []  # this episode's actions, to replay in set_state
        self._obs = np.zeros((self.n_agents, self.obs_dim), dtype=np.float32)
        self._steps = 0

    # ---------------------------------------------------------------- set-up
    def _set_up_actions(self, action_spaces: list) -> None:
        kinds = {type(space) for space in action_spaces}
        if kinds == {spaces.Discrete}:
            self.action_type = "discrete"
            self._choices = np.array([int(space.n) for space in action_spaces])
            self._starts = np.array([int(space.start) for space in action_spaces])
            self.action_size, self.action_width = int(self._choices.max()), 1
            self.action_widths = np.ones(self.n_agents, dtype=int)
            return
        if kinds == {spaces.Box} and all(len(space.shape) == 1 for space in action_spaces):
            self.action_type = "continuous"
            self.action_widths = np.array([space.shape[0] for space in action_spaces])
            self.action_width = self.action_size = int(self.action_widths.max())
            self._low = [np.asarray(space.low, np.float64) for space in action_spaces]
            self._high = [np.asarray(space.high, np.float64) for space in action_spaces]
            self._dtypes = [space.dtype for space in action_spaces]
            return
        found = ", ".join(sorted({type(space).__name__ for space in action_spaces}))
        raise ValueError(
            f"{self.env_id}: action spaces {found} are not supported; supported: {SUPPORTED}"
        )

    @property
    def choices(self) -> np.ndarray:
        return self._choices if self.action_type == "discrete" else super().choices

    def _state_size(self) -> int:
        state_space = getattr(self._env, "state_space", None)
        if isinstance(state_space, spaces.Box) and len(state_space.shape) == 1:
            return int(state_space.shape[0])
        return self.n_agents * self.obs_dim  # the stacked observations

    # ---------------------------------------------------------------- episode
    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start an episode. Every reset seeds the env from this team's own stream, so that
        an episode can be replayed from its seed and actions (`set_state`)."""
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self._episode_seed = int(self._rng.integers(2**31))
        self._taken = []
        return self._start()

    def _start(self) -> np.ndarray:
        obs, infos = self._env.reset(seed=self._episode_seed)
        self._steps = 0
        self.active[:] = 1.0
        return self._read(obs, infos)

    def advance(self, actions: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        self._taken.append(actions.copy())
        live = list(self._env.agents)
        obs, rewards, terminations, _, infos = self._env.step(self._per_agent(actions))
        self._steps += 1
        given = [float(rewards[a]) for a in live if a in rewards]
        if not np.isfinite(given).all():
            agent = next(a for a in live if a in rewards and not np.isfinite(float(rewards[a])))
            raise ValueError(
                f"{self.env_id}: {agent}'s reward is {float(rewards[agent])} at step "
                f"{self._steps}; the env must give finite rewards"
            )
        combine = np.sum if self.spec.team_reward == "sum" else np.mean
        reward = float(combine(given)) if given else 0.0
        packed = self._read(obs, infos)
        if self._env.agents and self._steps < self.episode_limit:
            return packed, reward, False, False
        # terminated: the last agents all ended for real; else cut by a time limit
        terminated = not self._env.agents and all(terminations.get(a, False) for a in live)
        return packed, reward, terminated, not terminated

    def _per_agent(self, actions: np.ndarray) -> dict[str, Any]:
        per_agent = {}
        for row, name in enumerate(self.possible_agents):
            if name not in self._env.agents:
                continue
            if self.action_type == "discrete":
                choice = int(actions[row, 0])
                if choice >= self._choices[row]:
                    raise ValueError(
                        f"{name}: action must be a choice 0..{self._choices[row] - 1}, got {choice}"
                    )
                per_agent[name] = choice + int(self._starts[row])
                continue
            action = np.clip(actions[row, : self.action_widths[row]], -1.0, 1.0)
            low, high = self._low[row], self._high[row]
            bounded = np.isfinite(low) & np.isfinite(high)
            mapped = np.where(bounded, low + (action + 1.0) * (high - low) / 2, action)
            per_agent[name] = mapped.astype(self._dtypes[row])
        return per_agent

    def _read(self, obs: Mapping[str, Any], infos: Mapping[str, Any]) -> np.ndarray:
        """The padded observations; updates `active` and (discrete) `available`."""
        self._obs[:] = 0.0
        discrete = self.action_type == "discrete"
        strangers = [a for a in self._env.agents if a not in self.possible_agents]
        if strangers or len(set(self._env.agents)) != len(self._env.agents):
            raise ValueError(
                f"{self.env_id}: the env's agents {list(self._env.agents)} are not distinct "
                f"members of its possible_agents {self.possible_agents}"
            )
        for row, name in enumerate(self.possible_agents):
            present = name in obs and name in self._env.agents
            self.active[row] = float(present)
            if not present:
                if discrete:
                    self.available[row] = 0.0
                    self.available[row, 0] = 1.0  # a gone agent's placeholder choice
                continue
            value, mask = obs[name], infos.get(name, {}).get("action_mask")
            if isinstance(value, Mapping):
                value, mask = value["observation"], value.get("action_mask", mask)
            value = np.asarray(value, np.float32).reshape(-1)
            if value.size != self._obs_sizes[row]:
                raise ValueError(
                    f"{self.env_id}: {name}'s observation has {value.size} values, its space "
                    f"{self._obs_sizes[row]}"
                )
            if not np.isfinite(value).all():
                raise ValueError(
                    f"{self.env_id}: {name}'s observation holds NaN or inf at step {self._steps}; "
                    "the env must give finite observations"
                )
            self._obs[row, : self._obs_sizes[row]] = value
            if self.agent_id:
                self._obs[row, -self.n_agents + row] = 1.0
            if discrete:
                self._set_available(row, mask)
        return self._obs.copy()

    def _set_available(self, row: int, mask) -> None:
        """An agent's own choices (all of them, or those its `action_mask` allows)."""
        own = int(self._choices[row])
        self.available[row] = 0.0
        self.available[row, :own] = 1.0 if mask is None else np.asarray(mask, np.float32)[:own]
        if not self.available[row].any():
            raise ValueError(
                f"{self.env_id}: {self.possible_agents[row]}'s action_mask allows no action"
            )

    # ---------------------------------------------------------------- state
    def get_state(self) -> dict:
        """The episode as its seed and actions so far (a PettingZoo env has no state API):
        `set_state` replays them, which is exact for an env that is deterministic given its
        reset seed and the actions."""
        return {
            "random": self._rng.bit_generator.state,
            "episode_seed": self._episode_seed,
            "actions": np.array(self._taken).reshape(-1, self.n_agents, self.action_width),
        }

    def set_state(self, state: dict) -> None:
        self._rng.bit_generator.state = state["random"]
        self._episode_seed = int(state["episode_seed"])
        self._taken = []
        self._start()
        for actions in np.asarray(state["actions"], dtype=np.float64):
            self.advance(actions)

    def observe(self) -> np.ndarray:
        return self._obs.copy()

    def state(self) -> np.ndarray:
        if self.state_dim != self.n_agents * self.obs_dim:
            return np.asarray(self._env.state(), dtype=np.float32)
        return self._obs.reshape(-1).copy()

    def render(self, height: int = 240, width: int = 320, camera_id: int = 0) -> np.ndarray:
        frame = self._env.render()
        if frame is None:
            raise RuntimeError(
                f"{self.env_id} renders nothing: build it with render_mode='rgb_array'"
            )
        return np.asarray(frame)

    def close(self) -> None:
        self._env.close()
