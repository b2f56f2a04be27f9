"""How well a legged policy follows velocity commands: a grid of commands as an operator's
joystick gives them, each held for whole episodes, against the velocity measured in the
robot's heading frame (`mat eval --grid`).

    rows = track(CheckpointPolicy.from_checkpoint("go2.pt"), JOYSTICK_GRID, episodes=5)
    print(table(rows))              # per command: measured vx, vy, yaw rate, errors, falls
    plot(rows, "tracking.png")      # commanded vs measured, one panel per axis

Velocities are each episode's mean after its first second (the start from standing still;
`mat_sdk.envs.core.base.SETTLE_SECONDS`), averaged over the episodes; an episode that ends
early (a fall) counts with what it measured before it ended, and a command whose every episode
ended within its first second has no measurement (NaN), only its falls.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mat_sdk.evaluation.episodes import CheckpointPolicy, evaluate_episodes

AXES = ("vx", "vy", "yaw_rate")
# each axis alone, standing, and a few combinations: what a joystick asks of a walking robot
JOYSTICK_GRID: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 0.0),
    (-0.5, 0.0, 0.0),
    (0.3, 0.0, 0.0),
    (0.6, 0.0, 0.0),
    (1.0, 0.0, 0.0),
    (0.0, -0.5, 0.0),
    (0.0, 0.5, 0.0),
    (0.0, 0.0, -1.0),
    (0.0, 0.0, 1.0),
    (0.6, 0.3, 0.0),
    (0.6, 0.0, 0.5),
)


def parse_command(text: str) -> tuple[float, float, float]:
    """'VX,VY,YAW' (m/s, m/s, rad/s) as a command of the grid: three finite numbers within
    the commands' limit (`terms.VelocityCommand.check`)."""
    from mat_sdk.envs.mujoco.terms import VelocityCommand

    try:
        command = VelocityCommand.check([float(part) for part in text.split(",")])
    except ValueError:
        raise ValueError(
            f"a grid command is VX,VY,YAW: three numbers within +-{VelocityCommand.LIMIT:g} "
            f"(m/s, m/s, rad/s), e.g. 0.3,0,0.5; got {text[:60]!r}"
        ) from None
    return tuple(float(v) for v in command)


@dataclass
class Tracked:
    """One command's episodes: the mean measured (vx, vy, yaw rate), how many fell."""

    command: tuple[float, float, float]
    measured: np.ndarray
    falls: int
    episodes: int

    @property
    def error(self) -> np.ndarray:
        return np.abs(self.measured - np.asarray(self.command))


def track(
    loaded: CheckpointPolicy,
    commands: Sequence[Sequence[float]] = JOYSTICK_GRID,
    episodes: int = 5,
    seed: int = 10_000,
    **options: Any,
) -> list[Tracked]:
    """Each command held for `episodes` episodes (`evaluate_episodes` with `command=`)."""
    rows = []
    for command in commands:
        result = evaluate_episodes(
            loaded, episodes, seed=seed, command=[float(v) for v in command], **options
        )
        if np.isnan(result.speeds).all():
            raise ValueError("--grid measures a floating-base robot's velocity; this env has none")
        measured = np.array(result.tracking, dtype=np.float64)
        kept = measured[~np.isnan(measured).any(axis=1)]  # all fell within the first second: NaN
        mean = kept.mean(axis=0) if len(kept) else np.full(3, np.nan)
        rows.append(Tracked(tuple(float(v) for v in command), mean, sum(result.ended), episodes))
    return rows


def summary(rows: Sequence[Tracked]) -> dict[str, float]:
    """Over the grid: the mean absolute linear (vx and vy) and yaw-rate errors, the share of
    episodes that fell, and the speed measured at a zero command (NaN if none is in it)."""
    errors = np.array([row.error for row in rows])
    standing = [row for row in rows if not any(row.command)]
    return {  # over the commands where an episode lasted past its first second
        "linear error (m/s)": float(np.nanmean(errors[:, :2])),
        "yaw-rate error (rad/s)": float(np.nanmean(errors[:, 2])),
        "falls": sum(row.falls for row in rows) / max(1, sum(row.episodes for row in rows)),
        "speed at zero command (m/s)": float(np.hypot(*standing[0].measured[:2]))
        if standing
        else float("nan"),
    }


def table(rows: Sequence[Tracked]) -> str:
    """A Markdown table, one row per command, and the grid's summary under it."""
    lines = [
        "| command vx, vy, yaw rate | measured vx (m/s) | measured vy (m/s) | measured yaw rate "
        "(rad/s) | error vx / vy / yaw | falls |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        vx, vy, yaw = row.measured
        error = " / ".join(f"{e:.3f}" for e in row.error)
        command = ", ".join(f"{v:g}" for v in row.command)
        falls = f"{row.falls} / {row.episodes}"
        lines.append(f"| {command} | {vx:.3f} | {vy:.3f} | {yaw:.3f} | {error} | {falls} |")
    figures = summary(rows)
    measured = sum(not np.isnan(row.measured).any() for row in rows)
    lines.append("")
    lines.append(
        f"mean absolute error over the {measured} of {len(rows)} commands measured (the others "
        f"fell within their first second): {figures['linear error (m/s)']:.3f} m/s linear, "
        f"{figures['yaw-rate error (rad/s)']:.3f} rad/s yaw; falls {figures['falls']:.0%} of the "
        f"episodes; at a zero command {figures['speed at zero command (m/s)']:.3f} m/s"
    )
    return "\n".join(lines)


def plot(rows: Sequence[Tracked], path: str | Path) -> Path:
    """Commanded against measured, one panel per axis (each command on its axis's panel
    where it asks for that axis)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, panels = plt.subplots(1, 3, figsize=(12, 4))
    units = ("m/s", "m/s", "rad/s")
    for k, (panel, axis, unit) in enumerate(zip(panels, AXES, units, strict=True)):
        asked = [row for row in rows if row.command[k] or not any(row.command)]
        commanded = [row.command[k] for row in asked]
        panel.plot(commanded, [row.measured[k] for row in asked], "o", label="measured")
        low, high = min(commanded, default=0.0), max(commanded, default=0.0)
        panel.plot([low, high], [low, high], "k--", lw=1, label="commanded")
        panel.set(xlabel=f"commanded {axis} ({unit})", ylabel=f"measured {axis} ({unit})")
        panel.legend()
    figure.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path
