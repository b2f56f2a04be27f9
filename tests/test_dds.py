"""The controller kit against a simulated Go2 in its own process, over the robot's own DDS
interface (`mat_runtime.unitree`, examples/go2_dds_sim.py): real timing across a process
boundary, faults injected on the robot's side."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from mat_runtime import Policy
from mat_runtime.controller import Controller, Mode
from mat_runtime.unitree import GO2_JOINTS, Go2LowLevel

REPO = Path(__file__).resolve().parents[1]
RATE = 50.0  # Hz, the bundle's control rate


def _robot(*faults: str, seconds: float = 20.0):
    """The simulated Go2 in a process of its own on a DDS domain of its own."""
    domain = 100 + os.getpid() % 100  # apart from other test runs on this machine
    process = subprocess.Popen(
        [sys.executable, str(REPO / "examples" / "go2_dds_sim.py"), "--seconds", str(seconds),
         "--domain", str(domain), *faults],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    return process, domain


def _drive(kit: Controller, robot: Go2LowLevel, seconds: float) -> list[dict]:
    """Tick the kit at the control rate against the robot: per tick the reading, the mode."""
    ticks = []
    start = time.perf_counter()
    for k in range(int(seconds * RATE)):
        reading, stamp = robot.read()
        robot.write(kit.tick(reading, stamp, [0.5, 0.0, 0.0]))
        ticks.append({"reading": reading, "stamp": stamp, "mode": kit.mode})
        time.sleep(max(0.0, start + (k + 1) / RATE - time.perf_counter()))
    return ticks


def _connected(go2_bundle, domain: int) -> tuple[Controller, Go2LowLevel]:
    policy = Policy.load(go2_bundle, threads=1)
    robot = Go2LowLevel(feet=tuple(policy.wiring.signals["contacts"]), domain=domain)
    deadline = time.monotonic() + 20
    while robot.read()[0] is None:
        assert time.monotonic() < deadline, "the simulated robot published no state"
        time.sleep(0.01)
    kit = Controller(policy, motor_order=GO2_JOINTS)
    kit.start()
    return kit, robot


def _session(go2_bundle, seconds: float, *faults: str) -> tuple[Controller, list[dict]]:
    """The kit driving the simulated robot (with `faults`) for `seconds`; its ticks."""
    process, domain = _robot(*faults)
    try:
        kit, robot = _connected(go2_bundle, domain)
        return kit, _drive(kit, robot, seconds)
    finally:
        process.kill()
        process.communicate()


def test_the_kit_stands_the_robot_up_over_dds_and_goes_soft_when_its_state_stops(go2_bundle):
    """Across the process boundary: the stand phase moves the measured joints to the start
    pose without a jump; then the robot stops publishing (`--freeze-after`) and the kit is in
    damping within its stale limit (5 ticks) and a tick or two of delivery."""
    kit, ticks = _session(go2_bundle, 4.5, "--freeze-after", "3.0")
    modes = [t["mode"] for t in ticks]
    assert modes[0] is Mode.STAND and Mode.POLICY in modes, modes
    stood = modes.index(Mode.POLICY)
    stand = np.array([t["reading"]["joint_vel"] for t in ticks[:stood]])
    assert np.abs(stand).max() < 5.0  # rad/s: a smooth move, no jump
    pose = ticks[stood]["reading"]["joint_pos"][kit._encoders]  # the bundle's order
    # reached, less what the trunk's weight bends the calves at the bundle's kp (0.12-0.15 rad)
    assert np.abs(pose - kit.stand_pose).max() < 0.25
    assert modes[-1] is Mode.DAMPING
    fault = next(t for t in kit.transitions if t.target is Mode.DAMPING)
    assert "no new reading for 5 ticks" in fault.reason
    stamps = [t["stamp"] for t in ticks]
    last_new = max(k for k in range(1, len(stamps)) if stamps[k] != stamps[k - 1]) + 1
    assert fault.tick - last_new == 5  # ticks count from 1: the fifth tick without news


def test_a_nan_from_the_robots_imu_makes_the_kit_go_soft_at_once(go2_bundle):
    kit, ticks = _session(go2_bundle, 4.0, "--nan-imu-after", "2.5")
    fault = next(t for t in kit.transitions if t.target is Mode.DAMPING)
    assert "gyro" in fault.reason and "nan" in fault.reason.lower(), fault.reason
    first_nan = next(k for k, t in enumerate(ticks) if np.isnan(t["reading"]["gyro"]).any())
    assert fault.tick == first_nan + 1  # the tick that read it (ticks count from 1)


def test_feet_not_named_after_the_go2s_legs_are_refused_naming_them():
    with pytest.raises(ValueError, match=r"feet are named after the Go2's legs .*got \['paw'\]"):
        Go2LowLevel(feet=("FL", "paw"))
