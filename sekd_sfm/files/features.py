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
      <key> attrs (photos with a mask file only, ``--masks``): mask_sha256 (of the file),
             mask_ignored (fraction of the photo's pixels ignored), mask_refused (why a mask
             was not used; the photo was used whole)
      attrs: masks (the masks folder of the last run that had one; "" after a run without)

``descriptors`` is D x N like hloc's files, so hloc's matchers read it unchanged.

Written crash-safe through the part store (``partstore``); one writer per file (``locking``).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import h5py
import numpy as np

from ..errors import SekdError
from . import shards

logger = logging.getLogger("sekd")

FORMAT = "sekd-features"
FORMAT_VERSION = 1
ARRAYS = ("keypoints", "descriptors", "scores", "image_size", "scales", "orientations")
#: An image group's attributes recording its mask (docs/masks.md); the arrays of an extracted photo carry them
#: under these names (``extract._mask_record``), only when the photo has a mask file.
MASK_ATTRS = ("mask_sha256", "mask_ignored", "mask_refused")
#: File attribute: the masks folder of the last run that was given one.
MASKS = "masks"


def read_attrs(path: Path, file_format: str = FORMAT, *, role: str = "input") -> dict:
    """The file attributes; SekdError if ``path`` is not a readable file of ``file_format``.

    ``role`` only words the error: "input" (a file to read; an hloc feature file, which has
    no ``format`` attribute, is accepted, see ``hloc_attrs``) or "output" (a file to resume).
    """
    kind = {FORMAT: "feature"}.get(file_format, file_format.removeprefix("sekd-"))
    fix = "delete it or choose another output" if role == "output" else {
        FORMAT: "pass a feature file written by `sekd extract` or by hloc's extract_features",
        "sekd-matches": "pass a match file written by `sekd match`"}.get(file_format, f"pass a {kind} file written by sekd")
    try:
        with h5py.File(path, "r") as f:
            attrs = dict(f.attrs)
            if "format" not in attrs and file_format == FORMAT and role == "input":
                return hloc_attrs(f, path)
    except OSError as exc:
        raise SekdError(f"{path}: not a readable HDF5 file ({exc}); {fix}") from exc
    if attrs.get("format") != file_format:
        raise SekdError(f"{path}: not a sekd {kind} file (no format='{file_format}' attribute); {fix}")
    if SHARDS in attrs:
        _check_shards(Path(path), json.loads(attrs[SHARDS]))
    return attrs


#: Attribute of a file whose arrays live in shard files (``shards``): {"folder", "files"}.
SHARDS = "shards"


def _check_shards(path: Path, record: dict) -> None:
    """SekdError when the shard folder a file references is missing or holds fewer shards than it did."""
    have = len(shards.shard_files(path))
    if have < int(record.get("files", 0)):
        raise SekdError(f"{path}: its arrays are in {record.get('files')} shard files under "
                        f"{shards.shard_root(path).name}/ beside it, {have} found there; keep that folder with the file "
                        "(they move together)")


def hloc_attrs(f: h5py.File, path: Path) -> dict:
    """Attributes standing in for those of a sekd file, for a feature file written by hloc.

    hloc stores no feature type: its descriptors (D x N, float32 or float16) are matched as
    float vectors by L2 distance, read as float32. SekdError if no image has keypoints, or if
    one lacks descriptors (detector-free matchers write keypoints only).
    """
    def visit(name: str, obj) -> str | None:
        if isinstance(obj, h5py.Group) and "keypoints" in obj:
            return name
        return None

    first = f.visititems(visit)
    if first is None:
        raise SekdError(f"{path}: not a feature file (no format='{FORMAT}' attribute and no image group with "
                        "keypoints, as sekd or hloc write them); pass the file written by `sekd extract`")
    if "descriptors" not in f[first]:
        raise SekdError(f"{path}: image '{first}' has keypoints but no descriptors (a file of a detector-free "
                        "matcher?); `sekd match` needs descriptors: extract them with `sekd extract`")
    desc = f[first]["descriptors"]
    if desc.dtype.kind != "f" or desc.ndim != 2:
        raise SekdError(f"{path}: image '{first}' has {desc.dtype} descriptors of shape {desc.shape}; an hloc feature "
                        "file must hold D x N float descriptors")
    return {"format": "hloc", "feature_type": "unknown", "descriptor_dim": int(desc.shape[0]),
            "descriptor_dtype": "float32", "config": json_attr({"feature": "unknown", "source": "hloc"}),
            "model_sha256": ""}


def list_keys(path: Path) -> list[str]:
    """Keys of the images stored in a feature file, sorted."""
    with h5py.File(path, "r") as f:
        return _keys_of(f)


def _keys_of(f: h5py.File) -> list[str]:
    keys: list[str] = []
    f.visititems(lambda name, obj: keys.append(name) if isinstance(obj, h5py.Group) and "keypoints" in obj else None)
    return sorted(keys)


def read_features(path: Path, key: str) -> dict[str, np.ndarray]:
    """Arrays of one image, with ``descriptors`` transposed back to N x D."""
    with h5py.File(path, "r") as f:
        if key not in f:
            raise SekdError(f"{path}: has no features for image '{key}'")
        group = f[key]
        # hloc may store float16 (its as_half option): everything downstream computes in float32.
        out = {name: group[name][()] for name in ARRAYS if name in group}
        out = {name: a.astype(np.float32) if a.dtype == np.float16 else a for name, a in out.items()}
        shards.check_present(key, out, path)
        if "descriptors" not in out:
            raise SekdError(f"{path}: image '{key}' has keypoints but no descriptors; extract them with `sekd extract`")
    out["descriptors"] = out["descriptors"].T
    return out


def write_image_group(f: h5py.File, key: str, arrays: dict[str, np.ndarray]) -> None:
    if key in f:  # a re-merged part replaces, never duplicates
        del f[key]
    group = f.create_group(key)
    for name in ARRAYS:
        if name in arrays:
            value = arrays[name].T if name == "descriptors" else arrays[name]
            group.create_dataset(name, data=value)
    if "uncertainty" in arrays:  # hloc's triangulation scales its error thresholds by it (pixels)
        group["keypoints"].attrs["uncertainty"] = float(arrays["uncertainty"])
    for name in MASK_ATTRS:
        if name in arrays:  # a 0-d array here (it travelled through the part store)
            value = np.asarray(arrays[name])
            group.attrs[name] = str(value) if value.dtype.kind == "U" else float(value)


def mask_records(path: Path) -> dict[str, str]:
    """``key -> mask_sha256`` of the images of a feature file extracted with a mask file ("" for the others).

    An image group made by ``--ray-merge virtual`` holds virtual datasets only: its attributes
    are read from the shard the datasets map, where the worker wrote them.
    """
    path = Path(path)
    with h5py.File(path, "r") as f:
        records: dict[str, str] = {}
        for key in _keys_of(f):
            group = f[key]
            sha = group.attrs.get("mask_sha256")
            if sha is None and group["keypoints"].is_virtual:
                sha = _shard_attr(path, group["keypoints"], key, "mask_sha256")
            records[key] = str(sha or "")
    return records


def _shard_attr(path: Path, dataset: h5py.Dataset, key: str, name: str) -> str | None:
    """Attribute ``name`` of ``key``'s group in the shard a virtual ``dataset`` maps (None if unreadable)."""
    source = dataset.virtual_sources()[0].file_name  # relative to the feature file's folder
    try:
        with h5py.File(path.parent / source, "r") as shard:
            return shard[key].attrs.get(name) if key in shard else None
    except OSError:
        return None



def json_attr(value: object) -> str:
    """JSON text for an HDF5 attribute (sorted keys so equal configurations compare equal)."""
    return json.dumps(value, sort_keys=True)


