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

Each shard also holds, under ``/.links/``, its items' groups of virtual datasets exactly as
the output will hold them (made by the worker, which has the arrays at hand): the merge then
copies each image's group (``H5Ocopy``, ~85 us per image) instead of building it (~300 us:
the merge's throughput is what bounds the cluster size, docs/cluster.md). A shard without
them (a writer killed in between cannot leave one: they are written in the same file) is
linked from its description.

Resume: a shard on disk counts as done whether or not a merge has referenced it yet; every
merge references the shards' keys the file does not hold (``link_shards``).
"""
from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np

from ..errors import SekdError
from .atomic import atomic_output, remove_folder, write_atomic

logger = logging.getLogger("sekd")

SUFFIX = ".shards"
MANIFEST = "manifest-"  # manifest-<time>-<pid>.json: shard descriptions sent by Ray workers
LINKS = ".links"  # a shard's group of its items' ready-made virtual-dataset groups
WriteGroup = Callable[[h5py.File, str, dict[str, np.ndarray]], None]


def shard_root(output: Path) -> Path:
    """``<output>.shards/``: the folder of the shards that ``output`` references."""
    output = Path(output)
    return output.with_name(output.name + SUFFIX)


def write_shard(output: Path, items: list[tuple[str, dict[str, np.ndarray]]], write_group: WriteGroup,
                writer: str = "") -> tuple[Path, dict[str, dict]]:
    """Write ``items`` (key, arrays) as one shard of ``output`` with ``write_group``; returns its path and
    its ``describe()`` (made while writing: the worker sends it, no second read of the shard).

    Durable before it is visible (``fsio.atomic_output``: temporary name, fsync, rename, folder
    fsync), so a merge never references a shard a crash could still lose. Holds its items'
    virtual-dataset groups under ``/.links/`` too (see the module's docstring).
    """
    target = shard_root(output) / f"{time.time_ns():020d}-{os.getpid()}{'-' + writer if writer else ''}.h5"
    source = f"{shard_root(output).name}/{target.name}".encode()  # relative to the output's folder
    with atomic_output(target) as tmp, h5py.File(tmp, "w") as f:
        for key, arrays in items:
            write_group(f, key, arrays)
        described = _describe_open(f)
        linker = _Linker()
        for key, arrays in described.items():
            linker.link_group(f, key, arrays, source, at=f"{LINKS}/{key}")
    return target, described


def shard_files(output: Path) -> list[Path]:
    """Complete shards of ``output``, oldest first (writers' temporaries, ``*.h5.<pid>.tmp``, are not)."""
    root = shard_root(output)
    return sorted(root.glob("*.h5")) if root.is_dir() else []


def describe(path: Path) -> dict[str, dict]:
    """What a merge needs to reference a shard's items without opening it: ``key -> {array: [shape, dtype, attrs]}``.

    ``shape`` is a list, ``dtype`` numpy's ``str`` (e.g. ``"<f4"``), ``attrs`` the array's
    attributes (JSON values). Ray workers send this with their keys; the driver saves it as a
    manifest (``write_manifest``), so merges need not open the shards.
    """
    with h5py.File(path, "r") as f:
        return _describe_open(f)


def _describe_open(f: h5py.File) -> dict[str, dict]:
    """``describe`` of an open shard (its ``/.links/`` left out)."""
    items: dict[str, dict] = {}

    def visit(name: str, obj) -> None:
        if isinstance(obj, h5py.Dataset) and not name.startswith(LINKS + "/"):
            key, _, array = name.rpartition("/")
            attrs = {k: v.item() if isinstance(v, np.generic) else v for k, v in obj.attrs.items()}
            items.setdefault(key, {})[array] = [list(obj.shape), obj.dtype.str, attrs]

    f.visititems(visit)
    return items


def write_manifest(output: Path, described: dict[str, dict]) -> Path:
    """Save ``shard name -> describe()`` (what Ray workers reported) beside the shards, atomically; returns its path."""
    path = shard_root(output) / f"{MANIFEST}{time.time_ns():020d}-{os.getpid()}.json"
    return write_atomic(path, json.dumps(described, separators=(",", ":")))


def _manifests(output: Path) -> dict[str, dict]:
    known: dict[str, dict] = {}
    root = shard_root(output)
    for path in sorted(root.glob(f"{MANIFEST}*.json")) if root.is_dir() else []:
        try:
            known.update(json.loads(path.read_text()))
        except (OSError, ValueError) as exc:  # the shards it describes are read instead
            logger.warning("%s: unreadable shard manifest (%s); the shards will be read instead", path, exc)
    return known


def describe_all(output: Path) -> dict[str, dict]:
    """``shard name -> describe()`` of every shard of ``output``: from the manifests where they
    describe it, else read from the shard itself (unreadable shards are left out, with a warning)."""
    known = _manifests(output)
    out = {}
    for path in shard_files(output):
        if path.name in known:
            out[path.name] = known[path.name]
            continue
        try:
            out[path.name] = describe(path)
        except OSError as exc:
            logger.warning("%s: unreadable shard (%s); its items will be computed again", path, exc)
    return out


def keys_of(described: dict[str, dict]) -> set[str]:
    """The item keys of ``describe_all``'s shard descriptions."""
    return {key for items in described.values() for key in items}


def all_keys(output: Path) -> set[str]:
    """Keys held by any shard of ``output`` (unreadable shards are skipped with a warning; their items are redone)."""
    return keys_of(describe_all(output))


def link_shards(f: h5py.File, output: Path, present: set[str], described: dict[str, dict]) -> int:
    """Reference, in the open output file ``f``, every shard item whose key is not in ``present``; returns the count.

    ``described`` is ``describe_all(output)``. Each array becomes a virtual dataset of the
    same path, shape and dtype mapping the shard's array (source path relative to the
    output's folder), with the array's attributes: a few HDF5 metadata writes per image, no
    array read. Float arrays are NaN-filled, integer ones -1-filled, so a missing shard is
    detectable (``check_present``).
    """
    count = 0
    relative = shard_root(output).name
    linker = _Linker()
    for name, items in described.items():
        todo = [key for key in items if key not in present]
        if not todo:
            continue
        copied = _copy_links(f, shard_root(output) / name, todo, linker)
        source = f"{relative}/{name}".encode()
        for key in todo:
            if key not in copied:
                linker.link_group(f, key, items[key], source)
            present.add(key)
            count += 1
    return count


def _copy_links(f: h5py.File, shard: Path, keys: list[str], linker: _Linker) -> set[str]:
    """Copy the ready-made groups of ``keys`` from ``shard``'s ``/.links/`` into ``f``; returns the keys copied
    (none from a shard written without them or unreadable here: those are built from the description)."""
    copied: set[str] = set()
    try:
        with h5py.File(shard, "r") as source:
            if LINKS not in source:
                return copied
            for key in keys:
                path = f"{LINKS}/{key}"
                if path not in source:
                    continue
                if key in f:  # a re-merged item replaces, never duplicates
                    del f[key]
                h5py.h5o.copy(source.id, path.encode(), f.id, key.encode(), lcpl=linker.lcpl)
                copied.add(key)
    except OSError as exc:  # e.g. not visible on this node: the description still links it
        logger.debug("%s: ready-made links not read (%s)", shard, exc)
    return copied


class _Linker:
    """Writes images' groups of virtual datasets through h5py's low-level API (~2x faster than
    ``create_virtual_dataset``: the merge's whole cost is these calls). The property lists and
    types that every image repeats are made once per merge, and copied per array (a further ~1.2x)."""

    def __init__(self):
        self.lcpl = h5py.h5p.create(h5py.h5p.LINK_CREATE)
        self.lcpl.set_create_intermediate_group(True)  # nested keys (a/b.jpg), as h5py's create_group
        self._dcpl: dict[str, tuple] = {}  # dtype str -> (dataset creation template with its fill value, HDF5 type)

    def _template(self, dtype: str) -> tuple:
        if dtype not in self._dcpl:
            numpy_dtype = np.dtype(dtype)
            dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
            dcpl.set_fill_value(np.array(np.nan if numpy_dtype.kind == "f" else -1, numpy_dtype))
            self._dcpl[dtype] = (dcpl, h5py.h5t.py_create(numpy_dtype))
        return self._dcpl[dtype]

    def link_group(self, f: h5py.File, key: str, arrays: dict[str, list], source_file: bytes,
                   at: str | None = None) -> None:
        """One image's group (at ``key``, or ``at``): a virtual dataset per array of ``arrays``
        (``describe``'s ``[shape, dtype, attrs]``) mapping ``/key/array`` of ``source_file``."""
        at = at or key
        if at in f:  # a re-merged item replaces, never duplicates
            del f[at]
        group = h5py.h5g.create(f.id, at.encode(), lcpl=self.lcpl)
        for name, (shape, dtype, attrs) in sorted(arrays.items()):
            template, h5type = self._template(dtype)
            space = h5py.h5s.create_simple(tuple(shape))
            dcpl = template.copy()  # a fresh list per array: set_virtual adds to the list's mappings
            dcpl.set_virtual(space, source_file, f"/{key}/{name}".encode(), space)
            dataset = h5py.h5d.create(group, name.encode(), h5type, space, dcpl=dcpl)
            for attr, value in attrs.items():
                value = np.asarray(value)
                h5py.h5a.create(dataset, attr.encode(), h5py.h5t.py_create(value.dtype),
                                h5py.h5s.create(h5py.h5s.SCALAR) if value.ndim == 0
                                else h5py.h5s.create_simple(value.shape)).write(np.ascontiguousarray(value))


def check_present(key: str, arrays: dict[str, np.ndarray], output: Path) -> None:
    """SekdError when the arrays of ``key`` read as the fill value: NaN keypoints mean its shard file is missing."""
    keypoints = arrays.get("keypoints")
    if keypoints is not None and keypoints.size and np.isnan(keypoints).any():
        raise SekdError(f"{output}: the arrays of '{key}' are in a shard file that is missing; keep the folder "
                        f"{shard_root(output).name}/ beside {Path(output).name} (they move together)")


def remove_temps(output: Path) -> None:
    """Delete the temporaries (``*.tmp``) of shard writers in ``<output>.shards/``: at the start of a
    run, holding the output's lock, every one is a killed worker's (a PID check would not do:
    the writers ran on other nodes)."""
    root = shard_root(output)
    for tmp in root.glob("*.tmp") if root.is_dir() else []:
        tmp.unlink(missing_ok=True)


def clear(output: Path) -> None:
    """Delete every shard of ``output`` (after a new, empty output replaced the one that referenced them)."""
    remove_folder(shard_root(output))
