"""The control loop's worst ticks, idle and under load (`mat bench jitter`).

First one step back to back: medians, then call by call (the machine's own spread, the floor
of the loop's figures). Then `mat_runtime.loop` (what `examples/controller.py` runs) on
simulated robots at the paper's model size, one ORT thread, `act(obs, out=...)`: n = 6
(cheetah-6x1) at 1 kHz and n = 64 (swimmer-65) at 100 Hz, each for `seconds` (one episode
throughout: no simulator resets between ticks) with the machine otherwise idle, and again
while one busy process per core (started and stopped here) competes for every CPU.
`keep_awake`: the loop's core is kept from idling between ticks by a SCHED_IDLE spinner
(`mat_runtime.loop.keep_awake`). After the idle rows, the core's own stalls with no policy
(`core_stalls`): gaps of a millisecond there are late ticks no controller can avoid.
"""

from __future__ import annotations

import multiprocessing
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from mat_runtime import Policy, loop
from mat_sdk.bench import machine
from mat_sdk.bench.runtime import untrained_bundle
from mat_sdk.common.timing import compare, print_table
from mat_sdk.envs import make_team

ROBOTS = (("cheetah-6x1", 1000.0), ("swimmer-65", 100.0))  # (env, rate): n = 6, n = 64


def _burn(cores: set[int]) -> None:
    """Spin forever at normal priority on any core (a child inherits the loop's pinning and
    SCHED_FIFO, which would make it compete as a real-time task, or starve the machine)."""
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    os.sched_setaffinity(0, cores)
    while True:
        pass


def _measure(bundle: Path, env_id: str, rate: float, seconds: float, spin: bool) -> dict:
    # one episode for the whole run: a simulator's reset (1.3-1.5 ms for a cheetah) is not a
    # controller's tick, and at 1 kHz each one would count as a late tick
    episode = int(rate * (seconds + 2 * loop.WARMUP)) + 1
    policy = Policy.load(bundle, threads=1)
    options = {**policy.env_options, "episode_limit": episode}  # the robot as trained
    team = make_team(env_id, faults=policy.env_faults, **options)
    obs = np.zeros((team.n_agents, policy.obs_dim), np.float32)
    obs[:] = team.reset(seed=0)
    actions = np.zeros((team.n_agents, policy.action_size), np.float32)

    def step() -> None:
        observed, _, terminated, truncated = team.step(actions)
        obs[:] = team.reset() if terminated or truncated else observed

    ticks = loop.run(lambda: policy.act(obs, out=actions), step, rate, seconds, spin=spin)
    p = ticks.percentiles()
    return {
        "robot": f"{env_id} (n = {team.n_agents})",
        "rate": f"{rate:g} Hz",
        **{f"act {name} µs": f"{value:.0f}" for name, value in p.items()},
        "late ticks": f"{ticks.late} / {len(ticks.act_seconds)}",
        "tick start p99 µs": f"{np.percentile(ticks.wake_seconds * 1e6, 99):.0f}",
    }


def call_overhead(bundle: Path, seconds: float = 3.0) -> list[dict]:
    """Back-to-back cost of one step at n = 6: `act(obs)`, `act(obs, out=...)` and ONNX
    Runtime's own call on the same bound buffers (what the Python around it adds)."""
    policy = Policy.load(bundle, threads=1)
    obs = np.random.default_rng(0).standard_normal((6, policy.obs_dim)).astype(np.float32)
    out = np.zeros((6, policy.action_size), np.float32)
    policy.act(obs, out=out)
    bound = policy._bound(1, 6)  # the buffers act(obs) just bound
    times = compare(
        {
            "act(obs)": lambda: policy.act(obs),
            "act(obs, out=...)": lambda: policy.act(obs, out=out),
            "ORT run_with_iobinding alone": lambda: bound.session.run_with_iobinding(bound.binding),
        },
        seconds=seconds,
    )
    fastest = min(times.values())
    return [
        {
            "call (n = 6, back to back)": name,
            "µs": f"{t * 1e6:.1f}",
            "vs ORT alone": f"{t / fastest:.2f}x",
        }
        for name, t in times.items()
    ]


def call_by_call(bundle: Path, calls: int = 20_000) -> list[dict]:
    """`act(obs, out=...)` at n = 6 timed call by call, back to back: the spread the machine
    itself gives a step, with no loop, sleep or wake-up (the floor of the loop's figures).
    A 0.5 ms pause every 20 calls keeps a SCHED_FIFO process under real-time throttling."""
    policy = Policy.load(bundle, threads=1)
    obs = np.random.default_rng(0).standard_normal((6, policy.obs_dim)).astype(np.float32)
    out = np.zeros((6, policy.action_size), np.float32)
    times, clock = np.empty(calls), time.perf_counter
    for i in range(-1000, calls):  # the first thousand warm up
        start = clock()
        policy.act(obs, out=out)
        if i >= 0:
            times[i] = clock() - start
        if i % 20 == 0:
            time.sleep(0.0005)
    micros = times * 1e6
    p50, p99, p999 = np.percentile(micros, [50, 99, 99.9])
    return [
        {
            "call (n = 6, one by one)": f"act(obs, out=...), {calls:,} calls",
            "p50 µs": f"{p50:.0f}",
            "p99 µs": f"{p99:.0f}",
            "p99.9 µs": f"{p999:.0f}",
            "max µs": f"{micros.max():.0f}",
        }
    ]


STALLS = (100e-6, 500e-6, 1e-3)  # gap lengths counted by `core_stalls`, seconds


def core_stalls(seconds: float) -> list[dict]:
    """How often the core itself stops running this process, with no policy at all: a tight
    loop reads the clock for `seconds` and counts the gaps between reads longer than each of
    STALLS (an interrupt, the kernel, a hypervisor taking the vCPU). A gap longer than a
    tick's slack makes a late tick whatever the controller does. The loop sleeps 0.5 ms
    every 5 ms, so a SCHED_FIFO process stays clear of real-time throttling; those sleeps
    are not counted."""
    clock, gaps = time.perf_counter, []
    end = clock() + seconds
    while clock() < end:
        last = clock()
        burst = last + 5e-3
        while last < burst:
            now = clock()
            if now - last > STALLS[0]:
                gaps.append(now - last)
            last = now
        time.sleep(0.0005)
    gaps = np.asarray(gaps)
    return [
        {
            "core, no policy": f"clock read back to back for {seconds:g} s",
            **{f"gaps > {limit * 1e6:.0f} µs": f"{(gaps > limit).sum()}" for limit in STALLS},
            "longest µs": f"{gaps.max() * 1e6:.0f}" if gaps.size else "-",
        }
    ]


def main(
    seconds: float = 10.0,
    cpu: int | None = None,
    fifo: int | None = None,
    spin: bool = False,
    keep_awake: bool = False,
) -> None:
    every_core = os.sched_getaffinity(0)  # before pinning: where the load runs
    awake = loop.keep_awake(cpu) if keep_awake else None  # started before SCHED_FIFO
    try:
        _tables(seconds, cpu, fifo, spin, every_core, awake)
    finally:
        if awake is not None:
            awake.terminate()
            awake.wait()


def _tables(seconds, cpu, fifo, spin, every_core, awake) -> None:
    notes = loop.realtime(cpu, fifo)
    if awake is not None:
        notes.append(f"CPU {cpu} kept awake by a SCHED_IDLE spinner")
    print(f"machine: {machine()}; {os.cpu_count()} CPUs; " + "; ".join(notes or ["no pinning"]))
    with tempfile.TemporaryDirectory() as tmp:
        bundles = {env_id: untrained_bundle(Path(tmp) / env_id, env_id)[0] for env_id, _ in ROBOTS}
        print_table(call_overhead(bundles["cheetah-6x1"]), "one step, back to back")
        print_table(call_by_call(bundles["cheetah-6x1"]), "one step, back to back, call by call")
        idle = [_measure(bundles[e], e, rate, seconds, spin) for e, rate in ROBOTS]
        print_table(idle, f"idle machine, {seconds:g} s per row")
        print_table(core_stalls(seconds), "the core's own stalls, idle machine")
        context = multiprocessing.get_context("spawn")
        burners = [
            context.Process(target=_burn, args=(every_core,), daemon=True) for _ in every_core
        ]
        for burner in burners:
            burner.start()
        try:
            loaded = [_measure(bundles[e], e, rate, seconds, spin) for e, rate in ROBOTS]
        finally:
            for burner in burners:
                burner.terminate()
                burner.join()
        print_table(loaded, f"{len(burners)} busy processes competing, {seconds:g} s per row")
