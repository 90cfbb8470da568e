"""The match file: hloc-compatible HDF5, one group per pair, nested ``name0 -> name1``.

Layout::

    matches.h5
      attrs: format="sekd-matches", format_version, feature_type, descriptor_dim,
             descriptor_dtype, features_config (JSON, the feature file's), config (JSON),
             features (path of the feature file), versions (JSON), created, modified
      <name0>/<name1>/matches0           N0 int32    index into name1's keypoints, -1 = unmatched
      <name0>/<name1>/matching_scores0   N0 float32  1 - d1/d2 (ratio margin, 0..1), 0 when unmatched
      attrs of the pair group: name0, name1

Pair groups nest the two image keys as HDF5 paths, as hloc's newer layout does, but
without hloc's replacement of '/' by '-' in each name (under which ``a/b.jpg`` and
``a-b.jpg`` collide). The path ``<name0>/<name1>`` splits into the two keys in exactly
one way for keys of one folder tree (a key cannot be both an image and a folder), and
each pair group also records ``name0`` and ``name1``. For keys without '/', the layout
is identical to hloc's, so hloc's readers load these files unchanged.

Each unordered pair is stored once; ``read_matches`` returns it in either order.
Writing uses the crash-safe parts + merge scheme of the feature file.
"""
from __future__ import annotations

import json

import h5py
import numpy as np

from .errors import SekdError

FORMAT = "sekd-matches"
FORMAT_VERSION = 1


def pair_key(name0: str, name1: str) -> str:
    """The part-store key of a pair (JSON, so any characters in names are safe)."""
    return json.dumps([name0, name1])


def pair_path(name0: str, name1: str) -> str:
    """HDF5 path of the pair group."""
    return f"{name0}/{name1}"


def write_pair_group(f: h5py.File, key: str, arrays: dict[str, np.ndarray]) -> None:
    """Store one pair's part (``matches0``, ``matching_scores0``) under ``name0/name1``."""
    name0, name1 = json.loads(key)
    path = pair_path(name0, name1)
    if path in f:  # a re-merged part replaces, never duplicates
        del f[path]
    group = f.create_group(path)
    group.create_dataset("matches0", data=arrays["matches0"].astype(np.int32))
    group.create_dataset("matching_scores0", data=arrays["matching_scores0"].astype(np.float32))
    group.attrs["name0"], group.attrs["name1"] = name0, name1


def list_pairs(path) -> list[tuple[str, str]]:
    """All pairs stored in a match file, as ``(name0, name1)`` in their stored orientation, sorted."""
    pairs = []

    def visit(name, obj):
        if isinstance(obj, h5py.Group) and "matches0" in obj:
            pairs.append((str(obj.attrs["name0"]), str(obj.attrs["name1"])))

    with h5py.File(path, "r") as f:
        f.visititems(visit)
    return sorted(pairs)


def stored_pairs(path, pairs: list[tuple[str, str]]) -> set[frozenset[str]]:
    """Which of ``pairs`` the file holds (in either order), as unordered pairs."""
    with h5py.File(path, "r") as f:
        return {frozenset(p) for p in pairs if _find(f, *p) is not None}


def _find(f: h5py.File, name0: str, name1: str) -> tuple[h5py.Group, bool] | None:
    for (a, b), swapped in (((name0, name1), False), ((name1, name0), True)):
        path = pair_path(a, b)
        if path in f and "matches0" in f[path]:
            return f[path], swapped
    return None


def _pair_matches(f: h5py.File, name0: str, name1: str, path) -> tuple[np.ndarray, np.ndarray]:
    found = _find(f, name0, name1)
    if found is None:
        raise SekdError(f"{path}: has no matches for the pair '{name0}' - '{name1}'; run `sekd match` for it")
    group, swapped = found
    matches0, scores0 = group["matches0"][()], group["matching_scores0"][()]
    idx0 = np.flatnonzero(matches0 >= 0)
    pairs = np.stack([idx0, matches0[idx0]], axis=1).astype(np.int64).reshape(-1, 2)
    return (pairs[:, ::-1].copy() if swapped else pairs), scores0[idx0]


def read_matches(path, name0: str, name1: str) -> tuple[np.ndarray, np.ndarray]:
    """Matches of a pair as ``M x 2`` int64 indices (name0's keypoint, name1's keypoint) and ``M`` scores.

    Works whichever order the pair was stored in; SekdError if the file lacks the pair.
    """
    with h5py.File(path, "r") as f:
        return _pair_matches(f, name0, name1, path)


def iter_matches(path, pairs):
    """Yield ``(name0, name1, M x 2 indices, M scores)`` for each pair, reading the file once."""
    with h5py.File(path, "r") as f:
        for name0, name1 in pairs:
            yield (name0, name1, *_pair_matches(f, name0, name1, path))
