"""A Unitree Go2 over its own low-level interface: DDS topics `rt/lowstate` and `rt/lowcmd`.

    robot = Go2LowLevel(feet=wiring.signals["contacts"])    # joins DDS domain 0
    kit = Controller(policy, motor_order=GO2_JOINTS)        # the SDK's motor order
    reading, stamp = robot.read()                           # the latest LowState_, by name
    robot.write(kit.tick(reading, stamp, command))          # one LowCmd_

The message types are Unitree's own (`unitree_go.msg.dds_.LowState_` / `LowCmd_`, as
unitree_sdk2 defines them; BSD-3-Clause), so the same controller talks to the simulated Go2
(examples/go2_dds_sim.py, in its own process at its own clock) and to a robot on the
network. Motors come in the SDK's order (FR, FL, RR, RL; hip, thigh, calf each), which the
controller kit maps onto the bundle's by joint name. What a real Go2 needs beyond this: the
`crc` field of each LowCmd_ (Unitree's crc32 over the message; the simulator does not check
it), the sport mode switched off, and the network interface given to Cyclone DDS
(`CYCLONEDDS_URI`).

Needs `cyclonedds` (`pip install 'mat-sdk[robot]'`); numpy otherwise, and never torch.
"""

# No `from __future__ import annotations`: Cyclone DDS reads the field types themselves.
from dataclasses import dataclass, field

import numpy as np
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from mat_runtime.controller import MotorCommand

STATE_TOPIC, COMMAND_TOPIC = "rt/lowstate", "rt/lowcmd"
LEGS = ("FR", "FL", "RR", "RL")  # the SDK's order
GO2_JOINTS = tuple(f"{leg}_{part}_joint" for leg in LEGS for part in ("hip", "thigh", "calf"))
MOTORS = 20  # slots in a message; the Go2 uses the first 12
SERVO = 0x01  # a motor's mode: closed-loop servo (0: off)
CONTACT_FORCE = 20  # foot_force above this reads as touching (the sensor's raw units)


# ---------------------------------------------------------------- Unitree's types
@dataclass
class MotorCmd_(IdlStruct, typename="unitree_go.msg.dds_.MotorCmd_"):
    mode: t.uint8 = 0
    q: t.float32 = 0.0
    dq: t.float32 = 0.0
    tau: t.float32 = 0.0
    kp: t.float32 = 0.0
    kd: t.float32 = 0.0
    reserve: t.array[t.uint32, 3] = field(default_factory=lambda: [0] * 3)


@dataclass
class MotorState_(IdlStruct, typename="unitree_go.msg.dds_.MotorState_"):
    mode: t.uint8 = 0
    q: t.float32 = 0.0
    dq: t.float32 = 0.0
    ddq: t.float32 = 0.0
    tau_est: t.float32 = 0.0
    q_raw: t.float32 = 0.0
    dq_raw: t.float32 = 0.0
    ddq_raw: t.float32 = 0.0
    temperature: t.uint8 = 0
    lost: t.uint32 = 0
    reserve: t.array[t.uint32, 2] = field(default_factory=lambda: [0] * 2)


@dataclass
class IMUState_(IdlStruct, typename="unitree_go.msg.dds_.IMUState_"):
    quaternion: t.array[t.float32, 4] = field(default_factory=lambda: [1.0, 0.0, 0.0, 0.0])
    gyroscope: t.array[t.float32, 3] = field(default_factory=lambda: [0.0] * 3)
    accelerometer: t.array[t.float32, 3] = field(default_factory=lambda: [0.0] * 3)
    rpy: t.array[t.float32, 3] = field(default_factory=lambda: [0.0] * 3)
    temperature: t.uint8 = 0


@dataclass
class BmsState_(IdlStruct, typename="unitree_go.msg.dds_.BmsState_"):
    version_high: t.uint8 = 0
    version_low: t.uint8 = 0
    status: t.uint8 = 0
    soc: t.uint8 = 0
    current: t.int32 = 0
    cycle: t.uint16 = 0
    bq_ntc: t.array[t.uint8, 2] = field(default_factory=lambda: [0] * 2)
    mcu_ntc: t.array[t.uint8, 2] = field(default_factory=lambda: [0] * 2)
    cell_vol: t.array[t.uint16, 15] = field(default_factory=lambda: [0] * 15)


@dataclass
class BmsCmd_(IdlStruct, typename="unitree_go.msg.dds_.BmsCmd_"):
    off: t.uint8 = 0
    reserve: t.array[t.uint8, 3] = field(default_factory=lambda: [0] * 3)


@dataclass
class LowState_(IdlStruct, typename="unitree_go.msg.dds_.LowState_"):
    head: t.array[t.uint8, 2] = field(default_factory=lambda: [0xFE, 0xEF])
    level_flag: t.uint8 = 0xFF  # low level
    frame_reserve: t.uint8 = 0
    sn: t.array[t.uint32, 2] = field(default_factory=lambda: [0] * 2)
    version: t.array[t.uint32, 2] = field(default_factory=lambda: [0] * 2)
    bandwidth: t.uint16 = 0
    imu_state: IMUState_ = field(default_factory=IMUState_)
    motor_state: t.array[MotorState_, MOTORS] = field(
        default_factory=lambda: [MotorState_() for _ in range(MOTORS)]
    )
    bms_state: BmsState_ = field(default_factory=BmsState_)
    foot_force: t.array[t.int16, 4] = field(default_factory=lambda: [0] * 4)
    foot_force_est: t.array[t.int16, 4] = field(default_factory=lambda: [0] * 4)
    tick: t.uint32 = 0  # the robot's clock, ms
    wireless_remote: t.array[t.uint8, 40] = field(default_factory=lambda: [0] * 40)
    bit_flag: t.uint8 = 0
    adc_reel: t.float32 = 0.0
    temperature_ntc1: t.uint8 = 0
    temperature_ntc2: t.uint8 = 0
    power_v: t.float32 = 0.0
    power_a: t.float32 = 0.0
    fan_frequency: t.array[t.uint16, 4] = field(default_factory=lambda: [0] * 4)
    reserve: t.uint32 = 0
    crc: t.uint32 = 0


@dataclass
class LowCmd_(IdlStruct, typename="unitree_go.msg.dds_.LowCmd_"):
    head: t.array[t.uint8, 2] = field(default_factory=lambda: [0xFE, 0xEF])
    level_flag: t.uint8 = 0xFF
    frame_reserve: t.uint8 = 0
    sn: t.array[t.uint32, 2] = field(default_factory=lambda: [0] * 2)
    version: t.array[t.uint32, 2] = field(default_factory=lambda: [0] * 2)
    bandwidth: t.uint16 = 0
    motor_cmd: t.array[MotorCmd_, MOTORS] = field(
        default_factory=lambda: [MotorCmd_() for _ in range(MOTORS)]
    )
    bms_cmd: BmsCmd_ = field(default_factory=BmsCmd_)
    wireless_remote: t.array[t.uint8, 40] = field(default_factory=lambda: [0] * 40)
    led: t.array[t.uint8, 12] = field(default_factory=lambda: [0] * 12)
    fan: t.array[t.uint8, 2] = field(default_factory=lambda: [0] * 2)
    gpio: t.uint8 = 0
    reserve: t.uint32 = 0
    crc: t.uint32 = 0


# ---------------------------------------------------------------- the controller's side
def gravity_in_body(quaternion) -> np.ndarray:
    """Gravity's direction in the body frame from the IMU's orientation (w, x, y, z)."""
    w, x, y, z = quaternion
    # the third row of the body-to-world rotation, negated: R^T (0, 0, -1)
    return -np.array([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)])


class Go2LowLevel:
    """The robot as the controller kit sees it: `read()` the latest state by signal name
    (joints in the SDK's order, `GO2_JOINTS`), `write()` one command per motor."""

    def __init__(self, feet: tuple[str, ...] = ("FL", "FR", "RL", "RR"), domain: int = 0):
        """`feet`: the bundle's contact signals, named after their legs, in its order."""
        unknown = [foot for foot in feet if foot not in LEGS]
        if unknown:
            raise ValueError(f"feet are named after the Go2's legs {LEGS}, got {unknown}")
        self._feet = np.array([LEGS.index(foot) for foot in feet])
        self.participant = DomainParticipant(domain)
        self._reader = DataReader(self.participant, Topic(self.participant, STATE_TOPIC, LowState_))
        self._writer = DataWriter(self.participant, Topic(self.participant, COMMAND_TOPIC, LowCmd_))
        self._latest: LowState_ | None = None
        self._command = LowCmd_()

    def read(self) -> tuple[dict[str, np.ndarray] | None, float | None]:
        """The newest state received (None before the first): the signals by name and the
        robot's clock (s). The same stamp again means no new state came (the kit counts it
        stale)."""
        for sample in self._reader.take(N=64):
            if isinstance(sample, LowState_):  # not a writer's coming or going
                self._latest = sample
        state = self._latest
        if state is None:
            return None, None
        motors = state.motor_state[: len(GO2_JOINTS)]
        imu = state.imu_state
        reading = {
            "joint_pos": np.array([m.q for m in motors], dtype=np.float64),
            "joint_vel": np.array([m.dq for m in motors], dtype=np.float64),
            "gravity": gravity_in_body(imu.quaternion),
            "gyro": np.array(imu.gyroscope, dtype=np.float64),
            "contacts": (np.array(state.foot_force)[self._feet] > CONTACT_FORCE).astype(float),
        }
        return reading, state.tick / 1000.0

    def write(self, motors: MotorCommand) -> None:
        """One LowCmd_: per motor (in the SDK's order) its target, speed, gains and feed-forward
        torque, in servo mode."""
        for k, slot in enumerate(self._command.motor_cmd[: len(GO2_JOINTS)]):
            slot.mode = SERVO
            slot.q, slot.dq = float(motors.q[k]), float(motors.dq[k])
            slot.kp, slot.kd, slot.tau = (
                float(motors.kp[k]),
                float(motors.kd[k]),
                float(motors.tau[k]),
            )
        self._writer.write(self._command)
