"""Shard files that an HDF5 output references instead of holding (``--ray-merge virtual``).

A Ray run of thousands of workers produces features faster than one driver can copy them
into ``features.h5`` (the copy is bound by the disk: ~300-440 images/s of 1 MB each,
docs/cluster.md). So, on request, each worker writes its task's images as one small HDF5
*shard* in hloc's layout under ``<output>.shards/`` (temporary name, fsync, rename: a shard
is complete or absent), and the driver's merge adds to ``<output>`` one group per image
whose arrays are HDF5 *virtual datasets* mapping the shard's arrays: a few KB per image
instead of 1 MB, and no array is read or copied.

Readers see an ordinary file: ``h5py``, hloc and every ``sekd`` command read the same keys
and arrays, as long as ``<output>.shards/`` stays beside ``<output>`` (source paths are
relative to the output's folder, so the pair moves together). A virtual array whose shard
is missing would read as its fill value, so float arrays are NaN-filled and
``check_present`` turns that into one clear error instead of silent zeros.

Resume: a shard on disk counts as done whether or not a merge has referenced it yet; every
merge references the shards' keys the file does not hold (``link_shards``).
"""
from __future__ import annotations

import logging
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np

from .fsio import temp_name

logger = logging.getLogger("sekd")

SUFFIX = ".shards"
WriteGroup = Callable[[h5py.File, str, dict[str, np.ndarray]], None]


def shard_root(output: Path) -> Path:
    """``<output>.shards/``: the folder of the shards that ``output`` references."""
    output = Path(output)
    return output.with_name(output.name + SUFFIX)


def write_shard(output: Path, items: list[tuple[str, dict[str, np.ndarray]]], write_group: WriteGroup,
                writer: str = "") -> Path:
    """Write ``items`` (key, arrays) as one shard of ``output`` with ``write_group``; returns its path.

    Durable before it is visible: written under a temporary name, fsynced, renamed, and the
    folder fsynced, so a merge never references a shard a crash could still lose.
    """
    root = shard_root(output)
    root.mkdir(parents=True, exist_ok=True)
    name = f"{time.time_ns():020d}-{os.getpid()}{'-' + writer if writer else ''}.h5"
    target = root / name
    tmp = root / f".{name}.{os.getpid()}.tmp"
    try:
        with h5py.File(tmp, "w") as f:
            for key, arrays in items:
                write_group(f, key, arrays)
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    _fsync_folder(root)
    return target


def _fsync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # some file systems do not open folders: the rename is as durable as they make it
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def shard_files(output: Path) -> list[Path]:
    """Complete shards of ``output``, oldest first (temporaries of writers are skipped)."""
    root = shard_root(output)
    if not root.is_dir():
        return []
    return sorted(p for p in root.glob("*.h5") if not p.name.startswith("."))


def shard_keys(path: Path) -> list[str]:
    """Top-level item paths of one shard: groups holding arrays (``a/b.jpg`` for nested keys)."""
    keys: list[str] = []
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: keys.append(name)
                     if isinstance(obj, h5py.Group) and any(isinstance(v, h5py.Dataset) for v in obj.values())
                     else None)
    return keys


def all_keys(output: Path) -> set[str]:
    """Keys held by any shard of ``output`` (unreadable shards are skipped with a warning; their items are redone)."""
    keys: set[str] = set()
    for path in shard_files(output):
        try:
            keys.update(shard_keys(path))
        except OSError as exc:
            logger.warning("%s: unreadable shard (%s); its items will be computed again", path, exc)
    return keys


def link_shards(f: h5py.File, output: Path, present: set[str]) -> int:
    """Reference, in the open output file ``f``, every shard item whose key is not in ``present``; returns the count.

    Each array becomes a virtual dataset of the same path, shape and dtype mapping the
    shard's array (source path relative to the output's folder); group and array attributes
    are copied. Float arrays are NaN-filled, integer ones -1-filled, so a missing shard is
    detectable (``check_present``).
    """
    count = 0
    relative = shard_root(output).name
    for path in shard_files(output):
        try:
            with h5py.File(path, "r") as shard:
                keys = [key for key in shard_keys(path) if key not in present]
                for key in keys:
                    _link_group(f, key, shard[key], f"{relative}/{path.name}")
                    present.add(key)
                count += len(keys)
        except OSError as exc:
            logger.warning("%s: unreadable shard (%s); its items will be computed again", path, exc)
    return count


def _link_group(f: h5py.File, key: str, source: h5py.Group, source_file: str) -> None:
    if key in f:  # a re-merged item replaces, never duplicates
        del f[key]
    group = f.create_group(key)
    group.attrs.update(source.attrs)
    for name, array in source.items():
        if not isinstance(array, h5py.Dataset):
            continue
        layout = h5py.VirtualLayout(shape=array.shape, dtype=array.dtype)
        layout[...] = h5py.VirtualSource(source_file, array.name, shape=array.shape, dtype=array.dtype)
        fill = np.nan if np.issubdtype(array.dtype, np.floating) else -1
        group.create_virtual_dataset(name, layout, fillvalue=fill)
        group[name].attrs.update(array.attrs)


def check_present(key: str, arrays: dict[str, np.ndarray], output: Path) -> None:
    """OSError-free check that virtual arrays were found: NaN keypoints mean the shard file is missing."""
    from .errors import SekdError

    keypoints = arrays.get("keypoints")
    if keypoints is not None and keypoints.size and np.isnan(keypoints).any():
        raise SekdError(f"{output}: the arrays of '{key}' are in a shard file that is missing; keep the folder "
                        f"{shard_root(output).name}/ beside {Path(output).name} (they move together)")


def clear(output: Path) -> None:
    """Delete every shard of ``output`` (after a new, empty output replaced the one that referenced them)."""
    root = shard_root(output)
    if root.is_dir():
        trash = temp_name(root)
        os.replace(root, trash)
        shutil.rmtree(trash, ignore_errors=True)
