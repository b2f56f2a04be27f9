"""A simulated Go2 in its own process at its own clock, behind the robot's own DDS interface.

    python examples/go2_dds_sim.py --seconds 60 &                     # the "robot"
    python examples/go2_controller.py runs/go2/onnx --dds --seconds 20  # its controller

Every physics step (2 ms, 500 Hz, paced to the wall clock) it takes the newest `rt/lowcmd`
(Unitree's `LowCmd_`, motors in the SDK's order), turns each motor's (q, dq, kp, kd, tau)
into a torque with the PD law the Go2's motor drivers run, tau = kp (q - q_measured) + kd
(dq - dq_measured) + tau_ff, clipped to the motor's limit, and steps MuJoCo's torque-motor Go2
(`robots/unitree_go2/scene.xml`); then it publishes `rt/lowstate` (`LowState_`: encoders,
IMU quaternion and gyroscope, foot forces, its clock in ms). A controller on the other side
sees what it would see on the robot: its own process, real timing, messages that arrive late
or not at all. It never resets itself: a robot that falls stays down.

Faults on purpose, for the controller's guards: `--freeze-after S` stops publishing (a stale
link), `--nan-imu-after S` sends a NaN gyroscope, `--drop P` loses that share of the state
messages, `--push-after S` shoves the trunk sideways.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mujoco
import numpy as np
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from go2_controller import heading_velocity

from mat_runtime.unitree import COMMAND_TOPIC, GO2_JOINTS, LEGS, STATE_TOPIC, LowCmd_, LowState_

MODEL = Path(__file__).parent / "robots" / "unitree_go2" / "scene.xml"


class Go2Sim:
    """MuJoCo's Go2 driven by LowCmd_ messages and read out as LowState_ messages."""

    def __init__(self, model_path: Path):
        self.model = mujoco.MjModel.from_xml_path(str(model_path))
        self.data = mujoco.MjData(self.model)
        mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key("home").id)
        mujoco.mj_forward(self.model, self.data)
        joints = [self.model.joint(name).id for name in GO2_JOINTS]
        self.qpos = np.array([self.model.jnt_qposadr[j] for j in joints])
        self.qvel = np.array([self.model.jnt_dofadr[j] for j in joints])
        self.motors = np.array(
            [np.flatnonzero(self.model.actuator_trnid[:, 0] == j)[0] for j in joints]
        )
        self.limit = self.model.actuator_ctrlrange[self.motors, 1]
        self.feet = [self.model.geom(leg).id for leg in LEGS]
        self.imu = self.model.site("imu").id
        self.base = self.model.body("base").id
        # the command in force: motors soft until the first LowCmd_ arrives
        self.q, self.dq, self.kp, self.kd, self.tau = (np.zeros(len(GO2_JOINTS)) for _ in range(5))
        self.state = LowState_()

    def command(self, message: LowCmd_) -> None:
        motors = message.motor_cmd[: len(GO2_JOINTS)]
        for name in ("q", "dq", "kp", "kd", "tau"):
            getattr(self, name)[:] = [getattr(m, name) for m in motors]

    def step(self) -> None:
        """One physics step under the motor drivers' PD law."""
        q, dq = self.data.qpos[self.qpos], self.data.qvel[self.qvel]
        torque = self.kp * (self.q - q) + self.kd * (self.dq - dq) + self.tau
        self.data.ctrl[self.motors] = np.clip(torque, -self.limit, self.limit)
        mujoco.mj_step(self.model, self.data)

    def read(self, nan_imu: bool = False) -> LowState_:
        data, state = self.data, self.state
        for k, motor in enumerate(state.motor_state[: len(GO2_JOINTS)]):
            motor.q, motor.dq = float(data.qpos[self.qpos[k]]), float(data.qvel[self.qvel[k]])
            motor.tau_est = float(data.actuator_force[self.motors[k]])
        frame = data.site_xmat[self.imu].reshape(3, 3)
        quaternion = np.zeros(4)
        mujoco.mju_mat2Quat(quaternion, data.site_xmat[self.imu])
        spin = data.xmat[self.base].reshape(3, 3) @ data.qvel[3:6]  # in the world
        gyro = frame.T @ spin
        state.imu_state.quaternion = quaternion.tolist()
        state.imu_state.gyroscope = [float("nan")] * 3 if nan_imu else gyro.tolist()
        state.foot_force = self._foot_forces()
        state.tick = round(data.time * 1000) & 0xFFFFFFFF
        return state

    def _foot_forces(self) -> list[int]:
        """Each foot's normal contact force (N), as the foot sensors' raw counts."""
        forces, wrench = [0.0] * len(self.feet), np.zeros(6)
        for i in range(self.data.ncon):
            contact = self.data.contact[i]
            for k, foot in enumerate(self.feet):
                if foot in (contact.geom1, contact.geom2):
                    mujoco.mj_contactForce(self.model, self.data, i, wrench)
                    forces[k] += abs(wrench[0])
        return [int(min(f, 32767)) for f in forces]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="how long the robot runs")
    parser.add_argument("--model", type=Path, default=MODEL, help="a Go2 MJCF with torque motors")
    parser.add_argument("--domain", type=int, default=0, help="the DDS domain")
    parser.add_argument("--freeze-after", type=float, help="stop publishing state after S s")
    parser.add_argument("--nan-imu-after", type=float, help="a NaN gyroscope after S s")
    parser.add_argument("--drop", type=float, default=0.0, help="share of state messages lost")
    parser.add_argument("--push-after", type=float, help="shove the trunk sideways after S s")
    parser.add_argument("--seed", type=int, default=0, help="the message-loss stream")
    parser.add_argument(
        "--measure-after", type=float, default=5.0,
        help="average the base's velocity in its heading's frame from S s on",
    )  # fmt: skip
    args = parser.parse_args()

    sim = Go2Sim(args.model)
    participant = DomainParticipant(args.domain)
    writer = DataWriter(participant, Topic(participant, STATE_TOPIC, LowState_))
    reader = DataReader(participant, Topic(participant, COMMAND_TOPIC, LowCmd_))
    random = np.random.default_rng(args.seed)
    period = sim.model.opt.timestep
    steps = int(args.seconds / period)
    start = time.perf_counter()
    origin = sim.data.xpos[sim.base].copy()
    late, velocity, counted = 0, np.zeros(3), 0
    for k in range(steps):
        for message in reader.take(N=64):  # the newest command is the one in force
            if isinstance(message, LowCmd_):  # not a writer's coming or going
                sim.command(message)
        seconds = k * period
        if args.push_after is not None and abs(seconds - args.push_after) < period / 2:
            sim.data.qvel[1] += 1.5  # m/s sideways, at once
        sim.step()
        if seconds >= args.measure_after:
            velocity += heading_velocity(sim.data, sim.base)
            counted += 1
        frozen = args.freeze_after is not None and seconds >= args.freeze_after
        if not frozen and random.uniform() >= args.drop:
            nan = args.nan_imu_after is not None and seconds >= args.nan_imu_after
            writer.write(sim.read(nan_imu=nan))
        wait = start + (k + 1) * period - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        else:
            late += 1
    moved = sim.data.xpos[sim.base] - origin
    print(
        f"{steps} physics steps in {time.perf_counter() - start:.1f} s ({late} late); the base "
        f"moved {moved[0]:+.2f} m forward, {moved[1]:+.2f} m sideways, and stands "
        f"{sim.data.xpos[sim.base][2]:.2f} m high"
    )
    if counted:
        vx, vy, yaw_rate = velocity / counted
        print(
            f"from {args.measure_after:g} s on, in its heading's frame: vx {vx:+.3f} m/s, "
            f"vy {vy:+.3f} m/s, yaw rate {yaw_rate:+.3f} rad/s"
        )


if __name__ == "__main__":
    main()
