"""Which joints each agent drives and observes, read from the compiled MuJoCo model.

A layout names the actuators each agent commands. Everything else is derived from the model:
an actuator's transmission gives the joints it drives (directly, or through the joints a
tendon couples), and the body tree gives each agent's neighbourhood. Nothing here is a
hand-typed index list, so a decomposition stays right when the model changes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

# The model stores enums as plain ints; compare against ints.
_FREE, _BALL, _SLIDE, _HINGE = (
    int(mujoco.mjtJoint.mjJNT_FREE),
    int(mujoco.mjtJoint.mjJNT_BALL),
    int(mujoco.mjtJoint.mjJNT_SLIDE),
    int(mujoco.mjtJoint.mjJNT_HINGE),
)
_JOINT_QPOS_WIDTH = {_FREE: 7, _BALL: 4, _SLIDE: 1, _HINGE: 1}
_JOINT_DOF_WIDTH = {_FREE: 6, _BALL: 3, _SLIDE: 1, _HINGE: 1}
_TRN_JOINT, _TRN_JOINT_IN_PARENT, _TRN_TENDON = (
    int(mujoco.mjtTrn.mjTRN_JOINT),
    int(mujoco.mjtTrn.mjTRN_JOINTINPARENT),
    int(mujoco.mjtTrn.mjTRN_TENDON),
)
_WRAP_JOINT = int(mujoco.mjtWrap.mjWRAP_JOINT)


@dataclass(frozen=True)
class AgentJoints:
    """One agent's share of the robot, as MuJoCo ids."""

    actuators: tuple[int, ...]
    joints: tuple[int, ...]  # driven by this agent's actuators
    upstream: tuple[int, ...]  # neighbour joints toward the root
    downstream: tuple[int, ...]  # the other neighbour joints (children, siblings)


def actuator_joints(model: mujoco.MjModel, actuator: int) -> list[int]:
    """Joints that an actuator drives: its own joint, or every joint its tendon couples."""
    kind = int(model.actuator_trntype[actuator])
    target = int(model.actuator_trnid[actuator, 0])
    if kind in (_TRN_JOINT, _TRN_JOINT_IN_PARENT):
        return [target]
    if kind == _TRN_TENDON:
        first, count = model.tendon_adr[target], model.tendon_num[target]
        wraps = range(first, first + count)
        return [int(model.wrap_objid[w]) for w in wraps if model.wrap_type[w] == _WRAP_JOINT]
    name = model.actuator(actuator).name
    raise ValueError(f"actuator {name!r} has a transmission this SDK cannot decompose ({kind})")


def root_joints(model: mujoco.MjModel) -> list[int]:
    """Joints of the bodies attached to the world: the robot's free root, not a limb."""
    return [j for j in range(model.njnt) if model.body_parentid[model.jnt_bodyid[j]] == 0]


def _body_path_to_root(model: mujoco.MjModel, body: int) -> list[int]:
    path = []
    while body != 0:
        path.append(body)
        body = int(model.body_parentid[body])
    return path


# A neighbourhood wider than any robot's body tree is deep; a larger recorded value is an error.
MAX_HOPS = 64


def _bodies_within(model: mujoco.MjModel, start: set[int], hops: int) -> dict[int, int]:
    """Breadth-first search over the body tree (parent and child edges): body -> hop count."""
    children: dict[int, list[int]] = {}
    for body in range(1, model.nbody):
        children.setdefault(int(model.body_parentid[body]), []).append(body)
    distance = dict.fromkeys(start, 0)
    frontier = sorted(start)
    for hop in range(1, hops + 1):
        nxt = []
        for body in frontier:
            for other in [int(model.body_parentid[body]), *children.get(body, [])]:
                if other != 0 and other not in distance:
                    distance[other] = hop
                    nxt.append(other)
        frontier = nxt
        if not frontier:  # the whole tree is within reach: more hops change nothing
            break
    return distance


def decompose(
    model: mujoco.MjModel, groups: Sequence[Sequence[str]], hops: int = 1
) -> list[AgentJoints]:
    """Resolve actuator-name groups into each agent's driven and neighbouring joints.

    Neighbours are the non-root joints on bodies at most `hops` edges away in the body tree
    (hop 0: other joints on the agent's own bodies). They are split into the joints toward
    the root and the rest, so that a slot keeps its meaning across robots of a family.
    """
    if isinstance(hops, bool) or not isinstance(hops, int) or not 0 <= hops <= MAX_HOPS:
        raise ValueError(f"hops must be an integer in 0..{MAX_HOPS}, got {str(hops)[:40]}")
    roots = set(root_joints(model))
    agents = []
    for group in groups:
        actuators = []
        for name in group:
            actuator = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, name)
            if actuator < 0:
                raise ValueError(f"the model has no actuator named {name!r}")
            actuators.append(actuator)
        joints = list(dict.fromkeys(j for a in actuators for j in actuator_joints(model, a)))
        own_bodies = {int(model.jnt_bodyid[j]) for j in joints}
        near = _bodies_within(model, own_bodies, hops)
        ancestors = {b for body in own_bodies for b in _body_path_to_root(model, body)}
        ancestors -= own_bodies
        neighbours = sorted(
            (j for j in range(model.njnt) if model.jnt_bodyid[j] in near),
            key=lambda j: (near[int(model.jnt_bodyid[j])], j),
        )
        neighbours = [j for j in neighbours if j not in roots and j not in joints]
        agents.append(
            AgentJoints(
                actuators=tuple(actuators),
                joints=tuple(joints),
                upstream=tuple(j for j in neighbours if model.jnt_bodyid[j] in ancestors),
                downstream=tuple(j for j in neighbours if model.jnt_bodyid[j] not in ancestors),
            )
        )
    return agents


def joint_qpos_indices(model: mujoco.MjModel, joint: int) -> np.ndarray:
    start = int(model.jnt_qposadr[joint])
    return np.arange(start, start + _JOINT_QPOS_WIDTH[int(model.jnt_type[joint])])


def joint_dof_indices(model: mujoco.MjModel, joint: int) -> np.ndarray:
    start = int(model.jnt_dofadr[joint])
    return np.arange(start, start + _JOINT_DOF_WIDTH[int(model.jnt_type[joint])])


def root_feature_indices(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """qpos and qvel indices of the root joints, leaving out horizontal position.

    Where the robot is on the floor does not change what it should do next; its height,
    orientation and velocities do.
    """
    qpos, qvel = [], []
    for joint in root_joints(model):
        kind = int(model.jnt_type[joint])
        index = joint_qpos_indices(model, joint)
        if kind == _FREE:
            index = index[2:]  # keep z and the orientation quaternion
        elif kind == _SLIDE and abs(model.jnt_axis[joint][2]) < 0.5:
            index = index[:0]  # a horizontal slide: absolute position
        qpos.extend(index)
        qvel.extend(joint_dof_indices(model, joint))
    return np.asarray(qpos, dtype=np.intp), np.asarray(qvel, dtype=np.intp)
