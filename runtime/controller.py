"""A safe controller around a bundle: the state machine and guards a robot-side controller
needs between its motors and the policy.

    kit = Controller(Policy.load("go2_onnx"), Safety(tilt=45), motor_order=SDK_JOINTS)
    kit.start()                                    # the operator: stand up, then walk
    while running:                                 # at the bundle's control rate
        motors = kit.tick(robot.read(), command=joystick, late=loop_was_late)
        robot.write(motors)                        # q, dq, kp, kd, tau per motor, SDK order
    kit.stop("operator")                           # the motors go soft

Three modes, as a robot vendor's own deployment has them:

- `damping`: every motor soft (no stiffness, some damping), whatever the policy says. The
  controller starts here and returns here on any fault, and stays until the operator starts
  it again.
- `stand`: from the pose measured when it began to the bundle's start pose (the joint targets
  at action 0) along a straight line over `Safety.stand_seconds`, with the bundle's gains.
- `policy`: the policy acts from the robot's signals through the bundle's wiring; the
  operator's velocity command is clamped to the ranges the policy was trained on (recorded in
  the bundle) and changes at most `Safety.command_rate` per second.

Guards, checked every tick, end in `damping` at once (the tick that sees them): a reading
with NaN or infinite values; no new reading (the same timestamp) for `Safety.stale_ticks`
ticks; `Safety.late_ticks` late ticks in a row; in `stand` and `policy`, the trunk tilted
past `Safety.tilt` or a joint faster than `Safety.joint_speed`; in `policy`, a joint within
`Safety.joint_margin` of its range's ends. Every change of mode is kept in `transitions`
and given to `log`.

Motors are numbered as the robot's SDK numbers them (`motor_order`: the joint names in the
SDK's order; default, the bundle's own order), so readings and commands are permuted here by
name, never by position. numpy and the runtime only: no torch, nothing of the training SDK.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from mat_runtime.errors import BundleError, InputError
from mat_runtime.policy import Policy


class Mode(enum.Enum):
    DAMPING = "damping"
    STAND = "stand"
    POLICY = "policy"


@dataclass(frozen=True)
class Safety:
    """The limits the guards hold and how the controller moves between modes."""

    tilt: float = 45.0  # degrees between the trunk's up axis and the vertical
    joint_margin: float = 0.02  # rad: how close to its range's ends a joint may come
    joint_speed: float = 30.0  # rad/s
    stale_ticks: int = 5  # ticks in a row without a new reading
    late_ticks: int = 3  # late ticks in a row
    stand_seconds: float = 2.0  # from the measured pose to the start pose
    command_rate: float = 2.0  # per second, for each velocity command (m/s, rad/s)
    damping_kd: float | None = None  # the soft motors' damping; None: the bundle's kd

    def __post_init__(self):
        for name in ("tilt", "joint_margin", "joint_speed", "stand_seconds", "command_rate"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"Safety.{name} must be a finite number > 0, got {value!r}")
        if not 0 < self.tilt < 180:
            raise ValueError(f"Safety.tilt must be in (0, 180) degrees, got {self.tilt!r}")
        for name in ("stale_ticks", "late_ticks"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"Safety.{name} must be an integer >= 1, got {value!r}")
        kd = self.damping_kd
        if kd is not None and not (isinstance(kd, int | float) and 0 <= kd < math.inf):
            raise ValueError(f"Safety.damping_kd must be a finite number >= 0, got {kd!r}")


@dataclass
class MotorCommand:
    """One tick's command per motor, in the SDK's order: the joint target q, its speed dq, the
    gains kp and kd, and a feed-forward torque tau (what a Unitree `LowCmd` motor takes)."""

    q: np.ndarray
    dq: np.ndarray
    kp: np.ndarray
    kd: np.ndarray
    tau: np.ndarray


@dataclass(frozen=True)
class Transition:
    tick: int
    source: Mode
    target: Mode
    reason: str


@dataclass
class Controller:
    """The state machine (the module docstring) for one bundle and one robot."""

    policy: Policy
    safety: Safety = field(default_factory=Safety)
    motor_order: Sequence[str] | None = None
    log: Callable[[str], None] | None = None

    def __post_init__(self):
        wiring = self.policy.wiring
        if wiring is None or not wiring.has_observation or "joint_pos" not in wiring.signals:
            raise BundleError(
                "the controller kit needs a bundle that observes its robot's signals "
                "(joint_pos, ...) through its wiring: export a robot built from them"
            )
        missing = [k for k, target in enumerate(wiring.targets) if target is None]
        if missing:
            raise BundleError(
                "the controller kit drives joint targets; this bundle's actions are raw "
                f"actuator controls (columns {missing[:5]})"
            )
        if any(gains is None for gains in wiring.servo):
            raise BundleError(
                "the bundle records no motor gains (kp, kd) for its joints: re-export it with "
                "this version of mat export"
            )
        self.wiring = wiring
        joints = list(wiring.signals["joint_pos"])  # the encoders, in the bundle's order
        if sorted(wiring.targets) != sorted(joints):
            raise BundleError(
                "the bundle's driven joints and its encoders differ: "
                f"{sorted(set(wiring.targets) ^ set(joints))}"
            )
        order = list(self.motor_order) if self.motor_order is not None else joints
        if sorted(order) != sorted(joints) or len(set(order)) != len(order):
            raise ValueError(
                f"motor_order must name each of the bundle's joints once, in the SDK's order; "
                f"missing {sorted(set(joints) - set(order))}, unknown "
                f"{sorted(set(order) - set(joints))}"
            )
        self.joints = order
        slot = {name: k for k, name in enumerate(order)}
        self._encoders = np.array([slot[name] for name in joints])  # bundle's -> SDK's
        self._columns = np.array([slot[name] for name in wiring.targets])
        n = len(order)
        self.kp, self.kd = np.zeros(n), np.zeros(n)
        self.kp[self._columns] = [kp for kp, _ in wiring.servo]
        self.kd[self._columns] = [kd for _, kd in wiring.servo]
        self.stand_pose = np.zeros(n)
        self.stand_pose[self._columns] = wiring.start_targets
        self.low, self.high = np.full(n, -np.inf), np.full(n, np.inf)
        for k, span in zip(self._columns, wiring.ranges, strict=True):
            if span is not None:
                self.low[k], self.high[k] = span
        kd = self.safety.damping_kd
        self.damping_kd = self.kd.copy() if kd is None else np.full(n, float(kd))
        self.command_names = list(wiring.command_ranges)
        ranges = np.array(list(wiring.command_ranges.values())).reshape(-1, 2)
        self.command_low, self.command_high = ranges[:, 0], ranges[:, 1]
        self.mode = Mode.DAMPING
        self.transitions: list[Transition] = []
        self.ticks = 0
        self._walk = False
        self._last_stamp: float | None = None
        self._stale = self._late = 0
        self._stand_from: np.ndarray | None = None
        self._stand_ticks = max(1, round(self.safety.stand_seconds / wiring.control_timestep))
        self._stand_tick = 0
        self._command = np.zeros(len(self.command_names))
        self._actions = np.zeros((len(wiring.agents), self.policy.action_size), np.float32)
        self._last_action = np.zeros(self._actions.size)

    # ------------------------------------------------------------------ the operator
    def start(self, walk: bool = True) -> None:
        """Stand up from damping (and with `walk`, hand over to the policy once stood)."""
        self._walk = walk
        if self.mode is Mode.DAMPING:
            self._enter(Mode.STAND, "operator start")
            self._stand_from, self._stand_tick = None, 0  # from the next reading

    def stop(self, reason: str = "operator stop") -> None:
        """Every motor soft, now, until `start` again."""
        self._enter(Mode.DAMPING, reason)

    @property
    def command(self) -> np.ndarray:
        """The velocity command the policy was last given: the operator's, clamped to the
        trained ranges and rate limited (a copy)."""
        return self._command.copy()

    # ------------------------------------------------------------------ each tick
    def tick(
        self,
        reading: Mapping[str, object],
        stamp: float,
        command: Sequence[float] | None = None,
        late: bool = False,
    ) -> MotorCommand:
        """This tick's motor command from the robot's `reading` (the bundle's signals by
        name, joints in the SDK's order), taken at `stamp` (seconds, the robot's clock), the
        operator's velocity `command` and whether this tick started `late`."""
        self.ticks += 1
        signals, fault = self._checked(reading, stamp, late)
        if fault:
            self._enter(Mode.DAMPING, fault)
        if self.mode is Mode.DAMPING or signals is None:
            q = signals["joint_pos"] if signals is not None else np.zeros(len(self.joints))
            return self._motors(q, np.zeros_like(self.kp), self.damping_kd)
        q = signals["joint_pos"]
        if self.mode is Mode.STAND:
            if self._stand_from is None:
                self._stand_from = q.copy()
            self._stand_tick += 1
            share = min(1.0, self._stand_tick / self._stand_ticks)
            target = self._stand_from + share * (self.stand_pose - self._stand_from)
            if share >= 1.0 and self._walk:
                self._enter(Mode.POLICY, "stood up")
                self._last_action[:] = 0.0
                self._command[:] = 0.0
            return self._motors(target, self.kp, self.kd)
        return self._motors(self._act(signals, command), self.kp, self.kd)

    def _act(self, signals: dict[str, np.ndarray], command) -> np.ndarray:
        given = {name: value for name, value in signals.items() if name in self.wiring.signals}
        given["joint_pos"] = signals["joint_pos"][self._encoders]
        if "joint_vel" in given:
            given["joint_vel"] = signals["joint_vel"][self._encoders]
        if self.command_names:
            given["command"] = self.filtered_command(command)
        if "last_action" in self.wiring.source:
            given["last_action"] = self._last_action
        obs = self.wiring.observe(**given)
        self.policy.act(obs, out=self._actions)
        self._last_action[:] = np.clip(self._actions, -1.0, 1.0).reshape(-1)
        _, targets = self.wiring.commands(self._actions)
        q = self.stand_pose.copy()
        q[self._columns] = targets
        return q

    def filtered_command(self, command: Sequence[float] | None) -> np.ndarray:
        """The operator's command clamped to the trained ranges, moved toward it at most
        `command_rate` per second from the last one."""
        wanted = np.zeros(len(self.command_names)) if command is None else np.asarray(command)
        if wanted.shape != self._command.shape or not np.isfinite(wanted).all():
            raise InputError(
                f"command must be {len(self.command_names)} finite numbers "
                f"({', '.join(self.command_names)}), got {str(command)[:80]}"
            )
        wanted = np.clip(wanted, self.command_low, self.command_high)
        step = self.safety.command_rate * self.wiring.control_timestep
        self._command += np.clip(wanted - self._command, -step, step)
        return self._command.copy()

    # ------------------------------------------------------------------ the guards
    def _checked(self, reading, stamp: float, late: bool) -> tuple[dict | None, str | None]:
        """The reading as float arrays and the first fault it shows (None: none)."""
        self._late = self._late + 1 if late else 0
        if self._late >= self.safety.late_ticks:
            return self._arrays(reading)[0], f"{self._late} late ticks in a row"
        if stamp == self._last_stamp:
            self._stale += 1
            if self._stale >= self.safety.stale_ticks:
                return self._arrays(reading)[0], f"no new reading for {self._stale} ticks"
        else:
            self._stale = 0
        self._last_stamp = stamp
        signals, fault = self._arrays(reading)
        if fault or self.mode is Mode.DAMPING:
            return signals, fault
        if "gravity" in signals:
            gravity = signals["gravity"]
            cosine = -gravity[2] / max(float(np.linalg.norm(gravity)), 1e-9)
            tilt = math.degrees(math.acos(max(-1.0, min(1.0, cosine))))
            if tilt > self.safety.tilt:
                return signals, f"trunk tilted {tilt:.0f} degrees (limit {self.safety.tilt:g})"
        if "joint_vel" in signals:
            fastest = int(np.argmax(np.abs(signals["joint_vel"])))
            speed = abs(float(signals["joint_vel"][fastest]))
            if speed > self.safety.joint_speed:
                return signals, (
                    f"joint {self.joints[fastest]} at {speed:.1f} rad/s "
                    f"(limit {self.safety.joint_speed:g})"
                )
        if self.mode is Mode.POLICY:
            q, margin = signals["joint_pos"], self.safety.joint_margin
            outside = np.flatnonzero((q < self.low + margin) | (q > self.high - margin))
            if outside.size:
                k = int(outside[0])
                return signals, (
                    f"joint {self.joints[k]} at {q[k]:.3f} rad, within {margin:g} of its range "
                    f"[{self.low[k]:.3f}, {self.high[k]:.3f}]"
                )
        return signals, None

    def _arrays(self, reading) -> tuple[dict | None, str | None]:
        """The reading's signals as float arrays, or a fault naming what is wrong."""
        if not isinstance(reading, Mapping) or "joint_pos" not in reading:
            return None, "the reading has no joint_pos"
        signals = {}
        for name, value in reading.items():
            try:
                array = np.asarray(value, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                return None, f"reading {name} is not numbers"
            if not np.isfinite(array).all():
                return None, f"reading {name} holds NaN or infinite values"
            signals[name] = array
        n = len(self.joints)
        for name in ("joint_pos", "joint_vel"):
            if name in signals and signals[name].shape != (n,):
                return None, f"reading {name} has {signals[name].size} values, not {n}"
        return signals, None

    def _motors(self, q: np.ndarray, kp: np.ndarray, kd: np.ndarray) -> MotorCommand:
        zeros = np.zeros(len(self.joints))
        return MotorCommand(q=q.copy(), dq=zeros, kp=kp.copy(), kd=kd.copy(), tau=zeros.copy())

    def _enter(self, mode: Mode, reason: str) -> None:
        if mode is self.mode:
            return
        self.transitions.append(Transition(self.ticks, self.mode, mode, reason))
        if self.log is not None:
            self.log(f"tick {self.ticks}: {self.mode.value} -> {mode.value} ({reason})")
        self.mode = mode
