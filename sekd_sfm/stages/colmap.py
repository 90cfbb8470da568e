"""pycolmap access in one place: the version check, COLMAP's log, option parsing, the database.

pycolmap's API changes between releases; everything here is written against the
tested range below (checked at import with a clear error outside it).
"""
from __future__ import annotations

import contextlib
import difflib
import importlib
import os
import sqlite3
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..runtime import keep_sigterm_handler

#: pycolmap versions this code is tested with (as pinned in pyproject.toml).
PYCOLMAP_RANGE = ((3, 12), (4, 3))


def _version_tuple(version: str) -> tuple[int, ...]:
    numbers = []
    for part in version.split("+")[0].split("."):
        digits = "".join(c for c in part if c.isdigit()) if part[:1].isdigit() else ""
        if not digits:
            break
        numbers.append(int(digits))
    return tuple(numbers)


def require_pycolmap():
    """The pycolmap module; SekdError if it is missing or outside the tested version range."""
    low, high = PYCOLMAP_RANGE
    wanted = f"pycolmap>={'.'.join(map(str, low))},<{'.'.join(map(str, high))}"
    try:
        pycolmap = keep_sigterm_handler(lambda: importlib.import_module("pycolmap"))
    except ImportError as exc:
        raise SekdError(f"pycolmap is not installed ({exc}); install it: pip install '{wanted}'") from exc
    version = _version_tuple(getattr(pycolmap, "__version__", "0"))
    if not low <= version < high:
        raise SekdError(f"pycolmap {pycolmap.__version__} is installed but sekd is tested with {wanted}; "
                        f"install a tested version: pip install '{wanted}'")
    return pycolmap


def open_database(path: Path):
    """An open COLMAP database, usable as a context manager (``Database.open`` where the API has it)."""
    pycolmap = require_pycolmap()
    if hasattr(pycolmap.Database, "open"):
        return pycolmap.Database.open(str(path))
    return pycolmap.Database(str(path))


@contextmanager
def read_only_database(path: str | Path) -> Iterator[sqlite3.Connection]:
    """The COLMAP database ``path`` opened by SQLite, read-only. pycolmap's ``Database.open`` writes (its schema):
    two processes opening a file at once can fail with "database is locked", and a file that must stay as it is
    could change."""
    with contextlib.closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as db:
        yield db


def sqlite_keypoints(db: sqlite3.Connection, image_id: int) -> np.ndarray:
    """An image's keypoints (``N x 2`` float64, COLMAP pixels) from a ``read_only_database`` connection."""
    rows, cols, data = db.execute("SELECT rows, cols, data FROM keypoints WHERE image_id = ?", (image_id,)).fetchone()
    return np.frombuffer(data, np.float32).reshape(rows, cols)[:, :2].astype(np.float64)


class KeypointCache:
    """Images' keypoints (``sqlite_keypoints``) as a worker reads them pair after pair: up to ``size`` images kept
    (a task's pairs share few images; memory stays flat on big scenes)."""

    def __init__(self, size: int = 256):
        self.size, self.items = size, {}

    def get(self, db: sqlite3.Connection, image_id: int) -> np.ndarray:
        if image_id not in self.items:
            if len(self.items) >= self.size:
                self.items.clear()
            self.items[image_id] = sqlite_keypoints(db, image_id)
        return self.items[image_id]


def sqlite_matches(db: sqlite3.Connection, image_id1: int, image_id2: int) -> np.ndarray:
    """A pair's raw matches (``M x 2`` uint32: indices into image 1's, then image 2's keypoints) from a
    ``read_only_database`` connection; none (``0 x 2``) for a pair without matches."""
    pair_id = require_pycolmap().image_pair_to_pair_id(image_id1, image_id2)
    row = db.execute("SELECT rows, data FROM matches WHERE pair_id = ?", (pair_id,)).fetchone()
    if row is None or not row[0]:
        return np.zeros((0, 2), np.uint32)
    matches = np.frombuffer(row[1], np.uint32).reshape(row[0], 2)
    return matches[:, ::-1].copy() if image_id1 > image_id2 else matches  # stored from the lower id


def delete_verified_pairs(database: str | Path, pairs: Iterable[tuple[int, int]]) -> None:
    """Delete the verified inliers of the image-id ``pairs`` from ``database`` (their raw matches stay): what the
    checks between verification and mapping (chance, view graph, capture order) drop."""
    with open_database(database) as db:
        for image1, image2 in pairs:
            db.delete_inlier_matches(image1, image2)


def log_prefix(path: Path) -> Path:
    """The prefix glog gives the files it writes for the log ``path`` (``colmap.log.<date>-<time>.<pid>``)."""
    return path.with_name(path.name + ".")


@contextmanager
def colmap_log(path: Path):
    """Send COLMAP's log (glog) to the file ``path`` instead of the console while the block runs.

    glog names its file ``<prefix><date>-<time>.<pid>``; at the end, the files written during
    the block (this process's and those of child processes given ``log_prefix(path)``, such
    as the mapper's) are joined in time order into ``path``, replacing the log of an earlier
    run. Yields ``path``. Errors are logged there too: the caller explains failures itself.
    """
    log = require_pycolmap().logging
    saved = (log.alsologtostderr, log.logtostderr, log.stderrthreshold, log.minloglevel)
    prefix = log_prefix(path)
    before = set(path.parent.glob(prefix.name + "*"))
    log.alsologtostderr, log.logtostderr, log.stderrthreshold, log.minloglevel = False, False, 3, 0
    for level in (log.WARNING, log.ERROR):
        log.set_log_destination(level, "")  # INFO's file already receives every level
    log.set_log_destination(log.INFO, str(prefix))
    try:
        yield path
    finally:
        log.set_log_destination(log.INFO, "")  # closes (and flushes) the file
        log.alsologtostderr, log.logtostderr, log.stderrthreshold, log.minloglevel = saved
        _join_logs(set(path.parent.glob(prefix.name + "*")) - before, path)


def clean_logs(path: Path) -> None:
    """Remove glog files of ``path`` left by a killed run (call it holding the output folder's lock)."""
    for stale in path.parent.glob(log_prefix(path).name + "*"):
        stale.unlink(missing_ok=True)


def _join_logs(files: set[Path], target: Path) -> None:
    if not files:
        return
    # glog's names sort by start time (<date>-<time>.<pid>); the mapper's child starts last.
    ordered = sorted(files, key=lambda p: (p.name.rsplit(".", 1)[0], p.stat().st_mtime))
    tmp = target.with_name("." + target.name + ".joining")  # outside the glob of log_prefix
    with open(tmp, "wb") as out:
        out.writelines(part.read_bytes() for part in ordered)
    os.replace(tmp, target)
    for part in ordered:
        part.unlink(missing_ok=True)


def _convert(text: str, current, key: str):
    """``text`` as the type of the option's current value (bool, int, float, str or enum); no eval."""
    try:
        if isinstance(current, bool):
            lowered = text.strip().lower()
            if lowered not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError("expected true or false")
            return lowered in ("true", "1", "yes")
        if type(current) is int:
            return int(text)
        if isinstance(current, float):
            return float(text)
        if isinstance(current, str):
            return text
        members = getattr(type(current), "__members__", None)
        if members:
            names = {name.lower(): value for name, value in members.items()}
            if text.strip().lower() not in names:
                raise ValueError(f"expected one of {', '.join(members)}")
            return names[text.strip().lower()]
    except ValueError as exc:
        raise SekdError(f"option {key}={text}: {exc} (current value {current!r})") from None
    raise SekdError(f"option {key}: values of type {type(current).__name__} cannot be set from the command line")


def set_options(options, assignments: list[str], what: str = "--mapper"):
    """Apply ``key=value`` strings to a pycolmap options object, validated against its fields.

    Nested fields are written with dots (``mapper.init_min_num_inliers=50``). Unknown keys
    and values of the wrong type are a SekdError that lists close valid names. Returns ``options``.
    """
    for assignment in assignments:
        key, sep, text = assignment.partition("=")
        key = key.strip()
        if not sep or not key:
            raise SekdError(f"{what} {assignment!r}: expected key=value, for example mapper.init_min_num_inliers=50")
        target, name = _resolve(options, key, what)
        setattr(target, name, _convert(text, getattr(target, name), key))
    return options


def option_names(options, prefix: str = "") -> list[str]:
    """Dotted names of all settable fields of a pycolmap options object."""
    names = []
    for name in options.todict():
        child = getattr(options, name)
        names += option_names(child, f"{prefix}{name}.") if hasattr(child, "todict") else [prefix + name]
    return names


def option_values(options) -> list[tuple[str, object]]:
    """``(dotted name, current value)`` of every settable field of a pycolmap options object (``--mapper help``)."""
    values = []
    for name in option_names(options):
        value = options
        for part in name.split("."):
            value = getattr(value, part)
        values.append((name, value))
    return values


def _resolve(options, key: str, what: str):
    *path, name = key.split(".")
    target = options
    for part in path:
        target = getattr(target, part, None) if part in _fields(target) else None
        if target is None or not hasattr(target, "todict"):
            break
    if target is None or name not in _fields(target) or hasattr(getattr(target, name), "todict"):
        close = difflib.get_close_matches(key, option_names(options), n=5, cutoff=0.5)
        hint = f"; did you mean {', '.join(close)}?" if close else f"; see `{what} help` for the list"
        raise SekdError(f"{what} {key}: no such option in pycolmap's {type(options).__name__}{hint}")
    return target, name


def _fields(options) -> dict:
    return options.todict() if hasattr(options, "todict") else {}
