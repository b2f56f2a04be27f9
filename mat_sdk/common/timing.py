"""Timing that holds on noisy machines: variants measured side by side in interleaved rounds,
and the Markdown tables they are reported in (benchmarks and `mat train`'s tuning)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np


def compare(variants: dict[str, Callable[[], object]], seconds: float = 1.0, rounds: int = 9):
    """Median seconds per call of each variant, measured in interleaved rounds.

    Every round runs each variant once for about `seconds / rounds / len(variants)`, so slow
    phases of a noisy machine hit all variants alike.
    """
    calls = {}
    for name, fn in variants.items():
        fn()
        n, start = 1, time.perf_counter()
        while time.perf_counter() - start < 0.02:
            fn()
            n += 1
        per_call = (time.perf_counter() - start) / n
        calls[name] = max(1, int(seconds / rounds / len(variants) / per_call))
    samples: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(rounds):
        for name, fn in variants.items():
            start = time.perf_counter()
            for _ in range(calls[name]):
                fn()
            samples[name].append((time.perf_counter() - start) / calls[name])
    return {name: float(np.median(times)) for name, times in samples.items()}


def print_table(rows: Sequence[dict], title: str = "") -> str:
    """Print rows as a Markdown table (ready to paste into BENCHMARKS.md) and return it."""
    columns = list(rows[0])
    lines = [f"| {' | '.join(columns)} |", f"|{'|'.join('---' for _ in columns)}|"]
    lines += [f"| {' | '.join(str(row[c]) for c in columns)} |" for row in rows]
    text = (f"### {title}\n\n" if title else "") + "\n".join(lines) + "\n"
    print(text, flush=True)
    return text
