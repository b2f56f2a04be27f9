"""Benchmarks that compare variants side by side in one run (`mat bench ...`).

Absolute times on shared machines are noisy; ratios measured in the same run are not.
"""

from __future__ import annotations

import platform
import time
from collections.abc import Callable, Sequence

import numpy as np


def time_per_call(fn: Callable[[], object], min_seconds: float = 0.5, repeats: int = 5) -> float:
    """Median seconds per call over `repeats` runs of at least `min_seconds / repeats` each."""
    fn()
    calls = 1
    while True:  # find how many calls fill one run
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        if time.perf_counter() - start > min_seconds / repeats:
            break
        calls *= 2
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        runs.append((time.perf_counter() - start) / calls)
    return float(np.median(runs))


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    return f"{platform.node()} ({cpu}), python {platform.python_version()}"


def print_table(rows: Sequence[dict], title: str = "") -> str:
    """Print rows as a Markdown table (ready to paste into BENCHMARKS.md) and return it."""
    columns = list(rows[0])
    lines = [f"| {' | '.join(columns)} |", f"|{'|'.join('---' for _ in columns)}|"]
    lines += [f"| {' | '.join(str(row[c]) for c in columns)} |" for row in rows]
    text = (f"### {title}\n\n" if title else "") + "\n".join(lines) + "\n"
    print(text, flush=True)
    return text
