"""Worker processes driven by two semaphores, without a pipe on the hot path.

The env vector (`mat_sdk.envs.core.vector`) and the split update
(`mat_sdk.training.gradients`) both run a fixed piece of work in spawned workers many times a
second. The work's inputs and outputs already sit in shared memory, so a round needs only a
signal each way: the caller releases "go", the worker releases "done". The pipe carries only
errors and the rare commands with arguments or results.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import time
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

SPIN_SECONDS = 0.002
_MESSAGE, _FAILED = 0, 1  # the handshake's flags


def usable_cores() -> int:
    """The cores this process may run on (its affinity), which decides how work is split."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


class Handshake:
    """The per-round signal between the caller and one worker.

    A semaphore's release and acquire also order the shared-memory writes around them, on
    every architecture. A waiting side polls its semaphore for `spin_seconds` before it
    sleeps: waking a sleeping process costs a wake-up each way plus a cold core, a visible
    share of a vector step (BENCHMARKS.md). Spin only when every process has a core of its
    own, or the spinning steals the work.
    """

    def __init__(self, context, spin_seconds: float):
        self.go, self.done = context.Semaphore(0), context.Semaphore(0)
        self.flags = context.RawArray("b", 2)  # [_MESSAGE]: a command waits on the pipe
        self.spin_seconds = spin_seconds

    def wait(self, semaphore, alive: Callable[[], bool]) -> bool:
        """Take `semaphore`; False if the other side died while we waited."""
        deadline = time.perf_counter() + self.spin_seconds
        while time.perf_counter() < deadline:
            if semaphore.acquire(False):
                return True
        while not semaphore.acquire(timeout=1.0):
            if not alive():
                return False
        return True


def serve(conn: Connection, handshake: Handshake, setup: Callable[[], Any]) -> None:
    """A worker's loop: `worker = setup()`, then `worker.step()` on each bare "go" and
    `worker.<command>(*arguments)` for a command sent through the pipe, until "close".

    Errors, in `setup` too, go back through the pipe with their traceback. A worker whose
    parent died exits instead of waiting forever.
    """
    parent_alive = mp.parent_process().is_alive
    flags = handshake.flags
    try:
        worker = setup()
        conn.send(("ok", None))
        handshake.done.release()
        while handshake.wait(handshake.go, parent_alive):
            if flags[_MESSAGE]:
                command, arguments = conn.recv()
                if command == "close":
                    break
                conn.send(("ok", getattr(worker, command)(*arguments)))
            else:
                worker.step()
            handshake.done.release()
    except KeyboardInterrupt:
        pass
    except Exception:
        flags[_FAILED] = 1
        conn.send(("error", traceback.format_exc()))
        handshake.done.release()
    finally:
        conn.close()


class WorkerProcess:
    """The caller's side of one spawned worker running `target(conn, handshake, *args)`,
    which must call `serve`."""

    def __init__(self, context, target: Callable, args: tuple, spin_seconds: float):
        self.pipe, child = context.Pipe()
        self.handshake = Handshake(context, spin_seconds)
        self.process = context.Process(
            target=target, args=(child, self.handshake, *args), daemon=True
        )
        self.process.start()
        child.close()
        self._message = True  # the first round is the worker's setup

    def go(self, command: str | None = None, arguments: tuple = ()) -> None:
        """Start a round: a step, or `command(*arguments)` when one is named."""
        self._message = command is not None
        self.handshake.flags[_MESSAGE] = self._message
        if self._message:
            self.pipe.send((command, arguments))
        self.handshake.go.release()

    def result(self) -> tuple[bool, Any]:
        """Wait for the round: (True, the command's result or None) or (False, the error)."""
        if not self.handshake.wait(self.handshake.done, self.process.is_alive):
            return False, "a worker process died"
        if self._message or self.handshake.flags[_FAILED]:
            status, detail = self.pipe.recv()
            return status == "ok", detail
        return True, None

    def close(self) -> None:
        """Ask the worker to stop (`join` then waits for it)."""
        self.handshake.flags[_MESSAGE] = 1
        with contextlib.suppress(BrokenPipeError, OSError):
            self.pipe.send(("close", ()))
        self.handshake.go.release()

    def join(self) -> None:
        """Wait for a closed worker; terminate it if it has not stopped within 5 s."""
        self.process.join(timeout=5)
        if self.process.is_alive():
            self.process.terminate()


def wait_all(workers: list[WorkerProcess], failure: str, cleanup: Callable[[], None]) -> list:
    """Every worker's result, in order. On an error: `cleanup()`, then RuntimeError with
    `failure` and the first worker's error."""
    results, errors = [], []
    for worker in workers:
        ok, detail = worker.result()
        (results if ok else errors).append(detail)
    if errors:
        cleanup()
        raise RuntimeError(f"{failure}:\n{errors[0]}")
    return results


def close_all(workers: list[WorkerProcess]) -> None:
    for worker in workers:
        worker.close()
    for worker in workers:
        worker.join()
