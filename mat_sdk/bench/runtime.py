"""One control step, four ways, side by side (`mat bench runtime`).

(a) runtime: `mat_runtime.Policy.act` (one `decode.onnx` call, input checks included);
(b) official: the official code's `get_actions` (`bench.reference.OfficialStyleMAT.act`):
    torch, the whole decoder re-run over all n positions for every agent (O(n^2)), with its
    masked-softmax attention and a validated `Normal` per agent;
(b') the same O(n^2) loop on our decoder (`official_loop_act`: fused attention, no
    distribution), to show how much of (b) is the algorithm and how much the code;
(c) torch cached: our KV-cached `MAT.act`;
(d) step graph: `Policy.load(bundle, graph="step")`, `encoder.onnx` then `decoder_step.onnx`
    once per agent with the KV caches (`mat_runtime.step`).
B = 1 unless stated, one thread everywhere, deterministic actions, interleaved rounds.
"""

from __future__ import annotations

import copy
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from mat_export.exporter import export
from mat_runtime import Policy
from mat_sdk.bench import machine
from mat_sdk.bench.reference import OfficialStyleMAT
from mat_sdk.common.timing import print_table
from mat_sdk.training.trainer import Trainer

SIZES = {
    "1 block, 1 head": {"n_block": 1, "n_head": 1},
    "3 blocks, 4 heads": {"n_block": 3, "n_head": 4},
}
# Scaled to 1,024 agents beside SIZES: attention limited to the 8 nearest agents on each side
# (`attention_window`), whose control step is linear in n where full attention's is not.
WINDOWED = {
    "1 block, 1 head, window 8": {"n_block": 1, "n_head": 1, "attention_window": 8},
    "3 blocks, 4 heads, window 8": {"n_block": 3, "n_head": 4, "attention_window": 8},
}
AGENTS = (2, 6, 17, 64, 256)


def latencies(
    variants: dict[str, Callable[[], object]], seconds: float, rounds: int = 5
) -> dict[str, np.ndarray]:
    """Seconds of every single call, variants interleaved round by round (>= 1 call each)."""
    samples: dict[str, list[float]] = {name: [] for name in variants}
    for fn in variants.values():
        fn()  # warm-up
    budget = seconds / rounds / len(variants)
    for _ in range(rounds):
        for name, fn in variants.items():
            start = time.perf_counter()
            while True:
                begin = time.perf_counter()
                fn()
                samples[name].append(time.perf_counter() - begin)
                if begin - start >= budget:
                    break
    return {name: np.asarray(times) for name, times in samples.items()}


def untrained_bundle(directory: Path, env_id: str = "cheetah-6x1", **model) -> tuple[Path, object]:
    """A freshly initialised policy for `env_id`, exported to `directory`/bundle, and its
    torch module: the speed of a step does not depend on what the weights learned."""
    with Trainer(
        env_id, "mat", num_envs=1, rollout_length=1, num_minibatches=1, **model
    ) as trainer:
        path = trainer.save(directory / "model.pt")
        policy = trainer.policy.eval()
    export(path, directory / "bundle", agent_counts=(1, 2))
    return directory / "bundle", policy


def official_loop_act(policy, obs: torch.Tensor) -> torch.Tensor:
    """The official code's loop on our decoder: the full decoder over all n positions, once per
    agent."""
    with torch.no_grad():
        rep, _ = policy.encoder(obs)
        batch, n, _ = obs.shape
        shifted = torch.zeros(batch, n, policy.cfg.action_size)
        actions = torch.zeros(batch, n, policy.cfg.action_size)
        for i in range(n):
            actions[:, i] = policy.decoder(shifted, rep)[:, i]
            if i + 1 < n:
                shifted[:, i + 1] = actions[:, i]
        return actions


def _variants(bundle: Path, policy, obs: np.ndarray) -> dict[str, Callable[[], object]]:
    runtime = Policy.load(bundle, threads=1)
    stepped = Policy.load(bundle, threads=1, graph="step")
    x = torch.from_numpy(obs)
    official = OfficialStyleMAT(copy.deepcopy(policy), obs.shape[1]).eval()

    return {
        "runtime": lambda: runtime.act(obs),
        "official": lambda: official.act(x),
        "official loop": lambda: official_loop_act(policy, x),
        "torch cached": lambda: policy.act(x, deterministic=True),
        "step graph": lambda: stepped.act(obs),
    }


def _us(seconds: float) -> str:
    return f"{seconds * 1e6:,.0f}"


SCALING = (64, 256, 1024)

# Run in a fresh process per agent count: how much resident memory acting at n adds to a
# loaded policy (ONNX Runtime keeps the buffers it grew for that n), in MiB. Resident, not
# the peak: the process's peak is set by its imports, far above these buffers.
_MEMORY_ADDED = """
import sys
import numpy as np
from mat_runtime import Policy

def resident_kib():
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS:"))

policy = Policy.load(sys.argv[1], threads=1)
n, dim = int(sys.argv[2]), policy.obs_dim
policy.act(np.zeros((1, dim), np.float32))
before = resident_kib()
for _ in range(3):
    policy.act(np.random.default_rng(0).standard_normal((n, dim)).astype(np.float32))
print((resident_kib() - before) / 1024)
"""


def memory_added_mib(bundle: Path, n: int) -> float:
    """What acting at n agents adds to a loaded policy's resident memory, in MiB (Linux)."""
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-c", _MEMORY_ADDED, str(bundle), str(n)],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    return float(done.stdout.strip())


def _scaling(bundle: Path, obs_dim: int, seconds: float) -> dict[int, float]:
    """p50 of the runtime at each n of SCALING, interleaved round by round, so a change in
    the machine's speed between the rows cannot skew their ratios."""
    runtime = Policy.load(bundle, threads=1)
    rng = np.random.default_rng(0)
    obs = {n: rng.standard_normal((n, obs_dim)).astype(np.float32) for n in SCALING}
    times = latencies({n: lambda x=x: runtime.act(x) for n, x in obs.items()}, seconds)
    return {n: float(np.median(times[n])) for n in SCALING}


def idle_cpu_ms(policy: Policy, obs: np.ndarray, idle: float = 0.01, rounds: int = 50) -> float:
    """CPU milliseconds the process burns while it idles `idle` seconds after an act, as a
    controller does between ticks (spinning threads keep burning)."""
    burned = 0.0
    for _ in range(rounds):
        policy.act(obs)
        start = time.process_time()
        time.sleep(idle)
        burned += time.process_time() - start
    return burned / rounds * 1e3


def spinning(bundle: Path, obs_dim: int, seconds: float, n: int = 6) -> list[dict]:
    """act's latency back-to-back and the CPU burned while idle, spin off and on, 1 and 2
    ONNX Runtime threads, interleaved."""
    obs = np.random.default_rng(0).standard_normal((n, obs_dim)).astype(np.float32)
    loaded = {
        (threads, spin): Policy.load(bundle, threads=threads, spin=spin)
        for threads in (1, 2)
        for spin in (False, True)
    }
    times = latencies({key: lambda p=p: p.act(obs) for key, p in loaded.items()}, seconds)
    return [
        {
            "threads": threads,
            "spin": "on" if spin else "off",
            "act p50 / p99 (µs)": f"{_us(np.median(times[key]))} / "
            f"{_us(np.percentile(times[key], 99))}",
            "CPU burned per 10 ms idle (ms)": f"{idle_cpu_ms(loaded[key], obs):.2f}",
        }
        for key in loaded
        for threads, spin in [key]
    ]


def main(agent_counts=AGENTS, seconds: float = 2.0, scale: bool = True) -> None:
    """The table of variants at `agent_counts`; with `scale`, the runtime alone at
    n = 64, 256, 1024 (the other variants are O(n^2) or Python loops: minutes at 1,024), full
    attention and windowed."""
    torch.set_num_threads(1)
    rows, scaling = [], []
    for label, model in SIZES.items():
        with tempfile.TemporaryDirectory() as tmp:
            bundle, policy = untrained_bundle(Path(tmp), **model)
            cases = [(1, n) for n in agent_counts] + [(40, 6)]
            for batch, n in cases:
                obs = np.random.default_rng(0).standard_normal((batch, n, policy.cfg.obs_dim))
                times = latencies(_variants(bundle, policy, obs.astype(np.float32)), seconds)
                p50 = {name: float(np.median(t)) for name, t in times.items()}
                rows.append(
                    {
                        "model": label,
                        "B": batch,
                        "agents": n,
                        "(a) runtime p50 / p99 (µs)": (
                            f"{_us(p50['runtime'])} / {_us(np.percentile(times['runtime'], 99))}"
                        ),
                        "(b) official p50 (µs)": _us(p50["official"]),
                        "(b') official loop, our decoder p50 (µs)": _us(p50["official loop"]),
                        "(c) torch cached p50 (µs)": _us(p50["torch cached"]),
                        "(d) step graph p50 (µs)": _us(p50["step graph"]),
                        "(a) vs (b)": f"{p50['official'] / p50['runtime']:.1f}x",
                        "(a) vs (d)": f"{p50['step graph'] / p50['runtime']:.1f}x",
                    }
                )
    print_table(rows, f"One control step, one thread — {machine()}")
    scaled = {**SIZES, **WINDOWED} if scale else {}
    for label, model in scaled.items():
        with tempfile.TemporaryDirectory() as tmp:
            bundle, policy = untrained_bundle(Path(tmp), **model)
            times = _scaling(bundle, policy.cfg.obs_dim, seconds)
            scaling += [
                {
                    "model": label,
                    "agents": n,
                    "runtime p50 (µs)": _us(t),
                    "t(n) / t(n / 4)": f"{t / times[n // 4]:.2f}" if n // 4 in times else "",
                    "memory added (MiB)": f"{memory_added_mib(bundle, n):.1f}",
                }
                for n, t in times.items()
            ]
    with tempfile.TemporaryDirectory() as tmp:
        bundle, policy = untrained_bundle(Path(tmp), **SIZES["1 block, 1 head"])
        table = spinning(bundle, policy.cfg.obs_dim, seconds)
    print_table(table, "Spinning (Policy.load(spin=...)), 1 block, n = 6")
    if scaling:
        print_table(
            scaling, "Scaling in n: the runtime alone, interleaved (linear: t(n)/t(n/4) = 4)"
        )
