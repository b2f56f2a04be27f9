"""One controller, a robot whose agent count changes between episodes, no reload.

    python -m benchmarks.transfer --out runs/transfer      # or any family policy:
    mat train mamujoco:ManySegmentSwimmer-3x2 mamujoco:ManySegmentSwimmer-4x2 \
        mamujoco:ManySegmentSwimmer-5x2 --steps 200000 --out runs/swimmer345
    mat export runs/swimmer345/checkpoint.pt -o runs/swimmer345/onnx
    python examples/variable_agents.py runs/swimmer345/onnx --sizes 4 8 3 10 12

The bundle is loaded once; then each episode the robot has the next size of `--sizes` (a
segment added or removed: the number in the env id the policy was trained on), and `act`
takes whatever number of agents it is given. A family (`mat envs` marks them) has the same
observation size for every count. Prints each episode's return beside a random team's on the
same start.
"""

from __future__ import annotations

import argparse
import re

import numpy as np

from mat_runtime import Policy
from mat_sdk.envs import Trusted, UntrustedEnvError, check_trusted, make_team


def run_episode(team, choose, seed: int) -> float:
    obs, total, done = team.reset(seed=seed), 0.0, False
    while not done:
        obs, reward, terminated, truncated = team.step(choose(obs))
        total += reward
        done = terminated or truncated
    return total


def family_member(env_id: str, size: int) -> str:
    """`env_id` with its count replaced: swimmer-6 -> swimmer-9, ...-4x2 -> ...-9x2."""
    member, replaced = re.subn(r"-\d+(x\d+)?$", lambda m: f"-{size}{m[1] or ''}", env_id)
    if not replaced:
        raise SystemExit(f"{env_id} names no count to change; train on a family (`mat envs`)")
    return member


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bundle", help="directory written by `mat export` (a family policy)")
    parser.add_argument(
        "--sizes", type=int, nargs="+", default=[4, 8, 3, 10, 12], help="one per episode"
    )
    parser.add_argument("--seed", type=int, default=100, help="the first episode's start")
    parser.add_argument(
        "--trust-env-code",
        action="store_true",
        help="import the module:function env id the bundle records: only for bundles you trust",
    )
    args = parser.parse_args()

    policy = Policy.load(args.bundle)  # once: one ONNX Runtime session serves every count below
    try:  # an id read from the bundle runs no code unless trusted
        manifest = policy.path / "manifest.json"
        check_trusted([policy.env_id], Trusted(manifest) if args.trust_env_code else manifest)
    except UntrustedEnvError as error:
        parser.exit(2, f"{error}\n")
    rng = np.random.default_rng(0)
    print(f"{policy}\ntrained on agent counts {policy.manifest['agents'].get('trained_counts')}\n")
    print("| episode | env | agents | policy return | random team |")
    print("|---|---|---|---|---|")
    for episode, size in enumerate(args.sizes):
        env_id = family_member(policy.env_id, size)
        team = make_team(env_id, **policy.env_options)  # as trained, other count
        if not team.variable_count:
            raise SystemExit(f"{policy.env_id} is not a family (`mat envs` marks them)")
        seed = args.seed + episode
        ours = run_episode(team, policy.act, seed)
        width = (team.n_agents, policy.action_size)
        random = run_episode(team, lambda obs, shape=width: rng.uniform(-1, 1, shape), seed)
        print(f"| {episode} | {env_id} | {team.n_agents} | {ours:.1f} | {random:.1f} |")


if __name__ == "__main__":
    main()
