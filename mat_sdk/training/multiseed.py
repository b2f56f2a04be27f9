"""`mat train ENV --seeds S`: S independent runs, one process each, sized to the cores.

Seed K is `runs.train` of the set's request with seed K into RUN/seed_K, run in a child
process (the same call `mat train --seed K --out RUN/seed_K` makes), so every tool takes
RUN/seed_K unchanged and a seed of a set equals a solo run. The update settings are tuned
once, by the set, and given to every seed. On CPU a seed's update is compute-bound, so
separate processes are the fast way to run many (BENCHMARKS.md). A failed seed is reported
with its log; the others carry on, and running the same command again resumes what did not
finish and skips what did. With `--ray` each seed is a Ray task instead (`ray_launcher`),
retried from its checkpoint when its run or worker is killed; its rollouts run in the task
(with `--workers`, in env worker processes beside it), not on Ray actors of their own.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import functools
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from tqdm import tqdm

from mat_sdk.common import files
from mat_sdk.common.processes import usable_cores
from mat_sdk.training.runs import RunRequest

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
        return int(lines[-1].split(",")[0]) if len(lines) > 1 else 0
    except (OSError, UnicodeDecodeError, ValueError):  # not written yet, or not ours: the
        return 0  # seed's own run sets a foreign file aside


SET_NAME = "seed_set.json"  # the set's request, which every seed's child reads


def seed_command(request_path: Path, seed: int) -> list[str]:
    """Seed K's child: the set's request as seed K, started through `_die_with_parent`."""
    parent = ["--parent", str(os.getpid())]
    return [*python("mat_sdk.training.multiseed:seed_main"), *parent, str(request_path), str(seed)]


def default_out(env_id: str, algo: str) -> Path:
    """A seed set's directory by default: runs/ENV-ALGO (its seeds in seed_K)."""
    return Path("runs") / f"{env_id.replace(':', '_')}-{algo}"


def seed_request(request: RunRequest, seed: int) -> RunRequest:
    """The set's request as seed K's own run: seed K in OUT/seed_K, resumed when it holds a
    checkpoint."""
    run = Path(request.out) / f"seed_{seed}"
    return dataclasses.replace(
        request, out=run, options={**request.options, "seed": seed},
        resume=(run / "checkpoint.pt").exists(), tune=False, free_cores=0,
    )  # fmt: skip


def train_seeds(
    request: RunRequest,
    seeds: list[int],
    ray_address: str | None = None,
    quiet: bool = False,
    say=print,
) -> list[int]:
    """Run `request` once per seed into OUT/seed_K (see the module docstring); the update
    settings tuned once here. -> the seeds that failed (the others finished)."""
    from mat_sdk.training.runs import tuned, with_task_recipe

    # a seed's rollouts run where its task runs: a nested Ray instance per seed would only
    # add processes to the cores its task holds
    request = with_task_recipe(
        dataclasses.replace(
            request,
            options={**request.options, "ray": None},
            given=[name for name in request.given if name != "ray"],
        )
    )
    out = Path(request.out)
    cores = usable_cores()
    workers = request.options.get("workers", 0)
    # tuned so that no seed waits for a core: each keeps its share of them
    share = cores // min(len(seeds), cores)
    settings = tuned(dataclasses.replace(request, free_cores=share - 1 - workers), say)
    request = dataclasses.replace(
        request, options={**request.options, **settings},
        given=sorted({*request.given, *settings}),
    )  # fmt: skip
    per_seed = 1 + workers + request.options.get("update_workers", 0)
    with files.RunLock(out):  # one seed set at a time in OUT
        files.write_text_atomic(out / SET_NAME, request.to_json())
        if ray_address is None:
            processes = max(1, min(len(seeds), cores // per_seed))
            say(f"{len(seeds)} seeds into {out}/seed_K, {processes} at a time")
            launch = _LocalSeed
        else:  # every seed a Ray task of per_seed CPUs, queued by Ray; OUT on shared storage
            processes = len(seeds)
            launch = ray_launcher(ray_address, per_seed)
            say(f"{len(seeds)} seeds into {out}/seed_K as Ray tasks of {per_seed} CPU(s)")
        return run_seeds(out / SET_NAME, seeds, out, request.steps, processes, quiet, launch)


def python(entry: str) -> list[str]:
    """A command line that runs `module:function` in a new interpreter whose import path is
    this one's: `python -m` or `-c` would put the working directory first, so a `random.py`
    lying there would be imported in place of the standard library's."""
    module, _, function = entry.partition(":")
    code = (
        f"import sys; sys.path.pop(0); sys.argv[0] = 'mat'; "
        f"from {module} import {function}; {function}()"
    )
    return [sys.executable, "-c", code]


class _LocalSeed:
    """One seed as a child process of this one."""

    def __init__(self, request_path: Path, seed: int, run: Path):
        self.log = (run / LOG_NAME).open("a")
        command = seed_command(request_path, seed)
        self.process = subprocess.Popen(command, stdout=self.log, stderr=subprocess.STDOUT)

    def poll(self) -> tuple[int, str] | None:
        """None while it runs, then (exit status, how it ended)."""
        code = self.process.poll()
        if code is None:
            return None
        self.log.close()
        return code, f"exit {code}"

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait()
        self.log.close()


class SeedInterrupted(RuntimeError):
    """A seed's child was killed by a signal: Ray retries the task, which resumes it."""


def _ray_seed(request_path: str, seed: int, run: str) -> int:
    """One seed as a Ray task: its child runs on the task's node, into `run` (a path every
    node sees, e.g. on shared storage), resuming from the checkpoint a killed try left."""
    run_dir = Path(run)
    run_dir.mkdir(parents=True, exist_ok=True)
    with (run_dir / LOG_NAME).open("a") as log:
        command = seed_command(Path(request_path), seed)
        code = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT).returncode
    if code < 0:
        raise SeedInterrupted(f"seed {seed}'s run was killed by signal {-code}")
    return code


class _RaySeed:
    """One seed as a Ray task; a killed try (its child or its worker) is retried."""

    def __init__(self, task, request_path: Path, seed: int, run: Path):
        import ray

        self.ray, self.ref = ray, task.remote(str(request_path.resolve()), seed, str(run.resolve()))

    def poll(self) -> tuple[int, str] | None:
        ready, _ = self.ray.wait([self.ref], timeout=0)
        if not ready:
            return None
        try:
            code = self.ray.get(self.ref)
        except self.ray.exceptions.RayError as error:
            return 1, f"Ray gave up after {RAY_RETRIES} retries: {str(error).splitlines()[0]}"
        return code, f"exit {code}"

    def stop(self) -> None:
        self.ray.cancel(self.ref, force=True)  # the worker dies, and its child with it


RAY_RETRIES = 3  # tries of a seed's task after its worker or child was killed


def ray_launcher(address: str, cpus_per_seed: int):
    """Start seeds as Ray tasks on the cluster at `address` ("local": a Ray instance here),
    each asking for `cpus_per_seed` CPUs and retried up to RAY_RETRIES times when killed."""
    from mat_sdk.training.ray_rollouts import connect

    connect(address)
    import ray

    task = ray.remote(
        num_cpus=cpus_per_seed, max_retries=RAY_RETRIES, retry_exceptions=[SeedInterrupted]
    )(_ray_seed)
    return functools.partial(_RaySeed, task)


def run_seeds(
    request_path: Path,
    seeds: list[int],
    out: Path,
    steps: int,
    processes: int,
    quiet: bool,
    launch=_LocalSeed,
) -> list[int]:
    """Run the request at `request_path` as seed K into out/seed_K for every seed not
    finished yet, at most `processes` at a time, each started by `launch(request_path, seed,
    run)` (a child process here, or `ray_launcher`'s tasks); returns the seeds that failed."""
    out.mkdir(parents=True, exist_ok=True)
    pending = [k for k in seeds if not (out / f"seed_{k}" / DONE_NAME).exists()]
    skipped = len(seeds) - len(pending)
    if skipped:
        print(f"{skipped} of {len(seeds)} seeds already finished in {out}; running the rest")
    running: dict[int, _LocalSeed | _RaySeed] = {}
    failed: list[int] = []
    bar = tqdm(total=steps * len(seeds), unit="step", disable=quiet, desc=f"{len(seeds)} seeds")
    try:
        while pending or running:
            while pending and len(running) < processes:
                seed = pending.pop(0)
                run = out / f"seed_{seed}"
                run.mkdir(exist_ok=True)
                running[seed] = launch(request_path, seed, run)
            time.sleep(0.5)
            for seed, launched in list(running.items()):
                result = launched.poll()
                if result is None:
                    continue
                del running[seed]
                run = out / f"seed_{seed}"
                if result[0] == 0:
                    (run / DONE_NAME).touch()
                else:
                    failed.append(seed)
                    tqdm.write(f"seed {seed} failed ({result[1]}); its log: {run / LOG_NAME}")
            bar.n = sum(min(steps, _steps_done(out / f"seed_{k}")) for k in seeds)
            bar.set_postfix(running=len(running), failed=len(failed))
            bar.refresh()
    finally:
        bar.close()
        for launched in running.values():  # interrupted: stop the children, keep their runs
            launched.stop()
    return sorted(failed)


def _die_with_parent(parent: int) -> None:
    """Be killed when the process that started this one dies (Linux's parent-death signal):
    a seed never outlives its `--seeds` run or its Ray task, so a retry or a rerun never
    races a stray run in the same directory."""
    with contextlib.suppress(OSError, AttributeError):  # not Linux: no such guarantee
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # the parent died before the signal was set
        sys.exit(f"the process that started this seed ({parent}) is gone")


PR_SET_PDEATHSIG = 1


def seed_main() -> None:
    """The seed child's entry point: `--parent PID REQUEST.json SEED` (`seed_command`)."""
    if len(sys.argv) != 5 or sys.argv[1] != "--parent":
        sys.exit("usage: python -c 'from mat_sdk.training.multiseed import seed_main; seed_main()' "
                 "--parent PID REQUEST.json SEED")  # fmt: skip
    _die_with_parent(int(sys.argv[2]))
    from mat_sdk.training.runs import RunRequest, train

    request = RunRequest.from_json(Path(sys.argv[3]).read_text())
    try:
        train(seed_request(request, int(sys.argv[4])), progress_bar=False)
    except (ValueError, OSError) as error:  # the user's to fix: one line, as `mat` says it
        sys.exit(f"mat: {error}")
