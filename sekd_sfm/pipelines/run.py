"""The run object every pipeline receives, and how a pipeline runs its list of steps.

A **Run** is one run of a pipeline over one output folder: the options of how it runs
(``RunOptions``: reuse, threads, progress, executor), the folder's lock, ONE executor opened
for the whole run (local, or a Ray cluster connected at the first stage with work and
disconnected when the run ends), the wall time of each step, and the contexts steps hold open
for the steps after them (COLMAP's log). A **pipeline** is a tuple of ``Step``s; each step is
a function ``step(run, state) -> state`` over the pipeline's state (a dataclass of what the
steps made so far: paths, options, counts)::

    RECONSTRUCT = (Step("extract", extract), Step("pairs", pairs), Step("match", match), ...)

    with Run(out, RunOptions(executor="ray"), lock="reconstruction folder") as run:
        state = run_steps(run, RECONSTRUCT, state)

A new stage is one module (in ``sekd_sfm/stages``) and one ``Step`` in a pipeline's tuple.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from ..execution import Executor, RayOptions, open_executor
from ..files.locking import exclusive_lock
from ..runtime import release_free_memory

State = TypeVar("State")


@dataclass(frozen=True)
class RunOptions:
    """How a run runs, as opposed to what it computes (the pipeline's configuration, which its record keeps)."""

    #: Recompute features and matches instead of reusing the files an earlier run left in the output folder.
    overwrite: bool = False
    #: CPU threads of extraction, matching and mapping, and the worker processes of keypoint refinement and
    #: geometric verification (None: every core the process may use).
    num_threads: int | None = None
    progress: bool = True
    #: Where stages spread over items run: ``local`` (this machine) or ``ray`` (the cluster of ``ray_options``).
    executor: str = "local"
    ray_options: RayOptions | None = None


class Run:
    """One run of a pipeline over ``out``: a context manager that opens the executor (and takes the folder's lock
    when ``lock`` names what the folder is), and closes both, and whatever steps held, when the block ends."""

    def __init__(self, out: str | Path, options: RunOptions | None = None, *, lock: str | None = None):
        self.out = Path(out)
        self.options = options or RunOptions()
        self.seconds: dict[str, float] = {}  # wall time of each timed step, in order
        self.places: dict[str, str] = {}    # where each timed step computed (``stage_table``)
        self.parts: dict[str, dict[str, float]] = {}  # step -> the seconds of its timed parts (``part``)
        self._step: str | None = None       # the timed step running now
        self._lock = lock
        self._stack = ExitStack()
        self._executor: Executor | None = None

    def __enter__(self) -> Run:
        try:
            # The executor first: a wrong executor setting (no cluster answers) fails before the folder is made.
            self._executor = self._stack.enter_context(
                open_executor(self.options.executor, self.options.ray_options, processes=self.options.num_threads))
            if self._lock is not None:
                self.out.mkdir(parents=True, exist_ok=True)
                self._stack.enter_context(exclusive_lock(self.out, what=self._lock))
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self._executor = None
        self._stack.close()

    @property
    def executor(self) -> Executor:
        """The run's executor, open from the start of the run to its end."""
        if self._executor is None:
            raise RuntimeError("Run.executor outside its `with Run(...)` block")
        return self._executor

    @property
    def progress(self) -> bool:
        return self.options.progress

    @property
    def num_threads(self) -> int | None:
        return self.options.num_threads

    def hold(self, context: AbstractContextManager) -> Any:
        """Enter ``context`` until the run ends (a step opens what later steps still use); returns its value."""
        return self._stack.enter_context(context)

    @contextmanager
    def timed(self, name: str) -> Iterator[None]:
        """Record the block's wall time as step ``name`` (s, 3 decimals), and where it computed, also when it fails:
        the places of the executor's stages run inside it (``Executor.places``), else ``driver`` (this process,
        with the threads of the libraries it calls)."""
        start, stages, self._step = time.perf_counter(), len(self.executor.places), name
        try:
            yield
        finally:
            self._step = None
            self.seconds[name] = round(time.perf_counter() - start, 3)
            self.places[name] = ", ".join(dict.fromkeys(self.executor.places[stages:])) or "driver"

    @contextmanager
    def part(self, name: str) -> Iterator[None]:
        """Record the block's wall time as part ``name`` of the timed step running now (s, 3 decimals; a part
        run twice adds up), so that a step's table row says where its time went; outside a timed step, nothing."""
        step, start = self._step, time.perf_counter()
        try:
            yield
        finally:
            if step is not None:
                parts = self.parts.setdefault(step, {})
                parts[name] = round(parts.get(name, 0.0) + time.perf_counter() - start, 3)

    def timings(self) -> dict[str, float]:
        """Each timed step's seconds and their ``total``, as records keep them."""
        return {**self.seconds, "total": round(sum(self.seconds.values()), 3)}

    def stage_table(self) -> list[dict]:
        """Each timed step, in order: ``{"stage", "seconds", "ran_on"}`` (``local``, ``local: 2 processes``,
        ``Ray: 4 workers``, ``driver``), and ``parts`` (part -> seconds, in order) where it timed parts, as records
        keep them."""
        return [{"stage": name, "seconds": seconds, "ran_on": self.places.get(name, "driver"),
                 **({"parts": dict(self.parts[name])} if name in self.parts else {})}
                for name, seconds in self.seconds.items()]


@dataclass(frozen=True)
class Step:
    """One step of a pipeline: ``run(run, state) -> state``, timed under ``name`` unless ``timed`` is False (checks
    and bookkeeping that records do not list as stages); skipped, and not timed, where ``when(state)`` is False."""

    name: str
    run: Callable[[Run, Any], Any]
    timed: bool = True
    when: Callable[[Any], bool] | None = None


def run_steps(run: Run, steps: Sequence[Step], state: State) -> State:
    """Run ``steps`` in order over ``state``; returns the last step's state. After each timed step (a stage) the
    heap's free pages go back to the OS (``runtime.release_free_memory``)."""
    for step in steps:
        if step.when is not None and not step.when(state):
            continue
        if step.timed:
            with run.timed(step.name):
                state = step.run(run, state)
            release_free_memory()
        else:
            state = step.run(run, state)
    return state
