"""What an executor runs: a stage's worker class, its arguments, the batches of keys, and where results go.

A stage (extraction, matching, ...) owns a **worker**: a picklable class built once per process
(on this machine, or in each Ray actor) and then called batch after batch. Called with a batch
of keys it yields, in order, one ``(key, arrays or None, error)`` per key: the arrays of a
finished item, or ``None`` and a one-line reason for an item that cannot be computed (an
unreadable photo). A problem that stops every item (the worker cannot be built, the input
cannot be read) is raised as a ``SekdError``.

The executors (``local``, ``ray_run``) run the same worker class over the same batches, save
what it yields into the output's part store, count it, stop and resume, and merge the parts
into the output file: identical files follow from one worker class, not from copies kept alike.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from ..files.partstore import WriteGroup

#: One item's outcome: its key, its arrays (None when it failed), and why it failed ("" when it did not).
Result = tuple[str, "dict[str, np.ndarray] | None", str]
#: What a run does with a failed item: ``on_error(key, reason)``; raising stops the run.
OnError = Callable[[str, str], None]


class Worker(Protocol):
    """Built once per process from ``Stage.args``, then called per batch of keys."""

    def __call__(self, keys: list[str]) -> Iterable[Result]: ...


@dataclass(frozen=True)
class Stage:
    """One stage's work, as an executor needs it.

    ``batches``: the keys still to compute, in the order a local run computes them; one
    worker call per batch (the unit whose results must not depend on what else a task holds,
    e.g. the pairs padded into one matrix). ``joinable``: the keys are independent, so an
    executor may give several batches to one call (one call for a whole local run; Ray tasks
    of ``RayOptions.images_per_task`` keys). ``per_task``: batches per Ray task on a small
    cluster (``ray_pool.task_size`` grows it with the cluster). ``write_group`` stores one item
    in the output HDF5 file (the merge, and shard files). ``built``: a worker this process has
    already built (the driver's), used instead of building another one here. ``unit``, ``items``, ``verb``: how progress and logs name an item,
    the items and their making (``img``, ``images``, ``extracted``). ``driver_may_help``:
    whether the driver may run ``built`` on some keys while Ray workers start (only for workers
    that compute exactly what Ray's CPU workers compute). ``local_processes``: the worker is single-threaded
    Python and NumPy, so a local run spreads its tasks (``per_task`` batches each) over one process per core.
    ``keep_parts``: the finished items stay in the output's part store, not merged into ``output``: for a stage's
    results in progress (``files.pairresults``), which its caller reads from the part store (as safe as the file)
    and removes once its real output is written, so copying them into HDF5 first would be work thrown away.
    """

    name: str
    worker: type
    args: tuple
    batches: list[list[str]]
    output: Path
    write_group: WriteGroup
    unit: str = "item"
    items: str = "items"
    verb: str = "computed"
    joinable: bool = False
    per_task: int = 1
    shardable: bool = False
    built: Worker | None = field(default=None, compare=False, repr=False)
    driver_may_help: bool = False
    local_processes: bool = False
    keep_parts: bool = False

    @property
    def keys(self) -> list[str]:
        """Every key of the stage, in order."""
        return [key for batch in self.batches for key in batch]

    def build(self) -> Worker:
        """The worker of this process: ``built`` if the caller made one, else a new one."""
        return self.built if self.built is not None else self.worker(*self.args)


def calls(joinable: bool, batches: list[list[str]]) -> Iterator[list[str]]:
    """The keys of each worker call over ``batches``: all of them at once when ``joinable`` (``Stage.joinable``),
    else batch by batch."""
    if joinable:
        joined = [key for batch in batches for key in batch]
        if joined:
            yield joined
        return
    yield from batches
