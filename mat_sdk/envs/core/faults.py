"""Faults: a robot's silenced, weakened or missing parts, as values.

    Fault.zero("bfoot")                 # the joint's motor gives no force; its agent stays
    Fault.weak("FR_calf_joint", 0.5)    # the motor keeps half its force
    Fault.remove("agent_2")             # the agent leaves the team: the agent count drops
    Fault.parse("FR_calf_joint=weak:0.5")   # the CLI's `--fault` form

A fault names an agent (all its actuators) or an actuated joint. Envs take a sequence of
faults; checkpoints, manifests and older code write them as a mapping `{name: mode}` with
modes "zero", "remove" and "weak:S" (`as_mapping`, `faults_of`), which loads the same.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Literal

KINDS = ("zero", "remove", "weak")
MODES = ("zero", "remove", "weak:S")  # as a mapping writes them; S: the force a weak motor keeps
WEAK = "weak:"
USAGE = "NAME=zero, NAME=remove or NAME=weak:S (S: the share of force a weak motor keeps)"


@dataclass(frozen=True)
class Fault:
    target: str  # an agent's name or an actuated joint's
    kind: Literal["zero", "remove", "weak"]
    strength: float = 0.0  # the share of its force a motor keeps: S for "weak", else 0

    def __post_init__(self):
        if not isinstance(self.target, str) or not self.target:
            raise ValueError(
                f"a fault names an agent or joint by a non-empty string, got {self.target!r}"
            )
        if self.kind not in KINDS:
            raise ValueError(f"fault {self.target}={self.kind!r}: mode must be one of {MODES}")
        weak = self.kind == "weak"
        valid = isinstance(self.strength, int | float) and not isinstance(self.strength, bool)
        if not valid or (weak and not 0 < self.strength < 1) or (not weak and self.strength):
            _refuse_strength(self.target, f"{WEAK}{self.strength}" if weak else self.kind)

    @classmethod
    def zero(cls, target: str) -> Fault:
        return cls(target, "zero")

    @classmethod
    def remove(cls, target: str) -> Fault:
        return cls(target, "remove")

    @classmethod
    def weak(cls, target: str, strength: float) -> Fault:
        return cls(target, "weak", strength)

    @classmethod
    def of(cls, target: object, mode: object) -> Fault:
        """A fault from its mapping form, `target: "zero" | "remove" | "weak:S"`."""
        if not isinstance(mode, str) or not (mode in ("zero", "remove") or mode.startswith(WEAK)):
            raise ValueError(f"fault {target}={mode!r}: mode must be one of {MODES}")
        if mode.startswith(WEAK):
            try:
                strength = float(mode[len(WEAK) :])
            except ValueError:
                strength = math.nan
            if not 0 < strength < 1:  # said with the mode as given
                _refuse_strength(target, mode)
            return cls(target, "weak", strength)  # type: ignore[arg-type]
        return cls(target, mode)  # type: ignore[arg-type]

    @classmethod
    def parse(cls, text: str) -> Fault:
        """`NAME=MODE`, as `--fault` takes it."""
        target, sep, mode = text.partition("=")
        if not sep or not target:
            raise ValueError(f"{text!r}: a fault is {USAGE}")
        try:
            return cls.of(target, mode)
        except ValueError as error:
            raise ValueError(f"{text!r}: {error}; a fault is {USAGE}") from None

    @property
    def mode(self) -> str:
        """The mapping form's mode: "zero", "remove" or "weak:S"."""
        return f"{WEAK}{self.strength:g}" if self.kind == "weak" else self.kind

    def __str__(self) -> str:
        return f"{self.target}={self.mode}"


def _refuse_strength(target: object, mode: str) -> None:
    raise ValueError(
        f"fault {target}={mode!r}: a weak motor keeps a share of its force strictly between 0 "
        "and 1, e.g. weak:0.5 (zero for none)"
    )


FaultsLike = Iterable[Fault] | Mapping[str, str] | None  # what the envs' functions accept


def faults_of(value: FaultsLike) -> tuple[Fault, ...]:
    """Faults from a sequence of `Fault`s or their mapping form (None: none), each checked
    before any name reaches MuJoCo (whose name lookup crashes on a non-string); one fault
    per target."""
    if value is None:
        return ()
    if isinstance(value, Mapping):
        faults = tuple(Fault.of(target, mode) for target, mode in value.items())
    elif isinstance(value, str | bytes) or not isinstance(value, Iterable):
        raise ValueError(
            f"faults are a list of envs.Fault (or a mapping of agent or joint names to "
            f"{', '.join(repr(m) for m in MODES)}), got {value!r}"
        )
    else:
        faults = tuple(value)
        strays = [f for f in faults if not isinstance(f, Fault)]
        if strays:
            raise ValueError(
                f"faults must be envs.Fault values (Fault.zero(name), ...), got {strays[0]!r}"
            )
    targets = [fault.target for fault in faults]
    twice = sorted({t for t in targets if targets.count(t) > 1})
    if twice:
        raise ValueError(f"one fault per agent or joint; {', '.join(twice)} has several")
    return faults


def as_mapping(faults: Iterable[Fault]) -> dict[str, str]:
    """The mapping form `{target: mode}`, as checkpoints and manifests store faults."""
    return {fault.target: fault.mode for fault in faults}
