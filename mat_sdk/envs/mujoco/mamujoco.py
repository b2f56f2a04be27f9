"""Gymnasium-Robotics' MaMuJoCo (`mamujoco_v1`) behind the team interface.

So results on e.g. `mamujoco:HalfCheetah-6x1` compare directly with published MA-MuJoCo
numbers (the paper's MAT reaches about 9,000 there). Defaults follow the paper's set-up:
`agent_obsk=0` and a one-hot agent id appended to every observation.

`ManySegmentSwimmer-Kx2` and `ManySegmentAnt-Kx2` are families: one observation size for
every K, so one policy can serve any count. They default to `agent_obsk=1` and no one-hot id
(which would tie the observation size to K).

`pad_agents=M` is the official MAT code's answer to a changing count, kept as a baseline:
every K is padded to M agents whose observations are zero, whose actions are dropped and
who are inactive (`masks`), so the loss skips them; a one-hot id then has M entries.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import io
import math
import re
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path

import mujoco
import numpy as np

from mat_runtime.wiring_schema import NO_ACTUATOR, ActionColumn, AgentWiring, WiringSpec
from mat_sdk.envs.core.base import (
    ArrayTeam,
    checked_episode_limit,
    diverged,
    end_diverged,
    position_features,
    render_failed,
    restore_whole,
)
from mat_sdk.envs.core.checks import (
    is_real,
    saved_array,
    saved_whole_number,
    set_random_state,
    short,
)
from mat_sdk.envs.core.faults import Fault, faults_of
from mat_sdk.envs.mujoco.randomization import Randomization, Randomizer

PREFIX = "mamujoco:"
_ID = re.compile(r"mamujoco:(\w+)-(\w+)$")
FAMILIES = ("ManySegmentSwimmer", "ManySegmentAnt")  # any K: mamujoco:<family>-Kx2


@contextlib.contextmanager
def _asset_lock(needed: bool):
    """Hold a lock across processes while a family env is built: Gymnasium-Robotics writes
    each family's model to one fixed file inside its package and deletes it after loading,
    so two processes building the same K at once (env workers, parallel runs) collide."""
    if not needed:
        yield
        return
    with open(Path(tempfile.gettempdir()) / "mat_sdk-mamujoco-assets.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@functools.cache
def _family_width(scenario: str, agent_obsk: int) -> int:
    """The widest agent observation of a family: that of K = 3, whose middle agent has a
    neighbour on each side, as every inner agent of a longer chain has."""
    from gymnasium_robotics import mamujoco_v1

    with _asset_lock(True):
        env = mamujoco_v1.parallel_env(scenario, "3x2", agent_obsk=agent_obsk)
    width = max(env.observation_space(a).shape[0] for a in env.possible_agents)
    env.close()
    return width


class MaMuJoCoTeam(ArrayTeam):
    """A MaMuJoCo scenario with the array API of `RobotTeam` (obs padded to one size)."""

    action_type = "continuous"
    description = "Gymnasium-Robotics"

    @staticmethod
    def is_family(env_id: str) -> bool:
        """Whether the id names a scenario of a family (`FAMILIES`): any K, one obs size."""
        match = _ID.match(env_id)
        return bool(match) and match.group(1) in FAMILIES

    def __init__(
        self,
        env_id: str,
        *,
        faults: Iterable[Fault] | Mapping[str, str] | None = None,
        seed: int | None = None,
        agent_id: bool | None = None,
        agent_obsk: int | None = None,
        episode_limit: int | None = None,
        position: str | None = None,
        pad_agents: int | None = None,
        randomize: bool | Mapping | Randomization | None = None,
    ):
        # Its import prints a notice about Adroit envs, which this SDK never uses.
        with contextlib.redirect_stderr(io.StringIO()):
            from gymnasium_robotics import mamujoco_v1

        match = _ID.match(env_id)
        if not match:
            raise ValueError(f"MaMuJoCo ids look like 'mamujoco:HalfCheetah-6x1', got {env_id!r}")
        scenario, conf = match.groups()
        self.variable_count = scenario in FAMILIES
        if self.variable_count:
            self.description = "Gymnasium-Robotics, any K (agent_obsk=1, no one-hot id)"
        if agent_obsk is None:
            agent_obsk = 1 if self.variable_count else 0
        self.env_id = env_id
        try:
            with _asset_lock(self.variable_count):
                self._env = mamujoco_v1.parallel_env(scenario, conf, agent_obsk=agent_obsk)
        except Exception as error:  # "Custom env not implemented!", "UNKNOWN partitioning ..."
            raise ValueError(
                f"{env_id!r}: Gymnasium-Robotics' MaMuJoCo has no scenario {scenario!r} with "
                f"partition {conf!r} ({error}); e.g. mamujoco:HalfCheetah-6x1, mamujoco:Ant-4x2"
            ) from None
        self.possible_agents = list(self._env.possible_agents)
        self._real = len(self.possible_agents)  # agents of the scenario; the rest are padding
        self.agents = self.possible_agents + self._padding(pad_agents)
        self.n_agents = len(self.agents)
        self.agent_id = (not self.variable_count) if agent_id is None else bool(agent_id)
        widths = [self._env.action_space(a).shape[0] for a in self.possible_agents]
        self.action_widths = np.array(widths + [max(widths)] * (self.n_agents - self._real))
        self.action_width = int(self.action_widths.max())
        self.action_size = self.action_width
        self._raw_obs_dims = [self._env.observation_space(a).shape[0] for a in self.possible_agents]
        self._raw_obs_width = max(self._raw_obs_dims)
        if self.variable_count:  # K = 2 has no agent with two neighbours; pad to the family's
            self._raw_obs_width = max(self._raw_obs_width, _family_width(scenario, agent_obsk))
        self.obs_dim = self._raw_obs_width + (self.n_agents if self.agent_id else 0)
        self._positions = position_features(position, self._real)  # [agents, 0..2]
        self.obs_dim += self._positions.shape[1]
        self.state_dim = self._env.state().shape[0] if hasattr(self._env, "state") else 0
        spec_limit = self._env.single_agent_env.spec.max_episode_steps
        self.episode_limit = checked_episode_limit(episode_limit, spec_limit or 1000)
        self._action_mask = self._fault_mask(faults_of(faults))
        self.control_timestep = float(self._env.single_agent_env.unwrapped.dt)
        self._picture = None  # a dm_control Physics to draw frames with
        self._seed = seed
        self._steps = 0
        self._root_qpos = self._moving_root()
        self._start_x = math.nan  # the root's x at the episode's start (`travelled`)
        self.randomization = Randomization.parse(randomize)
        self._randomizer = None
        if self.randomization is not None:  # its observation is one signal, "obs"
            physics = self._env.single_agent_env.unwrapped
            self._randomizer = Randomizer(
                self.randomization, physics.model, physics.data, self.control_timestep,
                [("obs", self._real * self._raw_obs_width)], env_id,
                action_shape=self._action_mask.shape,
            )  # fmt: skip

    def _padding(self, pad_agents: int | None) -> list[str]:
        """The names of the padding agents `pad_agents` asks for (none if None); sets masks."""
        if pad_agents is None:
            return []
        if isinstance(pad_agents, bool) or not isinstance(pad_agents, int | np.integer):
            raise ValueError(f"pad_agents must be an integer agent count, got {pad_agents!r}")
        if pad_agents < self._real:
            raise ValueError(
                f"pad_agents={pad_agents} is fewer than the {self._real} agents of {self.env_id}"
            )
        count = int(pad_agents)
        self.masks = True
        self.active = np.array([1.0] * self._real + [0.0] * (count - self._real), np.float32)
        self.available = np.ones((count, 1), np.float32)  # continuous: no choices to mask
        return [f"pad_{row}" for row in range(self._real, count)]

    def reset(self, seed: int | None = None) -> np.ndarray:
        if seed is None and self._seed is not None:
            seed, self._seed = self._seed, None  # the first reset takes the constructor's seed
        obs, _ = self._env.reset(seed=seed)
        self._steps = 0
        self._start_x = self._root_x()
        if self._randomizer is not None:  # the robot of this episode (start noise: the env's own)
            self._randomizer.new_episode(self._random())
        return self._sensed(obs)

    def _moving_root(self) -> int | None:
        """The qpos index of the root's x where the scenario's robot moves along x (its first
        joint a free joint or a slide along x, as Gymnasium's locomotion tasks); else None."""
        model = self._env.single_agent_env.unwrapped.model
        if not model.njnt:
            return None
        root = model.jnt_type[0]
        along_x = root == mujoco.mjtJoint.mjJNT_SLIDE and np.allclose(model.jnt_axis[0], (1, 0, 0))
        return int(model.jnt_qposadr[0]) if root == mujoco.mjtJoint.mjJNT_FREE or along_x else None

    def _root_x(self) -> float:
        if self._root_qpos is None:
            return math.nan
        return float(self._env.single_agent_env.unwrapped.data.qpos[self._root_qpos])

    def travelled(self) -> float:
        """How far the robot moved along x in this episode (m; the distance the Gymnasium
        reward's forward velocity pays for); NaN for scenarios without a moving root."""
        return self._root_x() - self._start_x

    def _random(self) -> np.random.Generator:
        return self._env.single_agent_env.unwrapped.np_random

    def _sensed(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        packed = self._pack(obs)
        if self._randomizer is not None:
            raw = packed[: self._real, : self._raw_obs_width].reshape(-1).astype(np.float64)
            self._randomizer.noise(raw, self._random())
            packed[: self._real, : self._raw_obs_width] = raw.reshape(self._real, -1)
        return packed

    def advance(self, actions: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        # faults silence or weaken entries
        actions = np.clip(actions, -1.0, 1.0) * self._action_mask
        per_agent = {
            name: actions[row, : self.action_widths[row]]
            for row, name in enumerate(self.possible_agents)  # padding's actions are dropped
        }
        if self._randomizer is not None:  # a push now; the motors get a late action
            self._randomizer.push(self._random())
            late = self._randomizer.delay(actions)
            per_agent = {name: late[row, : self.action_widths[row]]
                         for row, name in enumerate(self.possible_agents)}  # fmt: skip
        physics = self._env.single_agent_env.unwrapped
        data, substep = physics.data, physics.model.opt.timestep
        time_before = data.time
        obs, rewards, terminations, truncations, _ = self._env.step(per_agent)
        self._steps += 1
        first = self.possible_agents[0]
        packed, reward = self._sensed(obs), float(rewards[first])
        if diverged(data, time_before, self.control_timestep, substep, reward):
            packed, reward = end_diverged(self.env_id, self._steps, packed)
            return packed, reward, False, True
        truncated = bool(truncations[first]) or self._steps >= self.episode_limit
        return packed, reward, bool(terminations[first]), truncated

    def _fault_mask(self, faults: tuple[Fault, ...]) -> np.ndarray:
        """`[n, action_width]`: each entry's torque fraction: 0 where a "zero" fault silences
        the entry's actuator, S where a "weak:S" fault weakens it (the action scaled: these
        are torque motors), else 1.

        A fault names an agent (all its actuators) or a joint by its MaMuJoCo label
        (`bfoot`), as for our own robots; "remove" is not offered, since a MaMuJoCo
        scenario fixes its team.
        """
        joints = {
            node.label: (row, col)
            for row, partition in enumerate(self._env.agent_action_partitions)
            for col, node in enumerate(partition)
        }
        mask = np.ones((self.n_agents, self.action_width))
        for fault in faults:
            name, strength = fault.target, fault.strength
            if fault.kind == "remove":
                raise ValueError(
                    f"MaMuJoCo faults support modes 'zero' and 'weak:S' only (a scenario fixes "
                    f"its team); got {fault}"
                )
            if name in self.agents:
                mask[self.agents.index(name)] = strength
            elif name in joints:
                mask[joints[name]] = strength
            else:
                raise ValueError(
                    f"fault names {name!r}, which is neither an agent nor an actuated joint of "
                    f"{self.env_id}; agents: {', '.join(self.agents)}; joints: {', '.join(joints)}"
                )
        return mask

    def wiring(self) -> WiringSpec:
        """How the policy's arrays map onto the robot (see `RobotTeam.wiring`): per agent the
        joints it drives, each action column as the MuJoCo ctrl it sets (Gymnasium writes the
        action to ctrl as is), and the control timestep. Gymnasium-Robotics builds the
        observations itself, so their layout is not described here."""
        model = self._env.single_agent_env.unwrapped.model
        agents = []
        for row, partition in enumerate(self._env.agent_action_partitions):
            ids = [int(node.act_ids) for node in partition]
            actuators = [model.actuator(i).name or f"#{i}" for i in ids]  # Ant's have no names
            action = [
                ActionColumn(actuator=name, ctrl=i, scale=1.0, offset=0.0)
                for name, i in zip(actuators, ids, strict=True)
            ]
            action += [NO_ACTUATOR] * (self.action_width - len(actuators))
            joints = tuple(node.label for node in partition)
            agents.append(AgentWiring(self.agents[row], tuple(actuators), joints, tuple(action)))
        for name in self.agents[self._real :]:  # padding drives nothing
            agents.append(AgentWiring(name, (), (), (NO_ACTUATOR,) * self.action_width))
        return WiringSpec(
            control_timestep=self.control_timestep,
            physics_timestep=float(model.opt.timestep),
            agents=tuple(agents),
        )

    def get_state(self) -> dict:

        env = self._env.single_agent_env.unwrapped
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        physics = np.empty(mujoco.mj_stateSize(env.model, spec))
        mujoco.mj_getState(env.model, env.data, physics, spec)
        return {
            "physics": physics,
            "random": env.np_random.bit_generator.state,
            "steps": self._steps,
            "start_x": self._start_x,
            **({"randomizer": self._randomizer.get_state()} if self._randomizer else {}),
        }

    def set_state(self, state: dict) -> None:
        """An episode as `get_state` saved it (a resumed run's env). Every value is checked
        before it is used, and a state refused part of the way leaves the env as it was."""
        restore_whole(self, state, self._restore)

    def _restore(self, state: dict) -> None:
        env = self._env.single_agent_env.unwrapped
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        size = mujoco.mj_stateSize(env.model, spec)
        physics = saved_array(state["physics"], (size,), "physics state")
        steps = saved_whole_number(state["steps"], "step count", self.episode_limit)
        start_x = state.get("start_x", math.nan)  # absent: saved before it was kept
        if not is_real(start_x) or math.isinf(start_x):
            raise ValueError(f"a saved start position must be a number, got {short(start_x)}")
        set_random_state(env.np_random, state["random"])
        if self._randomizer is not None:
            self._randomizer.set_state(state["randomizer"])
        mujoco.mj_setState(env.model, env.data, physics, spec)
        self._steps, self._start_x, self._seed = steps, float(start_x), None
        mujoco.mj_forward(env.model, env.data)

    def state(self) -> np.ndarray:
        return np.asarray(self._env.state(), dtype=np.float32)

    def render(self, height: int = 240, width: int = 320, camera_id: int = 0) -> np.ndarray:
        """An RGB frame `[height, width, 3]` from the model's camera `camera_id` (HalfCheetah's
        first camera tracks the robot; a model without cameras gets the free camera).

        Drawn by dm_control from a copy of the scene, as our robots are: dm_control picks its
        GL backend (MUJOCO_GL) at the first frame, where `mujoco.Renderer` would take the one
        in force when `mujoco` was first imported.
        """
        from dm_control.mujoco import Physics, wrapper

        env = self._env.single_agent_env.unwrapped
        try:
            if self._picture is None:
                self._picture = Physics.from_model(wrapper.MjModel(env.model))
            mujoco.mj_copyData(self._picture.data.ptr, env.model, env.data)
            camera = camera_id if env.model.ncam else -1
            return self._picture.render(height=height, width=width, camera_id=camera)
        except Exception as error:
            raise render_failed(error) from error

    def close(self) -> None:
        self._env.close()

    def _pack(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        packed = np.zeros((self.n_agents, self.obs_dim), dtype=np.float32)
        for row, name in enumerate(self.possible_agents):  # padding's rows stay zero
            packed[row, : self._raw_obs_dims[row]] = obs[name]
            if self.agent_id:
                packed[row, self._raw_obs_width + row] = 1.0
        if self._positions.shape[1]:
            packed[: self._real, -self._positions.shape[1] :] = self._positions
        return packed
