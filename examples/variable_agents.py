"""One bundle, several robots: a policy trained on `swimmer-N` acting on `swimmer-M`.

    mat train swimmer-6 --steps 300000 --out runs/swimmer
    mat export runs/swimmer/checkpoint.pt -o runs/swimmer/onnx
    python examples/variable_agents.py runs/swimmer/onnx --sizes 4 6 9 12

A swimmer with M links has M - 1 agents (one per joint) and the same observation size for
every M, so the exported policy serves any length through the runtime alone: `act` takes
whatever number of agents it is given. Prints the policy's mean return beside a random
team's for each length.
"""

from __future__ import annotations

import argparse

import numpy as np

from mat_runtime import Policy
from mat_sdk.envs import make_team


def run_episodes(team, choose, episodes: int, seed: int) -> list[float]:
    returns = []
    for episode in range(episodes):
        obs, total, done = team.reset(seed=seed + episode), 0.0, False
        while not done:
            obs, reward, terminated, truncated = team.step(choose(obs))
            total += reward
            done = terminated or truncated
        returns.append(total)
    return returns


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bundle", help="directory written by `mat export` (a swimmer policy)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[4, 6, 9, 12])
    parser.add_argument("--episodes", type=int, default=3)
    args = parser.parse_args()

    policy = Policy.load(args.bundle)
    rng = np.random.default_rng(0)
    print(f"{policy}\n")
    print("| env | agents | policy return (mean ± std) | random team |")
    print("|---|---|---|---|")
    for size in args.sizes:
        team = make_team(f"swimmer-{size}", **policy.env_options)  # as trained, but M links
        ours = run_episodes(team, policy.act, args.episodes, seed=100)
        random = run_episodes(
            team,
            lambda obs: rng.uniform(-1, 1, (len(obs), policy.action_size)),
            args.episodes,
            seed=100,
        )
        print(
            f"| swimmer-{size} | {team.n_agents} | {np.mean(ours):.1f} ± {np.std(ours):.1f} "
            f"| {np.mean(random):.1f} |"
        )


if __name__ == "__main__":
    main()
