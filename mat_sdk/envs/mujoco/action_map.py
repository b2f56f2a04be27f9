"""Which entries of a team's action array drive which actuator, and how an action becomes a
control: the actuator's range (`ctrl = low + (a + 1) * half`), or a joint target around the
start pose (`JointTargets`), sent to a position servo or turned into torque by a PD layer.

Faults decide what is driven: a zeroed actuator's entry drives nothing, a removed agent's row
is gone, a weak actuator keeps a share of its force (`resolve_faults`).
"""

from __future__ import annotations

import mujoco
import numpy as np

from mat_runtime.wiring_schema import NO_ACTUATOR, ActionColumn
from mat_sdk.envs.core.faults import Fault
from mat_sdk.envs.mujoco.actuation import JointTargets, target_map
from mat_sdk.envs.mujoco.decomposition import actuator_joints


def actuator_name(model, actuator: int) -> str:
    """An actuator's name, or `#index` for an unnamed one."""
    return model.actuator(actuator).name or f"#{actuator}"


def resolve_faults(
    model, members, agents: list[str], faults: tuple[Fault, ...], env_id: str
) -> tuple[set[int], set[int], dict[int, float]]:
    """Zeroed actuators, removed agents and weak actuators (with the force each keeps): each
    fault names an agent of `agents` or an actuated joint of one of the team's `members`."""
    zeroed: set[int] = set()
    removed: set[int] = set()
    weakened: dict[int, float] = {}
    for fault in faults:
        targets, actuators = _fault_target(model, members, agents, fault.target, env_id)
        if fault.kind == "remove":
            removed.update(targets)
        elif fault.kind == "zero":
            zeroed.update(actuators)
        else:
            weakened.update(dict.fromkeys(actuators, fault.strength))
    if len(removed) == len(members):
        raise ValueError("faults remove every agent; at least one must stay")
    for agent in removed:
        zeroed.update(members[agent].actuators)
    return zeroed, removed, weakened


def _fault_target(model, members, agents, name: str, env_id: str) -> tuple[list[int], list[int]]:
    if name in agents:
        agent = agents.index(name)
        return [agent], list(members[agent].actuators)
    joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
    hits = [
        (i, a)
        for i, member in enumerate(members)
        for a in member.actuators
        if joint >= 0 and joint in actuator_joints(model, a)
    ]
    if not hits:
        joints = [model.joint(j).name for member in members for j in member.joints]
        raise ValueError(
            f"fault names {name!r}, which is neither an agent nor an actuated joint of "
            f"{env_id}; agents: {', '.join(agents)}; joints: {', '.join(joints)}"
        )
    return sorted({i for i, _ in hits}), [a for _, a in hits]


class ActionMap:
    """The driven entries of the `[n, width]` action array and the controls they set.

    `driven`: flat indices into the team's action array; `driven_full`: the same entries in
    the `[all team agents, width]` array (a removed agent's row kept); `ctrl_index`: the
    actuator each drives; `targets`: joint targets around the start pose (None: the
    actuator's range)."""

    def __init__(
        self,
        model,
        members,
        active: list[int],
        width: int,
        zeroed: set[int],
        targets: JointTargets | None,
        start_qpos: np.ndarray,
        moment: float | None,
    ):
        self._model = model
        self.width = width
        driven, full, actuators = [], [], []
        for row, agent in enumerate(active):
            for col, actuator in enumerate(members[agent].actuators):
                if actuator not in zeroed:
                    driven.append(row * width + col)
                    full.append(agent * width + col)
                    actuators.append(actuator)
        self.driven = np.array(driven, dtype=np.intp)
        self.driven_full = np.array(full, dtype=np.intp)
        self.ctrl_index = np.array(actuators, dtype=np.intp)
        low, high = model.actuator_ctrlrange[self.ctrl_index].T
        self.ctrl_low, self.ctrl_half = low, (high - low) / 2
        self.targets = None
        if targets is not None:
            self.targets = target_map(model, self.ctrl_index, start_qpos, targets, moment)

    def columns(self, rows: int) -> list[list[ActionColumn]]:
        """Per row of the action array, per column, the wiring of the actuator it drives
        (`NO_ACTUATOR`: it drives nothing)."""
        columns = [[NO_ACTUATOR] * self.width for _ in range(rows)]
        for k, entry in enumerate(self.driven.tolist()):
            columns[entry // self.width][entry % self.width] = self._column(k)
        return columns

    def _column(self, k: int) -> ActionColumn:
        """The wiring of driven actuator k."""
        model, ctrl = self._model, int(self.ctrl_index[k])
        named = {"actuator": actuator_name(model, ctrl), "ctrl": ctrl}
        if self.targets is None:
            half = float(self.ctrl_half[k])
            return ActionColumn(scale=half, offset=float(self.ctrl_low[k]) + half, **named)
        targets = self.targets
        joint = int(model.actuator_trnid[ctrl, 0])
        named |= {"scale": float(targets.scale[k]), "offset": float(targets.offset[k])}
        named["target"] = model.joint(joint).name
        if targets.pd:
            torque = (float(targets.low[k]), float(targets.high[k]))
            return ActionColumn(kp=targets.kp, kd=targets.kd, torque=torque, **named)
        low, high = (
            float(v) if np.isfinite(v) else None for v in (targets.low[k], targets.high[k])
        )
        servo = None
        if model.actuator_biastype[ctrl] == mujoco.mjtBias.mjBIAS_AFFINE:
            # a position servo: the gains the robot's motor driver must be given for it
            servo = (
                float(model.actuator_gainprm[ctrl, 0]),
                float(-model.actuator_biasprm[ctrl, 2]),
            )
        joint_range = None
        if model.jnt_limited[joint]:
            joint_range = (float(model.jnt_range[joint, 0]), float(model.jnt_range[joint, 1]))
        return ActionColumn(low=low, high=high, servo=servo, range=joint_range, **named)
