"""hloc's HDF5 readers and writers, reproduced for the compatibility tests (hloc is not on PyPI).

Mirrors cvg/Hierarchical-Localization at commit c13273bd0ecc2917a35910fd843712a1c6243193
(2025-12-10): ``names_to_pair`` / ``names_to_pair_old`` from hloc/utils/parsers.py,
``list_h5_names`` / ``get_keypoints`` / ``find_pair`` / ``get_matches`` from hloc/utils/io.py,
and the storage step of ``hloc.extract_features.main`` (per-image group, ``as_half``
float16, ``keypoints.attrs["uncertainty"]``) and ``hloc.match_features`` (one group per
pair under ``names_to_pair``). Written from that code's behaviour, kept to what the tests
need; any change of hloc's key or layout must be made here too.
"""
from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np


def names_to_pair(name0: str, name1: str, separator: str = "/") -> str:
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


def names_to_pair_old(name0: str, name1: str) -> str:
    return names_to_pair(name0, name1, separator="_")


def list_h5_names(path: Path) -> list[str]:
    names = []
    with h5py.File(str(path), "r", libver="latest") as fd:
        def visit_fn(_, obj):
            if isinstance(obj, h5py.Dataset):
                names.append(obj.parent.name.strip("/"))

        fd.visititems(visit_fn)
    return list(set(names))


def get_keypoints(path: Path, name: str, return_uncertainty: bool = False):
    with h5py.File(str(path), "r", libver="latest") as hfile:
        dset = hfile[name]["keypoints"]
        p = dset.__array__()
        uncertainty = dset.attrs.get("uncertainty")
    if return_uncertainty:
        return p, uncertainty
    return p


def find_pair(hfile: h5py.File, name0: str, name1: str) -> tuple[str, bool]:
    pair = names_to_pair(name0, name1)
    if pair in hfile:
        return pair, False
    pair = names_to_pair(name1, name0)
    if pair in hfile:
        return pair, True
    pair = names_to_pair_old(name0, name1)
    if pair in hfile:
        return pair, False
    pair = names_to_pair_old(name1, name0)
    if pair in hfile:
        return pair, True
    raise ValueError(f"Could not find pair {(name0, name1)}... Maybe you matched with a different list of pairs? ")


def get_matches(path: Path, name0: str, name1: str) -> tuple[np.ndarray, np.ndarray]:
    with h5py.File(str(path), "r", libver="latest") as hfile:
        pair, reverse = find_pair(hfile, name0, name1)
        matches = hfile[pair]["matches0"].__array__()
        scores = hfile[pair]["matching_scores0"].__array__()
    idx = np.where(matches != -1)[0]
    matches = np.stack([idx, matches[idx]], -1)
    if reverse:
        matches = np.flip(matches, -1)
    scores = scores[idx]
    return matches, scores


def write_features(path: Path, name: str, pred: dict[str, np.ndarray], uncertainty: float,
                   as_half: bool = True) -> None:
    """Store one image as ``hloc.extract_features.main`` does (``pred`` as the model returns it: descriptors D x N)."""
    if as_half:
        pred = {k: v.astype(np.float16) if v.dtype == np.float32 else v for k, v in pred.items()}
    with h5py.File(str(path), "a", libver="latest") as fd:
        if name in fd:
            del fd[name]
        grp = fd.create_group(name)
        for k, v in pred.items():
            grp.create_dataset(k, data=v)
        grp["keypoints"].attrs["uncertainty"] = uncertainty


def write_matches(path: Path, name0: str, name1: str, matches0: np.ndarray, scores0: np.ndarray) -> None:
    """Store one pair as ``hloc.match_features.writer_fn`` does (int16 matches, float16 scores)."""
    pair = names_to_pair(name0, name1)
    with h5py.File(str(path), "a", libver="latest") as fd:
        if pair in fd:
            del fd[pair]
        grp = fd.create_group(pair)
        grp.create_dataset("matches0", data=matches0.astype(np.int16))
        grp.create_dataset("matching_scores0", data=scores0.astype(np.float16))
