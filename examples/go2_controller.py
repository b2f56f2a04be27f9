"""The Go2's controller: the bundle acts from what the robot's hardware gives, nothing more,
behind the controller kit's safety states.

    PYTHONPATH=examples mat train go2:walk ... --out runs/go2          # docs/REAL_ROBOTS.md
    mat export runs/go2/checkpoint.pt -o runs/go2/onnx --trust-env-code
    python examples/go2_controller.py runs/go2/onnx --command 0.7 0 0 --seconds 20
    python examples/go2_controller.py runs/go2/onnx --joystick     # a scripted operator
    python examples/go2_dds_sim.py & python examples/go2_controller.py runs/go2/onnx --dds

Every tick (50 Hz) it reads the joint encoders (angle and velocity of the 12 joints, by
name), the IMU (orientation and angular velocity) and the four foot contact switches, and
gives them to the kit (`mat_runtime.controller`, docs/DEPLOYMENT.md): it stands the robot up
from its measured pose, hands over to the policy, clamps the operator's command to the
trained ranges, and makes every motor soft on a fault (a tilt past 45 degrees, a joint too
fast or at its range's end, a stale or NaN reading). Each tick's command is per motor a
joint target and the gains kp, kd, as the Go2's low-level command message carries them. Only
`mat_runtime` (numpy + onnxruntime) runs the policy: torch is blocked, and nothing of the
training SDK is imported.

The "robot" here is MuJoCo stepping the model (`SimulatedGo2`), whose motor driver takes each
tick's targets and gains, so the loop can be run and measured anywhere; on the real Go2,
`read` gets the same numbers from its low-level state message (motor q, dq; IMU quaternion,
gyroscope; foot force > threshold) and `write` sends q, dq, kp, kd, tau per motor. A fault
here counts as a fall: the simulation puts the robot back on its feet and the operator
starts the kit again.

`--dds` drives a robot over its own low-level interface instead (`mat_runtime.unitree`: DDS
topics rt/lowstate and rt/lowcmd, Unitree's message types, motors in the SDK's order, which
the kit maps by joint name): the simulated Go2 of examples/go2_dds_sim.py in its own process,
or a Go2 on the network. The robot is not reset there: after a fault the kit holds damping.

`--joystick` plays an operator's scripted sequence instead of one command (stand, forward,
stop, turn, sideways, back; `JOYSTICK`), through the kit's clamp and rate limit, and reports
per segment the robot's measured velocity in its heading's frame (the simulation's truth: a
real robot needs motion capture for it) against the command, after a settling second.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __name__ == "__main__":  # prove the point: importing torch now raises ImportError
    sys.modules["torch"] = None

import mujoco
import numpy as np

from mat_runtime import BundleError, Policy, loop
from mat_runtime.controller import Controller, Mode, MotorCommand

MODEL = Path(__file__).parent / "robots" / "unitree_go2" / "scene_mjx.xml"
# (seconds, (vx m/s, vy m/s, yaw rate rad/s)): an operator's session with the stick
JOYSTICK = (
    (3.0, (0.0, 0.0, 0.0)),  # stand
    (5.0, (0.6, 0.0, 0.0)),  # forward
    (3.0, (0.0, 0.0, 0.0)),  # stop
    (5.0, (0.0, 0.0, 0.8)),  # turn on the spot
    (5.0, (0.0, 0.3, 0.0)),  # sideways
    (5.0, (-0.3, 0.0, 0.0)),  # back
)
SETTLE = 1.0  # s after each change of command that the report leaves out


def heading_velocity(data, base: int) -> np.ndarray:
    """The base's (vx, vy) in its heading's frame and its yaw rate: what a velocity command
    names, from the simulation's state (the frame training reports, `ArrayTeam.tracking`)."""
    frame = data.xmat[base].reshape(3, 3)
    yaw = np.arctan2(frame[1, 0], frame[0, 0])
    cos, sin = np.cos(yaw), np.sin(yaw)
    vx, vy = data.qvel[0:2]
    spin = frame @ data.qvel[3:6]  # the free joint's angular velocity, in the world
    return np.array([cos * vx + sin * vy, -sin * vx + cos * vy, spin[2]])


class SimulatedGo2:
    """The hardware's side, simulated: sensors to read, joint targets to write."""

    def __init__(self, model_path: Path, joints: list[str], feet: list[str], control: float):
        self.model = mujoco.MjModel.from_xml_path(str(model_path))
        self.data = mujoco.MjData(self.model)
        self.substeps = round(control / self.model.opt.timestep)
        ids = [self.model.joint(name).id for name in joints]
        self.qpos = np.array([self.model.jnt_qposadr[j] for j in ids])
        self.qvel = np.array([self.model.jnt_dofadr[j] for j in ids])
        self.feet = np.array([self.model.geom(name).id for name in feet])
        self.imu = self.model.site("imu").id
        self.base = self.model.body("base").id
        # each joint's actuator, in the encoders' order: the motors `write` drives
        self.motors = np.array(
            [np.flatnonzero(self.model.actuator_trnid[:, 0] == j)[0] for j in ids]
        )
        self.reset()

    def reset(self) -> None:
        mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key("home").id)
        mujoco.mj_forward(self.model, self.data)
        self.start = self.data.xpos[self.base].copy()

    def read(self) -> tuple[dict[str, np.ndarray], float]:
        """What the robot measures, and when: encoders, IMU (as gravity's direction and the
        gyro, in the IMU's frame) and foot contacts; the simulation's clock."""
        data = self.data
        frame = data.site_xmat[self.imu].reshape(3, 3)
        base = data.xmat[self.base].reshape(3, 3)
        spin = base @ data.qvel[3:6]  # the free joint's angular velocity, in the world
        touching = np.isin(self.feet, np.concatenate([data.contact.geom1, data.contact.geom2]))
        reading = {
            "joint_pos": data.qpos[self.qpos].copy(),
            "joint_vel": data.qvel[self.qvel].copy(),
            "gravity": frame.T @ np.array([0.0, 0.0, -1.0]),
            "gyro": frame.T @ spin,
            "contacts": touching.astype(np.float64),
        }
        return reading, float(data.time)

    def velocity(self) -> np.ndarray:
        return heading_velocity(self.data, self.base)

    def write(self, motors: MotorCommand) -> None:
        """Send each motor (in the encoders' order) its target and gains, as the motor driver
        takes them; the simulation then runs one control period."""
        self.model.actuator_gainprm[self.motors, 0] = motors.kp
        self.model.actuator_biasprm[self.motors, 1] = -motors.kp
        self.model.actuator_biasprm[self.motors, 2] = -motors.kd
        self.data.ctrl[self.motors] = motors.q
        mujoco.mj_step(self.model, self.data, self.substeps)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bundle", help="a Go2 bundle (`mat export` of a go2:walk checkpoint)")
    parser.add_argument(
        "--command", type=float, nargs=3, default=[0.7, 0.0, 0.0],
        metavar=("VX", "VY", "YAW_RATE"), help="velocity command (m/s, rad/s)",
    )  # fmt: skip
    parser.add_argument(
        "--seconds", type=float,
        help="how long to walk [20; with --joystick, the script's 26 s, its segments scaled]",
    )  # fmt: skip
    parser.add_argument(
        "--joystick", action="store_true",
        help="play the scripted operator's sequence (JOYSTICK) instead of --command",
    )  # fmt: skip
    parser.add_argument("--model", type=Path, default=MODEL, help="the MJCF the robot runs")
    parser.add_argument(
        "--dds", action="store_true",
        help="drive a robot over DDS (examples/go2_dds_sim.py, or a Go2) instead of in-process",
    )  # fmt: skip
    parser.add_argument("--cpu", type=int, help="pin the process to this core")
    args = parser.parse_args()

    for note in loop.realtime(args.cpu, None):
        print(note)
    try:
        policy = Policy.load(args.bundle, threads=1)
    except BundleError as error:  # a damaged or edited bundle: say which field, once
        parser.error(str(error))
    wiring = policy.wiring
    if wiring is None or not {"joint_pos", "contacts"} <= set(wiring.signals):
        parser.error(
            f"{args.bundle} does not observe the Go2's joint encoders and foot contacts (a "
            "go2:walk bundle does)"
        )
    robot, kit = _dds(parser, policy) if args.dds else _simulated(parser, policy, args.model)
    if args.joystick:
        scale = 1.0 if args.seconds is None else args.seconds / sum(s for s, _ in JOYSTICK)
        script = tuple((seconds * scale, command) for seconds, command in JOYSTICK)
    else:
        script = ((20.0 if args.seconds is None else args.seconds, tuple(args.command)),)
    ends = np.cumsum([seconds for seconds, _ in script])
    # per segment, after its settling second: the sums of the measured velocity and of the
    # command the policy was given (clamped to the trained ranges), their count; its falls
    sums, given = np.zeros((len(script), 3)), np.zeros((len(script), 3))
    counts, falls = np.zeros(len(script)), np.zeros(len(script))
    state = {"falls": 0, "motors": None, "segment": 0, "time": 0.0, "down": False}
    kit.start()

    def act() -> None:
        segment = min(int(np.searchsorted(ends, state["time"], side="right")), len(script) - 1)
        state["segment"] = segment
        command = np.array(script[segment][1])
        state["motors"] = kit.tick(*robot.read(), command)

    def step() -> None:
        robot.write(state["motors"])
        state["time"] += wiring.control_timestep
        segment = state["segment"]
        began = ends[segment] - script[segment][0]
        if not args.dds and kit.mode is Mode.POLICY and state["time"] - began > SETTLE:
            sums[segment] += robot.velocity()
            given[segment] += kit.command
            counts[segment] += 1
        if kit.mode is Mode.DAMPING and not state["down"]:  # a guard tripped: a fall, or close
            state["falls"] += 1
            falls[segment] += 1
            if args.dds:  # a robot out there is not put back on its feet by us
                state["down"] = True
            else:
                robot.reset()
                kit.start()

    seconds = float(ends[-1])
    ticks = loop.run(act, step, 1 / wiring.control_timestep, seconds, warmup=0.0)
    print(f"{policy}\n{ticks.summary()}")
    if args.dds:  # the robot's side knows where it went
        print(f"falls {state['falls']}; modes: {kit.mode.value} at the end")
        return
    travelled = float((robot.data.xpos[robot.base] - robot.start)[0])
    speed = travelled / max(robot.data.time, 1e-9)
    if args.joystick:
        _report(
            script, sums / counts[:, None].clip(1), given / counts[:, None].clip(1), counts, falls
        )
    else:
        print(
            f"command {args.command}: falls {state['falls']}; {travelled:.2f} m forward in the "
            f"last {robot.data.time:.1f} s, its stand-up included ({speed:.2f} m/s)"
        )
        vx, vy, yaw_rate = sums[0] / max(counts[0], 1)
        print(
            f"in its heading's frame, after the policy's first second: vx {vx:+.3f} m/s, "
            f"vy {vy:+.3f} m/s, yaw rate {yaw_rate:+.3f} rad/s"
        )
    assert "torch" not in {m for m, module in sys.modules.items() if module}


def _simulated(parser, policy: Policy, model: Path) -> tuple[SimulatedGo2, Controller]:
    """The Go2 simulated in this process, with the kit on the bundle's own motor order."""
    wiring = policy.wiring
    try:
        robot = SimulatedGo2(
            model, wiring.signals["joint_pos"], wiring.signals["contacts"],
            wiring.control_timestep,
        )  # fmt: skip
    except KeyError as error:  # MuJoCo's lookup by name
        parser.error(f"{policy.path} names what {model.name} does not have: {error}")
    if wiring.ctrl_index.max(initial=-1) >= robot.model.nu:
        parser.error(
            f"{policy.path} drives actuator {wiring.ctrl_index.max()}, and {model.name} has "
            f"{robot.model.nu}"
        )
    try:
        return robot, Controller(policy, log=print)
    except BundleError as error:
        parser.error(str(error))


def _dds(parser, policy: Policy, wait: float = 10.0):
    """A robot over DDS, once its first state arrived, and the kit on the SDK's motor order."""
    from mat_runtime.unitree import GO2_JOINTS, Go2LowLevel

    try:
        robot = Go2LowLevel(feet=tuple(policy.wiring.signals["contacts"]))
        kit = Controller(policy, motor_order=GO2_JOINTS, log=print)
    except (ValueError, BundleError) as error:
        parser.error(str(error))
    deadline = time.monotonic() + wait
    while robot.read()[0] is None:
        if time.monotonic() > deadline:
            parser.error(f"no robot state on rt/lowstate within {wait:g} s: is the robot on?")
        time.sleep(0.01)
    return robot, kit


def _report(script, measured, given, counts, falls) -> None:
    """Per segment: the operator's command, what the policy was given (clamped to the trained
    ranges), the measured (vx, vy, yaw rate), the error against the operator's, falls."""
    print("seconds  operator (vx, vy, yaw)  given to the policy   measured"
          "                |error| lin   yaw  falls")  # fmt: skip
    linear, yaw = [], []
    rows = zip(script, measured, given, counts, falls, strict=True)
    for (seconds, command), velocity, sent, count, fell in rows:
        if not count:
            print(f"{seconds:7.1f}  {command!s:22} (no policy time after settling)   {int(fell)}")
            continue
        error = np.abs(velocity - np.array(command))
        linear.append(float(np.hypot(*error[:2])))
        yaw.append(float(error[2]))
        shown = ["(" + ", ".join(f"{v:+.2f}" for v in x) + ")" for x in (sent, velocity)]
        print(
            f"{seconds:7.1f}  {command!s:22} {shown[0]:21} {shown[1]:23} "
            f"{linear[-1]:10.3f} {yaw[-1]:5.3f}  {int(fell)}"
        )
    if linear:
        print(
            f"mean |error| over {len(linear)} segments: {np.mean(linear):.3f} m/s, "
            f"{np.mean(yaw):.3f} rad/s; falls {int(falls.sum())}"
        )


if __name__ == "__main__":
    main()
