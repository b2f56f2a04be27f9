"""A control step's latency, side by side in one run: the bare policy, the controller kit
around it, and a state/command round trip over DDS with a process on the other side.

    python -m benchmarks.control_latency runs/t57/seed_1/onnx --ticks 2000

Rows (each p50 / p99 / max over `--ticks` ticks, interleaved round by round):
- `Policy.act`: the bundle's one call on a Go2 observation;
- `Controller.tick`: the kit in policy mode (checks, observation from the signals, the call,
  motor targets), from a reading of the simulated Go2;
- DDS round trip: a `LowCmd_` written here, taken by an echo process that answers with a
  `LowState_`, taken here (Unitree's message types, `mat_runtime.unitree`): twice the one-way
  time a command and a state spend between the controller and a robot's process;
- the whole tick over DDS: read the newest state, tick the kit, write the command, and the
  round trip to the next state.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))

from go2_controller import MODEL, SimulatedGo2

from mat_runtime import Policy
from mat_runtime.controller import Controller, Mode

ECHO = """
import sys, time
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from mat_runtime.unitree import LowCmd_, LowState_
participant = DomainParticipant(int(sys.argv[1]))
commands = DataReader(participant, Topic(participant, "bench/lowcmd", LowCmd_))
states = DataWriter(participant, Topic(participant, "bench/lowstate", LowState_))
state, deadline = LowState_(), time.monotonic() + float(sys.argv[2])
while time.monotonic() < deadline:
    for command in commands.take(N=8):
        if isinstance(command, LowCmd_):
            state.tick = command.reserve  # the command's number, echoed
            states.write(state)
    time.sleep(0.00005)
"""


def percentiles(seconds: list[float]) -> str:
    us = np.array(seconds) * 1e6
    return f"{np.percentile(us, 50):8.0f} {np.percentile(us, 99):8.0f} {us.max():8.0f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bundle", help="a Go2 bundle (a go2:walk checkpoint, exported)")
    parser.add_argument("--ticks", type=int, default=2000)
    parser.add_argument("--domain", type=int, default=77)
    args = parser.parse_args()

    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    from mat_runtime.unitree import LowCmd_, LowState_

    policy = Policy.load(args.bundle, threads=1)
    wiring = policy.wiring
    robot = SimulatedGo2(
        MODEL, wiring.signals["joint_pos"], wiring.signals["contacts"], wiring.control_timestep
    )
    kit = Controller(policy, log=None)
    kit.start()
    stamp = 0.0
    while kit.mode is not Mode.POLICY:  # stand up first: the rows measure policy ticks
        reading, stamp = robot.read()
        robot.write(kit.tick(reading, stamp, (0.5, 0, 0)))
    reading, _ = robot.read()
    obs = wiring.observe(**{k: v for k, v in reading.items()}, command=[0.5, 0, 0],
                         last_action=np.zeros(12))  # fmt: skip

    echo = subprocess.Popen([sys.executable, "-c", ECHO, str(args.domain), "600"])
    participant = DomainParticipant(args.domain)
    commands = DataWriter(participant, Topic(participant, "bench/lowcmd", LowCmd_))
    states = DataReader(participant, Topic(participant, "bench/lowstate", LowState_))
    message = LowCmd_()

    def round_trip(number: int) -> None:
        message.reserve = number
        commands.write(message)
        while True:
            for state in states.take(N=8):
                if isinstance(state, LowState_) and state.tick == number:
                    return

    try:
        for warm in range(1, 1000):  # discovery, and both sides' first messages
            message.reserve = warm
            commands.write(message)
            time.sleep(0.01)
            if any(isinstance(s, LowState_) for s in states.take(N=64)):
                break
        rows: dict[str, list[float]] = {name: [] for name in
                                        ("Policy.act", "Controller.tick", "DDS round trip",
                                         "tick + DDS round trip")}  # fmt: skip
        for k in range(args.ticks):  # interleaved: each row sees the same machine
            start = time.perf_counter()
            policy.act(obs)
            rows["Policy.act"].append(time.perf_counter() - start)
            stamp += wiring.control_timestep
            start = time.perf_counter()
            motors = kit.tick(reading, stamp, (0.5, 0, 0))
            rows["Controller.tick"].append(time.perf_counter() - start)
            start = time.perf_counter()
            round_trip(10_000 + 2 * k)
            rows["DDS round trip"].append(time.perf_counter() - start)
            stamp += wiring.control_timestep
            start = time.perf_counter()
            motors = kit.tick(reading, stamp, (0.5, 0, 0))
            round_trip(10_001 + 2 * k)
            rows["tick + DDS round trip"].append(time.perf_counter() - start)
        assert kit.mode is Mode.POLICY, kit.transitions  # every row measured policy ticks
        del motors
    finally:
        echo.kill()
    print(f"{'row':<24} {'p50 us':>8} {'p99 us':>8} {'max us':>8}   ({args.ticks} ticks each)")
    for name, seconds in rows.items():
        print(f"{name:<24} {percentiles(seconds)}")


if __name__ == "__main__":
    main()
