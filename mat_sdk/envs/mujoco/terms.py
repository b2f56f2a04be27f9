"""Reusable task terms for legged and other floating-base robots: rewards, terminations and
velocity commands, composed in `from_mjcf` without physics code.

    envs.from_mjcf(
        "go2.xml", layout,
        reward=[terms.TrackVelocity(1.0), terms.TrackYawRate(0.5), terms.Upright(1.0),
                terms.ActionRate(0.01), terms.Torque(2e-4)],
        terminate=[terms.TrunkHeight(0.15), terms.Tilt(60)],
        commands=terms.VelocityCommand(vx=(0.0, 1.0)),
    )

A reward term's `value(step)` is what it measures, signed so that more is better (penalties
are <= 0); the step's reward is the sum of `weight * value`, and each term's share is logged
under its `name`. A termination term's `ends(step)` says whether the episode ends. `step` is a
`Step`: the state after the env step, the command, and the actions of this step and the one
before.

Robot-relative units: penalties on effort, power, bouncing and height are measured in units
of the robot itself (`RobotScale`: its weight, its standing height, the speed sqrt(g h) of
a body falling that height), so one set of weights serves a 12 kg and a 50 kg quadruped. The
old absolute forms stay as options (`Torque(relative=False)`, ...). docs/REAL_ROBOTS.md has
the numbers behind the choice.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import mujoco
import numpy as np

from mat_sdk.envs.core.checks import finite_range, is_real, short
from mat_sdk.envs.mujoco.trunk import Contacts, Trunk, geom_ids


@dataclass(frozen=True)
class RobotScale:
    """The units robot-relative terms measure in: the robot's mass (kg), gravity (m/s^2) and
    the floating base's standing height (m, at the start pose)."""

    mass: float
    gravity: float
    height: float

    @property
    def weight(self) -> float:
        """m g, N."""
        return self.mass * self.gravity

    @property
    def torque(self) -> float:
        """m g h, N m: the moment of the robot's weight at its own height."""
        return self.weight * self.height

    @property
    def speed(self) -> float:
        """sqrt(g h), m/s: a Froude speed; vertical speeds and power scale with it."""
        return math.sqrt(self.gravity * self.height)

    @property
    def time(self) -> float:
        """sqrt(h / g), s: the robot's pendulum time; its steps' durations scale with it."""
        return math.sqrt(self.height / self.gravity)

    @classmethod
    def of(cls, model: mujoco.MjModel, height: float) -> RobotScale:
        mass = float(model.body_mass[1:].sum())
        gravity = float(np.linalg.norm(model.opt.gravity)) or 9.81
        return cls(mass, gravity, max(float(height), 1e-3))


@dataclass
class Step:
    """What terms read after an env step (the task keeps it up to date), and what they
    derive from the model once (`cached`)."""

    data: mujoco.MjData
    model: mujoco.MjModel
    trunk: Trunk
    command: np.ndarray  # the episode's command (empty without commands)
    action: np.ndarray  # this step's action of every actuator, in [-1, 1] (undriven: 0)
    previous_action: np.ndarray
    control_timestep: float
    scale: RobotScale | None = None  # the robot's own units (None: not a floating base)
    start_qpos: np.ndarray | None = None  # the pose episodes start from
    # what stateful terms remember within an episode (cleared at its start, checkpointed)
    memory: dict[str, np.ndarray] = field(default_factory=dict)
    _cache: dict = field(default_factory=dict)

    def cached(self, key, make):
        """`make(model)`, computed once per key."""
        if key not in self._cache:
            self._cache[key] = make(self.model)
        return self._cache[key]


@dataclass(frozen=True)
class CommandCurriculum:
    """Commands that widen as the robot learns to follow them (legged_gym's command
    curriculum, kept per env copy). At level 0 each of vx, vy and yaw rate is drawn from
    this curriculum's range, at level `levels` from the command's own, and in between from
    ranges that widen linearly. A command followed to within `tolerance` (the mean error
    after its first second: m/s of vx and vy together, rad/s of the yaw rate) moves the
    copy up a level; a fall, or a command missed by more than twice the tolerance, moves it
    down one. Every new command is a small step from commands the policy already follows,
    and the level settles where the policy follows about as many commands as it misses.
    The levels are part of an env copy's state, so a resumed run goes on from where it was."""

    vx: tuple[float, float] = (0.0, 0.0)
    vy: tuple[float, float] = (0.0, 0.0)
    yaw_rate: tuple[float, float] = (0.0, 0.0)
    levels: int = 10
    tolerance: tuple[float, float] = (0.2, 0.3)  # m/s, rad/s

    def __post_init__(self):
        for name in VelocityCommand.names:
            object.__setattr__(
                self, name, finite_range(getattr(self, name), f"CommandCurriculum.{name}")
            )
        if not (isinstance(self.levels, int) and 1 <= self.levels <= 1000):
            raise ValueError(
                f"CommandCurriculum.levels must be a whole number in 1..1000, got "
                f"{short(self.levels)}"
            )
        tolerance = tuple(self.tolerance) if isinstance(self.tolerance, tuple | list) else ()
        if len(tolerance) != 2 or not all(is_real(v) and 0 < v < math.inf for v in tolerance):
            raise ValueError(
                "CommandCurriculum.tolerance must be two numbers > 0 (m/s, rad/s), got "
                f"{short(self.tolerance)}"
            )
        object.__setattr__(self, "tolerance", tuple(float(v) for v in tolerance))


@dataclass(frozen=True)
class VelocityCommand:
    """A base velocity to follow, sampled from the task's seeded stream: forward `vx` and
    sideways `vy` (m/s, in the base's frame) and `yaw_rate` (rad/s), each uniform in its
    (low, high) range; with `standing`, that share of the commands is zero (stand still, on
    purpose: a joystick at rest); with `resample_seconds`, a new command every so many
    seconds within an episode, as an operator moves the stick (else one per episode). Every
    agent observes it (signal `command`); a controller passes the operator's command in its
    place."""

    vx: tuple[float, float] = (0.0, 0.0)
    vy: tuple[float, float] = (0.0, 0.0)
    yaw_rate: tuple[float, float] = (0.0, 0.0)
    standing: float = 0.0
    resample_seconds: float | None = None
    curriculum: CommandCurriculum | None = None  # None: the whole ranges from the start
    names = ("vx", "vy", "yaw_rate")

    LIMIT = 10.0  # m/s and rad/s: far past any legged robot's, so a typo fails loudly

    def __post_init__(self):
        for name in self.names:
            low, high = finite_range(getattr(self, name), f"VelocityCommand.{name}")
            if max(abs(low), abs(high)) > self.LIMIT:
                raise ValueError(
                    f"VelocityCommand.{name} must lie within +-{self.LIMIT:g}, got "
                    f"[{low:.4g}, {high:.4g}]"
                )
            object.__setattr__(self, name, (low, high))
        if not (is_real(self.standing) and 0 <= self.standing <= 1):
            raise ValueError(
                f"VelocityCommand.standing is a share in [0, 1], got {short(self.standing)}"
            )
        every = self.resample_seconds
        if every is not None and not (is_real(every) and math.isfinite(every) and every > 0):
            raise ValueError(
                f"VelocityCommand.resample_seconds must be a number of seconds > 0 or None, "
                f"got {short(every)}"
            )
        if self.curriculum is not None and not isinstance(self.curriculum, CommandCurriculum):
            raise ValueError(
                f"VelocityCommand.curriculum must be a CommandCurriculum or None, got "
                f"{short(self.curriculum)}"
            )

    def ranges(self, level: int | None = None) -> np.ndarray:
        """[3, 2]: the (low, high) of vx, vy and yaw rate at a curriculum `level` (None, or
        no curriculum: the command's own)."""
        own = np.array([getattr(self, name) for name in self.names])
        if self.curriculum is None or level is None:
            return own
        first = np.array([getattr(self.curriculum, name) for name in self.names])
        return first + (own - first) * (
            min(max(level, 0), self.curriculum.levels) / self.curriculum.levels
        )

    def sample(self, random: np.random.RandomState, level: int | None = None) -> np.ndarray:
        low, high = self.ranges(level).T
        command = low + (high - low) * random.uniform(size=3)
        if self.standing and random.uniform() < self.standing:  # no draw without standing
            command[:] = 0.0
        return command

    @classmethod
    def check(cls, command) -> np.ndarray:
        """A fixed command given as an env option (evaluation at one speed), or a row of a
        tracking grid: three finite numbers within `LIMIT`."""
        try:
            value = np.asarray(command, dtype=np.float64) if command is not None else None
        except (TypeError, ValueError):
            value = None
        if (
            value is None
            or value.shape != (3,)
            or not np.isfinite(value).all()
            or np.abs(value).max() > cls.LIMIT
        ):
            raise ValueError(
                f"command must be three finite numbers within +-{cls.LIMIT:g} "
                f"({', '.join(cls.names)}), got {short(command)}"
            )
        return value


# ------------------------------------------------------------------------- rewards
@dataclass(frozen=True)
class Term:
    """A reward term: `weight * value(step)` is added to the step's reward. Its parameters
    are checked when it is made (`_positive`, ...), not at the first step."""

    weight: float = 1.0

    def __post_init__(self):
        if not (is_real(self.weight) and math.isfinite(self.weight)):
            raise ValueError(
                f"{self.name}: weight must be a finite number, got {short(self.weight)}"
            )

    @property
    def name(self) -> str:
        """The term's name in logs and breakdowns: its class name in snake case."""
        return re.sub(r"(?<!^)(?=[A-Z])", "_", type(self).__name__).lower()

    def value(self, step: Step) -> float:
        raise NotImplementedError

    def _positive(self, *fields: str) -> None:
        for field_name in fields:
            value = getattr(self, field_name)
            if not (is_real(value) and 0 < value < math.inf):
                raise ValueError(
                    f"{type(self).__name__}.{field_name} must be a finite number > 0, got "
                    f"{short(value)}"
                )


@dataclass(frozen=True)
class Alive(Term):
    """1 for every step the robot has not fallen (an episode that ends early loses it)."""

    def value(self, step: Step) -> float:
        return 1.0


@dataclass(frozen=True)
class ForwardVelocity(Term):
    """The base's forward speed (m/s, along its own x axis, level): moving forward pays."""

    def value(self, step: Step) -> float:
        return float(step.trunk.velocity(step.data)[0])


@dataclass(frozen=True)
class TrackVelocity(Term):
    """How closely the base's horizontal velocity (its frame) follows the command's vx, vy:
    exp(-error^2 / sigma), 1 when exact.

    With `over_standing`, what tracking gains over standing still: the same kernel minus its
    value at zero velocity, exp(-command^2 / sigma). Standing then earns 0 at any command
    (negative at a zero command if the robot moves), where the plain kernel pays it up to 1
    for small commands: under a joystick's commands, most of them small, that share is what
    makes standing a policy's first optimum."""

    sigma: float = 0.25
    over_standing: bool = False
    needs_commands = True

    def __post_init__(self):
        super().__post_init__()
        self._positive("sigma")

    def value(self, step: Step) -> float:
        command = step.command[:2]
        error = step.trunk.velocity(step.data)[:2] - command
        return _tracking(error @ error, command @ command, self.sigma, self.over_standing)


@dataclass(frozen=True)
class TrackYawRate(Term):
    """How closely the base's yaw rate follows the command's: exp(-error^2 / sigma); with
    `over_standing`, minus what standing still earns (`TrackVelocity`)."""

    sigma: float = 0.25
    over_standing: bool = False
    needs_commands = True

    def __post_init__(self):
        super().__post_init__()
        self._positive("sigma")

    def value(self, step: Step) -> float:
        command = float(step.command[2])
        error = float(step.trunk.angular_velocity(step.data)[2]) - command
        return _tracking(error**2, command**2, self.sigma, self.over_standing)


def _tracking(error_squared, command_squared, sigma: float, over_standing: bool) -> float:
    kernel = math.exp(-float(error_squared) / sigma)
    return kernel - math.exp(-float(command_squared) / sigma) if over_standing else kernel


@dataclass(frozen=True)
class FeetAirTime(Term):
    """Steps of a useful length: when a foot lands, its time in the air minus `threshold`
    seconds (legged_gym's term; short shuffles cost, strides pay), only while the command
    asks to move; and every step, a foot in the air for longer than `longest` seconds costs
    the excess (a leg held up is no step: without it, three-legged gaits win)."""

    feet: tuple[str, ...] = ()  # empty: the robot's feet (`LeggedRobot.feet`)
    threshold: float = 0.5
    longest: float = 1.0

    def __post_init__(self):
        super().__post_init__()
        self._positive("threshold", "longest")

    def value(self, step: Step) -> float:
        contacts = step.cached(("contacts", self.feet), lambda m: Contacts(m, self.feet))
        touching = contacts.read(step.data) > 0
        key = f"air_time.{'.'.join(self.feet)}"
        air = step.memory.setdefault(key, np.zeros(len(self.feet)))
        landed = (air > 0) & touching
        air += step.control_timestep
        moving = step.command.size == 0 or float(np.linalg.norm(step.command[:2])) > 0.1
        strides = float(((air - self.threshold) * landed).sum()) if moving else 0.0
        held = float(np.maximum(air - self.longest, 0.0)[~touching].sum())
        air[touching] = 0.0
        return strides - held


@dataclass(frozen=True)
class FeetRhythm(Term):
    """Steps in the robot's own rhythm (Isaac Lab's air-time reward for Spot, in the robot's
    units). While the command asks to move, each foot earns how long its current phase, in
    the air or on the floor, has lasted, as a share of `phase`, until the phase outlasts
    `phase`; then nothing until the foot changes phase. A foot that never lifts (a shuffle)
    earns nothing after its first phase, and phases of `phase` earn the most. At a zero
    command a foot earns its time on the floor and pays for its time in the air, the same
    way. The mean over the feet, in [-1, 1).

    `phase` is in units of the robot's pendulum time sqrt(h / g) (`RobotScale.time`): 1.3
    is 0.22 s on the Go2 and 0.3 s on Spot (Isaac Lab's); seconds with `relative=False`."""

    feet: tuple[str, ...] = ()  # empty: the robot's feet (`LeggedRobot.feet`)
    phase: float = 1.3
    relative: bool = True

    def __post_init__(self):
        super().__post_init__()
        self._positive("phase")

    def value(self, step: Step) -> float:
        contacts = step.cached(("contacts", self.feet), lambda m: Contacts(m, self.feet))
        touching = (contacts.read(step.data) > 0).astype(float)
        key = f"phase_time.{'.'.join(self.feet)}"
        # row 0: how long each foot has been in its phase; row 1: on the floor (1) or not
        memory = step.memory.setdefault(key, np.stack([np.zeros_like(touching), touching]))
        elapsed, was_touching = memory
        elapsed[touching != was_touching] = 0.0
        elapsed += step.control_timestep
        was_touching[:] = touching
        phase = self.phase * (step.scale.time if self.relative else 1.0)
        share = elapsed / phase
        if step.command.size == 0 or float(np.linalg.norm(step.command)) > 0.1:  # moving
            return float(np.where(share < 1.0, share, 0.0).mean())
        return float(np.clip(np.where(touching > 0, share, -share), -1.0, 1.0).mean())


@dataclass(frozen=True)
class FeetSlip(Term):
    """Minus the squared horizontal speed of every foot on the floor, in units of g h (the
    robot's speed scale squared, `RobotScale`): a planted foot stays put, so a gait of
    sliding feet (a shuffle) costs what a stride does not. A foot given as a body is its
    lowest geom (the one on the floor)."""

    feet: tuple[str, ...] = ()  # empty: the robot's feet (`LeggedRobot.feet`)

    def value(self, step: Step) -> float:
        contacts = step.cached(("contacts", self.feet), lambda m: Contacts(m, self.feet))
        groups = step.cached(("foot_geoms", self.feet), lambda m: geom_ids(m, self.feet, "foot"))
        velocity = step.cached("velocity_scratch", lambda m: np.zeros(6))
        data, slip = step.data, 0.0
        for group, down in zip(groups, contacts.read(data) > 0, strict=True):
            if down:
                geom = int(group[np.argmin(data.geom_xpos[group, 2])])
                mujoco.mj_objectVelocity(step.model, data, mujoco.mjtObj.mjOBJ_GEOM, geom,
                                         velocity, 0)  # fmt: skip
                slip += velocity[3] ** 2 + velocity[4] ** 2  # world frame: [rotation, linear]
        return -slip / step.scale.speed**2


@dataclass(frozen=True)
class Upright(Term):
    """Minus the squared horizontal part of gravity in the base frame: 0 when level."""

    def value(self, step: Step) -> float:
        tilt = step.trunk.gravity(step.data)[:2]
        return -float(tilt @ tilt)


@dataclass(frozen=True)
class VerticalVelocity(Term):
    """Minus the base's squared vertical speed, in units of sqrt(g h) (`relative`, the
    default) or m/s: a smooth gait does not bounce."""

    relative: bool = True

    def value(self, step: Step) -> float:
        speed = step.trunk.world_velocity(step.data)[2]
        if self.relative:
            speed /= step.scale.speed
        return -float(speed**2)


@dataclass(frozen=True)
class RollPitchRate(Term):
    """Minus the base's squared roll and pitch rates."""

    def value(self, step: Step) -> float:
        rates = step.trunk.angular_velocity(step.data)[:2]
        return -float(rates @ rates)


@dataclass(frozen=True)
class BaseHeight(Term):
    """Minus the squared distance of the base's height from `target`: a fraction of the
    standing height (`relative`, the default; 1.0: as it starts) or metres."""

    target: float = 1.0
    relative: bool = True

    def __post_init__(self):
        super().__post_init__()
        self._positive("target")

    def value(self, step: Step) -> float:
        height = step.trunk.height(step.data)
        if self.relative:
            return -float((height / step.scale.height - self.target) ** 2)
        return -float((height - self.target) ** 2)


@dataclass(frozen=True)
class Torque(Term):
    """Minus the sum of squared actuator forces: effort costs. Relative (the default), each
    force is in units of m g h, the moment of the robot's weight at its standing height, so
    a robot twice as heavy pays the same for the same gait; absolute, in N m (or N)."""

    relative: bool = True

    def value(self, step: Step) -> float:
        force = step.data.actuator_force
        if self.relative:
            force = force / step.scale.torque
        return -float(force @ force)


@dataclass(frozen=True)
class Energy(Term):
    """Minus the mechanical power of the actuated joints, sum |force * joint velocity|: in
    units of m g sqrt(g h) (`relative`, the default), or W."""

    relative: bool = True

    def value(self, step: Step) -> float:
        power = float(np.abs(step.data.qfrc_actuator * step.data.qvel).sum())
        return -power / (step.scale.weight * step.scale.speed) if self.relative else -power


@dataclass(frozen=True)
class ActionRate(Term):
    """Minus the squared change of every action since the step before: smooth commands."""

    def value(self, step: Step) -> float:
        change = step.action - step.previous_action
        return -float(change @ change)


@dataclass(frozen=True)
class JointLimits(Term):
    """Minus how far hinge and slide joints are past `fraction` of their range (in joint
    units, summed): staying off the mechanical stops."""

    fraction: float = 0.9

    def __post_init__(self):
        super().__post_init__()
        if not (is_real(self.fraction) and 0 < self.fraction <= 1):
            raise ValueError(f"JointLimits.fraction must be in (0, 1], got {short(self.fraction)}")

    def value(self, step: Step) -> float:
        address, middle, half = step.cached(("limits", self.fraction), self._limits)
        return -float(np.maximum(np.abs(step.data.qpos[address] - middle) - half, 0.0).sum())

    def _limits(self, model):
        slide = int(mujoco.mjtJoint.mjJNT_SLIDE)  # slides and hinges come after it
        limited = model.jnt_limited.astype(bool) & (model.jnt_type >= slide)
        low, high = model.jnt_range[limited].T
        return model.jnt_qposadr[limited], (low + high) / 2, (high - low) / 2 * self.fraction


@dataclass(frozen=True)
class StandStill(Term):
    """At a zero command (speeds under `below`), how close the hinge and slide joints are to
    the start pose: exp(-mean distance / `width`), the distance in joint units (rad, m), 1 at
    the pose; 0 while the command asks to move. A robot told to stand stands in its pose
    rather than stepping in place (legged_gym's stand_still). A kernel that pays, not a cost:
    under `only_positive_rewards` a cost that outweighs the step's other terms clips every
    standing step to 0, and a policy standing anywhere earns the same."""

    below: float = 0.1
    width: float = 0.25
    needs_commands = True

    def __post_init__(self):
        super().__post_init__()
        self._positive("below", "width")

    def value(self, step: Step) -> float:
        if step.command.size and float(np.abs(step.command).max()) >= self.below:
            return 0.0
        address = step.cached("joint_qpos", _joint_qpos)
        distance = np.abs(step.data.qpos[address] - step.start_qpos[address]).mean()
        return math.exp(-float(distance) / self.width)


def _joint_qpos(model: mujoco.MjModel) -> np.ndarray:
    """The qpos addresses of the hinge and slide joints (not a floating base's)."""
    slide = int(mujoco.mjtJoint.mjJNT_SLIDE)  # slides and hinges come after it
    return model.jnt_qposadr[model.jnt_type >= slide]


# ------------------------------------------------------------------------- terminations
@dataclass(frozen=True)
class TrunkHeight:
    """End the episode when the base is lower than `minimum` (m): it fell."""

    minimum: float = 0.15

    def __post_init__(self):
        if not (is_real(self.minimum) and math.isfinite(self.minimum)):
            raise ValueError(
                f"TrunkHeight.minimum must be a finite number, got {short(self.minimum)}"
            )

    def ends(self, step: Step) -> bool:
        return step.trunk.height(step.data) < self.minimum


@dataclass(frozen=True)
class Tilt:
    """End the episode when the base tilts more than `degrees` from upright."""

    degrees: float = 60.0

    def __post_init__(self):
        if not (is_real(self.degrees) and 0 < self.degrees <= 180):
            raise ValueError(
                f"Tilt.degrees must be a number in (0, 180], got {short(self.degrees)}"
            )

    def ends(self, step: Step) -> bool:
        return -step.trunk.gravity(step.data)[2] < math.cos(math.radians(self.degrees))


@dataclass(frozen=True)
class IllegalContact:
    """End the episode when any of these geoms or bodies (trunk, thighs) touches anything."""

    names: tuple[str, ...] = ()  # empty: the robot's trunk (`LeggedRobot.trunk`)

    def ends(self, step: Step) -> bool:
        contacts = step.cached(("contacts", self.names), lambda m: Contacts(m, self.names))
        return bool(contacts.read(step.data).any())


TERMINATIONS = (TrunkHeight, Tilt, IllegalContact)
