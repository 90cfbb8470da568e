"""The Ray actor pool: a few tasks queued at each actor, the next to whichever finishes; lost actors' tasks redone.

Knows nothing of what the actors compute: a task is a batch of columns, a result what the actor returns.
"""
from __future__ import annotations

import logging
import math
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
from tqdm import tqdm

from ..errors import SekdError
from .ray_connect import RayOptions, _first_line

logger = logging.getLogger("sekd")

TASK_GROWTH = 32


def task_size(base: int, workers: int) -> int:
    """Items per task: ``base`` up to ``TASK_GROWTH`` workers, then proportionally more.

    The driver spends a roughly fixed CPU time per task (~0.6-0.8 ms, docs/cluster.md), so the
    tasks it receives per second, not the items, must stay bounded: growing the task with the
    cluster keeps them at what 32 workers send (~40-70/s for CPU extraction at 640 px), while a
    worker's death still costs only one task.
    """
    return max(base, math.ceil(base * workers / TASK_GROWTH))


def _workers(ray, options: RayOptions) -> int:
    """Actors to start: as many as the cluster's CPUs (or GPUs) hold at the requested size."""
    resources = ray.cluster_resources()
    cpus, gpus = resources.get("CPU", 0.0), resources.get("GPU", 0.0)
    if options.threads_per_worker > cpus:
        raise SekdError(f"--threads-per-worker {options.threads_per_worker} but the Ray cluster has {cpus:g} CPUs; "
                        "lower it or add nodes")
    if options.gpus_per_worker > gpus:
        raise SekdError(f"--gpus-per-worker {options.gpus_per_worker:g} but the Ray cluster has {gpus:g} GPUs; "
                        "use --gpus-per-worker 0 (CPU workers) or add GPU nodes")
    fit = int(cpus // options.threads_per_worker)
    if options.gpus_per_worker:
        fit = min(fit, int(gpus // options.gpus_per_worker))
    return max(1, min(options.workers or fit, fit))


class RunActors:
    """The Ray actors of one run: started at the first stage with work, kept for every later stage, stopped at the end.

    An actor's process imports torch and sekd and joins the cluster once per run, not once per stage: with an
    actor pool per stage, a two-raylet ``sekd reconstruct`` paid ~4 s of start-up at each of its six spread
    stages (docs/cluster.md). Each actor is a ``host`` (a class built with the thread count, called with a
    task) that builds a stage's worker from the task itself (``ray_run._RunActor``). A killed actor process
    is restarted (its constructor runs again) whenever the cluster has room; its unfinished calls fail at once
    (no retries at the same actor) and go to whichever actor is free (``_pool_results``): a node that leaves
    for good holds nothing up.
    """

    def __init__(self, ray, host: type, options: RayOptions):
        self.ray = ray
        self.host_class = ray.remote(host).options(num_cpus=options.threads_per_worker,
                                                   num_gpus=options.gpus_per_worker or None,
                                                   max_restarts=-1, max_task_retries=0)
        self.threads = options.threads_per_worker
        self.actors: list = []

    def first(self, count: int) -> list:
        """The first ``count`` actors, started now if fewer are running."""
        while len(self.actors) < count:
            self.actors.append(self.host_class.remote(self.threads))
        return self.actors[:count]

    def release(self) -> None:
        """Tell every actor to drop the stage it built (its model, caches, GPU memory); does not wait."""
        for actor in self.actors:
            actor.release.remote()

    def stop(self) -> None:
        """Stop every actor, which frees their CPUs and GPUs."""
        for actor in self.actors:
            self.ray.kill(actor)
        self.actors = []


@contextmanager
def _stream(actors: RunActors, tasks: list[dict], workers: int) -> Iterator[Iterator[dict]]:
    """The results over ``tasks`` (any order) from the run's first ``workers`` actors; each actor drops the stage
    when the block ends (kept for the next stage). A block left by an error or Ctrl-C stops the actors instead:
    the tasks they still hold must not write on while the run fails or the next stage begins."""
    try:
        yield _pool_results(actors.ray, actors.first(workers), tasks, _warn_worker_lost)
    except BaseException:
        actors.stop()
        raise
    actors.release()


def _warn_worker_lost(reason: str) -> None:
    tqdm.write(f"warning: a Ray worker stopped ({reason}); its unfinished tasks go to the other workers", file=sys.stderr)


def _columns(items: list[dict]) -> dict[str, np.ndarray]:
    """One task's batch: the items' fields as columns (``{"key": array of str}``), the workers' input."""
    return {name: np.array([item[name] for item in items], dtype=object) for name in items[0]}


#: Tasks queued at each actor: the next one is already there when a task ends, so no actor
#: waits for the driver between tasks.
TASKS_IN_FLIGHT = 2

#: How long the driver lets results gather before it looks at them again (seconds); far below
#: a task's duration (0.2-2 s for CPU extraction), so no worker runs out of queued tasks.
WAIT_SECONDS = 0.05


#: Seconds between asks whether an actor whose process died is back (Ray restarts it).
REPROBE_SECONDS = 1.0


def _pool_results(ray, actors: list, tasks: list[dict[str, np.ndarray]],
                  on_worker_lost: Callable[[str], None] | None = None) -> Iterator[dict]:
    """Run ``tasks`` on ``actors`` (each called as ``actor.__call__(batch)``), yielding results as they finish.

    An actor gets its first ``TASKS_IN_FLIGHT`` tasks (one, when there are fewer than that per actor) once it is
    up (``__ray_ready__``
    answers: an actor the cluster cannot place holds no task), then each finished task is
    replaced by the next one at the same actor, so faster actors take more tasks. A task whose
    actor died (its process killed, its machine gone) goes back to the front of the queue, in
    order, for the actors that are up, and the dead actor gets tasks again once Ray has
    restarted it (asked every ``REPROBE_SECONDS``); ``on_worker_lost(reason)`` is told each
    time. While no actor is up the run waits (one warning), as Ray waits for resources.

    The driver's only work is this loop (~0.6 ms of its CPU per task; through Ray Data's
    ``map_batches`` it spent 3-6x more CPU per image and the workers started ~1 s later:
    docs/cluster.md, run M).
    """
    return _ActorPool(ray, actors, tasks, on_worker_lost).results()


class _ActorPool:
    """The state of ``_pool_results``: which actor holds which task, which are up, which restart."""

    def __init__(self, ray, actors: list, tasks: list[dict[str, np.ndarray]],
                 on_worker_lost: Callable[[str], None] | None):
        from ray.exceptions import RayActorError

        self.ray, self.on_worker_lost, self.lost = ray, on_worker_lost, RayActorError
        self.todo = deque(tasks)
        # Few tasks (a hierarchical mapping's clusters: minutes each) go one per actor: queued at the first actor
        # up, the second task would wait there for the first while another actor idles.
        self.in_flight = TASKS_IN_FLIGHT if len(tasks) >= TASKS_IN_FLIGHT * len(actors) else 1
        self.running: dict = {}  # result reference -> (actor computing it, its batch)
        self.load: dict = {}  # actor that is up -> tasks it holds
        self.starting = {actor.__ray_ready__.remote(): actor for actor in actors}  # asked whether it is up
        self.ask_again: dict = {}  # actor not up yet -> monotonic time to ask again

    def results(self) -> Iterator[dict]:
        waited = False
        # Ends when every task is done. A lost actor is asked again and again whether Ray has
        # restarted it (max_restarts=-1): while none is up, the run waits, as Ray does for resources.
        while self.todo or self.running:
            self._ask_again()
            waiting = [*self.running, *self.starting]
            if not waiting:
                time.sleep(WAIT_SECONDS)
                continue
            # One pass over the references per WAIT_SECONDS, however many tasks finished meanwhile:
            # a pass costs the driver ~1 ms with 1,024 tasks in flight (512 workers), so its load
            # stays flat as the cluster grows, and every worker still holds a queued task meanwhile.
            ready, _ = self.ray.wait(waiting, num_returns=len(waiting), timeout=WAIT_SECONDS)
            returned = []  # tasks of actors that died, in their order
            for ref in ready:
                if ref in self.starting:
                    self._on_ready(ref)
                    continue
                actor, batch = self.running.pop(ref)
                if actor in self.load:
                    self.load[actor] = max(0, self.load[actor] - 1)
                try:
                    result = self.ray.get(ref)
                except self.lost as exc:
                    returned.append(batch)  # only this task is redone; chunks already written stay
                    self._on_lost(actor, _first_line(exc))
                    continue
                self._give(actor)
                yield result
            if returned:
                self.todo.extendleft(reversed(returned))
                for actor in list(self.load):  # the actors that are up take them at once
                    self._give(actor)
            if self.ask_again and not self.load and not self.running and not waited:  # lost them all
                waited = True
                logger.warning("no Ray worker is up: waiting for the cluster to start or restart them "
                               "(Ctrl-C keeps every finished item)")

    def _give(self, actor) -> None:
        """Fill ``actor`` up to its tasks in flight (``TASKS_IN_FLIGHT``, or 1 for a few tasks) from the queue."""
        while self.todo and self.load[actor] < self.in_flight:
            batch = self.todo.popleft()
            self.running[actor.__call__.remote(batch)] = (actor, batch)
            self.load[actor] += 1

    def _on_ready(self, ref) -> None:
        actor = self.starting.pop(ref)
        try:
            self.ray.get(ref)
        except self.lost:  # not back yet (Ray restarts it when the cluster has room)
            self.ask_again[actor] = time.monotonic() + REPROBE_SECONDS
            return
        self.load[actor] = 0
        self._give(actor)

    def _on_lost(self, actor, reason: str) -> None:
        if actor not in self.load:
            return  # another task of the same loss
        del self.load[actor]
        self.ask_again[actor] = time.monotonic() + REPROBE_SECONDS
        if self.on_worker_lost is not None:
            self.on_worker_lost(reason)

    def _ask_again(self) -> None:
        now = time.monotonic()
        for actor, when in list(self.ask_again.items()):
            if when <= now:
                del self.ask_again[actor]
                self.starting[actor.__ray_ready__.remote()] = actor


