"""The results of a per-item stage in progress whose output is not a features or matches file: refinement's
alignments and verification's geometries (per pair), the hierarchical mapper's clusters, retrieval's
global descriptors (per image).

One HDF5 file beside the stage's real output, one group per item under a digest of its key (image
names may hold '/'; the key is kept as the attribute ``pair``, whatever the item), and the file's ``format`` and
``signature`` (what the results were computed from). An executor fills it through the crash-safe
part store; a killed run's pairs are reused by the next run with the same signature, and the file
goes once the stage's output holds what it was for. The items computed stay in the part store and are read from
there (``items``): they are never copied into the file::

    results = PairResults(out / "x-pairs.h5", "sekd-x-pairs", signature)
    stage = Stage(..., batches=results.missing(keys), output=results.path, write_group=write_pair_group)
    arrays = results.compute(stage, executor, progress)   # {key: {name: array}}; or run(), then items()
    ... write the output ...
    results.remove()
"""
from __future__ import annotations

import hashlib
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np

from ..errors import SekdError
from . import partstore


def write_pair_group(f: h5py.File, key: str, arrays: dict[str, np.ndarray]) -> None:
    """Store one pair's arrays (a re-merged part replaces its group, never duplicates it)."""
    name = hashlib.sha1(key.encode()).hexdigest()
    if name in f:
        del f[name]
    group = f.create_group(name)
    group.attrs["pair"] = key
    for array_name, value in arrays.items():
        group.create_dataset(array_name, data=value)


class PairResults:
    """The per-pair results file ``path`` for inputs ``signature``: made (or replaced, when it holds another
    signature's results) on construction, with the part store an executor writes into."""

    def __init__(self, path: Path, file_format: str, signature: str, max_items: int = 64):
        self.path, self.format = Path(path), file_format
        self.parts = partstore.PartStore(self.path, max_items=max_items)
        stale = self.path.is_file() and not self._holds(signature)
        partstore.prepare_output(self.path, {"format": file_format, "signature": signature}, self.parts,
                                 overwrite=stale, compare=("signature",))

    def _holds(self, signature: str) -> bool:
        try:
            with h5py.File(self.path, "r") as f:
                return f.attrs.get("format") == self.format and f.attrs.get("signature") == signature
        except OSError:
            return False

    def stored(self) -> set[str]:
        """The keys of the pairs finished so far (in the file or its part store)."""
        with h5py.File(self.path, "r") as f:
            return {str(group.attrs["pair"]) for group in f.values()} | self.parts.keys()

    def missing(self, keys: list[str]) -> list[list[str]]:
        """``keys`` not finished yet, one batch each, in order."""
        done = self.stored()
        return [[key] for key in keys if key not in done]

    def run(self, stage, executor, progress: bool = True) -> Path:
        """Run ``stage`` (its output this file) on ``executor``; returns this file. An item fails only with its whole
        run (its worker raises): the finished ones stay for the next run, and a file with none is removed.

        The items stay in the part store (``Stage.keep_parts``), where ``items`` reads them: the caller removes
        them once its output is written, so copying them into the HDF5 file (one group and its datasets per item,
        then read back) would be the driver's serial work thrown away."""
        def on_error(key: str, error: str) -> None:
            raise SekdError(error)

        try:
            executor.run(replace(stage, keep_parts=True), self.parts, on_error, progress=progress)
        except BaseException:
            if not self.stored():
                self.remove()
            raise
        return self.path

    def items(self) -> Iterator[tuple[str, dict[str, np.ndarray]]]:
        """Every finished item's key and arrays, one chunk in memory at a time: the part store's, then those an earlier
        version merged into the file (a key in both: the part store's, the newer)."""
        seen = set()
        for key, arrays in self.parts.items():
            seen.add(key)
            yield key, arrays
        with h5py.File(self.path, "r") as f:
            for group in f.values():
                key = str(group.attrs["pair"])
                if key not in seen:
                    yield key, {name: data[()] for name, data in group.items()}

    def compute(self, stage, executor, progress: bool = True) -> dict[str, dict[str, np.ndarray]]:
        """``run``, then every item's arrays, by key (for results that fit in memory)."""
        self.run(stage, executor, progress)
        return dict(self.items())

    def remove(self) -> None:
        """The file and its parts, once the stage's output holds what they were for."""
        self.parts.clear()
        self.path.unlink(missing_ok=True)
