"""A fixed-rate control loop that acts with `mat_runtime` alone — what runs on the robot.

    mat train cheetah-6x1 --steps 20000 --out runs/demo      # any trained checkpoint
    mat export runs/demo/checkpoint.pt -o runs/demo/onnx
    python examples/controller.py runs/demo/onnx --rate 100 --seconds 10

The "robot" here is the dm_control simulation from `mat_sdk.envs` (MuJoCo, no torch); on
hardware, replace `team.observe()` / `team.step()` with your sensor read and actuator write.
torch is blocked at start-up, so this script fails loudly if anything tries to import it.
"""

from __future__ import annotations

import argparse
import sys
import time

sys.modules["torch"] = None  # prove the point: importing torch now raises ImportError

import numpy as np

from mat_runtime import Policy
from mat_sdk.envs import make_team


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bundle", help="directory written by `mat export`")
    parser.add_argument(
        "--env", help="env id (default: the robot the policy was trained on, faults included)"
    )
    parser.add_argument("--rate", type=float, default=100.0, help="control rate in Hz")
    parser.add_argument("--seconds", type=float, default=10.0, help="how long to run")
    parser.add_argument("--fault", action="append", default=[], metavar="NAME=zero|remove")
    parser.add_argument(
        "--spin",
        action="store_true",
        help="busy-wait for the next tick instead of sleeping: one core stays hot, and act is "
        "~3-4x faster on a VM whose idle vCPU goes cold (see README)",
    )
    args = parser.parse_args()

    policy = Policy.load(args.bundle, threads=1)
    faults = dict(f.split("=", 1) for f in args.fault)
    if args.env is None:  # the trained robot: its faults (unless --fault) and env options
        team = make_team(policy.env_id, faults or policy.env_faults, **policy.env_options)
    else:
        team = make_team(args.env, faults or None)
    obs = team.reset(seed=0)
    period = 1.0 / args.rate
    act_times, late, episode_return, returns = [], 0, 0.0, []
    start = next_tick = time.perf_counter()
    for _ in range(int(args.seconds * args.rate)):
        begin = time.perf_counter()
        actions = policy.act(obs)
        act_times.append(time.perf_counter() - begin)
        # discrete policies return one choice per agent; the team takes [n_agents, 1]
        obs, reward, terminated, truncated = team.step(
            actions[:, None] if policy.discrete else actions
        )
        episode_return += reward
        if terminated or truncated:
            returns.append(episode_return)
            obs, episode_return = team.reset(), 0.0
        next_tick += period
        slack = next_tick - time.perf_counter()
        if slack > 0:
            if args.spin:
                while time.perf_counter() < next_tick:
                    pass
            else:
                time.sleep(slack)
        else:
            late += 1  # the step overran its slot; do not try to catch up
            next_tick = time.perf_counter()
    elapsed = time.perf_counter() - start
    steps = len(act_times)
    micros = np.array(act_times) * 1e6
    print(f"{policy} on {team.env_id} with agents {team.agents}")
    print(f"{steps} steps in {elapsed:.2f} s: {steps / elapsed:.1f} Hz (target {args.rate:g} Hz)")
    p50, p99 = np.median(micros), np.percentile(micros, 99)
    print(f"act: p50 {p50:.0f} µs, p99 {p99:.0f} µs, max {micros.max():.0f} µs; late ticks: {late}")
    if len(returns) > 10:  # e.g. a one-step game
        finished = f"mean {np.mean(returns):.2f} ± {np.std(returns):.2f} over {len(returns)}"
    else:
        finished = ", ".join(f"{r:.1f}" for r in returns) or "none finished"
    print(f"episode returns: {finished}; current episode so far: {episode_return:.1f}")
    assert "torch" not in {m for m, mod in sys.modules.items() if mod}


if __name__ == "__main__":
    main()
