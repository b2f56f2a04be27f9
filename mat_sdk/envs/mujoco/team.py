"""A robot as a team of agents, stepped with arrays: the fast core under every env API.

`RobotTeam.step` takes actions `[n_agents, action_width]` and returns observations
`[n_agents, obs_dim]`. It steps MuJoCo directly (the way dm_control's `Physics.step` does)
and builds every observation with one gather from a precomputed index table, so the team
costs little more than the physics itself.

Observation of an agent, in order (each block zero-padded to the widest agent's):
own joints' positions | velocities | upstream neighbours' positions | velocities |
downstream positions | velocities | shared features | own previous action (when observed) |
one-hot agent id | position (`base.POSITIONS`, when asked for); `observation_map.py` gathers
it from the robot's signals, `action_map.py` turns actions into controls, and `wiring()`
describes both for a controller.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from mat_runtime.wiring_schema import AgentWiring, WiringSpec
from mat_sdk.envs.core.base import (
    SETTLE_SECONDS,
    ArrayTeam,
    checked_episode_limit,
    diverged,
    end_diverged,
    position_features,
    render_failed,
    restore_whole,
)
from mat_sdk.envs.core.checks import saved_array, saved_whole_number, set_random_state
from mat_sdk.envs.core.faults import Fault, faults_of
from mat_sdk.envs.mujoco.action_map import ActionMap, actuator_name, resolve_faults
from mat_sdk.envs.mujoco.actuation import weaken
from mat_sdk.envs.mujoco.decomposition import decompose
from mat_sdk.envs.mujoco.observation_map import ObservationMap
from mat_sdk.envs.mujoco.randomization import Randomization, Randomizer
from mat_sdk.envs.mujoco.trunk import Trunk

if TYPE_CHECKING:
    from mat_sdk.envs.mujoco.sources import RobotSpec

_FULL_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # includes ctrl and the solver's warmstart


class RobotTeam(ArrayTeam):
    """A multi-agent robot with the array API. See `mat_sdk.envs.make` for the options."""

    action_type = "continuous"

    def __init__(
        self,
        spec: RobotSpec,
        *,
        faults: Iterable[Fault] | Mapping[str, str] | None = None,
        seed: int | None = None,
        agent_id: bool | None = None,
        hops: int | None = None,
        episode_limit: int | None = None,
        task: str | None = None,
        position: str | None = None,
        command: list[float] | None = None,
        randomize: bool | Mapping | Randomization | None = None,
    ):
        """Options left as None take the spec's (`RobotSpec.hops`, ...). `position` appends
        an identity that does not depend on the agent count (`base.POSITIONS`); `command`
        holds a robot with velocity commands at (vx, vy, yaw_rate) in every episode;
        `randomize` varies the robot per episode and step (`randomization.py`; false: off)."""
        self.spec = spec
        self.env_id = spec.env_id
        self._env = spec.load(seed, task)
        self.physics = self._env.physics
        self._task = self._env.task
        if command is not None:
            if not hasattr(self._task, "set_command"):
                raise ValueError(f"{spec.env_id} takes no command: it has no velocity commands")
            self._task.set_command(command)
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
        self.faults = faults_of(faults)
        zeroed, removed, weakened = resolve_faults(
            self._model, self.team, self.possible_agents, self.faults, spec.env_id
        )
        weaken(self._model, weakened)
        self.active = [i for i in range(len(self.team)) if i not in removed]
        self.agents = [self.possible_agents[i] for i in self.active]
        self.n_agents = len(self.active)
        self.action_widths = np.array([len(self.team[i].actuators) for i in self.active])
        self.action_width = max(len(a.actuators) for a in self.team)
        self.action_size = self.action_width  # the policy's action size
        self._reward = (
            spec.fast_reward if task is None and spec.fast_reward else self._task.get_reward
        )
        self.reward_terms = tuple(getattr(self._task, "reward_terms", ()))
        scale = getattr(self._task, "robot_scale", None)  # from_mjcf tasks with terms
        self.actions = ActionMap(
            self._model, self.team, self.active, self.action_width, zeroed, spec.actions,
            getattr(self._task, "start_qpos", self._model.qpos0),
            None if scale is None else scale.torque,
        )  # fmt: skip
        # every driven actuator's action, as the task's terms and observations see it
        self._record = getattr(self._task, "record_action", None)
        self._end_step = getattr(self._task, "end_step", None)
        self.observations = ObservationMap(
            spec, self.physics, self._task, self.team, self.active, self.possible_agents,
            self.agent_id, self._positions, self.actions,
        )  # fmt: skip
        self.obs_dim, self.state_dim = self.observations.obs_dim, self.observations.state_dim
        given = spec.randomize if randomize is None else randomize
        self.randomization = Randomization.parse(given)
        self._randomizer = None
        if self.randomization is not None:
            sources = [(signal.name, signal.size) for signal in self.observations.signals]
            self._randomizer = Randomizer(
                self.randomization, self._model, self._data, self.control_timestep, sources,
                spec.env_id, action_shape=(len(self.actions.driven),),
            )  # fmt: skip
        self._steps = 0
        try:  # a floating base, whose forward travel `travelled` measures
            self._base = Trunk(self._model)
        except ValueError:
            self._base = None
        self._start = self._base_position()
        self._tracked = np.zeros(4)  # sums of vx, vy, yaw rate and their count (`tracking`)
        self._settle_steps = round(SETTLE_SECONDS / self.control_timestep)

    # ---------------------------------------------------------------- set-up
    def joint_names(self, agent: int) -> list[str]:
        """MuJoCo names of the joints an agent drives."""
        return [self._model.joint(j).name for j in self.team[agent].joints]

    def task_features(self) -> np.ndarray:
        """The task's features now (e.g. a target's position), the `task` part of the
        observation source in `wiring()`; empty for tasks without them."""
        return np.asarray(self.observations.task_features(), dtype=np.float64)

    def wiring(self) -> WiringSpec:
        """How the policy's arrays map onto this robot, for a controller on the hardware
        (`mat_runtime.wiring_schema` gives the layout):

        - per agent, the actuators and joints it drives and, per action column, the actuator
          it commands (its name and index in MuJoCo's ctrl) with
          `ctrl = offset + scale * clip(action, -1, 1)`, clipped to [low, high] where given
          (`NO_ACTUATOR`: none). With joint targets the value is the joint's target around
          the start pose; a torque motor's column also gives the PD gains kp, kd that turn
          the target into its torque on the robot;
        - the observation: `obs[i, j] = (source - offset)[index[i][j]]` with `source` the
          concatenation of the named signals and `constants` (0, 1, positions), at the
          ranges in `source`; `signals` names each signal's columns; `offset` (when present)
          holds the start pose under `joint_pos`; the name and columns of each feature;
        - per joint-target column, the joint's range and, for a position servo, its gains
          [kp, kd] (what a robot's motor driver must be given to act as the model did);
        - the velocity commands' trained ranges, for a robot that takes them;
        - the control timestep, and where the observation normaliser is."""
        columns = self.actions.columns(len(self.active))
        agents = tuple(
            AgentWiring(
                name=self.agents[row],
                actuators=tuple(actuator_name(self._model, a) for a in self.team[agent].actuators),
                joints=tuple(self.joint_names(agent)),
                action=tuple(columns[row]),
            )
            for row, agent in enumerate(self.active)
        )
        commands = getattr(getattr(self._task, "recipe", None), "commands", None)
        return WiringSpec(
            control_timestep=float(self.control_timestep),
            physics_timestep=float(self._model.opt.timestep),
            agents=agents,
            observation=self.observations.layout(),
            # the ranges the policy was trained on, for a controller
            commands={}
            if commands is None
            else {name: tuple(getattr(commands, name)) for name in commands.names},
        )

    # ---------------------------------------------------------------- episode
    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start an episode; a seed restarts the task's random stream (initial pose, target)."""
        if seed is not None and hasattr(self._task, "_random"):  # suite tasks' random stream
            self._task._random = np.random.RandomState(seed)
        randomizer, random = self._randomizer, self._task._random
        if randomizer is not None:
            randomizer.new_episode(random)
        with self.physics.reset_context():
            self._task.initialize_episode(self.physics)
            if randomizer is not None:
                randomizer.perturb_start(random)
        self._steps = 0
        self._start = self._base_position()
        self._tracked[:] = 0.0
        return self._sensed()

    def _base_position(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A floating base's horizontal position and heading (unit vector), else None."""
        if self._base is None:
            return None
        heading = self._data.xmat[self._base.body].reshape(3, 3)[:2, 0]
        position = self._data.qpos[self._base.qpos : self._base.qpos + 2].copy()
        return position, heading / max(float(np.linalg.norm(heading)), 1e-9)

    def term_values(self) -> np.ndarray:
        return self._task.term_values if self.reward_terms else np.zeros(0)

    def travelled(self) -> float:
        if self._start is None:
            return math.nan
        position, heading = self._start
        return float((self._data.qpos[self._base.qpos : self._base.qpos + 2] - position) @ heading)

    def tracking(self) -> np.ndarray:
        count = self._tracked[3]
        return self._tracked[:3] / count if count else np.full(3, math.nan)

    def command_level(self) -> float:
        curriculum = getattr(self._task, "curriculum", None)
        return math.nan if curriculum is None else curriculum.share

    def _track(self) -> None:
        """Add this step's velocity in the heading's frame to `tracking`'s sums."""
        base, data = self._base, self._data
        r = data.xmat[base.body].tolist()  # row-major 3 x 3; plain floats: a per-step cost
        vx, vy, _, wx, wy, wz = data.qvel[base.qvel : base.qvel + 6].tolist()
        hx, hy = r[0], r[3]  # the base's x axis, horizontal part
        norm = max(math.hypot(hx, hy), 1e-9)
        tracked = self._tracked
        tracked[0] += (vx * hx + vy * hy) / norm
        tracked[1] += (vy * hx - vx * hy) / norm
        tracked[2] += r[6] * wx + r[7] * wy + r[8] * wz  # the world z of the body's rates
        tracked[3] += 1.0

    def advance(self, actions: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        actuation = self.actions
        flat = actions.reshape(-1)[actuation.driven]  # a copy: clipped in place below
        np.minimum(flat, 1.0, out=flat)
        np.maximum(flat, -1.0, out=flat)
        if self._record is not None:
            self._record(actuation.ctrl_index, flat)
        if self._randomizer is not None:  # a push now; the motors get a late action
            self._randomizer.push(self._task._random)
            flat = self._randomizer.delay(flat)
        time_before = self._data.time
        ctrl, targets = actuation.ctrl_index, actuation.targets
        if targets is None:
            self._data.ctrl[ctrl] = actuation.ctrl_low + (flat + 1.0) * actuation.ctrl_half
            self._physics_step()
        elif not targets.pd:
            self._data.ctrl[ctrl] = np.clip(targets.targets(flat), targets.low, targets.high)
            self._physics_step()
        else:  # a PD layer at the physics rate turns the targets into torques
            goal = targets.targets(flat)
            for substep in range(self.substeps):
                self._data.ctrl[ctrl] = targets.torques(self._data, goal)
                self._physics_step(1, first=substep == 0, last=substep == self.substeps - 1)
        self._steps += 1
        if self._base is not None and self._steps > self._settle_steps:
            self._track()
        reward = float(self._reward(self.physics))
        if self._end_step is not None:  # e.g. a new velocity command, seen in this obs
            self._end_step()
        obs = self._sensed()
        step, substep = self.control_timestep, self._model.opt.timestep
        if diverged(self._data, time_before, step, substep, reward):
            obs, reward = end_diverged(self.env_id, self._steps, obs)
            return obs, reward, False, True
        terminated = self._task.get_termination(self.physics) is not None
        return obs, reward, terminated, self._steps >= self.episode_limit

    def _physics_step(self, substeps: int | None = None, first=True, last=True) -> None:
        """`substeps` physics steps the way dm_control's legacy step takes them: the first
        finishes the step the last `mj_step1` began, and the last begins the next one, so
        positions and sensors are up to date for the reward."""
        substeps = self.substeps if substeps is None else substeps
        if first:
            mujoco.mj_step2(self._model, self._data)
            substeps -= 1
        if substeps > 0:
            mujoco.mj_step(self._model, self._data, substeps)
        if last:
            mujoco.mj_step1(self._model, self._data)

    def observe(self) -> np.ndarray:
        """The observation of the state now, `[n_agents, obs_dim]` (without sensor noise)."""
        observations = self.observations
        return observations.observation(observations.source())

    def _sensed(self) -> np.ndarray:
        """The observation as the agents sense it: with this step's noise, when randomized."""
        observations = self.observations
        source = observations.source()
        if self._randomizer is not None:
            self._randomizer.noise(source, self._task._random)
        return observations.observation(source)

    def get_state(self) -> dict:
        """Everything that decides the rest of the episode, to resume it exactly."""
        physics = np.empty(mujoco.mj_stateSize(self._model, _FULL_STATE))
        mujoco.mj_getState(self._model, self._data, physics, _FULL_STATE)
        return {
            "physics": physics,
            "geom_pos": self._model.geom_pos.copy(),  # tasks place targets here at reset
            "random": self._task._random.get_state(),
            "steps": self._steps,
            **({"task": self._task.get_state()} if hasattr(self._task, "get_state") else {}),
            **({"start": list(self._start)} if self._start is not None else {}),
            **({"randomizer": self._randomizer.get_state()} if self._randomizer else {}),
        }

    def set_state(self, state: dict) -> None:
        """An episode as `get_state` saved it (a resumed run's env). Every value is checked
        before it is used, and a state refused part of the way leaves the env as it was."""
        restore_whole(self, state, self._restore)

    def _restore(self, state: dict) -> None:
        model = self._model
        size = mujoco.mj_stateSize(model, _FULL_STATE)
        physics = saved_array(state["physics"], (size,), "physics state")
        geom_pos = saved_array(state["geom_pos"], (model.ngeom, 3), "geom placement")
        steps = saved_whole_number(state["steps"], "step count", self.episode_limit)
        start = self._start
        if start is not None and "start" in state:  # absent: saved before it was kept
            saved = state["start"]
            if len(saved) != len(start):
                raise ValueError(f"a saved start pose must be {len(start)} arrays")
            start = tuple(
                saved_array(value, own.shape, "start pose")
                for value, own in zip(saved, start, strict=True)
            )
        set_random_state(self._task._random, state["random"])
        mujoco.mj_setState(model, self._data, physics, _FULL_STATE)
        model.geom_pos[:] = geom_pos
        self._steps = steps
        if "task" in state:
            self._task.set_state(state["task"])
        self._start = start
        if self._randomizer is not None:
            self._randomizer.set_state(state["randomizer"])
        mujoco.mj_forward(model, self._data)

    def state(self) -> np.ndarray:
        """The global state: all joint positions (less horizontal root position) and velocities."""
        return self.observations.state()

    def render(self, height: int = 240, width: int = 320, camera_id: int = 0) -> np.ndarray:
        """An RGB frame `[height, width, 3]`; needs a GL backend (set MUJOCO_GL=egl or osmesa).
        A model without cameras is filmed by a free camera that follows the robot."""
        try:
            if self._model.ncam == 0:
                return self._follow(height, width)
            return self.physics.render(height=height, width=width, camera_id=camera_id)
        except Exception as error:
            raise render_failed(error) from error

    def _follow(self, height: int, width: int) -> np.ndarray:
        """A frame from a camera that tracks the robot's root body from the side and above."""
        renderer = getattr(self, "_renderer", None)
        if renderer is None or (renderer.height, renderer.width) != (height, width):
            renderer = self._renderer = mujoco.Renderer(self._model, height, width)
        camera = mujoco.MjvCamera()
        camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        camera.trackbodyid = self._base.body if self._base is not None else 1
        camera.distance = 1.2 * float(self._model.stat.extent)
        camera.azimuth, camera.elevation = 120.0, -15.0
        renderer.update_scene(self._data, camera)
        return renderer.render()
