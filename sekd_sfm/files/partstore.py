"""The part store: how an output file is written so that a crash never leaves a half file.

Writing: crash-safe at linear cost (details and measurements in docs/files.md).

* While a run goes on, finished items (images here, pairs for the match file) go to the
  *part store* ``<output>.parts/``: buffered in memory up to a bounded batch (at most
  ``max_items`` items, ``max_bytes`` bytes or ``max_seconds`` seconds), then written as one
  ``.npz`` *chunk* by write-to-temporary + rename. Every item is written once; thousands
  of pairs make one chunk file, not thousands of files.
* At the end of the run (also on Ctrl-C / SIGTERM) ``merge_parts`` writes the HDF5 file
  once: copy of the previous file (a few KB on a first run), append of every chunk, fsync,
  rename over ``<output>``. Bytes written for N items: parts + file, about 2x the data,
  linear in N (copying the growing file at every checkpoint would be quadratic).
* The output path always holds a complete HDF5 file: ``prepare_output`` creates it empty
  (atomically) before any work, and it is only ever replaced whole by rename. ``kill -9``
  at any moment leaves the last file plus complete chunks; the next run counts both as
  done and merges the chunks: nothing is lost (an item still in the memory buffer is
  recomputed) or duplicated (a killed merge leaves the chunks; a merge killed after its
  rename is recognised by the ``merge_id`` attribute and its chunks are dropped).
* One writer per output (``sekd_sfm.files.locking.exclusive_lock``, taken by
  ``extract_features`` / ``match_features``); temporary names carry the writer's PID.
"""
from __future__ import annotations

import contextlib
import glob
import json
import logging
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import h5py
import numpy as np

from ..errors import Interrupted, SekdError
from . import shards
from .atomic import fsync_replace, remove_folder, temp_name
from .features import FORMAT, SHARDS, _keys_of, list_keys, read_attrs, write_image_group

logger = logging.getLogger("sekd")

def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, owned by someone else
        return True
    return True


def remove_stale_temps(path: Path) -> None:
    """Delete ``<name>.*.<pid>.tmp`` files and folders beside ``path`` left by killed writers (dead PID, or ours)."""
    for tmp in path.parent.glob(f"{glob.escape(path.name)}.*tmp") if path.parent.is_dir() else []:
        pid = tmp.name.rsplit(".", 2)[-2]
        if tmp.name.endswith(".tmp") and pid.isdigit() and (int(pid) == os.getpid() or not _pid_alive(int(pid))):
            shutil.rmtree(tmp, ignore_errors=True) if tmp.is_dir() else tmp.unlink(missing_ok=True)


def create_empty(path: Path, attrs: dict) -> None:
    """Write a feature (or match) file with attributes and no items, atomically (replaces ``path``)."""
    tmp = temp_name(path)
    try:
        with h5py.File(tmp, "w") as f:
            for name, value in attrs.items():
                f.attrs[name] = value
        fsync_replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)



MERGE_ID = "merge_id"
#: A part store's marker: the merge id of a merge that is renaming its file into place.
MERGING = "MERGING"


class PartStore:
    """Finished items of a run in progress (``key -> arrays``), in chunk files under ``<output>.parts/``.

    ``save`` buffers items in memory and writes them as one ``.npz`` chunk (temporary name +
    rename, so a chunk is complete or absent) once the buffer holds ``max_items`` items,
    ``max_bytes`` bytes of arrays, or its oldest item is ``max_seconds`` old (0 = every item at
    once). So memory stays bounded by one batch, and a kill loses at most that batch, which
    the next run recomputes. The defaults write every item at once (one chunk per ``save``);
    runs pass a batch size (``extract_features``: 64 images, ``match_features``: 1024 pairs)
    and call ``flush`` (``merge_parts`` does). Chunk names sort by time of writing (then
    PID, sequence), and a key saved twice counts once: its last saved arrays win.
    """

    def __init__(self, output: Path, *, max_items: int = 1, max_bytes: int = 64 << 20, max_seconds: float = 10.0,
                 writer: str = ""):
        self.output = Path(output)
        self.writer = writer  # goes into chunk names: writers on other machines (Ray workers) never collide
        self.root = self.output.with_name(self.output.name + ".parts")
        self.max_items, self.max_bytes, self.max_seconds = max_items, max_bytes, max_seconds
        self._buffer: list[tuple[str, dict[str, np.ndarray]]] = []
        self._bytes, self._since, self._seq = 0, 0.0, 0

    def save(self, key: str, arrays: dict[str, np.ndarray]) -> None:
        """Add one finished item; it reaches the disk at the next ``flush`` (automatic when the batch is full)."""
        arrays = {name: np.asarray(value) for name, value in arrays.items()}
        if not self._buffer:
            self._since = time.monotonic()
        self._buffer.append((key, arrays))
        self._bytes += sum(a.nbytes for a in arrays.values())
        if (len(self._buffer) >= self.max_items or self._bytes >= self.max_bytes
                or time.monotonic() - self._since >= self.max_seconds):
            self.flush()

    def flush(self) -> Path | None:
        """Write the buffered items as one chunk file (nothing if the buffer is empty); returns its path."""
        if not self._buffer:
            return None
        self.root.mkdir(parents=True, exist_ok=True)
        self._seq += 1
        name = f"{time.time_ns():020d}-{os.getpid()}{'-' + self.writer if self.writer else ''}-{self._seq:06d}.npz"
        target, tmp = self.root / name, self.root / f".{name}.{os.getpid()}.tmp"
        members = {"__keys__": np.array([key for key, _ in self._buffer], dtype=str)}
        for i, (_, arrays) in enumerate(self._buffer):
            members.update({f"{i}.{k}": v for k, v in arrays.items()})
        try:
            with open(tmp, "wb") as f:
                np.savez(f, **members)
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        self._buffer, self._bytes = [], 0
        return target

    def chunks(self) -> list[Path]:
        """Complete chunk files, oldest first (temporaries of killed writers are deleted)."""
        if not self.root.is_dir():
            return []
        for tmp in self.root.glob(".*.tmp"):
            pid = tmp.name.rsplit(".", 2)[-2]
            if not pid.isdigit() or int(pid) == os.getpid() or not _pid_alive(int(pid)):
                tmp.unlink(missing_ok=True)
        return sorted(self.root.glob("*.npz"))

    def _chunk_keys(self, chunk: Path) -> list[str] | None:
        try:
            with np.load(chunk) as data:
                return [str(k) for k in data["__keys__"]]
        except Exception:  # noqa: BLE001 - a damaged chunk (disk trouble) is dropped and its items redone
            logger.warning("%s: unreadable part file, its items will be computed again", chunk)
            chunk.unlink(missing_ok=True)
            return None

    def _index(self, chunks: list[Path] | None = None) -> dict[str, tuple[Path, int]]:
        """Where the last saved version of each key is: ``key -> (chunk, position)``; reads keys only."""
        index = {}
        for chunk in self.chunks() if chunks is None else chunks:
            for i, key in enumerate(self._chunk_keys(chunk) or []):
                index[key] = (chunk, i)
        return index

    def keys(self) -> set[str]:
        """Keys of all saved items (chunks on disk and the buffer), without reading their arrays."""
        return set(self._index()) | {key for key, _ in self._buffer}

    def items(self, chunks: list[Path] | None = None) -> Iterator[tuple[str, dict[str, np.ndarray]]]:
        """Yield each saved key once with its last saved arrays, one chunk in memory at a time.

        Only the buffered items that were flushed count (call ``flush`` first); ``chunks``
        restricts the walk to these chunk files (default: all).
        """
        index = self._index(chunks)
        for chunk in sorted({c for c, _ in index.values()}):
            try:
                with np.load(chunk) as data:
                    keys = [str(k) for k in data["__keys__"]]
                    members: dict[int, dict[str, np.ndarray]] = {}
                    for member in data.files:
                        if member != "__keys__":
                            i, name = member.split(".", 1)
                            members.setdefault(int(i), {})[name] = data[member]
            except Exception:  # noqa: BLE001 - see _chunk_keys
                logger.warning("%s: unreadable part file, its items will be computed again", chunk)
                chunk.unlink(missing_ok=True)
                continue
            for i, key in enumerate(keys):
                if index.get(key) == (chunk, i):
                    yield key, members.get(i, {})

    def load_all(self) -> dict[str, dict[str, np.ndarray]]:
        """All saved items in memory at once (for small stores and tests; runs use ``items``)."""
        return dict(self.items())

    def recover(self) -> None:
        """Finish a merge killed between its rename and its cleanup: drop the chunks the file already holds.

        Before renaming its file into place, ``merge_parts`` writes its merge id (also stored in
        the file) and the names of the chunks it merged into ``MERGING`` here. If the file at
        ``output`` carries that id, the rename happened and those chunks (only those) go;
        otherwise the marker goes and the chunks stay for the next merge.
        """
        marker = self.root / MERGING
        try:
            merging = json.loads(marker.read_text())
        except FileNotFoundError:
            return
        except (OSError, ValueError):  # a torn marker: its merge cannot have renamed yet
            merging = {}
        try:
            with h5py.File(self.output, "r") as f:
                landed = bool(merging) and str(f.attrs.get(MERGE_ID, "")) == merging.get("merge_id")
        except OSError:
            landed = False
        self.drop([self.root / name for name in merging.get("chunks", [])] if landed else [])

    def drop(self, chunks: list[Path]) -> None:
        """Delete merged ``chunks``, then the ``MERGING`` marker, then the store's folder if nothing else is left."""
        for chunk in chunks:
            chunk.unlink(missing_ok=True)
        (self.root / MERGING).unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            self.root.rmdir()

    def clear(self) -> None:
        """Forget every item: the buffer and the chunk files."""
        self._buffer, self._bytes = [], 0
        remove_folder(self.root)


WriteGroup = Callable[[h5py.File, str, dict[str, np.ndarray]], None]


def merge_parts(path: Path, parts: PartStore, attrs: dict | None = None, write_group: WriteGroup | None = None) -> int:
    """Write all saved parts (and new ``attrs``) into the HDF5 file: copy, append, fsync, rename, once.

    Call it once, at the end of a run: each call copies the whole file (none when there is
    nothing new). ``write_group(f, key, arrays)`` stores one part (default: a feature-file
    image group), so other files (matches) reuse the same crash-safe scheme. Streams the
    chunks (memory: one chunk). Shards of ``<path>.shards/`` not referenced yet are referenced
    by virtual datasets (``shards``). Returns the number of parts merged and shard items referenced.
    """
    parts.flush()
    parts.recover()
    described = shards.describe_all(path) if shards.shard_files(path) else {}  # read once: the check and the links
    if not parts.chunks() and not shards.keys_of(described) - set(list_keys(path)) and _has_attrs(path, attrs or {}):
        parts.drop([])
        return 0
    merge = Merge(path, parts, write_group)
    try:
        return merge.finish(attrs, described)
    finally:
        merge.discard()


class Merge:
    """``merge_parts`` begun while the run goes on: chunks are written as they are reported.

    Opens a temporary copy of the file; ``add`` writes finished chunks' items into it (a run
    on Ray calls it as the workers report them, so the merge's copying overlaps their work);
    ``finish`` adds whatever is left (chunks, shards, ``attrs``) and renames the copy into place
    exactly as ``merge_parts`` does (``MERGING`` marker, fsync, rename, then the chunks go).
    Until then the file is untouched: ``discard`` (or a kill: the copy is a stale temporary the
    next run removes) leaves it and every chunk as they were, for the next run to merge.
    A key written twice keeps the arrays written last.
    """

    def __init__(self, path: Path, parts: PartStore, write_group: WriteGroup | None = None):
        self.path, self.parts, self.write_group = Path(path), parts, write_group or write_image_group
        parts.recover()  # a killed merge's leftovers first: its chunks may already be in the file
        self.tmp = temp_name(self.path)
        shutil.copyfile(self.path, self.tmp)
        self.file: h5py.File | None = h5py.File(self.tmp, "a")
        self.merged: set[Path] = set()
        self.written: set[str] = set()

    def add(self, chunks: Iterable[Path]) -> None:
        """Write these chunks' items into the copy; chunks not visible here yet are left for ``finish``."""
        fresh = sorted(c for c in chunks if c not in self.merged and c.exists())
        for key, arrays in self.parts.items(fresh):
            self.write_group(self.file, key, arrays)
            self.written.add(key)
        self.merged.update(fresh)

    def finish(self, attrs: dict | None = None, described: dict[str, dict] | None = None) -> int:
        """Add every chunk and shard not merged yet and ``attrs``, then replace the file; returns the items merged.

        ``described``: ``shards.describe_all(path)`` if the caller has read it already.
        """
        self.parts.flush()
        self.add(self.parts.chunks())
        f, count = self.file, len(self.written)
        shard_files = shards.shard_files(self.path)
        if described is None:
            described = shards.describe_all(self.path) if shard_files else {}
        present = set(_keys_of(f))
        if shards.keys_of(described) - present:
            count += shards.link_shards(f, self.path, present, described)
            f.attrs[SHARDS] = json.dumps({"folder": shards.shard_root(self.path).name, "files": len(shard_files)})
        merge_id = uuid.uuid4().hex
        f.attrs.update(attrs or {})
        f.attrs["modified"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        f.attrs[MERGE_ID] = merge_id
        f.close()
        self.file = None
        chunks = sorted(self.merged)
        if chunks:
            _write_atomic(self.parts.root / MERGING, json.dumps({"merge_id": merge_id, "chunks": [c.name for c in chunks]}))
        fsync_replace(self.tmp, self.path)
        self.parts.drop(chunks)
        return count

    def discard(self) -> None:
        """Close and delete the copy (nothing after ``finish``): the file and the chunks stay as they were."""
        if self.file is not None:
            with contextlib.suppress(Exception):
                self.file.close()
            self.file = None
        self.tmp.unlink(missing_ok=True)


def _has_attrs(path: Path, attrs: dict) -> bool:
    """Whether the file already holds ``attrs`` (then a merge without parts would change nothing)."""
    with h5py.File(path, "r") as f:
        return all(name in f.attrs and np.array_equal(f.attrs[name], value) for name, value in attrs.items())


def finish_run(path: Path, parts: PartStore, attrs: dict | None = None, write_group: WriteGroup | None = None,
               what: str = "items", merge: Merge | None = None) -> int:
    """``merge_parts`` at the end of a run (or ``merge.finish``, begun during it); Ctrl-C / SIGTERM during it
    becomes ``Interrupted`` (parts kept)."""
    try:
        return merge.finish(attrs) if merge is not None else merge_parts(path, parts, attrs, write_group)
    except KeyboardInterrupt:
        raise Interrupted(f"interrupted while writing {path}: the finished {what} are kept in {parts.root}; "
                          "run the same command again to resume") from None


def keep_parts(parts: PartStore) -> None:
    """Flush the buffered items of a run that is failing, so the next run reuses them.

    Best effort: an OS failure here (the disk may be what failed) must not hide the first error.
    """
    try:
        parts.flush()
    except OSError as exc:
        logger.warning("%s: could not save the last finished items (%s); they will be computed again", parts.root, exc)


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # the part store's temporary pattern
    tmp.write_text(text)
    os.replace(tmp, path)



def prepare_output(path: Path, attrs: dict, parts: PartStore, overwrite: bool, compare: tuple[str, ...],
                   what: str = "configuration") -> None:
    """Create ``path`` with ``attrs``, or check that the existing file agrees on the ``compare`` attributes.

    A resumed run must add to a file made the same way; a different one is refused.
    ``overwrite`` replaces the file, but only a sekd file of the same kind (``attrs["format"]``):
    anything else at ``path`` (a text file, a COLMAP database, a folder) is refused and left
    alone. Leftovers of killed writers are removed first. Call it holding the output's lock.
    """
    remove_stale_temps(path)
    shards.remove_temps(path)
    if overwrite and (path.exists() or path.is_symlink()):
        check_replaceable(path, attrs["format"])
        parts.clear()  # first: old parts must never reach the new file
        create_empty(path, attrs)
        shards.clear(path)  # after: the old file referenced them until the new one replaced it
        return
    if not path.exists():
        parts.clear()
        path.parent.mkdir(parents=True, exist_ok=True)
        create_empty(path, attrs)
        shards.clear(path)
        return
    existing = read_attrs(path, attrs["format"], role="output")
    parts.recover()
    for name in compare:
        if existing.get(name) != attrs.get(name):
            raise SekdError(
                f"{path}: was made with a different {what} ({name}={existing.get(name)}, now {attrs.get(name)}); "
                "pass --overwrite to replace it or choose another output file"
            )


def check_replaceable(path: Path, file_format: str) -> None:
    """SekdError unless ``path`` is an HDF5 file with ``format == file_format`` (what --overwrite may replace)."""
    kind = {FORMAT: "features"}.get(file_format, file_format.removeprefix("sekd-"))
    refuse = f"--overwrite only replaces a sekd {kind} file; delete it yourself or choose another output"
    if path.is_dir():
        raise SekdError(f"{path}: is a folder; {refuse}")
    try:
        with h5py.File(path, "r") as f:
            found = f.attrs.get("format")
    except OSError:
        raise SekdError(f"{path}: is not an HDF5 file; {refuse}") from None
    if found != file_format:
        what = f"a {found!s} file" if found is not None else "an HDF5 file without a sekd format"
        raise SekdError(f"{path}: is {what}, not a sekd {kind} file; {refuse}")

