"""The feature file: hloc-compatible HDF5, written so that a crash never leaves a half file.

Layout (one group per image, nested by the image key's folders, as hloc does)::

    features.h5
      attrs: format="sekd-features", format_version, feature_type, descriptor_dim,
             descriptor_dtype, config (JSON), model_sha256, versions (JSON), created
      <key>/keypoints     N x 2 float32   x, y in original image pixels, OpenCV centres
      <key>/descriptors   D x N           float32 (unit L2 for SEKD) or uint8 bytes (binary)
      <key>/scores        N float32       detector score, decreasing
      <key>/image_size    2 int32         original (width, height)
      <key>/scales, <key>/orientations    N float32, classic features only

``descriptors`` is D x N like hloc's files, so hloc's matchers read it unchanged.

Crash safety: the output file is only ever replaced whole (copy, append, fsync, rename).
While a run goes on, each finished image is saved as its own small file in
``<output>.parts/`` (also by rename); a merge moves them into the HDF5 file. A run killed
at any moment leaves the last merged file, which opens, plus parts, which the next run
merges: nothing is lost or duplicated.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from pathlib import Path

import h5py
import numpy as np

from .errors import SekdError

FORMAT = "sekd-features"
FORMAT_VERSION = 1
ARRAYS = ("keypoints", "descriptors", "scores", "image_size", "scales", "orientations")


def _fsync_replace(tmp: Path, target: Path) -> None:
    with open(tmp, "rb+") as f:
        os.fsync(f.fileno())
    os.replace(tmp, target)


def create_empty(path: Path, attrs: dict) -> None:
    """Write a feature file with attributes and no images, atomically."""
    tmp = path.with_name(path.name + ".tmp")
    with h5py.File(tmp, "w") as f:
        for name, value in attrs.items():
            f.attrs[name] = value
    _fsync_replace(tmp, path)


def read_attrs(path: Path, file_format: str = FORMAT) -> dict:
    """The file attributes; SekdError if ``path`` is not a readable file of ``file_format``."""
    try:
        with h5py.File(path, "r") as f:
            attrs = dict(f.attrs)
    except OSError as exc:
        raise SekdError(f"{path}: not a readable HDF5 file ({exc}); delete it or choose another output") from exc
    if attrs.get("format") != file_format:
        kind = {FORMAT: "feature"}.get(file_format, file_format.removeprefix("sekd-"))
        raise SekdError(f"{path}: not a sekd {kind} file (no format='{file_format}' attribute); choose another output")
    return attrs


def list_keys(path: Path) -> list[str]:
    """Keys of the images stored in a feature file, sorted."""
    keys = []
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: keys.append(name) if isinstance(obj, h5py.Group) and "keypoints" in obj else None)
    return sorted(keys)


def read_features(path: Path, key: str) -> dict[str, np.ndarray]:
    """Arrays of one image, with ``descriptors`` transposed back to N x D."""
    with h5py.File(path, "r") as f:
        if key not in f:
            raise SekdError(f"{path}: has no features for image '{key}'")
        group = f[key]
        out = {name: group[name][()] for name in ARRAYS if name in group}
    out["descriptors"] = out["descriptors"].T
    return out


def _write_group(f: h5py.File, key: str, arrays: dict[str, np.ndarray]) -> None:
    if key in f:  # a re-merged part replaces, never duplicates
        del f[key]
    group = f.create_group(key)
    for name in ARRAYS:
        if name in arrays:
            value = arrays[name].T if name == "descriptors" else arrays[name]
            group.create_dataset(name, data=value)


class PartStore:
    """Finished images of a run in progress, one ``.npz`` per image, written by rename."""

    def __init__(self, output: Path):
        self.root = output.with_name(output.name + ".parts")

    def _file(self, key: str) -> Path:
        return self.root / (hashlib.sha1(key.encode("utf-8")).hexdigest() + ".npz")

    def save(self, key: str, arrays: dict[str, np.ndarray]) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        target = self._file(key)
        tmp = target.with_suffix(".tmp")
        with open(tmp, "wb") as f:
            np.savez(f, __key__=np.array(key), **arrays)
        os.replace(tmp, target)

    def load_all(self) -> dict[str, dict[str, np.ndarray]]:
        """All complete parts by key (unreadable leftovers are dropped and recomputed)."""
        parts = {}
        for file in sorted(self.root.glob("*.npz")) if self.root.is_dir() else []:
            try:
                with np.load(file) as data:
                    arrays = {k: data[k] for k in data.files}
                parts[str(arrays.pop("__key__"))] = arrays
            except Exception:  # noqa: BLE001 - a torn file is simply redone
                file.unlink(missing_ok=True)
        return parts

    def clear(self) -> None:
        shutil.rmtree(self.root, ignore_errors=True)


def merge_parts(path: Path, parts: PartStore, attrs: dict | None = None, write_group=None) -> int:
    """Move all saved parts (and new ``attrs``) into the HDF5 file: copy, append, fsync, rename.

    ``write_group(f, key, arrays)`` stores one part (default: a feature-file image group),
    so other files (matches) reuse the same crash-safe scheme. Returns the number of parts merged.
    """
    write_group = write_group or _write_group
    pending = parts.load_all()
    if pending or attrs:
        tmp = path.with_name(path.name + ".tmp")
        shutil.copyfile(path, tmp)
        with h5py.File(tmp, "a") as f:
            for key in sorted(pending):
                write_group(f, key, pending[key])
            f.attrs.update(attrs or {})
            f.attrs["modified"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        _fsync_replace(tmp, path)
    parts.clear()
    return len(pending)


def json_attr(value: object) -> str:
    """JSON text for an HDF5 attribute (sorted keys so equal configurations compare equal)."""
    return json.dumps(value, sort_keys=True)


def prepare_output(path: Path, attrs: dict, parts: PartStore, overwrite: bool, compare: tuple[str, ...],
                   what: str = "configuration") -> None:
    """Create ``path`` with ``attrs``, or check that the existing file agrees on the ``compare`` attributes.

    A resumed run must add to a file made the same way; a different one is refused
    (``overwrite`` replaces it). Leftovers of a killed merge are removed first.
    """
    path.with_name(path.name + ".tmp").unlink(missing_ok=True)
    if path.exists() and overwrite:
        path.unlink()
    if not path.exists():
        parts.clear()
        path.parent.mkdir(parents=True, exist_ok=True)
        create_empty(path, attrs)
        return
    existing = read_attrs(path, attrs["format"])
    for name in compare:
        if existing.get(name) != attrs.get(name):
            raise SekdError(
                f"{path}: was made with a different {what} ({name}={existing.get(name)}, now {attrs.get(name)}); "
                "pass --overwrite to replace it or choose another output file"
            )
