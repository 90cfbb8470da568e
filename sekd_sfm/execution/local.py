"""Run a stage on this machine: its worker over the batches, results into the part store, one progress bar.

A stage whose worker is single-threaded (``Stage.local_processes``: keypoint refinement's NumPy, geometric
verification's RANSAC) is spread over worker processes, one per core; the others (extraction and matching,
whose torch already uses every core) run in this process.
"""
from __future__ import annotations

import multiprocessing
import signal
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait

from tqdm import tqdm

from ..errors import Interrupted
from ..files import partstore
from .stage import OnError, Result, Stage, Worker, calls

#: Tasks queued per process beyond the one it runs: enough to keep it busy, few enough that Ctrl-C or a failure
#: waits for little.
QUEUED_PER_PROCESS = 2


def run_local(stage: Stage, parts: partstore.PartStore, on_error: OnError, *, progress: bool = True,
              processes: int = 1) -> int:
    """Compute ``stage.batches`` with the stage's worker here; each finished item goes to ``parts``.

    ``processes``: worker processes for a stage that asks for them (``Stage.local_processes``); 1 computes in
    this process. Returns the processes used. Ctrl-C writes what is finished into the output and raises
    ``Interrupted`` (the same command resumes); any other failure leaves the finished items in ``parts`` for
    the next run.
    """
    used = processes_for(stage, processes)
    bar = tqdm(total=len(stage.keys), unit=stage.unit, desc=stage.name, disable=not progress, dynamic_ncols=True)
    finished = 0
    try:
        for key, arrays, error in (_in_processes(stage, used) if used > 1 else _here(stage)):
            if arrays is None:
                on_error(key, error)
            else:
                parts.save(key, arrays)
                finished += 1
            bar.update(1)
    except KeyboardInterrupt:
        bar.close()
        saved = save_interrupted(stage, parts, finished)
        raise Interrupted(f"interrupted: {saved} more {stage.items} saved in {stage.output}; "
                          "run the same command again to resume") from None
    except BaseException:
        partstore.keep_parts(parts)  # finished items stay for the next run
        raise
    finally:
        bar.close()
    return used


def save_interrupted(stage: Stage, parts: partstore.PartStore, finished: int) -> int:
    """What an interrupted run keeps: its finished items merged into the output, or left in the part store for a
    stage that keeps its parts there (``finished``: how many this run finished); returns the items saved."""
    if stage.keep_parts:
        partstore.keep_parts(parts)
        return finished
    return partstore.finish_run(stage.output, parts, write_group=stage.write_group, what=stage.items)


def processes_for(stage: Stage, processes: int) -> int:
    """The worker processes a local run of ``stage`` uses: up to ``processes`` for a stage that asks for them and
    has more than one task's worth of keys, else 1 (this process)."""
    if not stage.local_processes or processes <= 1:
        return 1
    tasks = -(-len(stage.keys) // max(1, stage.per_task))
    return max(1, min(processes, tasks))


def _here(stage: Stage) -> Iterator[Result]:
    worker = stage.build()
    for keys in calls(stage.joinable, stage.batches):
        yield from worker(keys)


_WORKER: Worker | None = None


def _start_process(worker: type, args: tuple) -> None:
    """A worker process's start: Ctrl-C is the parent's to handle (it stops the pool), then the worker is built."""
    global _WORKER
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _WORKER = worker(*args)


def _call(keys: list[str]) -> list[Result]:
    return list(_WORKER(keys))


def _in_processes(stage: Stage, processes: int) -> Iterator[Result]:
    """The stage's results computed by ``processes`` worker processes, ``stage.per_task`` batches per task, as
    tasks finish.

    Forked where the system can (Linux): a spawned process would run the caller's script again from the top,
    which a script without ``if __name__ == "__main__":`` cannot take, and would pay ~0.3 s of imports. The
    workers that ask for processes use NumPy, SciPy, OpenCV, h5py and pycolmap, which work in a forked child,
    never torch (whose OpenMP threads, started by extraction in the parent, would not exist in it)."""
    tasks = [[key for batch in stage.batches[i:i + stage.per_task] for key in batch]
             for i in range(0, len(stage.batches), stage.per_task)]
    method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
    pool = ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context(method),
                               initializer=_start_process, initargs=(stage.worker, stage.args))
    running: set[Future] = set()
    try:
        for keys in tasks:
            running.add(pool.submit(_call, keys))
            while len(running) >= processes * (1 + QUEUED_PER_PROCESS):
                yield from _finished(running)
        while running:
            yield from _finished(running)
    except BaseException:
        _stop_workers(pool)  # a task may run for minutes (a cluster's mapping): its work is lost either way
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Kill ``pool``'s worker processes at once (Ctrl-C, or a failed task: the others' running work is redone by
    the next run)."""
    if hasattr(pool, "kill_workers"):  # Python 3.14
        pool.kill_workers()
        return
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        process.kill()


def _finished(running: set[Future]) -> Iterator[Result]:
    """Wait for at least one task of ``running`` and yield its results (a worker's exception is raised here)."""
    done, _ = wait(running, return_when=FIRST_COMPLETED)
    for future in done:
        running.discard(future)
        yield from future.result()
