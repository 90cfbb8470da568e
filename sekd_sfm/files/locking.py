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
