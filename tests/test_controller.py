"""The controller kit (`mat_runtime.controller`) on a simulated Go2 whose motor driver takes
what a real one does (per motor: target, kp, kd): stand-up, hand-over to the policy, and each
guard ending in damping, logged."""

from __future__ import annotations

import json
import math
import shutil

import mujoco
import numpy as np
import pytest

from tests.recipes import with_examples

with_examples()
import go2  # noqa: E402  (examples/, put on the path just above)
import go2_controller  # noqa: E402

from mat_runtime import BundleError, InputError, Policy  # noqa: E402
from mat_runtime.controller import Controller, Mode, Safety  # noqa: E402


def DrivenGo2(policy: Policy) -> go2_controller.SimulatedGo2:
    """The example's simulated Go2, whose motor driver takes each tick's targets and gains."""
    wiring = policy.wiring
    return go2_controller.SimulatedGo2(
        go2.MODELS / "scene_mjx.xml", wiring.signals["joint_pos"], wiring.signals["contacts"],
        wiring.control_timestep,
    )  # fmt: skip


def _run(kit: Controller, robot: DrivenGo2, ticks: int, command=(0.5, 0.0, 0.0), **tampered):
    """`ticks` ticks of kit and robot; `tampered`: signal -> function changing its reading."""
    motors = []
    for _ in range(ticks):
        reading, _ = robot.read()
        for name, change in tampered.items():
            reading[name] = change(reading[name])
        motor = kit.tick(reading, robot.data.time, command)
        robot.write(motor)
        motors.append(motor)
    return motors


def _lying(robot: DrivenGo2) -> None:
    """The robot on its belly, legs folded: where a stand-up starts."""
    robot.data.qpos[7:] = np.tile([0.0, 1.2, -2.6], 4)
    robot.data.qpos[2] = 0.12
    mujoco.mj_forward(robot.model, robot.data)


def test_it_stands_up_without_a_jump_then_walks(go2_bundle):
    policy = Policy.load(go2_bundle)
    logged = []
    kit = Controller(policy, Safety(stand_seconds=1.0), log=logged.append)
    robot = DrivenGo2(policy)
    _lying(robot)
    idle = _run(kit, robot, 5)
    assert kit.mode is Mode.DAMPING and all(np.all(m.kp == 0) for m in idle)
    kit.start()
    stand = _run(kit, robot, 50)  # 1 s at 50 Hz
    assert kit.mode is Mode.POLICY
    targets = np.array([m.q for m in stand])
    np.testing.assert_allclose(targets[-1], kit.stand_pose, atol=1e-9)
    # no jump: the target moves in 50 equal steps from the measured pose (the first is
    # targets[0]), the largest a joint's 1/50 of its way
    steps = np.abs(np.diff(targets, axis=0))
    np.testing.assert_allclose(steps, np.abs(kit.stand_pose - targets[0]) / 49 + 0 * steps)
    upright = robot.data.xmat[robot.base].reshape(3, 3)[2, 2]
    assert upright > math.cos(math.radians(20)) and robot.data.qpos[2] > 0.2, "not standing"
    walking = _run(kit, robot, 50)
    assert kit.mode is Mode.POLICY and not np.allclose(walking[-1].q, kit.stand_pose)
    assert [t.target for t in kit.transitions] == [Mode.STAND, Mode.POLICY]
    assert logged == [
        "tick 5: damping -> stand (operator start)",
        "tick 55: stand -> policy (stood up)",
    ]


@pytest.mark.parametrize(
    ("tampered", "reason"),
    [
        ({"gyro": lambda g: g * np.nan}, "reading gyro holds NaN"),
        ({"gravity": lambda g: np.array([math.sin(1), 0, -math.cos(1)])}, "tilted 57 degrees"),
        ({"joint_vel": lambda v: v + np.eye(12)[4] * 40.0}, "joint FR_thigh_joint at 39"),
        ({"joint_pos": lambda q: q + np.eye(12)[2] * 3.0}, "of its range"),
    ],
)  # fmt: skip
def test_each_guard_ends_in_damping_in_the_tick_that_sees_it(go2_bundle, tampered, reason):
    policy = Policy.load(go2_bundle)
    kit = Controller(policy, Safety(stand_seconds=0.2))
    robot = DrivenGo2(policy)
    kit.start()
    _run(kit, robot, 15)
    assert kit.mode is Mode.POLICY
    before = kit.ticks
    [motor] = _run(kit, robot, 1, **tampered)
    assert kit.mode is Mode.DAMPING and np.all(motor.kp == 0) and np.all(motor.kd > 0)
    last = kit.transitions[-1]
    assert last.tick == before + 1 and last.target is Mode.DAMPING and reason in last.reason
    _run(kit, robot, 5)  # latched: no guard clears it, only the operator
    assert kit.mode is Mode.DAMPING


def test_stale_readings_late_ticks_and_the_operator_stop_end_in_damping(go2_bundle):
    policy = Policy.load(go2_bundle)
    safety = Safety(stand_seconds=0.2, stale_ticks=4, late_ticks=3)
    kit = Controller(policy, safety)
    robot = DrivenGo2(policy)
    kit.start()
    _run(kit, robot, 15)
    reading, _ = robot.read()
    for k in range(5):  # a new state, then the same four times: the robot stopped publishing
        kit.tick(reading, robot.data.time, (0.5, 0, 0))
        assert kit.mode is (Mode.POLICY if k < 4 else Mode.DAMPING)
    assert kit.transitions[-1].reason == "no new reading for 4 ticks"

    robot.reset()  # standing again, as the operator would have it
    kit.start()
    _run(kit, robot, 15)
    for k in range(3):
        robot.data.time += 0.02
        kit.tick(*robot.read(), (0.5, 0, 0), late=True)
        assert kit.mode is (Mode.POLICY if k < 2 else Mode.DAMPING)
    assert kit.transitions[-1].reason == "3 late ticks in a row"

    robot.reset()
    kit.start()
    _run(kit, robot, 15)
    assert kit.mode is Mode.POLICY
    kit.stop()
    assert kit.mode is Mode.DAMPING and kit.transitions[-1].reason == "operator stop"


def test_commands_are_clamped_to_the_trained_ranges_at_a_limited_rate(go2_bundle):
    policy = Policy.load(go2_bundle)
    kit = Controller(policy, Safety(command_rate=2.0))
    low, high = kit.command_low, kit.command_high
    assert kit.command_names == ["vx", "vy", "yaw_rate"]
    assert high[0] == go2.WALK.vx[1]  # what the task trained on, from the bundle
    seen = [kit.filtered_command([5.0, -5.0, 0.0]) for _ in range(60)]
    assert np.allclose(np.diff([c[0] for c in seen])[:10], 2.0 * 0.02)  # 2 m/s per s
    np.testing.assert_allclose(seen[-1], np.clip([5.0, -5.0, 0.0], low, high))
    with pytest.raises(InputError, match="command must be 3 finite numbers"):
        kit.filtered_command([np.nan, 0, 0])


def test_motors_in_the_sdks_order_are_mapped_by_joint_name(go2_bundle):
    policy = Policy.load(go2_bundle)
    ours = Controller(policy, Safety(stand_seconds=0.2))
    order = list(reversed(ours.joints))
    theirs = Controller(policy, Safety(stand_seconds=0.2), motor_order=order)
    robot = DrivenGo2(policy)
    ours.start(), theirs.start()
    permute = [ours.joints.index(name) for name in order]
    for _ in range(20):
        reading, _ = robot.read()
        mine = ours.tick(reading, robot.data.time, (0.5, 0, 0))
        sdk = {**reading, "joint_pos": reading["joint_pos"][permute],
               "joint_vel": reading["joint_vel"][permute]}  # fmt: skip
        other = theirs.tick(sdk, robot.data.time, (0.5, 0, 0))
        np.testing.assert_allclose(other.q, mine.q[permute], atol=1e-6)
        np.testing.assert_allclose(other.kp, mine.kp[permute])
        robot.write(mine)
    assert ours.mode is theirs.mode is Mode.POLICY
    with pytest.raises(ValueError, match=r"motor_order .* unknown \['FL_knee'\]"):
        Controller(policy, motor_order=[*order[:-1], "FL_knee"])


def test_bad_limits_and_a_bundle_without_gains_are_refused_naming_them(go2_bundle, tmp_path):
    with pytest.raises(ValueError, match="Safety.tilt must be a finite number > 0"):
        Safety(tilt=0)
    with pytest.raises(ValueError, match="Safety.stale_ticks must be an integer >= 1"):
        Safety(stale_ticks=0.5)
    old = tmp_path / "old"
    shutil.copytree(go2_bundle, old)
    manifest = json.loads((old / "manifest.json").read_text())
    for agent in manifest["wiring"]["agents"]:
        for column in agent["action"]:
            column.pop("servo")
    (old / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match="records no motor gains"):
        Controller(Policy.load(old))
    manifest["wiring"]["agents"][0]["action"][0]["servo"] = [-1.0, 2.0]
    (old / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match=r"servo must be \[kp, kd\]"):
        Policy.load(old)
    manifest["wiring"]["agents"][0]["action"][0]["servo"] = [50.0, 0.5]
    manifest["wiring"]["commands"]["vx"] = [0.0, 1e9]
    (old / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match=r"wiring.commands must map names to \[low, high\]"):
        Policy.load(old)
