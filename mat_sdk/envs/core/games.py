"""Small discrete games that test coordination in seconds, with the team array API.

`coordination-N`: N agents, N options, one-step episodes. Agent 0 alone observes a random
option r and must pick it; the team is rewarded (1) only when all picks are different.
Agents after the first cannot see r, so they succeed for sure only by conditioning on the
actions chosen before them, which is what MAT's decoder does. Decentralised actors can at
best fix a guess for the others, right only when r is the option they left out: for N = 3
they score at most 1/3, MAT up to 1.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping

import numpy as np

from mat_sdk.envs.core.base import ArrayTeam
from mat_sdk.envs.core.faults import Fault, faults_of

_ID = re.compile(r"coordination-(\d+)$")


class CoordinationGame(ArrayTeam):
    action_type = "discrete"
    description = "discrete test game: N agents pick from N options, all different (N >= 2)"

    def __init__(
        self,
        env_id: str,
        *,
        faults: Iterable[Fault] | Mapping[str, str] | None = None,
        seed: int | None = None,
    ):
        match = _ID.match(env_id)
        if not match or int(match.group(1)) < 2:
            raise ValueError(
                f"coordination games look like 'coordination-3' (N >= 2), got {env_id!r}"
            )
        self.env_id = env_id
        self.size = int(match.group(1))
        faults = faults_of(faults)
        removed = {fault.target for fault in faults}
        names = [f"agent_{i}" for i in range(self.size)]
        if removed - set(names) or any(fault.kind != "remove" for fault in faults):
            raise ValueError(
                "coordination games support '<agent>=remove' faults only, got "
                + ", ".join(map(str, faults))
            )
        self.active = [i for i, name in enumerate(names) if name not in removed]
        self.agents = [names[i] for i in self.active]
        self.n_agents = len(self.agents)
        self.action_size = self.size
        self.action_width, self.action_widths = 1, np.ones(self.n_agents, dtype=int)
        self.obs_dim = 2 * self.size
        self.state_dim = self.size
        self.episode_limit = 1
        self._rng = np.random.default_rng(seed)
        self._target = 0

    def reset(self, seed: int | None = None) -> np.ndarray:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self._target = int(self._rng.integers(self.size))
        return self.observe()

    def observe(self) -> np.ndarray:
        obs = np.zeros((self.n_agents, self.obs_dim), dtype=np.float32)
        if self.active[0] == 0:
            obs[0, self._target] = 1.0
        obs[np.arange(self.n_agents), self.size + np.array(self.active)] = 1.0
        return obs

    def advance(self, actions: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        picks = actions.reshape(self.n_agents).astype(int)  # option indices
        leader_right = self.active[0] != 0 or picks[0] == self._target
        reward = float(leader_right and len(set(picks.tolist())) == self.n_agents)
        return self.observe(), reward, True, False

    def state(self) -> np.ndarray:
        return np.eye(self.size, dtype=np.float32)[self._target]

    def get_state(self) -> dict:
        return {"rng": self._rng.bit_generator.state, "target": self._target}

    def set_state(self, state: dict) -> None:
        self._rng.bit_generator.state = state["rng"]
        self._target = state["target"]
