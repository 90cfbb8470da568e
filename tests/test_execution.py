"""The local executor (sekd_sfm.execution): a stage in this process or over worker processes, same items either way."""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from sekd_sfm.errors import SekdError
from sekd_sfm.execution import LocalExecutor, Stage
from sekd_sfm.execution.local import processes_for
from sekd_sfm.files import partstore


class Squares:
    """A worker: each key ``"k"`` gives ``k**2`` and the process that computed it; key ``"bad"`` fails alone, key
    ``"fatal"`` stops the run."""

    def __init__(self, offset: int):
        self.offset = offset

    def __call__(self, keys: list[str]):
        for key in keys:
            if key == "fatal":
                raise SekdError("the input cannot be read")
            if key == "bad":
                yield key, None, "unreadable"
                continue
            time.sleep(0.05)  # a task outlasts a process's start: both processes take some, however busy the machine
            yield key, {"value": np.array([int(key) ** 2 + self.offset]), "pid": np.array([os.getpid()])}, ""


def _write(f, key: str, arrays: dict) -> None:
    group = f.require_group(key)
    for name, value in arrays.items():
        group.create_dataset(name, data=value)


def _stage(tmp_path, keys: list[str], processes: bool = True) -> Stage:
    return Stage(name="squares", worker=Squares, args=(1,), batches=[[key] for key in keys],
                 output=tmp_path / "out.h5", write_group=_write, joinable=True, per_task=2, local_processes=processes)


def _run(stage: Stage, processes: int, errors: list | None = None) -> tuple[dict, LocalExecutor]:
    stage.output.parent.mkdir(parents=True, exist_ok=True)
    partstore.create_empty(stage.output, {})
    parts = partstore.PartStore(stage.output, max_items=4)
    executor = LocalExecutor(processes)
    executor.run(stage, parts, lambda key, error: errors.append((key, error)) if errors is not None else None,
                 progress=False)
    return _read(stage.output), executor


def _read(path) -> dict:
    import h5py

    with h5py.File(path, "r") as f:
        return {key: {name: d[()] for name, d in f[key].items()} for key in f}


def test_processes_compute_the_same_items_as_this_process(tmp_path):
    keys = [str(k) for k in range(9)] + ["bad"]
    errors: list = []
    here, one = _run(_stage(tmp_path / "here", keys), 1, errors)
    spread, two = _run(_stage(tmp_path / "spread", keys), 2, errors)
    assert sorted(here) == sorted(spread) == sorted(keys[:-1])
    assert all(here[k]["value"][0] == spread[k]["value"][0] == int(k) ** 2 + 1 for k in here)
    assert {int(here[k]["pid"][0]) for k in here} == {os.getpid()}
    assert len({int(spread[k]["pid"][0]) for k in spread}) == 2 and os.getpid() not in {
        int(spread[k]["pid"][0]) for k in spread}
    assert errors == [("bad", "unreadable")] * 2  # a failed item is reported by the driver either way
    assert one.places == ["local"] and two.places == ["local: 2 processes"]


def test_only_stages_that_ask_use_processes_and_never_more_than_their_tasks(tmp_path):
    assert processes_for(_stage(tmp_path, [str(k) for k in range(9)], processes=False), 4) == 1
    assert processes_for(_stage(tmp_path, ["1", "2", "3"]), 4) == 2  # two tasks of two keys at most
    assert processes_for(_stage(tmp_path, ["1", "2"]), 4) == 1
    assert processes_for(_stage(tmp_path, [str(k) for k in range(9)]), 1) == 1


def test_a_failing_worker_process_stops_the_run_and_keeps_what_finished(tmp_path):
    keys = [str(k) for k in range(12)] + ["fatal"]
    stage = _stage(tmp_path, keys)
    partstore.create_empty(stage.output, {})
    parts = partstore.PartStore(stage.output, max_items=1)
    with pytest.raises(SekdError, match="cannot be read"):
        LocalExecutor(2).run(stage, parts, lambda key, error: None, progress=False)
    kept = partstore.PartStore(stage.output).keys()
    assert kept and kept <= set(keys[:-1])  # the next run computes only the rest


def test_results_in_progress_are_read_from_the_part_store_never_copied_into_their_file(tmp_path):
    # PairResults.compute: the items stay in the part store (Stage.keep_parts), a later run with the same signature
    # computes only what is missing, and items an earlier version merged into the file still count.
    import h5py

    from sekd_sfm.files.pairresults import PairResults, write_pair_group

    path = tmp_path / "squares-pairs.h5"
    results = PairResults(path, "sekd-squares", "inputs-1", max_items=2)
    stage = Stage(name="squares", worker=Squares, args=(0,), batches=results.missing(["1", "2", "3"]), output=path,
                  write_group=write_pair_group, joinable=True)
    first = results.compute(stage, LocalExecutor(1), progress=False)
    assert {k: int(v["value"][0]) for k, v in first.items()} == {"1": 1, "2": 4, "3": 9}
    with h5py.File(path, "r") as f:
        assert len(f) == 0  # nothing copied into the file
    assert partstore.PartStore(path).keys() == {"1", "2", "3"}

    with h5py.File(path, "a") as f:  # an item merged by an earlier version, then a resumed run
        write_pair_group(f, "4", {"value": np.array([16]), "pid": np.array([0])})
    again = PairResults(path, "sekd-squares", "inputs-1", max_items=2)
    missing = again.missing(["1", "2", "3", "4", "5"])
    assert missing == [["5"]]
    second = again.compute(Stage(name="squares", worker=Squares, args=(0,), batches=missing, output=path,
                                 write_group=write_pair_group, joinable=True), LocalExecutor(1), progress=False)
    assert {k: int(v["value"][0]) for k, v in second.items()} == {"1": 1, "2": 4, "3": 9, "4": 16, "5": 25}
    again.remove()
    assert not path.exists() and not partstore.PartStore(path).root.exists()
