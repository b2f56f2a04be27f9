"""A PettingZoo env as a MAT SDK env: MPE's simple_spread (mpe2), 3 agents.

    PYTHONPATH=examples mat train mpe_envs:spread --steps 200000 --out runs/spread

Each function is a `module:function` env id; `from_pettingzoo` pads, masks and sums the
agents' rewards into the team's (docs/CUSTOM_ENVS.md).
"""

from functools import partial

from mat_sdk import envs

CYCLES = 25  # MPE's default episode length


def _simple_spread(seed: int | None, continuous: bool):
    from mpe2 import simple_spread_v3

    return simple_spread_v3.parallel_env(N=3, max_cycles=CYCLES, continuous_actions=continuous)


def spread() -> envs.PettingZooSpec:
    """simple_spread with discrete actions (5 choices per agent)."""
    return envs.from_pettingzoo(partial(_simple_spread, continuous=False), team_reward="mean")


def spread_continuous() -> envs.PettingZooSpec:
    """simple_spread with continuous actions (Box(0, 1, (5,)) per agent)."""
    return envs.from_pettingzoo(partial(_simple_spread, continuous=True), team_reward="mean")


def _speaker_listener(seed: int | None):
    from mpe2 import simple_speaker_listener_v4

    return simple_speaker_listener_v4.parallel_env(max_cycles=CYCLES)


def speaker_listener() -> envs.PettingZooSpec:
    """simple_speaker_listener: a speaker with 3 choices, a listener with 5 (padded to 5; the
    speaker's padding choices are never available)."""
    return envs.from_pettingzoo(_speaker_listener, team_reward="mean")
