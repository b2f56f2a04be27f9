"""`mat train ENV --seeds S`: S independent runs, one process each, sized to the cores.

Seed K is exactly `mat train ENV --seed K --out RUN/seed_K` (the same command, run as a child
process), so every tool takes RUN/seed_K unchanged and a seed of a set equals a solo run.
On CPU a seed's update is compute-bound, so separate processes are the fast way to run many
(BENCHMARKS.md). A failed seed is reported with its log; the others carry on, and running the
same command again resumes what did not finish and skips what did.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

from tqdm import tqdm

DONE_NAME = "finished"  # written in a seed's directory when its run ended well
LOG_NAME = "train.log"


def parse_seeds(text: str) -> list[int]:
    """`10` -> seeds 0..9; `3-7` -> 3..7; `0,4,9` -> those."""
    text = text.strip()
    if re.fullmatch(r"\d+", text):
        count = int(text)
        if count < 1:
            raise ValueError("--seeds 0 runs nothing; give a count >= 1, a range 3-7 or a list")
        return list(range(count))
    if match := re.fullmatch(r"(\d+)-(\d+)", text):
        first, last = int(match[1]), int(match[2])
        if last < first:
            raise ValueError(f"--seeds {text}: the range ends before it starts")
        return list(range(first, last + 1))
    if re.fullmatch(r"\d+(,\d+)+", text):
        seeds = [int(s) for s in text.split(",")]
        if len(set(seeds)) != len(seeds):
            raise ValueError(f"--seeds {text} names a seed twice")
        return seeds
    raise ValueError(f"--seeds {text!r}: give a count (10), a range (3-7) or a list (0,4,9)")


def _steps_done(run: Path) -> int:
    """Env steps in a seed's metrics.csv so far (0 before its first update)."""
    try:
        lines = (run / "metrics.csv").read_text().splitlines()
    except OSError:
        return 0
    return int(lines[-1].split(",")[0]) if len(lines) > 1 else 0


def run_seeds(
    train_args: list[str], seeds: list[int], out: Path, steps: int, processes: int, quiet: bool
) -> list[int]:
    """Run `mat train *train_args --seed K --out out/seed_K` for every seed not finished yet,
    at most `processes` at a time; returns the seeds that failed."""
    out.mkdir(parents=True, exist_ok=True)
    pending = [k for k in seeds if not (out / f"seed_{k}" / DONE_NAME).exists()]
    skipped = len(seeds) - len(pending)
    if skipped:
        print(f"{skipped} of {len(seeds)} seeds already finished in {out}; running the rest")
    running: dict[int, tuple[subprocess.Popen, object]] = {}
    failed: list[int] = []
    bar = tqdm(total=steps * len(seeds), unit="step", disable=quiet, desc=f"{len(seeds)} seeds")
    try:
        while pending or running:
            while pending and len(running) < processes:
                seed = pending.pop(0)
                run = out / f"seed_{seed}"
                run.mkdir(exist_ok=True)
                command = [
                    sys.executable,
                    "-m",
                    "mat_sdk",
                    "train",
                    *train_args,
                    "--seed",
                    str(seed),
                ]
                command += ["--out", str(run), "--quiet"]
                if (run / "checkpoint.pt").exists():
                    command.append("--resume")
                log = (run / LOG_NAME).open("a")
                running[seed] = (
                    subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT),
                    log,
                )
            time.sleep(0.5)
            for seed, (process, log) in list(running.items()):
                if process.poll() is None:
                    continue
                log.close()
                del running[seed]
                run = out / f"seed_{seed}"
                if process.returncode == 0:
                    (run / DONE_NAME).touch()
                else:
                    failed.append(seed)
                    tqdm.write(
                        f"seed {seed} failed (exit {process.returncode}); its log: {run / LOG_NAME}"
                    )
            bar.n = sum(min(steps, _steps_done(out / f"seed_{k}")) for k in seeds)
            bar.set_postfix(running=len(running), failed=len(failed))
            bar.refresh()
    finally:
        bar.close()
        for process, log in running.values():  # interrupted: stop the children, keep their runs
            process.terminate()
            process.wait()
            log.close()
    return sorted(failed)
