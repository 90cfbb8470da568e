"""Run a stage on a Ray cluster, writing exactly the files one machine writes.

Division of labour:

* the **driver** (the ``sekd`` process) only plans and merges: it cuts the stage's batches into
  tasks, hands them to a pool of actors (``ray_pool``: a few tasks queued at each actor, the
  next given to whichever finishes) and receives, per task, only the keys done (with the
  chunk file holding them) and the failures: a few hundred bytes, not the arrays. At the end
  it checks that every chunk reported is visible to it and merges them into the HDF5 file
  (``partstore.merge_parts``, as a local run does);
* each **actor** (``_RunActor``, started once per run and kept for every stage) builds the
  stage's worker (``_StageActor``) once, with the run's thread count, and then computes task
  after task: the same worker class, called on the same batches, as a local run. It writes
  each task's results as one chunk of the output's part
  store (``<output>.parts/``: temporary name + rename, the chunk name carrying the Ray node
  id and the PID) *before* the task returns, so every node must see the same files (shared
  storage). A key reported to the driver is on disk. A worker process killed mid-run
  (``kill -9``, a node leaving) is restarted by Ray and only its unfinished tasks are redone,
  by whichever worker is free; a torn temporary never counts as a chunk. A killed driver's
  rerun finds the chunks and redoes nothing finished. With ``RayOptions.merge="virtual"`` a
  task's items go to one shard file instead (``files.shards``), which the driver's merge
  references rather than copies.

Identical results: the workers get the driver's resolved configuration (the stage's worker
arguments) and check it themselves before they compute anything. Arrays are written by the
part store as on one machine (uncompressed ``.npz``), so they arrive bit for bit. torch rounds
differently with the number of threads, so the reference is a local run with ``num_threads``
equal to ``threads_per_worker``.
"""
from __future__ import annotations

import json
import logging
import math
import os
import pickle
import socket
import threading
import time
import uuid
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import Interrupted, SekdError
from ..files import partstore, shards
from ..files.atomic import write_atomic
from ..runtime import set_num_threads
from .local import save_interrupted
from .ray_connect import RayOptions, _free_cores_here
from .ray_pool import RunActors, _columns, _stream, _workers, task_size
from .stage import OnError, Result, Stage, Worker, calls

logger = logging.getLogger("sekd")

#: ``chunk`` of a row whose item the driver computed itself (``_DriverHelper``): counted there.
BY_DRIVER = "@driver"


def run_on_ray(ray, stage: Stage, parts: partstore.PartStore, on_error: OnError, *, options: RayOptions,
               progress: bool = True, merge: partstore.Merge | None = None, actors: RunActors | None = None) -> int:
    """Compute ``stage.batches`` on the connected cluster into ``parts`` (or shards); ``on_error`` for failed items.
    Returns the workers it used.

    ``merge``: a merge of the output begun for this run, fed with each task's chunk as it arrives. ``actors``: the
    run's actors (``RayExecutor``), kept after this stage; None: actors of this stage's own, stopped after it.
    """
    if actors is None:
        actors = RunActors(ray, _RunActor, options)
        try:
            return run_on_ray(ray, stage, parts, on_error, options=options, progress=progress, merge=merge,
                              actors=actors)
        finally:
            actors.stop()
    keys = stage.keys
    if not keys:
        return 0
    claims = _claims_path(stage.output)
    threads = _torch_threads()  # the helper switches to the workers' count; restored below
    virtual = options.merge == "virtual" and stage.shardable
    try:
        helper = None
        if stage.driver_may_help and _driver_should_help(ray, options):
            helper = _DriverHelper(stage, keys, parts, claims, options.threads_per_worker)
        fit = _workers(ray, options)
        tasks, per_task = _tasks(stage, fit, options)
        workers = min(fit, len(tasks))  # an actor with nothing to do only costs its start-up
        logger.info("Ray: %d workers x %d threads%s, %d tasks of %d", workers, options.threads_per_worker,
                    f" x {options.gpus_per_worker:g} GPU" if options.gpus_per_worker else "", len(tasks), per_task)
        args = (stage.worker, stage.args, options.threads_per_worker, str(Path(stage.output).resolve()),
                stage.write_group, "virtual" if virtual else "copy", str(claims.resolve()) if helper else "",
                stage.joinable)
        # The stage's arguments go to the object store once; each task names them (a reference in a list, which Ray
        # does not resolve), and an actor fetches them when the stage's first task reaches it.
        handle = (uuid.uuid4().hex, [ray.put(args)])
        tasks = [{**task, "stage": handle} for task in tasks]
        shard_meta: dict[str, dict] = {}
        try:
            with _stream(actors, tasks, workers) as results:
                _drain(results, stage, len(keys), parts, on_error, progress,
                       shards.shard_root(stage.output) if virtual else None, shard_meta, helper, merge)
        finally:  # also when interrupted: the merge then references these shards without opening them
            if shard_meta:
                shards.write_manifest(stage.output, shard_meta)
    finally:
        claims.unlink(missing_ok=True)
        set_num_threads(threads)
    return workers


def _torch_threads() -> int:
    import torch

    return torch.get_num_threads()


def _tasks(stage: Stage, workers: int, options: RayOptions) -> tuple[list[dict[str, np.ndarray]], int]:
    """The stage's batches cut into tasks (columns ``key`` and ``batch``), and the batches per task.

    A task is the unit of retry after a worker dies and of the driver's cost, so tasks grow
    with the cluster (``task_size``); ``options.images_per_task`` fixes it for stages whose
    items are independent (extraction).
    """
    per_task = (options.images_per_task if stage.joinable else None) or task_size(stage.per_task, workers)
    tasks = []
    for first in range(0, len(stage.batches), per_task):
        group = stage.batches[first:first + per_task]
        rows = [{"key": key, "batch": number} for number, batch in enumerate(group, first) for key in batch]
        if rows:
            tasks.append(_columns(rows))
    return tasks, per_task


def _node() -> str:
    return socket.gethostname()


def _writer() -> str:
    """This worker's tag in chunk names: the Ray node id (unique per node, even on one host), else the host name."""
    try:
        import ray
    except ImportError:  # outside Ray (tests call workers directly): the host name will do
        ray = None
    if ray is not None and ray.is_initialized():
        return ray.get_runtime_context().get_node_id()[:16]
    return "".join(c if c.isalnum() else "_" for c in _node())


def _rows(keys: list[str], errors: list[str], chunk: str = "", fatal: bool = False,
          meta: dict[str, dict] | None = None) -> dict[str, np.ndarray]:
    """One task's result: ``key``, ``error`` ("" = ok), ``chunk`` (file name holding the ok keys), ``fatal``, ``meta``.

    No arrays: these go to the part store (or shards) on the shared storage, so each row
    costs the driver a few hundred bytes whatever the result's size. ``meta``: per key, the
    shapes and dtypes of its arrays in a shard (``shards.describe``, JSON), so the driver
    references shards without opening them.
    """
    meta = meta or {}
    return {
        "key": np.array(keys, dtype=object),
        "error": np.array(errors, dtype=object),
        "chunk": np.array([chunk if not error else "" for error in errors], dtype=object),
        "fatal": np.full(len(keys), fatal),
        "meta": np.array([json.dumps(meta[key], separators=(",", ":")) if key in meta else "" for key in keys],
                         dtype=object),
    }


def _concat_rows(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {name: np.concatenate([a[name], b[name]]) for name in a}


class _TaskParts:
    """A worker's writer of one task's results, on disk before the task returns.

    ``merge="copy"``: one chunk of the output's part store; ``"virtual"``: one shard file
    (``shards.write_shard``, items stored by ``write_group``), which the output will reference.
    """

    def __init__(self, output: str, merge: str = "copy", write_group: partstore.WriteGroup | None = None):
        self.output, self.writer, self.merge = Path(output), _writer(), merge
        self.write_group = write_group
        self.meta: dict[str, dict] = {}

    def write(self, items: list[tuple[str, dict[str, np.ndarray]]]) -> tuple[str, str]:
        """``(file name, "")`` once ``items`` are on disk (``""`` if none), or ``("", problem)`` if it cannot be written.

        For a shard, ``self.meta`` then holds its ``shards.describe`` (else it is empty).
        """
        folder = shards.shard_root(self.output) if self.merge == "virtual" else partstore.PartStore(self.output).root
        self.meta = {}
        try:
            if self.merge == "virtual":
                if not items:
                    return "", ""
                path, self.meta = shards.write_shard(self.output, items, self.write_group, self.writer)
                return path.name, ""
            # A new store per task, flushed only here: a failed write leaves nothing buffered behind.
            parts = partstore.PartStore(self.output, max_items=len(items) + 1, max_bytes=1 << 62,
                                        max_seconds=math.inf, writer=self.writer)
            for key, arrays in items:
                parts.save(key, arrays)
            chunk = parts.flush()
        except OSError as exc:
            return "", (f"{folder}: the Ray worker on {_node()} cannot write its results there "
                        f"({exc.strerror or exc}); the output's folder must be writable shared storage at the same "
                        "path on every node")
        return (chunk.name if chunk else ""), ""


class _StageActor:
    """A Ray actor: builds the stage's worker once, then computes the tasks it is given (columns ``key``, ``batch``).

    A worker that cannot be built, or raises ``SekdError``, makes every row of the task fatal:
    the driver stops the run with that line. Keys the driver claimed (``_DriverHelper``) are
    skipped and reported as ``BY_DRIVER``.
    """

    def __init__(self, worker: type, args: tuple, threads: int, output: str, write_group, merge: str = "copy",
                 claims: str = "", joinable: bool = True):
        set_num_threads(threads)
        self.problem, self.worker = "", None
        try:
            self.worker = worker(*args)
        except (SekdError, OSError) as exc:
            self.problem = f"the Ray worker on {_node()}: {exc}"
        self.out = _TaskParts(output, merge, write_group)
        self.claims = Path(claims) if claims else None
        self.joinable = joinable

    def __call__(self, task: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        keys = [str(k) for k in task["key"]]
        if self.problem:
            return _rows(keys, [self.problem] * len(keys), fatal=True)
        theirs = sorted(set(keys) & _read_claims(self.claims))
        batches = _split(keys, task["batch"], set(theirs))
        try:
            done, errors = self._compute(batches)
        except SekdError as exc:
            return _rows(keys, [f"{exc} (Ray node {_node()})"] * len(keys), fatal=True)
        chunk, problem = self.out.write(done)
        if problem:
            return _rows(keys, [problem] * len(keys), fatal=True)
        mine = [key for batch in batches for key in batch]
        rows = _rows(mine, [errors.get(key, "") for key in mine], chunk, meta=self.out.meta)
        return _concat_rows(rows, _rows(theirs, [""] * len(theirs), BY_DRIVER)) if theirs else rows

    def _compute(self, batches: list[list[str]]) -> tuple[list[tuple[str, dict]], dict[str, str]]:
        done, errors = [], {}
        for keys in calls(self.joinable, batches):
            results: list[Result] = list(self.worker(keys))
            if [key for key, _, _ in results] != keys:  # a worker must answer every key, in order
                raise RuntimeError(f"{type(self.worker).__name__} answered other keys than it was given")
            for key, arrays, error in results:
                if arrays is None:
                    errors[key] = f"{error} (Ray node {_node()})"  # unreadable here: reported like any failure
                else:
                    done.append((key, arrays))
        return done, errors


class _RunActor:
    """A Ray actor kept for a whole run (``ray_pool.RunActors``): computes any stage's tasks.

    A task names its stage (``task["stage"]``: an id and a reference to the ``_StageActor`` arguments); the
    first task of a stage builds that stage's ``_StageActor``, replacing the previous stage's, and the stage's
    later tasks reuse it. A restarted actor process builds it again from its next task.
    """

    def __init__(self, threads: int):
        set_num_threads(threads)
        self.stage_id, self.stage = "", None

    def __call__(self, task: dict) -> dict[str, np.ndarray]:
        stage_id, (arguments,) = task["stage"]
        if stage_id != self.stage_id:
            import ray

            self.release()  # the previous stage's worker first: never two models at once
            self.stage = _StageActor(*ray.get(arguments))
            self.stage_id = stage_id
        return self.stage(task)

    def release(self) -> None:
        """Drop the stage's worker (its model, caches, GPU memory)."""
        self.stage_id, self.stage = "", None


def _split(keys: list[str], numbers: Iterable, skip: set[str]) -> list[list[str]]:
    """The task's keys grouped by their batch number (consecutive), without those in ``skip``."""
    batches: list[list[str]] = []
    last = None
    for key, number in zip(keys, numbers):
        if key in skip:
            continue
        if number != last or not batches:
            batches.append([])
            last = number
        batches[-1].append(key)
    return batches


def _read_claims(path: Path | None) -> set[str]:
    """Keys the driver claimed (one per line), or none; a claims file being replaced reads as before or after."""
    if path is None:
        return set()
    try:
        return set(path.read_text(encoding="utf-8").split("\n")) - {""}
    except OSError:
        return set()


def _claims_path(output: Path) -> Path:
    """This run's claims file (``_DriverHelper``): beside the output, named for a fresh id and the driver's PID
    (``<output>.claims-ID.PID.tmp``: a killed driver's file is removed by the next run, ``remove_stale_temps``)."""
    output = Path(output)
    return output.with_name(f"{output.name}.claims-{uuid.uuid4().hex[:8]}.{os.getpid()}.tmp")


def _driver_should_help(ray, options: RayOptions) -> bool:
    """Whether the driver computes items itself while the workers start (``_DriverHelper``).

    Only where it takes no core from a worker: CPU workers, and (by default) at least a
    worker's threads of cores on the driver's machine that Ray was not given. Where Ray holds
    every core of the driver's machine (a one-machine cluster), the driver's work slows the
    workers' start-up more than it adds (docs/benchmarks.md, Ray).
    """
    if options.gpus_per_worker or options.driver_helps is False:
        return False
    return options.driver_helps is True or _free_cores_here(ray) >= options.threads_per_worker


class _DriverHelper:
    """The driver computes items itself, from the end of the list, while the Ray workers start.

    A worker needs seconds to start (a process, Ray, torch, the model) while the driver holds
    a built worker (``Stage.built``) and idles; on a run of a few hundred images that start-up is
    a large part of the time. Before each item the driver adds its key to a claims file
    (replaced atomically, a path on the shared storage named for this run); workers skip claimed
    keys. Each item is on disk (a part chunk) before the progress bar counts it. It stops at the
    first result from the workers. A key the workers took before it was claimed is computed
    twice with identical numbers (same configuration and thread count); the part store keeps one.
    """

    def __init__(self, stage: Stage, keys: list[str], parts: partstore.PartStore, claims: Path, threads: int):
        self.worker: Worker = stage.build()
        self.keys, self.parts, self.claims, self.threads = keys, parts, claims, threads
        self.stop = threading.Event()
        self.claimed: list[str] = []
        self.errors: list[tuple[str, str]] = []
        self.done = 0
        self.thread: threading.Thread | None = None
        self.failure: BaseException | None = None

    def start(self, bar) -> None:
        self.bar = bar
        self.thread = threading.Thread(target=self._run, name="sekd-driver-helper", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        set_num_threads(self.threads)  # the workers' thread count: identical numbers
        try:
            for key in reversed(self.keys[len(self.keys) // 2:]):  # never more than half the run
                if self.stop.is_set():
                    break
                self.claimed.append(key)
                write_atomic(self.claims, "\n".join(self.claimed) + "\n", durable=False)
                for done, arrays, error in self.worker([key]):
                    if arrays is None:
                        self.errors.append((done, error))
                    else:
                        self.parts.save(done, arrays)
                        self.parts.flush()  # on disk before it counts, as the workers' results
                self.done += 1
                self.bar.update(1)
        except BaseException as exc:  # noqa: BLE001 - reported by the driver's thread in finish()
            self.failure = exc

    def finish(self, reraise: bool = True) -> None:
        """Stop after the current item and wait; re-raise what went wrong in the helper (with ``reraise``)."""
        self.stop.set()
        if self.thread is not None:
            self.thread.join()
        if reraise and self.failure is not None:
            raise self.failure


class _Progress:
    """What the driver counts while it drains results: items done, chunks reported, bytes and CPU spent."""

    def __init__(self):
        self.start, self.first, self.cpu0 = time.monotonic(), None, 0.0
        self.received, self.done = 0, 0
        self.chunks: set[str] = set()

    def first_result(self) -> None:
        self.first, self.cpu0 = time.monotonic(), time.process_time()  # from here on the driver only absorbs results

    def log(self, unit: str) -> None:
        """The driver's load: bytes received and CPU time per result (docs/benchmarks.md, Ray)."""
        end = time.monotonic()
        if self.first is None or not self.done:
            return
        cpu = time.process_time() - self.cpu0
        rate = f"; then {(self.done - 1) / (end - self.first):.2f} {unit}/s" if self.done > 1 and end > self.first else ""
        logger.info("Ray: %d %ss in %.1f s (first after %.1f s: worker start-up%s); driver received "
                    "%.0f B per %s, %d chunks; driver CPU %.2f ms per %s (%.1f%% of a core)",
                    self.done, unit, end - self.start, self.first - self.start, rate, self.received / self.done, unit,
                    len(self.chunks), 1000 * cpu / self.done, unit, 100 * cpu / max(end - self.first, 1e-3))


def _drain(results: Iterable[dict], stage: Stage, total: int, parts: partstore.PartStore, on_error: OnError,
           progress: bool, folder: Path | None = None, shard_meta: dict[str, dict] | None = None,
           helper: _DriverHelper | None = None, merge: partstore.Merge | None = None) -> None:
    """Count the keys the workers report as written, report failures, then check their chunks are visible here.

    ``shard_meta`` collects the workers' shard descriptions (``chunk -> key -> arrays``).
    ``merge``: a merge begun for this run; each reported chunk is written into it at once, so
    the driver copies while the workers compute, instead of all of it after them.
    """
    bar = tqdm(total=total, unit=stage.unit, desc=f"{stage.name} (ray)", disable=not progress, dynamic_ncols=True)
    seen = _Progress()
    if helper is not None:
        helper.start(bar)
    try:
        for batch in results:
            if seen.first is None:
                if helper is not None:  # the workers are up: the driver goes back to absorbing results
                    helper.finish()
                seen.first_result()
            seen.received += len(pickle.dumps(batch, protocol=pickle.HIGHEST_PROTOCOL))
            _absorb(batch, on_error, shard_meta)
            reported = {str(chunk) for chunk in batch["chunk"] if chunk and chunk != BY_DRIVER}  # ("": failed rows)
            seen.chunks |= reported
            fresh = int(sum(1 for chunk in batch["chunk"] if chunk != BY_DRIVER))
            seen.done += fresh
            bar.update(fresh)
            if merge is not None:
                merge.add(parts.root / chunk for chunk in reported)
        if helper is not None:
            helper.finish()  # a run so short that no worker result came back
            for key, error in helper.errors:
                on_error(key, error)
        _check_visible(folder or parts.root, seen.chunks)
    except KeyboardInterrupt:
        bar.close()
        if helper is not None:
            helper.finish(reraise=False)  # its saved items go into this merge
        saved = merge.finish() if merge is not None else save_interrupted(stage, parts, seen.done)
        raise Interrupted(f"interrupted: {saved} more {stage.items} saved in {stage.output}; "
                          "run the same command again to resume") from None
    finally:
        bar.close()
        if helper is not None:  # a failure (a worker's fatal error, no cluster) stops the helper before it surfaces
            helper.finish(reraise=False)
    if merge is not None:
        logger.info("Ray: %d of the %d %ss were in the output's copy when the workers finished", len(merge.written),
                    seen.done, stage.unit)
    if helper is not None and helper.done:
        logger.info("Ray: the driver %s %d of the %d %s itself while the workers started; the workers "
                    "the other %d", stage.verb, helper.done, total, stage.items, seen.done)
    seen.log(stage.unit)


def _absorb(batch: dict, on_error: OnError, shard_meta: dict[str, dict] | None) -> None:
    """Report a task's failed rows (a fatal one stops the run) and collect its shard descriptions."""
    for key, error, chunk, fatal, meta in zip(batch["key"], batch["error"], batch["chunk"], batch["fatal"],
                                              batch["meta"]):
        if error and fatal:
            raise SekdError(str(error))
        if error:
            on_error(str(key), str(error))
        elif chunk != BY_DRIVER and meta and shard_meta is not None:  # (BY_DRIVER: the helper counts it)
            shard_meta.setdefault(str(chunk), {})[str(key)] = json.loads(str(meta))


def _check_visible(folder: Path, chunks: set[str], wait: float = 10.0) -> None:
    """SekdError unless every file a worker reported is in the driver's view of ``folder`` (parts or shards).

    A missing one means the output's folder is not the same shared storage on every node:
    the results went to the workers' own disks. A few seconds' grace for the attribute
    caches of network file systems.
    """
    deadline = time.monotonic() + wait
    while True:
        have = set(os.listdir(folder)) if folder.is_dir() else set()
        missing = chunks - have
        if not missing or time.monotonic() > deadline:
            break
        time.sleep(1.0)
    if missing:
        raise SekdError(f"{folder}: {len(missing)} of {len(chunks)} files written by the Ray workers are not "
                        f"visible on the driver (e.g. {min(missing)}); the output's folder must be shared storage "
                        "mounted at the same path on every node")
