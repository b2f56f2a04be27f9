"""What a training run leaves in its directory: metrics.csv, TensorBoard events, a curve PNG."""

from __future__ import annotations

import csv
import math
import os
import threading
import warnings
from pathlib import Path

import numpy as np

from mat_sdk.common import files
from mat_sdk.policy.checkpoint import Progress, remove_stale_temp_files

METRICS_NAME = "metrics.csv"
# what every row has (`update_metrics`) and the curve reads; a header without them is no run's
REQUIRED_COLUMNS = ("steps", "updates", "return_mean", "return_min", "return_max", "episodes")
CURVE_NAME = "learning_curve.png"


def _quiet_tensorboard_disk_errors(args: threading.ExceptHookArgs) -> None:
    """TensorBoard writes its events in a thread of its own, which re-raises a disk error
    (full, read-only) there; the run's next write raises it again, as one line
    (`files.writing`). Print nothing for the thread's copy; anything else as before."""
    if type(args.thread).__name__ == "_AsyncWriterThread" and isinstance(args.exc_value, OSError):
        return
    _quiet_tensorboard_disk_errors.previous(args)


_quiet_tensorboard_disk_errors.previous = threading.excepthook


class RunLog:
    """Appends one row per update. On resume the file is repaired to what the checkpoint
    holds: rows after the checkpoint's update are dropped (a run killed between checkpoints
    and resumed has no duplicate rows), and so is a torn last line (killed mid-write)."""

    def __init__(self, out_dir: Path, resume_after: int = 0):
        from torch.utils.tensorboard import SummaryWriter

        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        remove_stale_temp_files(self.out_dir)
        self.path = self.out_dir / METRICS_NAME
        _set_aside_if_foreign(self.path)
        self._columns, rows, intact = _complete_rows(self.path)
        missing = [c for c in REQUIRED_COLUMNS if c not in (self._columns or REQUIRED_COLUMNS)]
        if missing:
            raise ValueError(
                f"{self.path} lacks the columns {missing} that every row of this SDK has (edited, "
                "or another program's?); move it aside to start a new one, nothing else is touched"
            )
        kept = [r for r in rows if int(r["updates"]) <= resume_after]
        if self._columns is None and not intact:  # only a torn header: nothing to keep
            self.path.write_text("")
        elif len(kept) != len(rows) or not intact:
            self._rewrite(kept)
        self._file = self.path.open("a", newline="")
        self._writer = None
        if threading.excepthook is not _quiet_tensorboard_disk_errors:  # the app's hook after
            _quiet_tensorboard_disk_errors.previous = threading.excepthook
            threading.excepthook = _quiet_tensorboard_disk_errors
        events = self.out_dir / "tensorboard"
        with files.writing(events):
            self._tensorboard = SummaryWriter(log_dir=str(events))

    def _rewrite(self, rows: list[dict]) -> None:
        """Replace the file atomically: a crash during the repair loses no row."""
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        with tmp.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=self._columns)
            writer.writeheader()
            writer.writerows(rows)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, self.path)

    def write(self, metrics: dict) -> None:
        with files.writing(self.path):
            self._write(metrics)

    def _write(self, metrics: dict) -> None:
        if self._writer is None:
            new_file = self._columns is None
            self._columns = self._columns or list(metrics)
            self._writer = csv.DictWriter(self._file, fieldnames=self._columns)
            if new_file:
                self._writer.writeheader()
        self._writer.writerow({k: metrics.get(k, "") for k in self._columns})
        self._file.flush()
        for key, value in metrics.items():
            if key not in ("steps", "updates") and not math.isnan(value):
                self._tensorboard.add_scalar(key, value, metrics["steps"])

    def close(self) -> None:
        with files.writing(self.out_dir):
            self._file.close()
            self._tensorboard.close()
            plot_curve(self.path, self.out_dir / CURVE_NAME)


def update_metrics(
    progress: Progress,
    finished: list[float],
    rewards,
    losses: dict[str, float],
    env_steps: int,
    rollout_s: float,
    update_s: float,
) -> dict[str, float]:
    """One update's row of metrics.csv: progress, the returns of the episodes that finished,
    the team reward per env step (`rewards` of its `env_steps`), the losses and diagnostics,
    and the timings."""
    return {
        "steps": progress.steps,
        "updates": progress.updates,
        "return_mean": float(np.mean(finished)) if finished else math.nan,
        "return_min": float(np.min(finished)) if finished else math.nan,
        "return_max": float(np.max(finished)) if finished else math.nan,
        "episodes": len(finished),
        # the team reward per env step in this rollout: a signal every update, also while
        # no episode has ended yet (dm_control tasks: 0..1)
        "reward_per_step": float(rewards.mean()),
        **losses,
        "rollout_s": rollout_s,
        "update_s": update_s,
        "steps_per_s": env_steps / (rollout_s + update_s),
    }


class ProgressBar:
    """tqdm over env steps, showing the latest finished episodes' mean return ("-" until one
    finishes), the team reward per step and env-steps/s."""

    def __init__(self, total: int, done: int, enabled: bool):
        from tqdm.auto import tqdm

        self._bar = tqdm(
            total=total, initial=done, unit="step", disable=not enabled, dynamic_ncols=True
        )
        self._shown_return = "-"

    def show(self, metrics: dict[str, float], steps: int) -> None:
        if metrics["episodes"]:
            self._shown_return = f"{metrics['return_mean']:.1f}"
        self._bar.update(steps)
        self._bar.set_postfix(
            ret=self._shown_return,
            rew=f"{metrics['reward_per_step']:.3g}",
            sps=f"{metrics['steps_per_s']:.0f}",
        )

    def close(self) -> None:
        self._bar.close()


class ForeignMetrics(UserWarning):
    """A run directory's metrics.csv was not one this SDK writes; it was moved aside."""


def _set_aside_if_foreign(path: Path) -> None:
    """A metrics file that is not ours (binary, another program's columns) is renamed to
    `metrics.csv.unreadable[.N]`, with a warning: a run starts a new one and loses nothing."""
    try:
        header = next(csv.reader([path.read_text().partition("\n")[0]]), [])
    except FileNotFoundError:
        return
    except (OSError, UnicodeDecodeError, csv.Error):
        header = []
    if not path.stat().st_size or {"steps", "updates"} <= set(header):
        return
    aside = path.with_name(f"{path.name}.unreadable")
    number = 1
    while aside.exists():
        aside = path.with_name(f"{path.name}.unreadable.{number}")
        number += 1
    path.rename(aside)
    warnings.warn(
        f"{path} is not a metrics file of this SDK (unreadable, or without steps and updates "
        f"columns); moved it to {aside} and started a new one",
        ForeignMetrics,
        stacklevel=3,
    )


def _complete_rows(path: Path) -> tuple[list[str] | None, list[dict], bool]:
    """(header, the rows that are whole, whether the file was intact) of a metrics file.

    A row is whole when its line ends in a newline, it has every column, and its update
    number reads; no header (an empty or missing file) gives (None, [], True)."""
    if not path.exists():
        return None, [], True
    text = path.read_text()
    lines = text.splitlines(keepends=True)
    whole = [line for line in lines if line.endswith("\n")]
    if not whole:
        return None, [], not text
    reader = csv.DictReader(whole)
    columns = list(reader.fieldnames or [])
    rows = [row for row in reader if _readable(row, columns)]
    return columns, rows, len(rows) + 1 == len(lines)


def _readable(row: dict, columns: list[str]) -> bool:
    if None in row or any(row.get(c) is None for c in columns):
        return False
    try:
        int(row["updates"])
    except (KeyError, ValueError):
        return False
    return True


def read_metrics(path: Path) -> list[dict]:
    with Path(path).open(newline="") as handle:
        return list(csv.DictReader(handle))


def plot_curve(metrics_path: Path, png_path: Path, title: str | None = None) -> Path | None:
    """One run's episode return (mean, min-max band) against env steps."""
    return plot_runs({Path(metrics_path).parent.name: metrics_path}, png_path, title)


def plot_runs(
    runs: dict[str, Path],
    png_path: Path,
    title: str | None = None,
    references: dict[str, float] | None = None,
) -> Path | None:
    """Several runs' episode returns (mean line, min-max band) against env steps, one figure;
    `references`: label -> return, drawn as dashed horizontal lines (e.g. published results)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    plotted = False
    for label, metrics_path in runs.items():
        rows = [r for r in read_metrics(metrics_path) if r["return_mean"] not in ("", "nan")]
        if not rows:
            continue
        steps = [int(r["steps"]) for r in rows]
        mean = [float(r["return_mean"]) for r in rows]
        low = [float(r["return_min"]) for r in rows]
        high = [float(r["return_max"]) for r in rows]
        ax.plot(steps, mean, label=f"{label} (mean)")
        ax.fill_between(steps, low, high, alpha=0.2)
        plotted = True
    if not plotted:
        plt.close(fig)
        return None
    for label, value in (references or {}).items():
        ax.axhline(value, linestyle="--", color="gray", linewidth=1)
        ax.annotate(  # at the right edge: the legend takes a corner on the left
            label,
            (0.99, value),
            xycoords=("axes fraction", "data"),
            ha="right",
            va="bottom",
            fontsize=8,
        )
    ax.set_xlabel("env steps")
    ax.set_ylabel("episode return")
    ax.set_title(title or ", ".join(runs))
    ax.legend()
    fig.tight_layout()
    fig.savefig(png_path, dpi=100)
    plt.close(fig)
    return png_path
