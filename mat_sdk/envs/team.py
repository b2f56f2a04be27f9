"""A robot as a team of agents, stepped with arrays: the fast core under every env API.

`RobotTeam.step` takes actions `[n_agents, action_width]` and returns observations
`[n_agents, obs_dim]`. It steps MuJoCo directly (the way dm_control's `Physics.step` does)
and builds every observation with one gather from a precomputed index table, so the team
costs little more than the physics itself.

Observation of an agent, in order (each block zero-padded to the widest agent's):
own joints' qpos | own qvel | upstream neighbours' qpos | qvel | downstream qpos | qvel |
shared features (root height/orientation/velocities, task features) | one-hot agent id |
position (`base.POSITIONS`, when asked for).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from mat_sdk.envs.base import (
    NO_ACTUATOR,
    ArrayTeam,
    check_faults,
    checked_episode_limit,
    diverged,
    end_diverged,
    position_features,
    render_failed,
)
from mat_sdk.envs.decomposition import (
    actuator_joints,
    decompose,
    joint_dof_indices,
    joint_qpos_indices,
    root_feature_indices,
    root_joints,
)

if TYPE_CHECKING:
    from mat_sdk.envs.sources import RobotSpec

_FULL_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # includes ctrl and the solver's warmstart


def _actuator_name(model, actuator: int) -> str:
    """An actuator's name, or `#index` for an unnamed one."""
    return model.actuator(actuator).name or f"#{actuator}"


class RobotTeam(ArrayTeam):
    """A multi-agent robot with the array API. See `mat_sdk.envs.make` for the options."""

    action_type = "continuous"

    def __init__(
        self,
        spec: RobotSpec,
        faults: Mapping[str, str] | None = None,
        *,
        seed: int | None = None,
        agent_id: bool | None = None,
        hops: int | None = None,
        episode_limit: int | None = None,
        task: str | None = None,
        position: str | None = None,
    ):
        """Options left as None take the spec's (`RobotSpec.hops`, ...). `position` appends
        an identity that does not depend on the agent count (`base.POSITIONS`)."""
        self.spec = spec
        self.env_id = spec.env_id
        self._env = spec.load(seed, task)
        self.physics = self._env.physics
        self._task = self._env.task
        self._model, self._data = self.physics.model.ptr, self.physics.data.ptr
        self.control_timestep = self._env.control_timestep()
        self.substeps = round(self.control_timestep / self._model.opt.timestep)
        limit = spec.episode_limit if episode_limit is None else episode_limit
        self.episode_limit = checked_episode_limit(limit, self._env._step_limit)
        agent_id = spec.agent_id if agent_id is None else agent_id
        self.agent_id = (not spec.variable_count) if agent_id is None else bool(agent_id)

        self.variable_count = spec.variable_count
        self._positions = position_features(position, len(spec.groups))
        self.team = decompose(self._model, spec.groups, spec.hops if hops is None else hops)
        self.possible_agents = spec.names()
        self.faults = dict(faults or {})
        zeroed, removed = self._resolve_faults(self.faults)
        self.active = [i for i in range(len(self.team)) if i not in removed]
        self.agents = [self.possible_agents[i] for i in self.active]
        self.n_agents = len(self.active)
        self.action_widths = np.array([len(self.team[i].actuators) for i in self.active])
        self.action_width = max(len(a.actuators) for a in self.team)
        self.action_size = self.action_width  # the policy's action size
        self._reward = (
            spec.fast_reward if task is None and spec.fast_reward else self._task.get_reward
        )
        self._build_action_map(zeroed)
        self._build_observation_map()
        self._steps = 0

    # ---------------------------------------------------------------- set-up
    def joint_names(self, agent: int) -> list[str]:
        """MuJoCo names of the joints an agent drives."""
        return [self._model.joint(j).name for j in self.team[agent].joints]

    def _resolve_faults(self, faults: Mapping[str, str]) -> tuple[set[int], set[int]]:
        """Map `{agent or joint name: mode}` to zeroed actuators and removed agents."""
        zeroed: set[int] = set()
        removed: set[int] = set()
        check_faults(faults)
        for name, mode in faults.items():
            agents, actuators = self._fault_target(name)
            if mode == "remove":
                removed.update(agents)
            else:
                zeroed.update(actuators)
        if len(removed) == len(self.team):
            raise ValueError("faults remove every agent; at least one must stay")
        for agent in removed:
            zeroed.update(self.team[agent].actuators)
        return zeroed, removed

    def _fault_target(self, name: str) -> tuple[list[int], list[int]]:
        if name in self.possible_agents:
            agent = self.possible_agents.index(name)
            return [agent], list(self.team[agent].actuators)
        joint = mujoco.mj_name2id(self._model, mujoco.mjtObj.mjOBJ_JOINT, name)
        hits = [
            (i, a)
            for i, member in enumerate(self.team)
            for a in member.actuators
            if joint >= 0 and joint in actuator_joints(self._model, a)
        ]
        if not hits:
            joints = [n for i in range(len(self.team)) for n in self.joint_names(i)]
            raise ValueError(
                f"fault names {name!r}, which is neither an agent nor an actuated joint of "
                f"{self.spec.env_id}; agents: {', '.join(self.possible_agents)}; "
                f"joints: {', '.join(joints)}"
            )
        return sorted({i for i, _ in hits}), [a for _, a in hits]

    def _build_action_map(self, zeroed: set[int]) -> None:
        """Which entries of the `[n, action_width]` action array drive which actuator."""
        driven, actuators = [], []
        for row, agent in enumerate(self.active):
            for col, actuator in enumerate(self.team[agent].actuators):
                if actuator not in zeroed:
                    driven.append(row * self.action_width + col)
                    actuators.append(actuator)
        self._action_driven = np.array(driven, dtype=np.intp)
        self._ctrl_index = np.array(actuators, dtype=np.intp)
        low, high = self._model.actuator_ctrlrange[self._ctrl_index].T
        self._ctrl_low, self._ctrl_half = low, (high - low) / 2

    def _build_observation_map(self) -> None:
        """One index table that gathers every observation from [qpos | qvel | extra | 0 | 1]."""
        model = self._model
        nq, nv = model.nq, model.nv
        n_extra = len(self._extra_features())
        zero, one = nq + nv + n_extra, nq + nv + n_extra + 1
        constants = [0.0, 1.0]  # then each agent's position features, if any

        def qpos(joints):
            return [int(i) for j in joints for i in joint_qpos_indices(model, j)]

        def qvel(joints):
            return [nq + int(i) for j in joints for i in joint_dof_indices(model, j)]

        parts = {
            f"{field}.{kind}": [getter(getattr(member, field)) for member in self.team]
            for field in ("joints", "upstream", "downstream")
            for kind, getter in (("qpos", qpos), ("qvel", qvel))
        }
        widths = {name: max(len(entries) for entries in block) for name, block in parts.items()}
        root_qpos, root_qvel = root_feature_indices(model)
        shared = {}
        if self.spec.root_features:
            shared = {"root.qpos": root_qpos.tolist(), "root.qvel": (nq + root_qvel).tolist()}
        shared["task"] = list(range(nq + nv, nq + nv + n_extra))
        widths |= {name: len(entries) for name, entries in shared.items()}
        widths |= {"id": len(self.team) if self.agent_id else 0}
        widths |= {"position": self._positions.shape[1]}
        rows = []
        for agent in self.active:
            row = []
            for name, block in parts.items():
                row += block[agent] + [zero] * (widths[name] - len(block[agent]))
            for entries in shared.values():
                row += entries
            if self.agent_id:
                row += [one if i == agent else zero for i in range(len(self.team))]
            for value in self._positions[agent]:
                row.append(zero + len(constants))
                constants.append(float(value))
            rows.append(row)
        self._obs_index = np.array(rows, dtype=np.intp)
        self.obs_dim = self._obs_index.shape[1]
        # the name and columns of each feature, in order (every agent's row has the same)
        starts = np.cumsum([0, *widths.values()])
        self._features = [
            {"name": name, "start": int(start), "stop": int(start + width)}
            for (name, width), start in zip(widths.items(), starts, strict=False)
            if width
        ]
        horizontal = set(qpos(root_joints(model))) - set(root_qpos.tolist())
        kept_qpos = [i for i in range(nq) if i not in horizontal]
        self._state_index = np.array(
            [*kept_qpos, *range(nq, nq + nv), *range(nq + nv, nq + nv + n_extra)], dtype=np.intp
        )
        self.state_dim = len(self._state_index)
        self._constants = np.array(constants)

    def _extra_features(self) -> np.ndarray:
        features = self.spec.task_features
        return np.zeros(0) if features is None else features(self.physics)

    def task_features(self) -> np.ndarray:
        """The task's features now (e.g. a target's position), the `task` part of the
        observation source in `wiring()`; empty for tasks without them."""
        return np.asarray(self._extra_features(), dtype=np.float64)

    def wiring(self) -> dict:
        """How the policy's arrays map onto this robot, for a controller on the hardware:

        - per agent, the actuators and joints it drives and, per action column, the actuator
          it commands (its name and index in MuJoCo's ctrl) with
          `ctrl = offset + scale * clip(action, -1, 1)` (`NO_ACTUATOR`: none);
        - the observation: `obs[i, j] = source[index[i][j]]` with `source` the
          concatenation of qpos, qvel, the task features and `constants` (0, 1, positions),
          at the offsets in `source`, and the name and columns of each feature;
        - the control timestep, and where the observation normaliser is."""
        model, nq, nv = self._model, self._model.nq, self._model.nv
        n_task = len(self._extra_features())
        drives = dict(zip(self._action_driven.tolist(), range(len(self._ctrl_index)), strict=True))
        agents = []
        for row, agent in enumerate(self.active):
            action = []
            for col in range(self.action_width):
                k = drives.get(row * self.action_width + col)
                if k is None:
                    action.append(NO_ACTUATOR)
                    continue
                half, ctrl = float(self._ctrl_half[k]), int(self._ctrl_index[k])
                action.append(
                    {
                        "actuator": _actuator_name(model, ctrl),
                        "ctrl": ctrl,
                        "scale": half,
                        "offset": float(self._ctrl_low[k]) + half,
                    }
                )
            agents.append(
                {
                    "name": self.agents[row],
                    "actuators": [_actuator_name(model, a) for a in self.team[agent].actuators],
                    "joints": self.joint_names(agent),
                    "action": action,
                }
            )
        end = nq + nv + n_task
        return {
            "control_timestep": float(self.control_timestep),
            "physics_timestep": float(model.opt.timestep),
            "agents": agents,
            "observation": {
                "features": self._features,
                "source": {
                    "qpos": [0, nq],
                    "qvel": [nq, nq + nv],
                    "task": [nq + nv, end],
                    "constants": [end, end + len(self._constants)],
                },
                "constants": self._constants.tolist(),
                "index": self._obs_index.tolist(),
            },
        }

    # ---------------------------------------------------------------- episode
    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start an episode; a seed restarts the task's random stream (initial pose, target)."""
        if seed is not None and hasattr(self._task, "_random"):  # suite tasks' random stream
            self._task._random = np.random.RandomState(seed)
        with self.physics.reset_context():
            self._task.initialize_episode(self.physics)
        self._steps = 0
        return self.observe()

    def advance(self, actions: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        flat = actions.reshape(-1)[self._action_driven]  # a copy: clipped in place below
        np.minimum(flat, 1.0, out=flat)
        np.maximum(flat, -1.0, out=flat)
        self._data.ctrl[self._ctrl_index] = self._ctrl_low + (flat + 1.0) * self._ctrl_half
        time_before = self._data.time
        # dm_control's legacy step: positions and sensors are up to date for the reward.
        mujoco.mj_step2(self._model, self._data)
        if self.substeps > 1:
            mujoco.mj_step(self._model, self._data, self.substeps - 1)
        mujoco.mj_step1(self._model, self._data)
        self._steps += 1
        obs, reward = self.observe(), float(self._reward(self.physics))
        step, substep = self.control_timestep, self._model.opt.timestep
        if diverged(self._data, time_before, step, substep, reward):
            obs, reward = end_diverged(self.env_id, self._steps, obs)
            return obs, reward, False, True
        terminated = self._task.get_termination(self.physics) is not None
        return obs, reward, terminated, self._steps >= self.episode_limit

    def observe(self) -> np.ndarray:
        source = np.concatenate(
            (self._data.qpos, self._data.qvel, self._extra_features(), self._constants)
        )
        return source[self._obs_index].astype(np.float32)

    def get_state(self) -> dict:
        """Everything that decides the rest of the episode, to resume it exactly."""
        physics = np.empty(mujoco.mj_stateSize(self._model, _FULL_STATE))
        mujoco.mj_getState(self._model, self._data, physics, _FULL_STATE)
        return {
            "physics": physics,
            "geom_pos": self._model.geom_pos.copy(),  # tasks place targets here at reset
            "random": self._task._random.get_state(),
            "steps": self._steps,
        }

    def set_state(self, state: dict) -> None:
        mujoco.mj_setState(self._model, self._data, np.asarray(state["physics"]), _FULL_STATE)
        self._model.geom_pos[:] = state["geom_pos"]
        self._task._random.set_state(state["random"])
        self._steps = int(state["steps"])
        mujoco.mj_forward(self._model, self._data)

    def state(self) -> np.ndarray:
        """The global state: all joint positions (less horizontal root position) and velocities."""
        source = np.concatenate((self._data.qpos, self._data.qvel, self._extra_features()))
        return source[self._state_index].astype(np.float32)

    def render(self, height: int = 240, width: int = 320, camera_id: int = 0) -> np.ndarray:
        """An RGB frame `[height, width, 3]`; needs a GL backend (set MUJOCO_GL=egl or osmesa)."""
        try:
            return self.physics.render(height=height, width=width, camera_id=camera_id)
        except Exception as error:
            raise render_failed(error) from error
