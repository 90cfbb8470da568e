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
is identical to hloc's; for keys with '/', the group is also hard-linked under hloc's key
``name0.replace('/', '-') + '/' + name1.replace('/', '-')`` (no copy of the data), so hloc's
``get_matches`` reads every pair unchanged. Two pairs that hloc cannot tell apart
(``a/x.jpg`` next to ``a-x.jpg``) are refused.

Each unordered pair is stored once; ``read_matches`` returns it in either order.
Writing uses the crash-safe parts + merge scheme of the feature file.
"""
from __future__ import annotations

import json

import h5py
import numpy as np

from ..errors import SekdError

FORMAT = "sekd-matches"
FORMAT_VERSION = 1


def pair_key(name0: str, name1: str) -> str:
    """The part-store key of a pair (JSON, so any characters in names are safe)."""
    return json.dumps([name0, name1])


def pair_path(name0: str, name1: str) -> str:
    """HDF5 path of the pair group."""
    return f"{name0}/{name1}"


def hloc_pair_path(name0: str, name1: str, separator: str = "/") -> str:
    """The key under which hloc looks a pair up (``hloc.utils.parsers.names_to_pair``): '/' in names becomes '-'."""
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


def _check_hloc_keys(f: h5py.File, name0: str, name1: str) -> None:
    """SekdError if another pair already holds a key under which hloc would look this pair up.

    hloc tries ``names_to_pair`` in both orders, so ``a/x.jpg - b/y.jpg`` and ``a-x.jpg - b-y.jpg``
    (or ``b-y.jpg - a-x.jpg``) would be the same pair to hloc: refused rather than silently mixed up.
    """
    for key in (hloc_pair_path(name0, name1), hloc_pair_path(name1, name0)):
        if key not in f:
            continue
        obj = f[key]
        other = (str(obj.attrs.get("name0", "?")), str(obj.attrs.get("name1", "?"))) \
            if isinstance(obj, h5py.Group) and "matches0" in obj else None
        if other is None or {*other} != {name0, name1}:
            held = f"the pair '{other[0]}' - '{other[1]}'" if other else "an image folder"
            raise SekdError(
                f"{f.filename}: the pair '{name0}' - '{name1}' and {held} share hloc's key '{key}' "
                "(hloc replaces '/' in image names by '-'); rename one of the images so the names differ")


def write_pair_group(f: h5py.File, key: str, arrays: dict[str, np.ndarray]) -> None:
    """Store one pair's part (``matches0``, ``matching_scores0``) under ``name0/name1``.

    When hloc's key of the pair differs (a name holds '/'), the group is also linked under
    it (an HDF5 hard link: the same data, no copy), so hloc's ``get_matches`` finds it.
    """
    name0, name1 = json.loads(key)
    path, hloc = pair_path(name0, name1), hloc_pair_path(name0, name1)
    _check_hloc_keys(f, name0, name1)
    for old in {path, hloc}:  # a re-merged part replaces, never duplicates
        if old in f:
            del f[old]
    group = f.create_group(path)
    group.create_dataset("matches0", data=arrays["matches0"].astype(np.int32))
    group.create_dataset("matching_scores0", data=arrays["matching_scores0"].astype(np.float32))
    group.attrs["name0"], group.attrs["name1"] = name0, name1
    if hloc != path:
        f[hloc] = group


def check_hloc_keys(pairs: list[tuple[str, str]], path) -> None:
    """SekdError naming two of ``pairs`` that hloc could not tell apart (see ``_check_hloc_keys``), before any work."""
    seen: dict[frozenset[str], tuple[str, str]] = {}
    for name0, name1 in pairs:
        mangled = frozenset((name0.replace("/", "-"), name1.replace("/", "-")))
        first = seen.setdefault(mangled, (name0, name1))
        if {*first} != {name0, name1}:
            raise SekdError(
                f"{path}: the pairs '{first[0]}' - '{first[1]}' and '{name0}' - '{name1}' share hloc's key "
                f"'{hloc_pair_path(name0, name1)}' (hloc replaces '/' in image names by '-'); rename one of the images")


def list_pairs(path) -> list[tuple[str, str]]:
    """All pairs stored in a match file, as ``(name0, name1)`` in their stored orientation, sorted.

    A pair linked under hloc's key too counts once. Groups without names (a match file written
    by hloc) are listed by their key split at its '/' (hloc's key has exactly one).
    """
    pairs = set()

    def visit(name, obj):
        if isinstance(obj, h5py.Group) and "matches0" in obj:
            names = (obj.attrs["name0"], obj.attrs["name1"]) if "name0" in obj.attrs else name.split("/", 1)
            if len(names) != 2:  # hloc's old 'name0_name1' keys cannot be split back
                raise SekdError(f"{path}: the pair group '{name}' does not say which images it joins (an old hloc "
                                "match file); give the pairs with a pairs file")
            pairs.add((str(names[0]), str(names[1])))

    with h5py.File(path, "r") as f:
        f.visititems(visit)
    return sorted(pairs)


def stored_pairs(path, pairs: list[tuple[str, str]]) -> set[frozenset[str]]:
    """Which of ``pairs`` the file holds (in either order), as unordered pairs."""
    with h5py.File(path, "r") as f:
        hloc = _is_hloc(f)
        return {frozenset(p) for p in pairs if _find(f, *p, hloc=hloc) is not None}


def _is_hloc(f: h5py.File) -> bool:
    """A match file written by hloc (no format attribute): its pairs are under hloc's keys only."""
    return f.attrs.get("format") != FORMAT


def _find(f: h5py.File, name0: str, name1: str, hloc: bool | None = None) -> tuple[h5py.Group, bool] | None:
    """The pair's group and whether it is stored as (name1, name0).

    sekd's key; in a file written by hloc (``hloc``, default: read from the file) also hloc's
    keys, new then old ('_'). sekd's own files hold every pair under sekd's key.
    """
    tried = set()
    keys = (pair_path, hloc_pair_path, lambda a, b: hloc_pair_path(a, b, "_"))
    for key in keys if (_is_hloc(f) if hloc is None else hloc) else keys[:1]:
        for (a, b), swapped in (((name0, name1), False), ((name1, name0), True)):
            path = key(a, b)
            if path in tried:  # without '/' in the names, sekd's key is hloc's
                continue
            tried.add(path)
            if path in f and "matches0" in f[path]:
                group = f[path]
                # Under hloc's '-' keys (ambiguous), a group that names its pair must be this pair.
                if key is not pair_path and "name0" in group.attrs \
                        and {str(group.attrs["name0"]), str(group.attrs["name1"])} != {a, b}:
                    continue
                return group, swapped
    return None


def _pair_matches(f: h5py.File, name0: str, name1: str, path, hloc: bool | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    found = _find(f, name0, name1, hloc)
    if found is None:
        raise SekdError(f"{path}: has no matches for the pair '{name0}' - '{name1}'; run `sekd match` for it")
    group, swapped = found
    matches0, scores0 = group["matches0"][()], group["matching_scores0"][()]
    idx0 = np.flatnonzero(matches0 >= 0)
    pairs = np.stack([idx0, matches0[idx0]], axis=1).astype(np.int64).reshape(-1, 2)
    return (pairs[:, ::-1].copy() if swapped else pairs), scores0[idx0].astype(np.float32)  # hloc: float16


def read_matches(path, name0: str, name1: str) -> tuple[np.ndarray, np.ndarray]:
    """Matches of a pair as ``M x 2`` int64 indices (name0's keypoint, name1's keypoint) and ``M`` scores.

    Works whichever order the pair was stored in; SekdError if the file lacks the pair.
    """
    with h5py.File(path, "r") as f:
        return _pair_matches(f, name0, name1, path)


def iter_matches(path, pairs):
    """Yield ``(name0, name1, M x 2 indices, M scores)`` for each pair, reading the file once."""
    with h5py.File(path, "r") as f:
        hloc = _is_hloc(f)
        for name0, name1 in pairs:
            yield (name0, name1, *_pair_matches(f, name0, name1, path, hloc))
