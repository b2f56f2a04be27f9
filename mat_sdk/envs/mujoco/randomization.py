"""Domain randomization: the robot differs from episode to episode, the way a real one differs
from its model, so a policy trained over the spread does not depend on the exact simulation.

    envs.make("go2:walk", randomize=True)                     # every factor at its default range
    envs.make("go2:walk", randomize={"push": None, "latency": [0, 2]})  # one off, one wider
    envs.from_mjcf("arm.xml", layout, reward, randomize={"defaults": False, "friction": [0.5, 1]})

Per episode: friction, body masses, a payload on the floating base, its centre of mass,
actuator strength, joint damping and armature, extra start-pose noise, and the action latency
(k control steps, k drawn per episode). Per step: observation noise on each named signal, in
its own units, and pushes (a velocity kick on the base every few seconds). Every draw comes
from the env's own seeded stream, so a seed gives the same episodes at any worker count and a
resumed run continues exactly. A factor set to None is off; docs/REAL_ROBOTS.md says what each
one models and how to size its range for one's robot.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import mujoco
import numpy as np

from mat_sdk.envs.core.checks import finite_range, is_real, saved_array, short, whole_number
from mat_sdk.envs.mujoco.model_task import couple_joints
from mat_sdk.envs.mujoco.trunk import Trunk

Range = tuple[float, float]

# Uniform noise of +- this much on each observed signal, in the signal's own units. The
# hardware signals' levels follow legged_gym's (encoders 0.01 rad, 1.5 rad/s; gyro 0.2 rad/s;
# gravity 0.05); the raw joint state of the built-in robots gets an encoder-like level.
DEFAULT_NOISE = {
    "joint_pos": 0.01,
    "joint_vel": 1.5,
    "gyro": 0.2,
    "gravity": 0.05,
    "accel": 0.2,
    "qpos": 0.01,
    "qvel": 0.1,
}


# Bounds on every factor: past them a draw no longer models a real robot, and some (a
# latency of 1e9 steps, a mass of 1e-300) exhaust memory or break the simulation. The table
# with the reasons is in docs/REAL_ROBOTS.md.
SCALE_BOUNDS = {  # multiples of the model's own value
    "friction": (0.0, 10.0),
    "mass": (0.1, 10.0),
    "strength": (0.0, 10.0),
    "damping": (0.0, 10.0),
    "armature": (0.0, 10.0),
}
PAYLOAD_SHARE_BOUNDS = (-0.5, 2.0)  # shares of the robot's mass
MAX_PAYLOAD_SHARE = 2.0  # a payload in kg: at most twice the robot's mass
MAX_COM = 0.5  # m, and at most the base's own size (`Randomizer`)
MAX_START = 1.0  # rad or m of extra start noise
MAX_PUSH = 5.0  # m/s: a harder kick is a collision, not a push
PUSH_EVERY_BOUNDS = (0.0, 1e6)  # s
MAX_LATENCY = 50  # control steps, and at most 1 s of control (`Randomizer`)
MAX_LATENCY_SECONDS = 1.0
NOISE_MULTIPLE = 10.0  # a signal's noise: at most this many times its default level
NOISE_LIMIT = 10.0  # for a signal without a default level, in its own units
MAX_NOISE_SIGNALS = 1000


def noise_bound(signal: str) -> float:
    """The most noise a signal may get, in its own units."""
    default = DEFAULT_NOISE.get(signal)
    return NOISE_LIMIT if default is None else NOISE_MULTIPLE * default


@dataclass(frozen=True)
class Randomization:
    """What differs between episodes, and by how much (each factor: None switches it off).

    Scales multiply the model's own value; a range is drawn uniformly per episode."""

    friction: Range | None = (0.5, 1.25)  # every geom's friction, one scale per episode
    per_geom_friction: bool = False  # or a scale per geom
    mass: Range | None = (0.9, 1.1)  # each body's mass and inertia, a scale per body
    payload: Range | None = None  # kg added at the floating base's centre of mass
    payload_share: Range | None = (0.0, 0.15)  # or a share of the robot's own mass
    com: float | None = 0.02  # m: the base's centre of mass moves up to this on each axis
    strength: Range | None = (0.8, 1.2)  # each actuator's gain (a position actuator's kp)
    damping: Range | None = (0.8, 1.2)  # each joint's damping, a scale per joint
    armature: Range | None = (0.8, 1.2)  # each joint's armature (rotor inertia)
    start: float | None = 0.05  # extra start-pose noise on each joint, in its units, in range
    latency: tuple[int, int] | None = (0, 1)  # the action reaches the motors k steps late
    noise: Mapping[str, float] | None = field(default_factory=lambda: dict(DEFAULT_NOISE))
    push: float | None = 0.5  # m/s: a horizontal kick on the floating base, up to this
    push_every: Range = (5.0, 10.0)  # s between pushes

    def __post_init__(self):
        for name, (low, high) in SCALE_BOUNDS.items():
            _check_range(self, name, positive=True, bounds=(low, high))
        _check_range(self, "payload", positive=False)
        _check_range(self, "payload_share", positive=False, bounds=PAYLOAD_SHARE_BOUNDS)
        for name, most in (("com", MAX_COM), ("start", MAX_START), ("push", MAX_PUSH)):
            value = getattr(self, name)
            if value is not None and not (is_real(value) and 0 <= value <= most):
                raise ValueError(
                    f"randomize {name} must be a number in [0, {most:g}] or null, "
                    f"got {short(value)}"
                )
        _check_range(self, "push_every", positive=True, optional=False, bounds=PUSH_EVERY_BOUNDS)
        if self.latency is not None:
            pair = finite_range(self.latency, "randomize latency")
            if not all(v.is_integer() and 0 <= v <= MAX_LATENCY for v in pair):
                raise ValueError(
                    f"randomize latency is [low, high] control steps, whole numbers in "
                    f"0..{MAX_LATENCY}, got {short(self.latency)}"
                )
            object.__setattr__(self, "latency", (int(pair[0]), int(pair[1])))
        if not isinstance(self.per_geom_friction, bool):
            raise ValueError("randomize per_geom_friction must be true or false")
        if self.noise is not None:
            levels = self.noise.items() if isinstance(self.noise, Mapping) else None
            if (
                levels is None
                or len(self.noise) > MAX_NOISE_SIGNALS
                or not all(
                    isinstance(k, str) and is_real(v) and 0 <= v <= noise_bound(k)
                    for k, v in levels
                )
            ):
                raise ValueError(
                    'randomize noise maps signal names to levels >= 0 (e.g. {"joint_pos": '
                    f"0.01}}), each at most {NOISE_MULTIPLE:g}x its default level ({NOISE_LIMIT:g} "
                    f"for a signal without one), got {short(self.noise)}"
                )
            object.__setattr__(self, "noise", {k: float(v) for k, v in self.noise.items()})

    @classmethod
    def off(cls) -> Randomization:
        """Every factor off: the start for a randomization of one or two factors."""
        return cls(**{f.name: None for f in fields(cls) if f.name not in _NOT_FACTORS})

    @classmethod
    def parse(cls, value: Any) -> Randomization | None:
        """From the plain form a config or command line holds: None/false (off), true (the
        defaults), a mapping of factors over the defaults (`"defaults": false` over none),
        or a `Randomization`."""
        if value is None or value is False:
            return None
        if value is True:
            return cls()
        if isinstance(value, Randomization):
            return value
        if not isinstance(value, Mapping):
            raise ValueError(
                'randomize is true, false, or a mapping of factors (e.g. {"friction": [0.5, '
                f'1.25], "push": null}}), got {value!r}'
            )
        settings = dict(value)
        defaults = settings.pop("defaults", True)
        if not isinstance(defaults, bool):
            raise ValueError(f"randomize defaults must be true or false, got {defaults!r}")
        known = [f.name for f in fields(cls)]
        unknown = sorted(set(settings) - set(known), key=str)
        if unknown:
            raise ValueError(
                f"randomize has no factor(s) {unknown}; its factors: {', '.join(known)}"
            )
        base = cls() if defaults else cls.off()
        return replace(base, **settings)

    def to_dict(self) -> dict[str, Any]:
        """The plain form (lists, not tuples) that `parse` reads back, for JSON and manifests."""
        plain = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in plain.items()}


_NOT_FACTORS = ("per_geom_friction", "push_every")


def _check_range(
    config: Randomization,
    name: str,
    positive: bool,
    optional: bool = True,
    bounds: tuple[float, float] | None = None,
) -> None:
    value = getattr(config, name)
    if value is None and optional:
        return
    low, high = finite_range(value, f"randomize {name}")
    if positive and low <= 0:
        raise ValueError(f"randomize {name} must be [low, high] with 0 < low, got {short(value)}")
    if bounds is not None and not (bounds[0] <= low and high <= bounds[1]):
        raise ValueError(
            f"randomize {name} must lie within [{bounds[0]:g}, {bounds[1]:g}], got {short(value)}"
        )
    object.__setattr__(config, name, (low, high))


@dataclass
class Draws:
    """One episode's robot, as drawn: each factor's values (None: that factor is off)."""

    friction: np.ndarray | None = None  # a scale per geom (or one for all)
    mass: np.ndarray | None = None  # a scale per body (the world body's ignored)
    payload: float | None = None  # kg added to the floating base
    com: np.ndarray | None = None  # the base's centre-of-mass offset (m, 3)
    strength: np.ndarray | None = None  # a scale per actuator
    damping: np.ndarray | None = None  # a scale per hinge or slide
    armature: np.ndarray | None = None  # a scale per hinge or slide
    latency: int = 0  # control steps the action waits

    def changes_inertia(self) -> bool:
        """Whether MuJoCo's inertia-derived constants need recomputing."""
        return any(v is not None for v in (self.mass, self.payload, self.com, self.armature))

    def to_state(self) -> dict[str, np.ndarray]:
        """The drawn factors by name, as arrays (a checkpoint's env state)."""
        drawn = {f.name: getattr(self, f.name) for f in fields(self)}
        drawn["latency"] = drawn["latency"] or None
        return {k: np.array(v, dtype=np.float64) for k, v in drawn.items() if v is not None}

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> Draws:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(state) - known)
        if unknown:
            raise ValueError(f"randomization state: unknown factor(s) {unknown}")
        values = {k: np.asarray(v, dtype=np.float64) for k, v in state.items() if k != "latency"}
        if "latency" in state:
            values["latency"] = whole_number(state["latency"])
            if values["latency"] is None:
                raise ValueError(
                    "a saved randomization's latency must be a whole number of control steps, "
                    f"got {short(state['latency'])}"
                )
        if "payload" in values:
            values["payload"] = float(values["payload"])
        return cls(**values)


class Randomizer:
    """A `Randomization` applied to one robot's MuJoCo model and data. The team calls it at
    reset (`new_episode`, `perturb_start`) and every step (`delay`, `push`, `noise`); it keeps
    the model's own values to scale from, and what it drew, to restore an episode exactly."""

    def __init__(
        self,
        config: Randomization,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        control_timestep: float,
        signals: Sequence[tuple[str, int]],
        env_id: str,
        action_shape: tuple[int, ...],
    ):
        self.config, self._model, self._data = config, model, data
        self._dt = control_timestep
        self._action_shape = tuple(action_shape)  # what `delay` holds back
        try:  # a floating base: where payload, centre of mass and pushes act
            trunk = Trunk(model)
            self._base, self._base_dof = trunk.body, trunk.qvel
        except ValueError:
            self._base = self._base_dof = None
        self._joints = [j for j in range(model.njnt) if model.jnt_type[j] >= 2]  # hinges, slides
        self._joint_dofs = model.jnt_dofadr[self._joints]
        self._nominal = {
            name: getattr(model, name).copy()
            for name in ("geom_friction", "body_mass", "body_inertia", "body_ipos",
                         "actuator_gainprm", "actuator_biasprm", "dof_damping", "dof_armature")
        }  # fmt: skip
        self._affine = model.actuator_biastype == int(mujoco.mjtBias.mjBIAS_AFFINE)
        self.robot_mass = float(model.body_mass[1:].sum())
        self._check_against_model(env_id)
        self._scratch = mujoco.MjData(model)  # mj_setConst's workspace
        self._noise_index, self._noise_level = self._noise_table(signals, env_id)
        self.draws = Draws()
        self._pending: list[np.ndarray] = []
        self._next_push = math.inf

    def _check_against_model(self, env_id: str) -> None:
        """The bounds that depend on the robot: payload (a multiple of its mass, and never a
        base without mass), centre-of-mass offsets (the base's size), latency (1 s)."""
        config = self.config
        latency = config.latency[1] if config.latency is not None else 0
        if latency * self._dt > MAX_LATENCY_SECONDS:
            raise ValueError(
                f"{env_id}: randomize latency {list(config.latency)} control steps is more than "
                f"{MAX_LATENCY_SECONDS:g} s of control at {self._dt:g} s a step"
            )
        if self._base is None:
            return
        heaviest = MAX_PAYLOAD_SHARE * self.robot_mass
        lightest = self._nominal["body_mass"][self._base] * (config.mass or (1.0, 1.0))[0]
        for name, (low, high), unit in (
            ("payload", config.payload or (0.0, 0.0), 1.0),
            ("payload_share", config.payload_share or (0.0, 0.0), self.robot_mass),
        ):
            if high * unit > heaviest:
                raise ValueError(
                    f"{env_id}: randomize {name} up to {high:g} is more than "
                    f"{MAX_PAYLOAD_SHARE:g}x the robot's mass ({self.robot_mass:.3g} kg)"
                )
            if lightest + low * unit <= 0:
                raise ValueError(
                    f"{env_id}: randomize {name} [{low:g}, {high:g}] would leave the base "
                    f"(mass {lightest:g} kg at its lightest) with no mass; raise its low end"
                )
        base_geoms = self._model.geom_bodyid == self._base
        size = float(self._model.geom_rbound[base_geoms].max()) if base_geoms.any() else MAX_COM
        if config.com is not None and config.com > size:
            raise ValueError(
                f"{env_id}: randomize com {config.com:g} m moves the centre of mass outside the "
                f"base (its geoms reach {size:.3g} m)"
            )

    def _noise_table(self, signals, env_id: str) -> tuple[np.ndarray, np.ndarray]:
        """Which entries of the observation source get noise, and how much."""
        levels = self.config.noise or {}
        names = [name for name, _ in signals]
        if levels and levels != DEFAULT_NOISE:
            unknown = sorted(set(levels) - set(names))
            if unknown:
                raise ValueError(
                    f"{env_id}: randomize noise names signal(s) {unknown} the observation does "
                    f"not have; its signals: {', '.join(names)}"
                )
        index, level, start = [], [], 0
        for name, size in signals:
            if levels.get(name, 0.0) > 0:
                index += range(start, start + size)
                level += [levels[name]] * size
            start += size
        return np.array(index, dtype=np.intp), np.array(level)

    # ---------------------------------------------------------------- per episode
    def new_episode(self, rng) -> None:
        """Draw this episode's robot and apply it to the model (before the task's reset)."""
        config, model = self.config, self._model
        draws = Draws()
        if config.friction is not None:
            count = model.ngeom if config.per_geom_friction else 1
            draws.friction = rng.uniform(*config.friction, count)
        if config.mass is not None:
            draws.mass = rng.uniform(*config.mass, model.nbody)
        if self._base is not None and (config.payload or config.payload_share):
            kg = float(rng.uniform(*config.payload)) if config.payload else 0.0
            share = float(rng.uniform(*config.payload_share)) if config.payload_share else 0.0
            draws.payload = kg + share * self.robot_mass
        if config.com is not None and self._base is not None:
            draws.com = rng.uniform(-config.com, config.com, 3)
        if config.strength is not None:
            draws.strength = rng.uniform(*config.strength, model.nu)
        if config.damping is not None:
            draws.damping = rng.uniform(*config.damping, len(self._joint_dofs))
        if config.armature is not None:
            draws.armature = rng.uniform(*config.armature, len(self._joint_dofs))
        if config.latency is not None:
            low, high = config.latency
            draws.latency = low + min(int(rng.uniform(0, high - low + 1)), high - low)
        self.draws = draws
        self._apply(draws)
        self._pending = []
        self._next_push = self._push_interval(rng)

    def _apply(self, draws: Draws) -> None:
        model, nominal = self._model, self._nominal
        for name, values in nominal.items():
            getattr(model, name)[:] = values
        if draws.friction is not None:
            model.geom_friction[:] = nominal["geom_friction"] * draws.friction[:, None]
        if draws.mass is not None:
            scale = draws.mass.copy()
            scale[0] = 1.0  # the world body
            model.body_mass[:] = nominal["body_mass"] * scale
            model.body_inertia[:] = nominal["body_inertia"] * scale[:, None]
        if draws.payload is not None:
            model.body_mass[self._base] += draws.payload
        if draws.com is not None:
            model.body_ipos[self._base] = nominal["body_ipos"][self._base] + draws.com
        if draws.strength is not None:
            model.actuator_gainprm[:, 0] = nominal["actuator_gainprm"][:, 0] * draws.strength
            kp = nominal["actuator_biasprm"][:, 1] * draws.strength
            model.actuator_biasprm[:, 1] = np.where(self._affine, kp, model.actuator_biasprm[:, 1])
        dofs = self._joint_dofs
        if draws.damping is not None:
            model.dof_damping[dofs] = nominal["dof_damping"][dofs] * draws.damping
        if draws.armature is not None:
            model.dof_armature[dofs] = nominal["dof_armature"][dofs] * draws.armature
        if draws.changes_inertia():
            mujoco.mj_setConst(model, self._scratch)  # inertia-derived constants

    def perturb_start(self, rng) -> None:
        """Extra start-pose noise on every hinge and slide, kept inside each joint's range
        (inside the physics' reset, after the task placed the robot)."""
        if self.config.start is None:
            return
        model, data = self._model, self._data
        shift = rng.uniform(-self.config.start, self.config.start, len(self._joints))
        for joint, delta in zip(self._joints, shift, strict=True):
            address = model.jnt_qposadr[joint]
            value = data.qpos[address] + delta
            if model.jnt_limited[joint]:
                value = np.clip(value, *model.jnt_range[joint])
            data.qpos[address] = value
        couple_joints(model, data.qpos)

    def _push_interval(self, rng) -> float:
        if self.config.push is None or self._base is None:
            return math.inf
        return float(rng.uniform(*self.config.push_every))

    # ---------------------------------------------------------------- per step
    def delay(self, action: np.ndarray) -> np.ndarray:
        """The action the motors get now: the one sent `latency` steps ago (0 at the start)."""
        steps = self.draws.latency
        if not steps:
            return action
        if not self._pending:
            self._pending = [np.zeros_like(action) for _ in range(steps)]
        self._pending.append(action.copy())
        return self._pending.pop(0)

    def push(self, rng) -> None:
        """A horizontal velocity kick on the floating base when its time has come."""
        self._next_push -= self._dt
        if self._next_push > 0:
            return
        self._next_push += self._push_interval(rng)
        dof = self._base_dof
        self._data.qvel[dof : dof + 2] += rng.uniform(-self.config.push, self.config.push, 2)
        mujoco.mj_step1(self._model, self._data)  # velocity-dependent quantities anew

    def noise(self, source: np.ndarray, rng) -> None:
        """Add this step's observation noise to the observation source, in place."""
        if len(self._noise_index):  # `random` is faster than RandomState's `uniform`
            draw = rng.random(len(self._noise_index))
            source[self._noise_index] += 2.0 * self._noise_level * draw - self._noise_level

    # ---------------------------------------------------------------- exact resume
    def get_state(self) -> dict[str, Any]:
        return {
            "draws": self.draws.to_state(),
            "pending": [p.copy() for p in self._pending],
            "next_push": self._next_push,
        }

    def set_state(self, state: Mapping[str, Any]) -> None:
        """An episode's robot as `get_state` saved it, refused unless this randomization could
        have drawn it: every value is checked before any of the model is touched."""
        next_push = float(state["next_push"])
        if math.isnan(next_push):  # NaN would push on every step
            raise ValueError("a saved randomization's next push time must be a number, got nan")
        draws = Draws.from_state(state["draws"])
        self._check_draws(draws)
        pending = self._checked_pending(state["pending"], draws.latency)
        self.draws = draws
        self._apply(draws)
        self._pending, self._next_push = pending, next_push

    def _check_draws(self, draws: Draws) -> None:
        """Each saved factor one this randomization draws, of the size and within the range
        it draws: a scale of 1e9 or a latency of a million steps is a broken robot."""
        config, model, joints = self.config, self._model, len(self._joint_dofs)
        friction_count = model.ngeom if config.per_geom_friction else 1
        expected = {  # factor -> (its range, its shape), for the factors this config draws
            "friction": (config.friction, (friction_count,)),
            "mass": (config.mass, (model.nbody,)),
            "strength": (config.strength, (model.nu,)),
            "damping": (config.damping, (joints,)),
            "armature": (config.armature, (joints,)),
        }
        floating = self._base is not None  # payload and centre of mass act on the base
        com = config.com is not None and floating
        payload = (config.payload or config.payload_share) and floating  # as `new_episode`
        expected["com"] = ((-config.com, config.com) if com else None, (3,))
        expected["payload"] = (self._payload_range() if payload else None, ())
        for name, (bounds, shape) in expected.items():
            values = getattr(draws, name)
            if values is None:
                continue
            values = np.asarray(values)
            if bounds is None:
                raise ValueError(f"a saved randomization draws {name}, which this one leaves off")
            if values.shape != shape or not (
                np.isfinite(values).all() and (values >= bounds[0]).all()
                and (values <= bounds[1]).all()
            ):  # fmt: skip
                count = f"{shape[0]} numbers" if shape else "one number"
                got = np.array2string(values.ravel()[:4], precision=3)
                raise ValueError(
                    f"a saved randomization's {name} must be {count} within "
                    f"[{bounds[0]:g}, {bounds[1]:g}], got {got} (shape {values.shape})"
                )
        latency = config.latency or (0, 0)
        if not latency[0] <= draws.latency <= latency[1]:
            raise ValueError(
                f"a saved randomization's latency must lie in {latency[0]}..{latency[1]} control "
                f"steps, got {draws.latency}"
            )

    def _payload_range(self) -> tuple[float, float]:
        """The least and most kg `new_episode` adds to the base."""
        kg = self.config.payload or (0.0, 0.0)
        share = self.config.payload_share or (0.0, 0.0)
        return kg[0] + share[0] * self.robot_mass, kg[1] + share[1] * self.robot_mass

    def _checked_pending(self, saved: Sequence[Any], latency: int) -> list[np.ndarray]:
        """The actions on their way to the motors: none yet, or `latency` of them, each an
        action (within [-1, 1], the shape the env sends)."""
        if len(saved) not in (0, latency):
            raise ValueError(
                f"a saved randomization holds {len(saved)} late actions; its latency of "
                f"{latency} control steps holds 0 or {latency}"
            )
        pending = [
            saved_array(action, self._action_shape, "randomization's late action", 1.0)
            for action in saved
        ]
        return pending


SWEEPABLE = ("friction", "mass", "payload", "payload_share", "com", "strength", "damping",
             "armature", "start", "latency", "push")  # fmt: skip


def setting(factor: str, value: float) -> Randomization:
    """The nominal robot with one factor held at `value` (a point of a robustness sweep): a
    scale for friction, mass, strength, damping, armature; kg of payload; control steps of
    latency; and the largest centre-of-mass offset (m), start noise (in each joint's units) or
    push (m/s), each drawn up to that."""
    if factor not in SWEEPABLE:
        raise ValueError(f"cannot sweep {factor!r}; sweepable factors: {', '.join(SWEEPABLE)}")
    if factor in ("com", "start", "push"):
        return replace(Randomization.off(), **{factor: value})
    return replace(Randomization.off(), **{factor: (value, value)})
