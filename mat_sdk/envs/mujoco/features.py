"""Observations from signals a real robot has: `Observation` says which, `signals` reads them.

    envs.from_mjcf("go2.xml", layout, reward, observation=envs.Observation(
        imu="imu", contacts=("FL", "FR", "RL", "RR"), last_action=True))

With an `Observation`, every agent observes its own joints' positions (relative to the start
pose) and velocities and its neighbours' (what joint encoders give), then the whole robot's
signals in this order: the IMU (gravity's direction and the angular velocity in the IMU's
frame, optionally the linear acceleration), MJCF sensors by name, foot contacts, the task's
command, privileged signals (a simulator's, off unless asked), then its own previous action.

Each signal has a name: a controller on the robot passes the hardware's readings by these
names to `mat_runtime.Wiring.observe`, which builds the observation exactly as the env does.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from mat_sdk.envs.mujoco.trunk import Contacts, Trunk

PRIVILEGED = ("height", "velocity")  # what a simulator knows and a robot does not measure


@dataclass(frozen=True)
class Observation:
    """Which whole-robot signals each agent observes besides its joints (module docstring)."""

    imu: str | None = None  # the site (or body) whose frame the IMU measures in
    accelerometer: bool = False  # also the IMU's linear acceleration (an accelerometer sensor)
    sensors: tuple[str, ...] = ()  # MJCF sensors by name
    contacts: tuple[str, ...] = ()  # geoms or bodies (feet): 1 while touching anything
    command: bool = True  # the task's command, when the task samples commands
    last_action: bool = True  # the agent's own previous action
    privileged: tuple[str, ...] = ()  # "height", "velocity": a simulator's, not a robot's

    def __post_init__(self):
        for name in ("sensors", "contacts", "privileged"):
            value = getattr(self, name)
            if isinstance(value, str) or not all(isinstance(v, str) and v for v in value):
                raise ValueError(f"Observation.{name} must be a tuple of names, got {value!r}")
            object.__setattr__(self, name, tuple(value))
        unknown = set(self.privileged) - set(PRIVILEGED)
        if unknown:
            raise ValueError(f"privileged signals are {PRIVILEGED}, got {sorted(unknown)}")
        if self.accelerometer and self.imu is None:
            raise ValueError("accelerometer=True reads the IMU: name its site with imu=")
        for flag in ("accelerometer", "command", "last_action"):
            if not isinstance(getattr(self, flag), bool):
                raise ValueError(f"Observation.{flag} must be true or false")


@dataclass
class Signal:
    """One named input of the observation: its size, its columns' names (for a controller) and
    how the env reads it now."""

    name: str
    size: int
    labels: list[str]
    read: Callable[[], np.ndarray]
    per_agent: bool = False  # [agents x width]: each agent observes its own row


def robot_signals(
    observation: Observation, physics, command: Callable[[], np.ndarray], command_names
) -> list[Signal]:
    """The whole-robot signals an `Observation` asks for, in observation order (not the joints,
    nor the previous action: the team reads those)."""
    model, data = physics.model.ptr, physics.data.ptr
    signals = []
    if observation.imu is not None:
        trunk = Trunk(model, observation.imu)
        signals += [
            Signal("gravity", 3, ["x", "y", "z"], lambda: trunk.gravity(data)),
            Signal("gyro", 3, ["x", "y", "z"], lambda: trunk.angular_velocity(data)),
        ]
        if observation.accelerometer:
            signals.append(_accelerometer(model, data, trunk))
    for name in observation.sensors:
        signals.append(_sensor(model, data, name))
    if observation.contacts:
        feet = Contacts(model, observation.contacts)
        names = list(observation.contacts)
        signals.append(Signal("contacts", len(names), names, lambda: feet.read(data).copy()))
    if observation.command and command_names:
        signals.append(Signal("command", len(command_names), list(command_names), command))
    if observation.privileged:
        trunk = Trunk(model)
        if "height" in observation.privileged:
            signals.append(Signal("height", 1, ["z"], lambda: [trunk.height(data)]))
        if "velocity" in observation.privileged:
            signals.append(Signal("velocity", 3, ["x", "y", "z"], lambda: trunk.velocity(data)))
    return signals


def _sensor(model, data, name: str) -> Signal:
    sensor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
    if sensor < 0:
        known = [model.sensor(i).name for i in range(model.nsensor)]
        raise ValueError(
            f"the model has no sensor named {name!r}; its sensors: {', '.join(known) or 'none'}"
        )
    start, size = int(model.sensor_adr[sensor]), int(model.sensor_dim[sensor])
    labels = [str(i) for i in range(size)]
    return Signal(f"sensor.{name}", size, labels, lambda: data.sensordata[start : start + size])


def _accelerometer(model, data, trunk: Trunk) -> Signal:
    """The accelerometer sensor at the IMU's site (MuJoCo computes it with the dynamics)."""
    kind = mujoco.mjtSensor.mjSENS_ACCELEROMETER
    found = [
        i
        for i in range(model.nsensor)
        if model.sensor_type[i] == kind and model.sensor_objid[i] == trunk.site
    ]
    if trunk.site < 0 or not found:
        raise ValueError(
            "accelerometer=True needs an <accelerometer> sensor at the IMU's site in the model"
        )
    start = int(model.sensor_adr[found[0]])
    return Signal("accel", 3, ["x", "y", "z"], lambda: data.sensordata[start : start + 3])
