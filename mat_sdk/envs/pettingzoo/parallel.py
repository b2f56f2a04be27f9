"""The PettingZoo `ParallelEnv` face of a team: dicts keyed by agent name."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from mat_sdk.envs.core.base import as_array, invalid_action, real_actions


class TeamParallelEnv(ParallelEnv):
    """A PettingZoo parallel env over any `ArrayTeam` (robot, game or MaMuJoCo scenario).

    Every agent gets the shared team reward. Continuous actions are `Box(-1, 1)` arrays of the
    agent's own size, clipped when outside; discrete ones (games) are `Discrete(n)` choices,
    an int. A missing or unknown agent, a wrong shape, NaN or inf, or a choice out of range
    raises `ValueError` naming the agent.
    """

    metadata: ClassVar[dict] = {
        "name": "mat_sdk_team",
        "render_modes": ["rgb_array"],
        "is_parallelizable": True,
    }

    def __init__(self, team: Any, render_mode: str | None = None):
        self.team = team
        self.render_mode = render_mode
        self.possible_agents = list(team.agents)
        self.agents: list[str] = []
        self._obs_space = spaces.Box(-np.inf, np.inf, (team.obs_dim,), np.float32)
        self._discrete = team.action_type == "discrete"
        self._act_spaces = {
            name: spaces.Discrete(int(choices))
            if self._discrete
            else spaces.Box(-1.0, 1.0, (int(dim),), np.float32)
            for name, dim, choices in zip(
                team.agents, team.action_widths, team.choices, strict=True
            )
        }
        self.state_space = spaces.Box(-np.inf, np.inf, (team.state_dim,), np.float32)
        self._actions = np.zeros((team.n_agents, team.action_width))

    def observation_space(self, agent: str) -> spaces.Box:
        self._check_agent(agent)
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Box:
        self._check_agent(agent)
        return self._act_spaces[agent]

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs = self.team.reset(seed=seed)
        self.agents = list(self.possible_agents)
        return self._by_agent(obs), {a: {} for a in self.agents}

    def step(self, actions: Mapping[str, Any]):
        if not self.agents:
            raise RuntimeError("the episode is over: call reset() before step()")
        unknown = set(actions) - set(self.agents)
        if unknown:
            raise ValueError(
                f"actions for unknown agent(s) {sorted(unknown)}; agents: {self.agents}"
            )
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"no action for agent(s) {missing}; every agent must act each step")
        for row, agent in enumerate(self.agents):
            action = real_actions(as_array(actions[agent]), lambda _, agent=agent: agent)
            expected = self._act_spaces[agent].shape or (1,)  # a choice: an int
            if action.shape != expected and not (self._discrete and action.shape == ()):
                shape = "an int" if self._discrete else f"shape {expected}"
                raise ValueError(f"{agent}: action has shape {action.shape}, expected {shape}")
            action = action.reshape(expected)
            size = self._act_spaces[agent].n if self._discrete else self.team.action_size
            invalid = invalid_action(action, self.team.action_type, size)
            if invalid:
                raise ValueError(f"{agent}: {invalid[1]}, got {action}")
            self._actions[row, : expected[0]] = action
        obs, reward, terminated, truncated = self.team.advance(self._actions)  # checked above
        agents = self.agents
        if terminated or truncated:
            self.agents = []
        return (
            self._by_agent(obs, agents),
            dict.fromkeys(agents, reward),
            dict.fromkeys(agents, bool(terminated)),
            dict.fromkeys(agents, bool(truncated)),
            {a: {} for a in agents},
        )

    def state(self) -> np.ndarray:
        return self.team.state()

    def render(self) -> np.ndarray:
        return self.team.render()

    def close(self) -> None:
        close = getattr(self.team, "close", None)
        if close:
            close()

    def _by_agent(self, obs: np.ndarray, agents: list[str] | None = None) -> dict[str, np.ndarray]:
        return {name: obs[row] for row, name in enumerate(agents or self.possible_agents)}

    def _check_agent(self, agent: str) -> None:
        if agent not in self._act_spaces:
            raise ValueError(f"unknown agent {agent!r}; agents: {self.possible_agents}")
