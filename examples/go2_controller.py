"""The Go2's controller: the bundle acts from what the robot's hardware gives, nothing more,
behind the controller kit's safety states.

    PYTHONPATH=examples mat train go2:walk ... --out runs/go2          # docs/REAL_ROBOTS.md
    mat export runs/go2/checkpoint.pt -o runs/go2/onnx --trust-env-code
    python examples/go2_controller.py runs/go2/onnx --command 0.7 0 0 --seconds 20

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
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __name__ == "__main__":  # prove the point: importing torch now raises ImportError
    sys.modules["torch"] = None

import mujoco
import numpy as np

from mat_runtime import BundleError, Policy, loop
from mat_runtime.controller import Controller, Mode, MotorCommand

MODEL = Path(__file__).parent / "robots" / "unitree_go2" / "scene_mjx.xml"


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

    def read(self) -> dict[str, np.ndarray]:
        """What the robot measures: encoders, IMU (as gravity's direction and the gyro, in the
        IMU's frame) and foot contacts."""
        data = self.data
        frame = data.site_xmat[self.imu].reshape(3, 3)
        base = data.xmat[self.base].reshape(3, 3)
        spin = base @ data.qvel[3:6]  # the free joint's angular velocity, in the world
        touching = np.isin(self.feet, np.concatenate([data.contact.geom1, data.contact.geom2]))
        return {
            "joint_pos": data.qpos[self.qpos].copy(),
            "joint_vel": data.qvel[self.qvel].copy(),
            "gravity": frame.T @ np.array([0.0, 0.0, -1.0]),
            "gyro": frame.T @ spin,
            "contacts": touching.astype(np.float64),
        }

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
    parser.add_argument("--seconds", type=float, default=20.0, help="how long to walk")
    parser.add_argument("--model", type=Path, default=MODEL, help="the MJCF the robot runs")
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
    try:
        robot = SimulatedGo2(
            args.model, wiring.signals["joint_pos"], wiring.signals["contacts"],
            wiring.control_timestep,
        )  # fmt: skip
    except KeyError as error:  # MuJoCo's lookup by name
        parser.error(f"{args.bundle} names what {args.model.name} does not have: {error}")
    if wiring.ctrl_index.max(initial=-1) >= robot.model.nu:
        parser.error(
            f"{args.bundle} drives actuator {wiring.ctrl_index.max()}, and {args.model.name} has "
            f"{robot.model.nu}"
        )
    try:
        kit = Controller(policy, log=print)
    except BundleError as error:
        parser.error(str(error))
    command = np.array(args.command)
    state = {"falls": 0, "motors": None}
    kit.start()

    def act() -> None:
        state["motors"] = kit.tick(robot.read(), robot.data.time, command)

    def step() -> None:
        robot.write(state["motors"])
        if kit.mode is Mode.DAMPING:  # a guard tripped: a fall, or about to be one
            state["falls"] += 1
            robot.reset()
            kit.start()

    ticks = loop.run(act, step, 1 / wiring.control_timestep, args.seconds, warmup=0.0)
    travelled = float((robot.data.xpos[robot.base] - robot.start)[0])
    speed = travelled / max(robot.data.time, 1e-9)
    print(f"{policy}\n{ticks.summary()}")
    print(
        f"command {args.command}: falls {state['falls']}; {travelled:.2f} m forward in the last "
        f"{robot.data.time:.1f} s, its stand-up included ({speed:.2f} m/s)"
    )
    assert "torch" not in {m for m, module in sys.modules.items() if module}


if __name__ == "__main__":
    main()
