"""Your own robot as a team: any dm_control environment, or a bare MJCF model plus a reward.

    spec = envs.from_mjcf("arm.xml", {"shoulder": ["shoulder"], "hand": ["elbow", "wrist"]},
                          reward=reach_reward)
    team = spec.build(seed=0)                      # an ArrayTeam, like any built-in robot
    Trainer(spec)                                  # or give tools the id "my_module:my_function"

A layout lists the agents, each a list of actuator names. Everything else (driven joints,
neighbourhoods, root features, faults, state, rendering) is derived from the compiled model,
the same way for the built-in robots, which are `RobotSpec`s too (`robots.py`).
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from dm_control.rl import control

from mat_sdk.envs.core.base import user_call
from mat_sdk.envs.core.checks import finite_range, is_real
from mat_sdk.envs.core.recipe import TrainingRecipe
from mat_sdk.envs.mujoco import terms
from mat_sdk.envs.mujoco.actuation import JointTargets
from mat_sdk.envs.mujoco.features import Observation
from mat_sdk.envs.mujoco.model_task import ModelEnvironment
from mat_sdk.envs.mujoco.randomization import Randomization

Layout = Sequence[Sequence[str]] | Mapping[str, Sequence[str]]
# Physics steps per env step at most: more is no control rate, and one env step would run
# for minutes without answering Ctrl-C.
MAX_SUBSTEPS = 1000


@dataclass(frozen=True)
class RobotSpec:
    """How to build one multi-agent robot: its dm_control environment and its agents.

    `env_factory(seed)` returns a fresh `control.Environment` whose task draws its randomness
    from `seed`. It must be picklable (a module-level function or class instance) for env
    worker processes to build their own copies.
    """

    env_id: str
    env_factory: Callable[[int | None], control.Environment]
    groups: tuple[tuple[str, ...], ...]  # actuator names, one tuple per agent
    agent_names: tuple[str, ...] = ()  # default agent_0, agent_1, ...
    hops: int = 1  # neighbourhood radius in the kinematic tree
    agent_id: bool | None = None  # one-hot id; None: on, except for variable-count families
    episode_limit: int | None = None  # None: the environment's own time limit
    variable_count: bool = False  # a family served by one policy for any agent count
    root_features: bool = True  # root height/orientation/velocity in every observation
    task_features: Callable[[control.Physics], np.ndarray] | None = None
    # observations from the hardware's signals instead of the raw joint state (features.py)
    observation: Observation | None = None
    actions: JointTargets | None = None  # actions as joint targets (actuation.py)
    randomize: Randomization | None = None  # per-episode robot differences (randomization.py)
    # The task's reward in closed form, for speed; a test holds it equal to the task's.
    fast_reward: Callable[[control.Physics], float] | None = None
    description: str = ""
    recipe: TrainingRecipe | None = None  # the PPO settings the task trains with (recipe.py)

    def names(self) -> list[str]:
        return list(self.agent_names) or [f"agent_{i}" for i in range(len(self.groups))]

    def load(self, seed: int | None, task: str | None = None) -> control.Environment:
        """Build the dm_control environment (physics + task) with its own random stream."""
        factory = self.env_factory
        if task is not None:
            with_task = getattr(factory, "with_task", None)
            if with_task is None:
                raise ValueError(
                    f"{self.env_id}: the task option picks another dm_control suite task of a "
                    "built-in robot; this robot's environment is its own factory's"
                )
            factory = with_task(task)
        return factory(seed)

    def build(self, **options: Any):
        """The team (`RobotTeam`); options as `mat_sdk.envs.make_team` takes them."""
        from mat_sdk.envs.mujoco.team import RobotTeam

        return RobotTeam(self, **options)

    def renamed(self, env_id: str) -> RobotSpec:
        return replace(self, env_id=env_id)


def from_dm_control(
    env_factory: Callable[[int | None], control.Environment],
    layout: Layout,
    *,
    hops: int = 1,
    agent_id: bool = True,
    episode_limit: int | None = None,
    root_features: bool = True,
    observation: Observation | None = None,
    actions: JointTargets | None = None,
    env_id: str | None = None,
    description: str = "",
) -> RobotSpec:
    """A team over any dm_control environment: a suite task, or your own Task on your model.

    `layout` lists the agents' actuator names (a list of lists, or a dict agent name ->
    actuator names). It is checked against the model now; a mistake raises `ValueError`.
    `observation` and `actions`: as in `from_mjcf`.
    """
    if not callable(env_factory):
        raise ValueError(f"env_factory must be a function of a seed, got {env_factory!r}")
    names, groups = _split_layout(layout)
    if isinstance(env_factory, ModelEnvironment):  # ours (from_mjcf): errors say what is wrong
        environment = env_factory(0)
    else:
        environment = user_call(env_factory, "environment factory", 0)
    if not isinstance(environment, control.Environment):
        raise ValueError(
            f"{_name_of(env_factory)}(seed) must return a dm_control control.Environment, got "
            f"{type(environment).__name__}"
        )
    check_layout(environment.physics.model.ptr, groups)
    if isinstance(hops, bool) or not isinstance(hops, int) or hops < 0:
        raise ValueError(f"hops must be an integer >= 0, got {hops!r}")
    for value, kind, name in ((observation, Observation, "observation"),
                              (actions, JointTargets, "actions")):  # fmt: skip
        if value is not None and not isinstance(value, kind):
            raise ValueError(f"{name} must be an envs.{kind.__name__} or None, got {value!r}")
    spec = RobotSpec(
        env_id or f"dm_control:{_name_of(env_factory)}",
        env_factory,
        groups,
        agent_names=names,
        hops=hops,
        agent_id=agent_id,
        episode_limit=episode_limit,
        root_features=root_features,
        observation=observation,
        actions=actions,
        description=description or f"{len(groups)} agents over {_name_of(env_factory)}",
    )
    unused = [
        name for name in _all_actuators(environment) if name not in {a for g in groups for a in g}
    ]
    if unused:
        warnings.warn(
            f"{spec.env_id}: the layout leaves actuators {unused} to no agent; they stay at "
            "their start control",
            UnusedActuators,
            stacklevel=2,
        )
    if observation is not None or actions is not None:
        spec.build()  # refuse what the signals or targets cannot use, now
    return spec


class UnusedActuators(UserWarning):
    """A layout leaves some of the model's actuators to no agent."""


def _all_actuators(environment: control.Environment) -> list[str]:
    model = environment.physics.model.ptr
    return [model.actuator(i).name or f"#{i}" for i in range(model.nu)]


def check_layout(model, groups: Sequence[Sequence[str]]) -> None:
    """Refuse a layout that does not fit the model, naming the problem."""
    import mujoco

    actuators = [model.actuator(i).name for i in range(model.nu)]
    if not actuators:
        raise ValueError("the model has no actuators: nothing for agents to drive")
    if not groups:
        raise ValueError("the layout has no agents; list each agent's actuator names")
    owner: dict[str, int] = {}
    for agent, group in enumerate(groups):
        if not group:
            raise ValueError(f"agent {agent} of the layout drives no actuator")
        for name in group:
            if not isinstance(name, str) or not name:
                raise ValueError(
                    f"agent {agent} of the layout names an actuator by {name!r}; name each "
                    "actuator by its (non-empty) MJCF name"
                )
            if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, name) < 0:
                raise ValueError(
                    f"the model has no actuator named {name!r}; its actuators: "
                    f"{', '.join(actuators)}"
                )
            if name in owner:
                raise ValueError(
                    f"actuator {name!r} is in two agents ({owner[name]} and {agent}); "
                    "each actuator belongs to one agent"
                )
            owner[name] = agent


def _split_layout(layout: Layout) -> tuple[tuple[str, ...], tuple[tuple[str, ...], ...]]:
    if isinstance(layout, Mapping):
        names, groups = tuple(layout), tuple(layout.values())
        if not all(isinstance(n, str) and n for n in names) or len(set(names)) != len(names):
            raise ValueError(f"the layout's agent names must be distinct strings, got {names!r}")
    elif isinstance(layout, Sequence) and not isinstance(layout, str):
        names, groups = (), tuple(layout)
    else:
        raise ValueError(
            "layout lists each agent's actuator names: a list of lists, or a dict of agent name "
            f"-> list, got {layout!r}"
        )
    cleaned = []
    for group in groups:
        if isinstance(group, str) or not isinstance(group, Sequence):
            what = f"the string {group!r}" if isinstance(group, str) else repr(group)
            raise ValueError(f"each agent's actuators must be a list of names, got {what}")
        cleaned.append(tuple(group))
    return names, tuple(cleaned)


def _name_of(factory: Callable) -> str:
    return getattr(factory, "__name__", type(factory).__name__)


# ---------------------------------------------------------------------------- bare models


def from_mjcf(
    model: str | os.PathLike,
    layout: Layout,
    reward: Callable[[Any], float] | Sequence[terms.Term],
    *,
    terminate: Callable[[Any], bool] | Sequence | None = None,
    keyframe: str | None = None,
    start: Mapping[str, float] | None = None,
    reset_noise: float = 0.1,
    root_noise: tuple[float, float] = (0.0, 0.0),
    observation: Observation | None = None,
    actions: JointTargets | None = None,
    commands: terms.VelocityCommand | None = None,
    randomize: bool | Mapping[str, Any] | Randomization | None = None,
    episode_limit: int = 1000,
    substeps: int = 1,
    hops: int = 1,
    agent_id: bool = True,
    root_features: bool = True,
    env_id: str | None = None,
    only_positive_rewards: bool = False,
    recipe: TrainingRecipe | None = None,
) -> RobotSpec:
    """A team over a bare MuJoCo model: `model` is an MJCF path or XML string.

    - `reward`: a function of the physics, or a list of reward terms (`envs.terms`);
      `terminate` (optional): a function that ends an episode when true, or a list of
      termination terms.
    - Start: `start` joint angles by name (the base lowered onto the floor),
      or the `keyframe` (by name; `home` when the model has one); a floating base with
      neither is refused (qpos0 is rarely a standing pose). Noise respects each joint
      (`model_task`): hinges and slides by up to `reset_noise` in their units (at most that
      fraction of half their range), a free base by `root_noise` (horizontal metres, radians
      of turn). A start pose outside a joint's range is refused.
    - `only_positive_rewards` (legged_gym's): a step's reward is at least 0, so ending an
      episode early never pays; the logs show what the floor added (term `floor`).
    - `recipe` (`envs.TrainingRecipe`): the PPO settings `mat train` uses for this task.
    - `observation` (`envs.Observation`): build observations from signals the hardware has
      (joint encoders, IMU, sensors, contacts, command, previous action) instead of the raw
      joint state and the root's height, orientation and velocity (`root_features`).
    - `actions` (`envs.JointTargets`): joint targets around the start pose, with a PD layer
      for torque motors; otherwise an action spans each actuator's control range.
    - `commands` (`envs.terms.VelocityCommand`): a velocity command per episode.
    - `randomize`: domain randomization (`envs.Randomization`, true for its defaults, or a
      mapping of factors): friction, masses, payload, actuator strength, latency, sensor
      noise, pushes, ... drawn per episode; the `randomize` env option overrides it.
    One env step is `substeps` physics steps of the model's own timestep.
    """
    if not isinstance(model, str | os.PathLike):
        raise ValueError(f"model must be an MJCF file path or an XML string, got {model!r}")
    source = os.fspath(model)
    is_xml = source.lstrip().startswith("<")
    if not is_xml:
        path = Path(source)
        if not path.is_file():
            raise ValueError(f"model {source!r} is neither an MJCF file nor an XML string")
        source = str(path.resolve())
    if (
        isinstance(substeps, bool)
        or not isinstance(substeps, int)
        or not 1 <= substeps <= MAX_SUBSTEPS
    ):
        raise ValueError(f"substeps must be an integer in 1..{MAX_SUBSTEPS}, got {substeps!r}")
    if not is_real(reset_noise) or not 0 <= reset_noise < math.inf:
        raise ValueError(f"reset_noise must be a finite number >= 0, got {reset_noise!r}")
    shift, turn = finite_range(root_noise, "root_noise")
    if shift < 0 or turn < 0:
        raise ValueError(f"root_noise must be two numbers >= 0, got {root_noise!r}")
    if keyframe is not None and not isinstance(keyframe, str):
        raise ValueError(f"keyframe must be a keyframe's name or None, got {keyframe!r}")
    if commands is not None and not isinstance(commands, terms.VelocityCommand):
        raise ValueError(f"commands must be an envs.terms.VelocityCommand, got {commands!r}")
    if start is not None and not isinstance(start, Mapping):
        raise ValueError(f"start must map joint names to angles, got {start!r}")
    if recipe is not None and not isinstance(recipe, TrainingRecipe):
        raise ValueError(f"recipe must be an envs.TrainingRecipe, got {recipe!r}")
    randomization = Randomization.parse(randomize)
    factory = ModelEnvironment(
        source, _frozen(reward), _frozen(terminate), substeps, float(reset_noise), keyframe,
        (shift, turn), commands, None if start is None else tuple(start.items()),
        bool(only_positive_rewards),
    )  # fmt: skip
    name = "model" if is_xml else Path(source).stem
    spec = from_dm_control(
        factory,
        layout,
        hops=hops,
        agent_id=agent_id,
        episode_limit=episode_limit,
        root_features=root_features and observation is None,
        observation=observation,
        actions=actions,
        env_id=env_id or f"mjcf:{name}",
        description=f"{len(_split_layout(layout)[1])} agents over the MJCF model {name}; "
        + _start_said(keyframe, start),
    )
    spec = replace(spec, recipe=recipe)
    if randomization is None:
        return spec
    spec = replace(spec, randomize=randomization)
    spec.build()  # refuse what the randomization cannot apply to this model, now
    return spec


def _start_said(keyframe: str | None, start: Mapping[str, float] | None) -> str:
    """Where episodes start, for `mat envs` and `describe()`."""
    if start is not None:
        return f"episodes start from {len(start)} given joint angles, the base on the floor"
    if keyframe is not None:
        return f"episodes start from keyframe {keyframe!r}"
    return "episodes start from keyframe 'home' where the model has one, else qpos0"


def _frozen(value: Any) -> Any:
    """A list of terms as a tuple (the recipe is frozen and hashable); anything else as is."""
    return tuple(value) if isinstance(value, list) else value
