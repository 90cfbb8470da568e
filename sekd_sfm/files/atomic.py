"""Atomic file writes: one temporary-name pattern, one fsync-and-rename.

Every file sekd writes whole (pairs files, global descriptors, checkpoints, reports) goes
through ``atomic_output``: the data is written under ``<name>.<pid>.tmp`` beside the target,
flushed to disk, then renamed over the target, so a reader (or a rerun after a crash, a
full disk or kill -9) sees either the old file or the new one, never a torn one. The PID in
the name keeps two processes from writing the same temporary file, and lets
``partstore.remove_stale_temps`` tell a dead writer's leftovers from a live one's.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path


def temp_name(path: str | Path) -> Path:
    """A temporary name beside ``path``, unique to this process: ``<name>.<pid>.tmp``."""
    path = Path(path)
    return path.with_name(f"{path.name}.{os.getpid()}.tmp")


def fsync_replace(tmp: Path, target: Path, durable: bool = True) -> None:
    """Rename ``tmp`` over ``target``; with ``durable``, its data reaches the disk first and the rename is synced."""
    if durable:
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
    os.replace(tmp, target)
    if durable:
        with contextlib.suppress(OSError):  # not every file system lets a folder be fsynced
            fd = os.open(target.parent, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)


@contextlib.contextmanager
def atomic_output(path: str | Path, durable: bool = True) -> Iterator[Path]:
    """Yield a temporary path to write ``path``'s new content to; on success it replaces ``path``.

    On an exception (including KeyboardInterrupt) the temporary file is removed and ``path``
    is left as it was. The parent folder is created if needed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    try:
        yield tmp
        fsync_replace(tmp, path, durable)
    finally:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            tmp.unlink(missing_ok=True)


def write_atomic(path: str | Path, data: str | bytes, durable: bool = True) -> Path:
    """Write ``data`` (text as UTF-8) to ``path`` atomically (``atomic_output``); returns ``path``."""
    with atomic_output(path, durable) as tmp:
        tmp.write_bytes(data.encode("utf-8") if isinstance(data, str) else data)
    return Path(path)


def remove_folder(path: str | Path) -> None:
    """Delete the folder ``path`` if it exists: renamed away first (one atomic step), so no reader
    or rerun ever sees it half deleted."""
    path = Path(path)
    if path.is_dir():
        trash = temp_name(path)
        os.replace(path, trash)
        shutil.rmtree(trash, ignore_errors=True)


def write_json(data: dict, path: Path) -> Path:
    """Write ``data`` as indented JSON at ``path`` atomically (``<name>.tmp``, then a rename); returns ``path``."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=False))
    os.replace(tmp, path)
    return path
