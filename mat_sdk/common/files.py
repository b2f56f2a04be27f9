"""What runs, bundles and the zoo write: whole or not at all, one writer per directory, and a
full or read-only disk reported in one line that names the path.

    with files.RunLock(out):                       # a second writer is refused, naming us
        files.write_text_atomic(out / "card.json", text)
    files.replace_directory(staging, bundle)       # readers see the old or the new, never none
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

try:
    import fcntl
except ImportError:  # not POSIX: no locks
    fcntl = None

LOCK_NAME = ".lock"
# what a failed write can mean that is about the disk, not about the program
DISK_PROBLEMS = {
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EFBIG: "file too large",
}


class WriteFailed(OSError):
    """A file or directory could not be written; the message names it and why."""

    def __str__(self) -> str:
        return self.strerror or super().__str__()


def write_failed(error: OSError, path: str | os.PathLike) -> OSError:
    """`error` as one line naming `path` ("no space left on device"), when it is a problem of
    the disk (`DISK_PROBLEMS`); anything else as it was."""
    reason = DISK_PROBLEMS.get(error.errno)
    if reason is None or isinstance(error, WriteFailed):
        return error
    return WriteFailed(error.errno, f"cannot write {path}: {reason}", str(path))


@contextlib.contextmanager
def writing(path: str | os.PathLike) -> Iterator[None]:
    """Report a disk problem while writing `path` as `write_failed` does."""
    try:
        yield
    except OSError as error:
        raise write_failed(error, path) from None


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """A small text file (JSON beside a run, a card) written whole or not at all: a reader
    never sees half of it, and a full disk leaves the old file."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.tmp")
    with writing(path):
        try:
            with temporary.open("w") as handle:
                handle.write(text)
                handle.flush()
                os.fsync(handle.fileno())
            os.replace(temporary, path)
        except BaseException:
            temporary.unlink(missing_ok=True)
            raise
    return path


def replace_directory(staging: Path, target: Path) -> None:
    """Put the finished directory `staging` at `target`. Where the OS can swap two directories
    in one step (Linux), a reader sees the old or the new one, never neither; elsewhere the
    old one is moved aside first. Either way a crash leaves one of the two whole."""
    if not target.exists():
        staging.rename(target)
        return
    if _exchange(staging, target):
        shutil.rmtree(staging, ignore_errors=True)  # it holds the old one now
        return
    old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old.", dir=target.parent))
    old.rmdir()
    target.rename(old)
    staging.rename(target)
    shutil.rmtree(old, ignore_errors=True)


def _exchange(first: Path, second: Path) -> bool:
    """Swap two paths atomically (Linux's renameat2 with RENAME_EXCHANGE); False where the
    OS or its C library cannot."""
    rename = getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None)
    if rename is None:
        return False
    at_cwd, exchange = -100, 2
    done = rename(at_cwd, os.fsencode(first), at_cwd, os.fsencode(second), exchange)
    return done == 0


class RunLocked(RuntimeError):
    """Another process holds the run directory."""


class RunLock:
    """An exclusive lock on a directory for as long as one process writes it (a run, a seed
    set): a second writer is refused in one line naming the holder's pid, so two runs never
    interleave their checkpoints and metrics. Reentrant within a process; the OS releases it
    when the process dies, so a killed run leaves no stale lock."""

    _held: ClassVar[dict[Path, list]] = {}  # directory -> [file, depth], this process's locks

    def __init__(self, directory: str | os.PathLike):
        self.directory = Path(directory)

    def __enter__(self) -> RunLock:
        if fcntl is None:
            return self
        with writing(self.directory):
            self.directory.mkdir(parents=True, exist_ok=True)
        key = self.directory.resolve()
        held = self._held.get(key)
        if held is not None:
            held[1] += 1
            return self
        path = self.directory / LOCK_NAME
        with writing(path):
            handle = path.open("a+")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "unknown"
            handle.close()
            raise RunLocked(
                f"{self.directory} is in use by another run (pid {holder}); wait for it to "
                "finish, stop it, or choose another output directory"
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"{os.getpid()}\n")
        handle.flush()
        self._held[key] = [handle, 1]
        return self

    def __exit__(self, *exc) -> None:
        if fcntl is None:
            return
        key = self.directory.resolve()
        held = self._held[key]
        held[1] -= 1
        if held[1] == 0:
            del self._held[key]
            held[0].close()  # releases the lock; the file stays, naming the last holder
