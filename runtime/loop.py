"""A fixed-rate control loop and the figures a controller is judged by: its worst ticks.

    from mat_runtime import Policy, loop
    awake = loop.keep_awake(3)                    # optional: core 3 never idles
    notes = loop.realtime(cpu=3, fifo=80)        # pin + SCHED_FIFO where permitted
    ticks = loop.run(act=lambda: policy.act(obs, out=actions), step=robot_io, rate=1000)
    print(ticks.summary())                        # act p50 / p99 / p99.9 / max, late ticks

Each tick runs `act` (timed) and then `step` (sensor read, actuator write), then waits for the
next tick: it sleeps until `spin_margin` before it, then busy-waits the rest, because a
sleep's wake-up on Linux overshoots by tens of microseconds, a large share of a 1 ms tick.
Python's cyclic garbage collector is off while the loop runs (collected once before it, and
restored after): a collection over a simulator's heap pauses for milliseconds, a whole tick.
A tick that overruns its slot is late; the loop does not try to catch up (the next tick
starts at once and the schedule restarts from it).

Under SCHED_FIFO do not `spin` the whole gap: a real-time task that never sleeps hits the
kernel's real-time throttling (by default 50 ms of every second go to other tasks), which
stalls the loop for that long (BENCHMARKS.md). To keep a core from idling between ticks
without that, `keep_awake(cpu)` spins a second process on it at SCHED_IDLE, the lowest
priority, which the loop preempts the moment it wakes: an idle core drops into a sleep state
(and, in a virtual machine, is descheduled by the hypervisor) that the next tick pays to
leave.
"""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

SPIN_MARGIN = 200e-6  # seconds of busy-waiting before each tick
WARMUP = 1.0  # seconds run before measuring


def realtime(cpu: int | None = None, fifo: int | None = None) -> list[str]:
    """Pin this process to core `cpu` and/or run it under SCHED_FIFO at priority `fifo`
    (1-99), where the OS permits; returns one note per request saying what happened, so a
    controller can print why it runs without (e.g. no CAP_SYS_NICE in a container)."""
    notes = []
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})
            notes.append(f"pinned to CPU {cpu}")
        except (OSError, ValueError) as error:
            cores = sorted(os.sched_getaffinity(0))
            notes.append(f"not pinned to CPU {cpu} ({error}); allowed CPUs: {cores}")
    if fifo is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo))
            notes.append(f"SCHED_FIFO at priority {fifo} (sleep between ticks: do not spin)")
        except PermissionError:
            notes.append(
                "SCHED_FIFO not permitted: run as root or grant CAP_SYS_NICE "
                "(e.g. `sudo setcap cap_sys_nice+ep $(readlink -f $(which python))`, or "
                "rtprio in /etc/security/limits.conf); running at normal priority"
            )
        except (OSError, ValueError) as error:
            notes.append(f"SCHED_FIFO at priority {fifo} refused ({error}); normal priority")
    return notes


# Spins at SCHED_IDLE on one core until its parent exits (checked every few milliseconds).
_AWAKE = """
import os, sys
parent = os.getppid()
os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
os.sched_setaffinity(0, {int(sys.argv[1])})
print("ready", flush=True)
while os.getppid() == parent:
    for _ in range(100_000):
        pass
"""


def keep_awake(cpu: int) -> subprocess.Popen:
    """Keep core `cpu` from idling: a process spinning on it at SCHED_IDLE, which any other
    task (the controller above all) preempts at once. Returns once it spins; `.terminate()`
    it when done (it also ends with this process). It burns the core's idle time, so give
    it a core that serves the controller alone. Start it before `realtime`, or it starts
    as a real-time task (children inherit SCHED_FIFO) until it lowers itself."""
    if cpu not in os.sched_getaffinity(0):
        raise ValueError(
            f"CPU {cpu} is not one this process may use: {sorted(os.sched_getaffinity(0))}"
        )
    spinner = subprocess.Popen(
        [sys.executable, "-c", _AWAKE, str(cpu)], stdout=subprocess.PIPE, text=True
    )
    if spinner.stdout.readline().strip() != "ready":
        spinner.kill()
        raise RuntimeError(f"the process that keeps CPU {cpu} awake did not start")
    return spinner


@dataclass
class Ticks:
    """What a run of the loop measured."""

    act_seconds: np.ndarray  # each tick's act call
    wake_seconds: np.ndarray  # how late each tick started after its scheduled time
    late: int  # ticks whose act + step overran the period
    elapsed: float  # seconds from the first measured tick to the end
    rate: float  # the target, Hz

    def percentiles(self) -> dict[str, float]:
        """act's p50, p99, p99.9 and max, in microseconds."""
        micros = self.act_seconds * 1e6
        quantiles = np.percentile(micros, [50, 99, 99.9])
        return dict(zip(("p50", "p99", "p99.9"), quantiles.tolist(), strict=True)) | {
            "max": float(micros.max())
        }

    def summary(self) -> str:
        ticks = len(self.act_seconds)
        p = self.percentiles()
        wake = np.percentile(self.wake_seconds * 1e6, 99)
        return (
            f"{ticks} ticks in {self.elapsed:.2f} s: {ticks / self.elapsed:.1f} Hz "
            f"(target {self.rate:g} Hz)\n"
            f"act: p50 {p['p50']:.0f} µs, p99 {p['p99']:.0f} µs, p99.9 {p['p99.9']:.0f} µs, "
            f"max {p['max']:.0f} µs; late ticks: {self.late}; tick start p99 "
            f"{wake:.0f} µs after schedule"
        )


def run(
    act: Callable[[], object],
    step: Callable[[], object],
    rate: float,
    seconds: float = 10.0,
    warmup: float = WARMUP,
    spin: bool = False,
    spin_margin: float = SPIN_MARGIN,
) -> Ticks:
    """Run `act` then `step` at `rate` Hz for `warmup` seconds (not measured: caches, ORT's
    first calls), then for `seconds` measured; `spin`: busy-wait the whole gap (one core
    stays hot) instead of sleeping until `spin_margin` before each tick."""
    if rate <= 0 or seconds <= 0 or warmup < 0:
        raise ValueError(
            f"rate and seconds must be > 0 and warmup >= 0; got {rate}, {seconds}, {warmup}"
        )
    period = 1.0 / rate
    warm_ticks, ticks = int(warmup * rate), max(1, int(seconds * rate))
    act_seconds, wake_seconds = np.empty(ticks), np.empty(ticks)  # no allocation per tick
    collecting = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        return _ticks(act, step, rate, period, warm_ticks, ticks, spin, spin_margin,
                      act_seconds, wake_seconds)  # fmt: skip
    finally:
        if collecting:
            gc.enable()


def _ticks(act, step, rate, period, warm_ticks, ticks, spin, spin_margin, act_seconds,
           wake_seconds) -> Ticks:  # fmt: skip
    clock = time.perf_counter
    late, start, next_tick = 0, 0.0, clock()
    for tick in range(-warm_ticks, ticks):
        if tick == 0:
            late, start = 0, clock()
        begin = clock()
        act()
        done = clock()
        step()
        if tick >= 0:
            act_seconds[tick], wake_seconds[tick] = done - begin, max(0.0, begin - next_tick)
        next_tick += period
        if clock() >= next_tick:
            late += 1  # overran its slot: start the next tick now, not in a burst
            next_tick = clock()
            continue
        if not spin:
            pause = next_tick - clock() - spin_margin
            if pause > 0:
                time.sleep(pause)
        while clock() < next_tick:
            pass
    return Ticks(act_seconds, wake_seconds, late, clock() - start, rate)
