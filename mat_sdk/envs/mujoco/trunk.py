"""The floating base of a legged robot, as its IMU and a motion capture system would see it.

Read-only views of MuJoCo's state that observation features and reward terms share: the
base's orientation, gravity and velocities in its own frame (what an IMU measures), its height
and world-frame velocity (what only a simulator knows), and which geoms touch something.
"""

from __future__ import annotations

import mujoco
import numpy as np

DOWN = np.array([0.0, 0.0, -1.0])


class Trunk:
    """The robot's free-floating base (its one free joint), and an IMU frame on it: a site,
    or the base body itself."""

    def __init__(self, model: mujoco.MjModel, imu: str | None = None):
        free = [
            j
            for j in range(model.njnt)
            if int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)
        ]
        if len(free) != 1:
            raise ValueError(
                f"a legged robot's base is its one free joint; the model has {len(free)} free "
                "joints"
            )
        joint = free[0]
        self.body = int(model.jnt_bodyid[joint])
        self.qpos = int(model.jnt_qposadr[joint])  # x y z, then the quaternion w x y z
        self.qvel = int(model.jnt_dofadr[joint])  # world linear, then local angular velocity
        self.site = -1
        if imu is not None:
            self.site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, imu)
            if self.site < 0 and mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, imu) < 0:
                sites = [model.site(i).name for i in range(model.nsite)]
                raise ValueError(
                    f"the IMU frame {imu!r} is neither a site nor a body of the model; its "
                    f"sites: {', '.join(sites) or 'none'}"
                )

    def rotation(self, data: mujoco.MjData) -> np.ndarray:
        """The IMU frame's orientation in the world, 3 x 3 (columns: its axes)."""
        if self.site >= 0:
            return data.site_xmat[self.site].reshape(3, 3)
        return data.xmat[self.body].reshape(3, 3)

    def gravity(self, data: mujoco.MjData) -> np.ndarray:
        """The direction of gravity in the IMU frame: (0, 0, -1) when level."""
        return self.rotation(data).T @ DOWN

    def angular_velocity(self, data: mujoco.MjData) -> np.ndarray:
        """The base's angular velocity in the IMU frame (what a gyro measures), rad/s."""
        local = data.qvel[self.qvel + 3 : self.qvel + 6]  # in the base body's frame
        world = data.xmat[self.body].reshape(3, 3) @ local
        return self.rotation(data).T @ world

    def velocity(self, data: mujoco.MjData) -> np.ndarray:
        """The base's linear velocity in the IMU frame, m/s (privileged: a simulator's)."""
        return self.rotation(data).T @ data.qvel[self.qvel : self.qvel + 3]

    def world_velocity(self, data: mujoco.MjData) -> np.ndarray:
        return data.qvel[self.qvel : self.qvel + 3]

    def height(self, data: mujoco.MjData) -> float:
        """The base's height above the world's origin, m (privileged)."""
        return float(data.qpos[self.qpos + 2])


def geom_ids(model: mujoco.MjModel, names: tuple[str, ...], what: str) -> list[np.ndarray]:
    """For each name, the ids of that geom, or of every geom of that body; ValueError naming a
    name that is neither."""
    groups = []
    for name in names:
        geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name) if name else -1
        if geom >= 0:
            groups.append(np.array([geom]))
            continue
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name) if name else -1
        if body < 0:
            raise ValueError(f"{what} {name!r} is neither a geom nor a body of the model")
        groups.append(np.flatnonzero(model.geom_bodyid == body))
    return groups


class Contacts:
    """Which of some geoms or bodies (by name) touch anything now: 1.0 or 0.0 each."""

    def __init__(self, model: mujoco.MjModel, names: tuple[str, ...], what: str = "contact"):
        self.owner = np.full(model.ngeom + 1, len(names))  # the group of each geom; +1: none
        for k, group in enumerate(geom_ids(model, names, what)):
            self.owner[group] = k
        self._touched = np.zeros(len(names) + 1)

    def read(self, data: mujoco.MjData) -> np.ndarray:
        contacts = data.contact
        self._touched[:] = 0.0
        self._touched[self.owner[contacts.geom1]] = 1.0
        self._touched[self.owner[contacts.geom2]] = 1.0
        return self._touched[:-1]
