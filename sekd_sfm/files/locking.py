"""One writer per output: an advisory ``fcntl`` lock held for the whole run.

Two runs writing the same ``features.h5`` (a pipeline retry while the first still runs) would
interleave their merges; the second run is refused instead, naming the first one's PID.
The lock lives in ``<target>.lock`` beside the output (or ``<folder>/.lock`` for a run
folder). The kernel releases an ``fcntl`` lock when its process dies, even by ``kill -9``,
so a stale lock file left by a killed run is simply taken over by the next one.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from collections.abc import Iterator
from pathlib import Path

from ..errors import SekdError


def lock_path(target: Path) -> Path:
    """The lock file of ``target``: ``<folder>/.lock`` for a folder, ``<file>.lock`` for a file."""
    target = Path(target)
    return target / ".lock" if target.is_dir() else target.with_name(target.name + ".lock")


def _holder(fd: int) -> str:
    os.lseek(fd, 0, os.SEEK_SET)
    text = os.read(fd, 64).decode("ascii", "replace").strip()
    return text if text.isdigit() else "unknown"


@contextlib.contextmanager
def exclusive_lock(target: str | Path, what: str = "output") -> Iterator[Path]:
    """Hold the exclusive lock of ``target`` for the ``with`` block; SekdError if another process holds it.

    ``what`` names the target in the message (``"features file"``, ``"run folder"``).
    Yields the lock file's path. The lock file stays behind (harmless; reused next time).
    """
    path = lock_path(Path(target))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES, errno.EAGAIN):
                raise
            raise SekdError(
                f"{target}: this {what} is in use by another sekd process (PID {_holder(fd)}); "
                "wait for it to finish or choose another output"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode("ascii"))
        yield path
    finally:
        os.close(fd)  # closing the descriptor releases the lock


@contextlib.contextmanager
def writer_lock(path: Path, what: str) -> Iterator[None]:
    """Hold the exclusive lock of output ``path`` for the block: one writer per file.

    SekdError naming the other process's PID if it is taken, or if the lock file cannot
    be created (the output's folder is a file, is read-only, ...).
    """
    if path.is_dir():  # refused before a lock file is put into the user's folder
        raise SekdError(f"{path}: is a folder, not a {what}; give the name of a file to write (e.g. {path / 'out.h5'})")
    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(exclusive_lock(path, what=what))
        except OSError as exc:
            blocker = next((parent for parent in path.parents if parent.exists()), None)
            if blocker is not None and not blocker.is_dir():
                raise SekdError(f"{path}: cannot be written: {blocker} is a file, not a folder; "
                                "choose another output") from exc
            raise SekdError(f"{path}: cannot create its lock file ({exc.strerror or exc}); "
                            "choose an output in a writable folder") from exc
        yield


