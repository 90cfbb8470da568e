"""Where a stage runs: in this process (``local``) or on a Ray cluster (``ray``), writing the same files.

An executor runs a :class:`~sekd_sfm.execution.stage.Stage` (a worker class, its arguments, the
batches of keys) and owns everything around the computation: the part store, progress, Ctrl-C
and resume, the merge into the output file. It knows nothing about features or matches; the
stages (``sekd_sfm.stages.extract``, ``sekd_sfm.stages.match``) know nothing about Ray. Imports run one way:
stages -> execution -> files.

    with open_executor("ray", RayOptions(threads_per_worker=2)) as executor:
        executor.run(stage, parts, on_error, attrs=lambda: {"failed_images": "[]"})

``open_executor`` is the one place an executor's name and options are checked. A pipeline opens
one executor for its whole run (``sekd_sfm.pipelines.run.Run``) and hands it to every stage;
a stage called on its own with a name opens one for itself (``using``).
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Protocol

from ..files import partstore
from ..runtime import usable_cores
from .local import run_local
from .ray_connect import (
    EXECUTORS,
    MERGES,
    RAY_INSTALL,
    RayOptions,
    _connect,
    address_variable,
    check_executor,
    driver_merges_while_running,
)
from .ray_pool import task_size
from .stage import OnError, Result, Stage, Worker

logger = logging.getLogger("sekd")
Attrs = Callable[[], "dict | None"]


class Executor(Protocol):
    """Runs stages; a context manager (a Ray executor holds its connection for every stage run inside it).

    ``name``: ``local`` or ``ray``. ``virtual_merge``: whether results reach the output as shard files it
    references (``--ray-merge virtual``), which cannot replace an item in place. ``places``: where each stage it
    ran computed, in order (``local``, ``local: 2 processes``, ``Ray: 4 workers``), for the runs' stage tables."""

    name: str
    virtual_merge: bool
    places: list[str]

    def __enter__(self) -> Executor: ...

    def __exit__(self, *exc) -> None: ...

    def run(self, stage: Stage, parts: partstore.PartStore, on_error: OnError, *, progress: bool = True,
            attrs: Attrs | None = None) -> int: ...


class LocalExecutor:
    """Runs a stage on this machine: in this process, or over ``processes`` worker processes for a stage that asks
    for them (``Stage.local_processes``)."""

    name = "local"
    virtual_merge = False

    def __init__(self, processes: int | None = None):
        self.processes = processes or usable_cores()
        self.places: list[str] = []

    def __enter__(self) -> LocalExecutor:
        return self

    def __exit__(self, *exc) -> None:
        pass

    def run(self, stage: Stage, parts: partstore.PartStore, on_error: OnError, *, progress: bool = True,
            attrs: Attrs | None = None) -> int:
        """Compute the stage into ``parts``, then merge them into ``stage.output`` with ``attrs()``; returns the
        items merged."""
        used = run_local(stage, parts, on_error, progress=progress, processes=self.processes)
        if stage.keys:
            self.places.append(f"local: {used} processes" if used > 1 else "local")
        return _finish(stage, parts, attrs)


class RayExecutor:
    """Runs stages on a Ray cluster; connects at the first stage with work (not for a run with nothing to do)
    and, if it connected (or started a local cluster), disconnects when the block ends. Its actors
    (``ray_pool.RunActors``) start at the first stage and serve every stage until the block ends."""

    name = "ray"

    def __init__(self, options: RayOptions | None = None):
        self.options = options or RayOptions()
        self.ray, self.owned = None, False
        self.actors = None
        self.places: list[str] = []

    @property
    def virtual_merge(self) -> bool:
        return self.options.merge == "virtual"

    def __enter__(self) -> RayExecutor:
        return self

    def __exit__(self, *exc) -> None:
        if self.actors is not None:
            self.actors.stop()
        if self.owned:
            self.ray.shutdown()
        self.ray, self.owned, self.actors = None, False, None

    def run(self, stage: Stage, parts: partstore.PartStore, on_error: OnError, *, progress: bool = True,
            attrs: Attrs | None = None) -> int:
        """As ``LocalExecutor.run``, the computation on the cluster; the driver may copy results into the output as
        they arrive (``driver_merges_while_running``)."""
        from .ray_pool import RunActors  # Ray's imports only for a run on Ray
        from .ray_run import _RunActor, run_on_ray

        merge = None
        try:
            if stage.batches:
                if self.ray is None:
                    self.ray, self.owned = _connect(self.options)
                    self.actors = RunActors(self.ray, _RunActor, self.options)
                if driver_merges_while_running(self.options) and not stage.keep_parts:
                    merge = partstore.Merge(stage.output, parts, stage.write_group)  # fed as chunks arrive
                    logger.info("Ray: the driver copies the workers' results into the output as they arrive")
                workers = run_on_ray(self.ray, stage, parts, on_error, options=self.options, progress=progress,
                                     merge=merge, actors=self.actors)
                self.places.append(f"Ray: {workers} workers")
            return _finish(stage, parts, attrs, merge)
        finally:
            if merge is not None:
                merge.discard()  # after a failure: the file as it was, the chunks for the next run


def open_executor(name: str, options: RayOptions | None = None,
                  processes: int | None = None) -> LocalExecutor | RayExecutor:
    """The executor called ``name`` (``local`` or ``ray``); checks the name and, for Ray, that a cluster answers.
    ``processes``: a local executor's worker processes at most (None: one per usable core)."""
    check_executor(name, options)
    return RayExecutor(options) if name == "ray" else LocalExecutor(processes)


@contextmanager
def using(executor: str | Executor, options: RayOptions | None = None) -> Iterator[Executor]:
    """The executor to run a stage with: ``executor`` itself when it is one (a pipeline's, left open for its next
    stages), else a new one of that name, opened here and closed when the block ends."""
    if not isinstance(executor, str):
        yield executor
        return
    with open_executor(executor, options) as opened:
        yield opened


def _finish(stage: Stage, parts: partstore.PartStore, attrs: Attrs | None, merge: partstore.Merge | None = None) -> int:
    parts.flush()  # on disk before the merge: a merge that fails or is killed loses nothing
    if stage.keep_parts:
        return 0
    return partstore.finish_run(stage.output, parts, attrs() if attrs else None, stage.write_group, stage.items, merge)


__all__ = ["EXECUTORS", "MERGES", "RAY_INSTALL", "Executor", "LocalExecutor", "OnError", "RayExecutor", "RayOptions",
           "Result", "Stage", "Worker", "address_variable", "check_executor", "open_executor", "task_size", "using"]
