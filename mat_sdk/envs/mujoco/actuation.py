"""How an action drives an actuator: over its control range, or as a joint target around the
start pose (legged robots), with a joint PD layer for torque motors.

    envs.from_mjcf("go2_mjx.xml", layout, reward, actions=envs.JointTargets(scale=0.5))
    envs.from_mjcf("go2.xml", layout, reward, actions=envs.JointTargets(0.5, kp=30, kd=1))

Without `JointTargets`, an action a in [-1, 1] maps linearly onto the actuator's control range
(a = 0: its middle). With it, a is a joint target `start + scale * a` (rad or m) around the
start pose, `scale` one number, or per joint in robot-relative units (`torque=`: the target
reach that a joint's stiffness turns into that many times m g h, the moment of the robot's
weight at its standing height, so a stiff, strong joint moves less per unit of action). A
position actuator gets that target as its control, clipped to its control range; a torque
motor gets `kp (target - q) - kd dq/dt`, clipped to its control range and
recomputed at every physics step, as a robot's own low-level controller does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

_TRN_JOINT = int(mujoco.mjtTrn.mjTRN_JOINT)
_TARGET_JOINTS = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
_NO_BIAS = int(mujoco.mjtBias.mjBIAS_NONE)  # a torque motor; position actuators have a bias


@dataclass(frozen=True)
class JointTargets:
    """Actions as joint targets around the start pose (module docstring)."""

    scale: float = 0.5  # joint units (rad, m) per unit of action
    kp: float | None = None  # torque motors: stiffness, N m / rad
    kd: float | None = None  # torque motors: damping, N m s / rad
    torque: float | None = None  # or per joint: kp * scale = torque * m g h (module docstring)

    def __post_init__(self):
        for name in ("scale", "kp", "kd", "torque"):
            value = getattr(self, name)
            if value is None and name != "scale":
                continue
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"JointTargets.{name} must be a number, got {value!r}")
            if not (math.isfinite(value) and value >= 0 and (value > 0 or name == "kd")):
                raise ValueError(f"JointTargets.{name} must be finite and > 0, got {value!r}")
        if (self.kp is None) != (self.kd is None):
            raise ValueError("JointTargets: give kp and kd together (a PD layer), or neither")


@dataclass
class TargetMap:
    """Per driven actuator: its joint's qpos and dof address, the target's offset (the start
    pose) and scale, the control's bounds, and whether a PD layer computes its torque."""

    joint_qpos: np.ndarray
    joint_dof: np.ndarray
    offset: np.ndarray
    scale: np.ndarray  # per actuator
    low: np.ndarray
    high: np.ndarray
    pd: bool
    kp: float
    kd: float

    def targets(self, actions: np.ndarray) -> np.ndarray:
        return self.offset + self.scale * actions

    def torques(self, data: mujoco.MjData, targets: np.ndarray) -> np.ndarray:
        error = targets - data.qpos[self.joint_qpos]
        return np.clip(self.kp * error - self.kd * data.qvel[self.joint_dof], self.low, self.high)


def target_map(
    model: mujoco.MjModel,
    actuators: np.ndarray,
    start_qpos: np.ndarray,
    targets: JointTargets,
    weight_moment: float | None = None,
) -> TargetMap:
    """The `TargetMap` of these actuators, or ValueError naming one that cannot take targets:
    one that does not drive a single hinge or slide, a torque motor without kp and kd, or a
    position actuator given gains (its gains are the model's). `weight_moment`: the robot's
    m g h, for `JointTargets.torque`."""
    qpos, dof = [], []
    motor = []
    for actuator in actuators:
        name = model.actuator(actuator).name or f"#{actuator}"
        kind = int(model.actuator_trntype[actuator])
        joint = int(model.actuator_trnid[actuator, 0])
        if kind != _TRN_JOINT or int(model.jnt_type[joint]) not in _TARGET_JOINTS:
            raise ValueError(
                f"actuator {name!r} does not drive one hinge or slide joint, so it takes no "
                "joint target; drop JointTargets or that actuator"
            )
        qpos.append(int(model.jnt_qposadr[joint]))
        dof.append(int(model.jnt_dofadr[joint]))
        motor.append(int(model.actuator_biastype[actuator]) == _NO_BIAS)
    if any(motor) and not all(motor):
        raise ValueError("JointTargets takes position actuators or torque motors, not a mix")
    pd = bool(motor and motor[0])
    if pd and targets.kp is None:
        raise ValueError(
            "these actuators are torque motors: JointTargets needs kp and kd for the PD layer "
            "that turns joint targets into torques"
        )
    if not pd and targets.kp is not None:
        raise ValueError(
            "these are position actuators with gains of their own (the model's kp): give "
            "JointTargets no kp and kd"
        )
    low, high = model.actuator_ctrlrange[actuators].T
    limited = model.actuator_ctrllimited[actuators].astype(bool)
    low, high = np.where(limited, low, -np.inf), np.where(limited, high, np.inf)
    qpos = np.array(qpos, dtype=np.intp)
    scale = np.full(len(actuators), float(targets.scale))
    if targets.torque is not None:
        if weight_moment is None:
            raise ValueError("JointTargets(torque=) needs a floating base: it scales by m g h")
        stiffness = (
            np.full(len(actuators), targets.kp) if pd else -model.actuator_biasprm[actuators, 1]
        )
        if (stiffness <= 0).any():
            raise ValueError("JointTargets(torque=) needs every joint's stiffness (kp) > 0")
        scale = targets.torque * weight_moment / stiffness
    return TargetMap(
        qpos, np.array(dof, dtype=np.intp), start_qpos[qpos].copy(), scale,
        low, high, pd, float(targets.kp or 0.0), float(targets.kd or 0.0),
    )  # fmt: skip


def weaken(model: mujoco.MjModel, strengths: dict[int, float]) -> None:
    """Make each actuator produce `strengths[actuator]` times its force, in the model: its
    gain, its bias (a position actuator's kp and kv) and its force limits scaled alike, so
    the force at every control and state, and the most it can give, shrink by that factor.
    Domain randomization scales from these values, as from any other motor's."""
    for actuator, strength in strengths.items():
        if model.actuator_gaintype[actuator] != int(mujoco.mjtGain.mjGAIN_FIXED):
            name = model.actuator(actuator).name or f"actuator {actuator}"
            raise ValueError(f"a weak fault needs a fixed-gain actuator; {name} has another gain")
        model.actuator_gainprm[actuator, 0] *= strength
        model.actuator_biasprm[actuator, :3] *= strength
        model.actuator_forcerange[actuator] *= strength
