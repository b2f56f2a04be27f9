"""An env copy's place in a command curriculum (`terms.CommandCurriculum`): its level, and
how closely the robot has followed the command it was given."""

from __future__ import annotations

import math
from typing import Any

import mujoco
import numpy as np

from mat_sdk.envs.core.checks import saved_array, saved_whole_number
from mat_sdk.envs.mujoco.terms import CommandCurriculum
from mat_sdk.envs.mujoco.trunk import Trunk


class CurriculumProgress:
    """Level 0 at first. `follow` adds each step's tracking error (after the command's first
    `settle_steps`, while the robot gets going); `judge`, when the command ends, moves the
    level: up one when both mean errors are within tolerance, down one after a fall or when
    either error is over twice its tolerance (a command cut short by the episode's time
    limit is judged if a second of it was measured)."""

    def __init__(self, curriculum: CommandCurriculum, trunk: Trunk, settle_steps: int):
        self.curriculum, self.trunk, self.settle_steps = curriculum, trunk, settle_steps
        self.level = 0
        self._steps = 0  # since the command began
        self._errors = np.zeros(3)  # sums of the linear and yaw errors, and of steps counted

    @property
    def share(self) -> float:
        """How far along: 0 at the first level, 1 at the command's own ranges."""
        return self.level / self.curriculum.levels

    def follow(self, data: mujoco.MjData, command: np.ndarray) -> None:
        self._steps += 1
        if self._steps <= self.settle_steps:
            return
        velocity = self.trunk.velocity(data)
        errors = self._errors
        errors[0] += math.hypot(velocity[0] - command[0], velocity[1] - command[1])
        errors[1] += abs(float(self.trunk.angular_velocity(data)[2]) - command[2])
        errors[2] += 1.0

    def judge(self, fell: bool) -> None:
        """The command ended (a new one, or the episode's end): move the level, start over."""
        counted, tolerance = self._errors[2], self.curriculum.tolerance
        step = -1 if fell else 0
        if not fell and counted >= max(1, self.settle_steps):  # a second of it, at least
            linear, yaw = self._errors[:2] / counted
            if linear <= tolerance[0] and yaw <= tolerance[1]:
                step = 1
            elif linear > 2 * tolerance[0] or yaw > 2 * tolerance[1]:
                step = -1  # missed: else successes alone would climb to the top
        self.level = min(max(self.level + step, 0), self.curriculum.levels)
        self._steps = 0
        self._errors[:] = 0.0

    def get_state(self) -> dict[str, Any]:
        return {"level": self.level, "steps": self._steps, "errors": self._errors.copy()}

    def set_state(self, state: dict[str, Any]) -> None:
        levels = self.curriculum.levels
        level = saved_whole_number(state["level"], "command curriculum level", levels)
        steps = saved_whole_number(state["steps"], "command curriculum step count")
        errors = saved_array(state["errors"], (3,), "command curriculum errors", nonnegative=True)
        self.level, self._steps = level, steps
        self._errors[:] = errors
