"""A fixed-rate control loop that acts with `mat_runtime` alone — what runs on the robot.

    mat train cheetah-6x1 --steps 20000 --out runs/demo      # any trained checkpoint
    mat export runs/demo/checkpoint.pt -o runs/demo/onnx
    python examples/controller.py runs/demo/onnx --rate 100 --seconds 10
    python examples/controller.py runs/demo/onnx --rate 1000 --cpu 1 --fifo 80 --keep-awake

The "robot" here is the dm_control simulation from `mat_sdk.envs` (MuJoCo, no torch); on
hardware, replace `team.observe()` / `team.step()` with your sensor read and actuator write.
Each tick builds the agents' observations from the raw joint state with the bundle's wiring
(`Policy.describe()` prints it) and acts into preallocated arrays (`act(obs, out=...)`: no
allocation per call), after a warm-up. `--cpu` pins the process to a core and `--fifo` asks
for SCHED_FIFO (a note says so where the OS refuses); `--keep-awake` spins a SCHED_IDLE
process on that core so it never idles between ticks. torch is blocked at start-up, so this
script fails loudly if anything tries to import it.
"""

from __future__ import annotations

import argparse
import sys

sys.modules["torch"] = None  # prove the point: importing torch now raises ImportError

import numpy as np

from mat_runtime import Policy, loop
from mat_sdk.envs import Trusted, UntrustedEnvError, check_trusted, make_team


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bundle", help="directory written by `mat export`")
    parser.add_argument(
        "--env", help="env id (default: the robot the policy was trained on, faults included)"
    )
    parser.add_argument("--rate", type=float, default=100.0, help="control rate in Hz")
    parser.add_argument("--seconds", type=float, default=10.0, help="how long to measure")
    parser.add_argument("--warmup", type=float, default=1.0, help="seconds run before measuring")
    parser.add_argument("--fault", action="append", default=[], metavar="NAME=zero|remove|weak:S")
    parser.add_argument("--cpu", type=int, help="pin the process to this core")
    parser.add_argument(
        "--fifo", type=int, metavar="PRIORITY", help="SCHED_FIFO at this priority (1-99)"
    )
    parser.add_argument(
        "--spin",
        action="store_true",
        help="busy-wait the whole gap to the next tick instead of sleeping until just before "
        "it: one core stays hot, and act is faster on a VM whose idle vCPU goes cold",
    )
    parser.add_argument(
        "--keep-awake",
        action="store_true",
        help="spin a lowest-priority (SCHED_IDLE) process on the --cpu core, which the loop "
        "preempts: the core never drops into a sleep state between ticks",
    )
    parser.add_argument(
        "--trust-env-code",
        action="store_true",
        help="import the module:function env id the bundle records (it runs that module's "
        "code): only for bundles you trust",
    )
    args = parser.parse_args()
    if args.keep_awake and args.cpu is None:
        parser.error("--keep-awake keeps the loop's core awake: give it with --cpu")

    awake = loop.keep_awake(args.cpu) if args.keep_awake else None  # before SCHED_FIFO
    for note in loop.realtime(args.cpu, args.fifo):
        print(note)
    policy = Policy.load(args.bundle, threads=1)
    faults = dict(f.split("=", 1) for f in args.fault)
    if args.env is None:  # the trained robot: its faults (unless --fault) and env options
        try:  # an id read from the bundle runs no code unless trusted
            manifest = policy.path / "manifest.json"
            check_trusted([policy.env_id], Trusted(manifest) if args.trust_env_code else manifest)
        except UntrustedEnvError as error:
            parser.exit(2, f"{error}\n")
        team = make_team(
            policy.env_id, **{**policy.env_options, "faults": faults or policy.env_faults}
        )
    else:
        team = make_team(args.env, faults=faults or None)

    obs = np.zeros((team.n_agents, policy.obs_dim), np.float32)  # the sensor buffer
    obs[:] = team.reset(seed=0)
    shape = (team.n_agents,) if policy.discrete else (team.n_agents, policy.action_size)
    actions = np.zeros(shape, np.int64 if policy.discrete else np.float32)
    # discrete policies return one choice per agent; the team takes [n_agents, 1]
    command = actions[:, None] if policy.discrete else actions
    episode = {"return": 0.0, "finished": []}

    def act() -> None:
        policy.act(obs, out=actions)

    # as on hardware: each agent's observation gathered from the raw joint state by the
    # bundle's wiring (its layout), not taken from the simulator's own observation
    wiring = policy.wiring if policy.wiring and policy.wiring.has_observation else None
    if wiring is not None and hasattr(team, "physics"):
        data = team.physics.data
        names = ", ".join(feature.name for feature in wiring.features)
        print(f"observations built from the raw joint state by the bundle's wiring: {names}")

        def sense(_observed) -> None:
            obs[:] = wiring.observe(data.qpos, data.qvel, team.task_features())
    else:

        def sense(observed) -> None:
            obs[:] = observed

    def step() -> None:
        observed, reward, terminated, truncated = team.step(command)
        episode["return"] += reward
        if terminated or truncated:
            episode["finished"].append(episode["return"])
            observed, episode["return"] = team.reset(), 0.0
        sense(observed)

    ticks = loop.run(act, step, args.rate, args.seconds, args.warmup, args.spin)
    if awake is not None:
        awake.terminate()
    print(f"{policy} on {team.env_id} with agents {team.agents}")
    print(ticks.summary())
    returns = episode["finished"]
    if len(returns) > 10:  # e.g. a one-step game
        finished = f"mean {np.mean(returns):.2f} ± {np.std(returns):.2f} over {len(returns)}"
    else:
        finished = ", ".join(f"{r:.1f}" for r in returns) or "none finished"
    print(f"episode returns: {finished}; current episode so far: {episode['return']:.1f}")
    assert "torch" not in {m for m, mod in sys.modules.items() if mod}


if __name__ == "__main__":
    main()
