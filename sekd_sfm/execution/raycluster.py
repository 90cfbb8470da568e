"""Extraction and matching on a Ray cluster, writing exactly the files one machine writes.

``extract_features(..., executor="ray")`` and ``match_features(..., executor="ray")`` call
:func:`extract_on_ray` / :func:`match_on_ray` once the output file is prepared and locked and
the work still to do is known. Ray (the optional extra ``sekd-sfm[ray]``) is imported only then.

Division of labour:

* the **driver** (the ``sekd`` process) only plans and merges: it lists what is not done
  yet, hands it in tasks to a pool of actors (``_stream``: a few tasks queued at each actor,
  the next given to whichever finishes) and receives, per task, only the
  keys done (with the chunk file holding them) and the failures: a few hundred bytes, not
  the arrays. At the end it checks that every chunk reported is visible to it and merges
  them into the HDF5 file (``featurefile.merge_parts``, as a local run does);
* each **worker** is a stateful actor (``_ExtractWorker`` / ``_MatchWorker``) that loads
  the model, or opens the feature file, once and then processes batch after batch. It
  reads images and features by absolute path and writes each task's results as one chunk
  of the output's part store (``<output>.parts/``, ``featurefile.PartStore``: temporary
  name + rename, the chunk name carrying the Ray node id and the PID) *before* the task
  returns, so every node must see the same files (shared storage). A key reported to the
  driver is on disk. A worker process killed mid-run (``kill -9``, a node leaving) is
  restarted by Ray (``max_restarts=-1``) and only its unfinished tasks are redone, by
  whichever worker is free (``_pool_results``); a torn temporary never counts as a chunk.
  A killed driver's rerun finds the chunks and redoes nothing finished.
  With ``RayOptions.merge="virtual"`` a task's images go to one shard file instead
  (``shards``), which the driver's merge references rather than copies.

Identical results: workers run the same functions as the local loop (``extract._load`` /
``extract._features_of``; the same pair batches through ``match.match_batch``), with the
driver's resolved configuration (``precision="auto"`` is resolved once, on the driver), and
each worker checks that its own feature configuration (model checksum included) equals the
driver's before it computes anything. Arrays are written by ``PartStore`` as on one machine
(uncompressed ``.npz``), so they arrive bit for bit. torch rounds differently with the number
of threads (a few keypoints move in ~2% of photos), so the reference is a local run with
``num_threads`` equal to ``threads_per_worker``.
"""
from __future__ import annotations

import json
import logging
import math
import os
import pickle
import socket
import sys
import tempfile
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..files import features as ff
from ..files import shards
from ..errors import Interrupted, SekdError
from ..files.atomic import write_atomic

logger = logging.getLogger("sekd")

EXECUTORS = ("local", "ray")
RAY_INSTALL = 'pip install "sekd-sfm[ray]"'


@dataclass
class RayOptions:
    """Where and how wide to run on Ray.

    ``address``: ``auto`` = ``$RAY_ADDRESS``, else the cluster started with ``ray start`` on
    this machine, else a new local one sized to the machine; or ``HOST:PORT`` / ``ray://...``.
    ``threads_per_worker``: CPU threads (and Ray CPUs) per actor. ``gpus_per_worker``: GPUs
    per actor (0 = CPU actors; 0.5 puts two actors on a GPU). ``workers``: actors (None = as
    many as the cluster's CPUs or GPUs hold). ``images_per_task``: images per extraction
    task, the unit of retry after a worker dies and of the driver's cost (a few ms of its
    CPU per task); None = ``task_size(4, workers)``. Matching tasks are ``task_size(1,
    workers)`` of the local run's pair batches. ``driver_helps``: whether the driver extracts
    images itself while the workers start (``_DriverHelper``); None = only when its machine has
    cores no Ray node on it was given (``_driver_should_help``). ``merge_while_running``: whether
    the driver copies each task's results into the output as they arrive (``merge="copy"``);
    None = on the same condition (``driver_merges_while_running``).
    """

    address: str = "auto"
    threads_per_worker: int = 1
    gpus_per_worker: float = 0.0
    workers: int | None = None
    images_per_task: int | None = None
    merge: str = "copy"
    driver_helps: bool | None = None
    merge_while_running: bool | None = None


#: How extracted features reach ``features.h5``: ``copy`` = the arrays are copied in (one
#: self-contained file; the driver's copy runs at disk speed, ~300-440 images/s here);
#: ``virtual`` = workers write shard files under ``features.h5.shards/`` and the file
#: references them (``shards``; thousands of images/s, the folder must stay beside the file).
MERGES = ("copy", "virtual")


#: Workers up to which tasks keep their base size; beyond, tasks grow with the cluster.
TASK_GROWTH = 32


def task_size(base: int, workers: int) -> int:
    """Items per task: ``base`` up to ``TASK_GROWTH`` workers, then proportionally more.

    The driver spends a roughly fixed CPU time per task (~0.6-0.8 ms, docs/cluster.md), so the
    tasks it receives per second, not the items, must stay bounded: growing the task with the
    cluster keeps them at what 32 workers send (~40-70/s for CPU extraction at 640 px), while a
    worker's death still costs only one task.
    """
    return max(base, math.ceil(base * workers / TASK_GROWTH))


def check_executor(executor: str, options: RayOptions | None = None) -> None:
    """SekdError for an unknown executor; for ``ray``, when Ray is not installed or no cluster answers at the address.

    Called before anything is written, so a wrong setting leaves no file behind.
    """
    if executor not in EXECUTORS:
        raise SekdError(f"unknown executor {executor!r}; choose from {', '.join(EXECUTORS)}")
    if options is not None and options.merge not in MERGES:
        raise SekdError(f"unknown Ray merge {options.merge!r}; choose from {', '.join(MERGES)}")
    if executor == "ray":
        _import_ray()
        address = (options or RayOptions()).address
        if address != "auto":
            _check_reachable(address)
        elif address_variable():
            _check_reachable(address_variable(), what="$RAY_ADDRESS")


def address_variable() -> str | None:
    """``$RAY_ADDRESS`` when it names a cluster (what ``--ray-address auto`` uses first), else None."""
    value = os.environ.get("RAY_ADDRESS", "")
    return value if value not in ("", "auto") else None


def _import_ray():
    # Ray's C++ core prints operator notes to the driver's stderr (IP detection, actor
    # arguments in the object store) that read like failures between the progress lines; the
    # cluster's log files keep them. RAY_BACKEND_LOG_LEVEL=warning shows them here again.
    os.environ.setdefault("RAY_BACKEND_LOG_LEVEL", "fatal")
    try:
        import ray
    except ImportError:
        raise SekdError(f"--executor ray needs Ray, which is not installed: {RAY_INSTALL}") from None
    return ray


def _connect(options: RayOptions):
    """``(ray, owned)``: Ray connected to the cluster; ``owned`` when this call connected it (so it disconnects).

    ``auto``: ``$RAY_ADDRESS``; else a cluster running on this machine, whatever ``--temp-dir``
    ``ray start`` was given (``ray.init()`` alone finds only one under ``/tmp/ray`` and would
    quietly start a second, one-node cluster beside it); else a new local cluster sized to the
    machine, for this run only. An address given explicitly wins over ``$RAY_ADDRESS`` (which
    ``ray.init`` would otherwise prefer).
    """
    ray = _import_ray()
    if ray.is_initialized():
        return ray, False
    start = time.monotonic()
    notes: list[str] = []
    # (check_executor, run before this by every caller, refused an unreachable $RAY_ADDRESS)
    address = (address_variable() or "auto") if options.address == "auto" else options.address
    # Worker output stays in the cluster's logs: errors come back as results, and the
    # driver's terminal keeps one progress bar.
    init = {"log_to_driver": False, "logging_level": logging.WARNING}
    _cluster_messages_to_log(ray)
    with _stderr_to_log():
        if address == "auto":
            address = _running_cluster_address(notes)
        before = os.environ.pop("RAY_ADDRESS", None)  # ray.init would prefer it to its argument
        try:
            if address is None:
                _start_local_cluster(ray, init)
            else:
                ray.init(address=address, **init)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            if address is None:
                raise SekdError(f"no Ray cluster runs here and a local one could not start ({_first_line(exc)}); "
                                "start one with `ray start --head` or pass --ray-address HOST:PORT") from None
            raise SekdError(
                f"cannot connect to the Ray cluster at {address!r} ({_first_line(exc)}); "
                "start one with `ray start --head` or pass --ray-address HOST:PORT of a running one"
            ) from None
        finally:
            if before is not None:
                os.environ["RAY_ADDRESS"] = before
    for note in notes:
        logger.info(note)
    resources = ray.cluster_resources()
    nodes = sum(1 for node in ray.nodes() if node.get("Alive"))
    shape = (f"{nodes} node{'s' * (nodes != 1)}, {resources.get('CPU', 0):g} CPUs"
             + (f", {resources['GPU']:g} GPUs" if resources.get("GPU") else ""))
    if address is None:
        logger.info("Ray: started a local cluster for this run (%s) in %.1f s, none was running here; "
                    "`ray start --head` keeps one running between runs", shape, time.monotonic() - start)
    else:
        logger.info("Ray: connected to the cluster at %s (%s) in %.1f s", address, shape, time.monotonic() - start)
    return ray, True


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _start_local_cluster(ray, init: dict) -> None:
    """Start a one-node cluster for this run, with a token of its own and no dashboard.

    Ray 2.60 turns token authentication on for a cluster ``ray.init()`` starts and, when the
    user has no token, saves a new one to ``~/.ray/auth_token``; every later ``ray start
    --head`` on the machine then requires it, and a node joining with plain ``ray start
    --address`` is refused. So a throwaway cluster gets a random token in the environment
    (inherited by its processes, written nowhere; Ray still turns the mode on itself), unless
    the user chose a mode or has a token. No dashboard: its processes would take seconds of
    the cores the workers start on.
    """
    from ..runtime import usable_cores

    own = not any(os.environ.get(name) for name in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")) \
        and not (Path.home() / ".ray" / "auth_token").exists()
    if own:
        os.environ["RAY_AUTH_TOKEN"] = uuid.uuid4().hex + uuid.uuid4().hex
    ray.init(num_cpus=usable_cores(), include_dashboard=False, **init)


def _running_cluster_address(notes: list[str]) -> str | None:
    """``HOST:PORT`` of a Ray cluster running on this machine that answers from here, or None (``notes`` say why).

    Ray's own candidates, as ``ray status`` finds them: the latest ``ray start`` recorded under
    ``/tmp/ray``, then every GCS process on the machine (a cluster started with another
    ``--temp-dir`` is found only so). Resolved here because ``ray.init(address="auto")``
    connects but then loses its actors when the cluster has another ``--temp-dir`` (Ray 2.60),
    while the same address given explicitly works; and a GCS process seen on this machine may
    not be reachable from here (another network namespace or container sharing the process
    table), where Ray would retry it for minutes.
    """
    try:
        from ray._private.services import (  # no public equivalent
            find_bootstrap_address,
            find_gcs_addresses,
        )
    except ImportError:  # a Ray without them: let ray.init resolve "auto" itself (it fails if none runs)
        return "auto"
    latest = find_bootstrap_address(None)
    candidates = ([latest] if latest else []) + sorted(set(find_gcs_addresses()) - {latest})
    answering = [address for address in candidates if _answers(address)]
    if len(candidates) > len(answering):
        silent = ", ".join(sorted(set(candidates) - set(answering)))
        notes.append(f"Ray: a cluster on this machine does not answer from here ({silent})")
    if len(answering) > 1:
        notes.append(f"Ray: {len(answering)} clusters run here ({', '.join(answering)}), using {answering[0]}; "
                     "--ray-address chooses another")
    return answering[0] if answering else None


def _answers(address: str) -> bool:
    try:
        _check_reachable(address, timeout=2.0)
    except SekdError:
        return False
    return True


@contextmanager
def _stderr_to_log() -> Iterator[None]:
    """Send file descriptor 2 to the log while Ray connects, then restore it.

    Ray's C++ core writes operator notes straight to the process's stderr as it starts (how
    it found its IP address, the log level it read from RAY_BACKEND_LOG_LEVEL, token
    authentication), before and outside Python's logging; between the driver's own lines they
    read like failures. They are kept: logged at debug level (``SEKD_DEBUG=1`` shows them).
    """
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no usable stderr (a closed descriptor, an embedding host): nothing to hide
        saved = None
    if saved is None:
        yield
        return
    with tempfile.TemporaryFile() as notes:
        os.dup2(notes.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            notes.seek(0)
            text = notes.read().decode(errors="replace").strip()
            if text:
                logger.debug("Ray's notes while connecting:\n%s", text)


def _cluster_messages_to_log(ray) -> None:
    """Send the cluster's error messages to the debug log instead of the driver's stdout.

    Ray's driver prints what the cluster reports (a node marked dead, with the tail of its
    raylet's log: dozens of lines) on **stdout**, where sekd writes only the output's path for
    scripts, and between the progress lines. The worker loss itself is reported by sekd in one
    warning line (``_pool_results``); Ray's text stays in the debug log (``SEKD_DEBUG=1``).
    Ray calls ``ray._private.worker.print_to_stdstream`` by name for these messages; a Ray
    without it is left as it is.
    """
    module = getattr(getattr(ray, "_private", None), "worker", None)
    if module is None or not hasattr(module, "print_to_stdstream"):
        return

    def to_log(data: dict, ignore_prefix: bool = False) -> None:
        for line in data.get("lines", []):
            logger.debug("Ray (%s): %s", data.get("pid", "cluster"), line)

    module.print_to_stdstream = to_log


@contextmanager
def session(executor: str, options: RayOptions | None = None) -> Iterator[None]:
    """One Ray connection for several stages (``sekd reconstruct``: extraction, then matching).

    Inside it, ``extract_on_ray`` / ``match_on_ray`` find Ray connected and leave it so; a local
    cluster started for the run (no cluster here) is started and stopped once, not per stage.
    Does nothing for the local executor.
    """
    if executor != "ray":
        yield
        return
    options = options or RayOptions()
    check_executor(executor, options)
    ray, owned = _connect(options)
    try:
        yield
    finally:
        if owned:
            ray.shutdown()


def _check_reachable(address: str, timeout: float = 5.0, what: str = "--ray-address") -> None:
    """SekdError at once when nothing listens at ``HOST:PORT`` (Ray itself would retry for minutes).

    ``what``: where the address came from, for the message.
    """
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise SekdError(f"{what} {address!r}: expected HOST:PORT (e.g. 10.0.0.5:6379), ray://HOST:PORT or auto")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as exc:
        source = "" if what == "--ray-address" else f" (from {what})"
        raise SekdError(f"no Ray cluster answers at {address}{source} ({exc.strerror or exc}); start one there with "
                        "`ray start --head --port PORT`, or check the address (`ray status` on the head node)") from None


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
    """One output batch: ``key``, ``error`` ("" = ok), ``chunk`` (file name holding the ok keys), ``fatal``, ``meta``.

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


class _TaskParts:
    """A worker's writer of one task's results, on disk before the task returns.

    ``merge="copy"``: one chunk of the output's part store; ``"virtual"``: one shard file
    (``shards.write_shard``, feature groups), which the output will reference.
    """

    def __init__(self, output: str, merge: str = "copy"):
        self.output, self.writer, self.merge = Path(output), _writer(), merge

    def write(self, items: list[tuple[str, dict[str, np.ndarray]]]) -> tuple[str, str]:
        """``(file name, "")`` once ``items`` are on disk (``""`` if none), or ``("", problem)`` if it cannot be written.

        For a shard, ``self.meta`` then holds its ``shards.describe`` (else it is empty).
        """
        folder = shards.shard_root(self.output) if self.merge == "virtual" else ff.PartStore(self.output).root
        self.meta: dict[str, dict] = {}
        try:
            if self.merge == "virtual":
                if not items:
                    return "", ""
                path, self.meta = shards.write_shard(self.output, items, ff.write_image_group, self.writer)
                return path.name, ""
            # A new store per task, flushed only here: a failed write leaves nothing buffered behind.
            parts = ff.PartStore(self.output, max_items=len(items) + 1, max_bytes=1 << 62, max_seconds=math.inf,
                                 writer=self.writer)
            for key, arrays in items:
                parts.save(key, arrays)
            chunk = parts.flush()
        except OSError as exc:
            return "", (f"{folder}: the Ray worker on {_node()} cannot write its results there "
                        f"({exc.strerror or exc}); the output's folder must be writable shared storage at the same "
                        "path on every node")
        return (chunk.name if chunk else ""), ""


class _ExtractWorker:
    """A Ray actor: builds the extractor once, then extracts the images of each batch (``key`` column)."""

    def __init__(self, image_dir: str, config, described: dict, threads: int, output: str, merge: str = "copy",
                 claims: str = ""):
        from ..extract import describe_config
        from ..features import build_extractor
        from ..runtime import set_num_threads

        set_num_threads(threads)
        self.image_dir, self.config = Path(image_dir), config
        self.problem = ""
        try:
            self.extractor, info = build_extractor(config)
            mine = describe_config(config, self.extractor, info)
            if mine != described:
                self.problem = (f"the Ray worker on {_node()} would compute other features ({ff.json_attr(mine)}) than "
                                f"the driver ({ff.json_attr(described)}); install the same sekd-sfm and weights on every node")
        except (SekdError, OSError) as exc:
            self.problem = f"the Ray worker on {_node()} cannot build the extractor: {exc}"
        # Images are decoded on a background thread while the network runs (as the local loop does).
        self.pool = ThreadPoolExecutor(max_workers=1)
        self.out = _TaskParts(output, merge)
        self.claims = Path(claims) if claims else None

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        keys = [str(k) for k in batch["key"]]
        if self.problem:
            return _rows(keys, [self.problem] * len(keys), fatal=True)
        theirs = sorted(set(keys) & _read_claims(self.claims))
        if theirs:  # the driver extracted these itself while the workers started
            mine = [key for key in keys if key not in theirs]
            rows = self._extract(mine) if mine else _rows([], [])
            return _concat_rows(rows, _rows(theirs, [""] * len(theirs), BY_DRIVER))
        return self._extract(keys)

    def _extract(self, keys: list[str]) -> dict[str, np.ndarray]:
        from ..extract import _features_of, _load
        from ..files.images import ImageReadError

        color = getattr(self.extractor, "color", False)
        loads = [self.pool.submit(_load, self.image_dir / key, self.config.resize_max, color, self.config.max_pixels)
                 for key in keys]
        done, errors = [], []
        for key, load in zip(keys, loads):
            try:
                done.append((key, _features_of(self.extractor, load.result())))
                errors.append("")
            except ImageReadError as exc:  # unreadable here: reported like any unreadable image
                errors.append(f"{exc} (Ray node {_node()})")
        chunk, problem = self.out.write(done)
        if problem:
            return _rows(keys, [problem] * len(keys), fatal=True)
        return _rows(keys, errors, chunk, meta=self.out.meta)


#: ``chunk`` of a row whose image the driver extracted itself (``_DriverHelper``): counted there.
BY_DRIVER = "@driver"


def _concat_rows(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {name: np.concatenate([a[name], b[name]]) for name in a}


def _read_claims(path: Path | None) -> set[str]:
    """Keys the driver claimed (one per line), or none; a claims file being replaced reads as before or after."""
    if path is None:
        return set()
    try:
        return set(path.read_text(encoding="utf-8").split("\n")) - {""}
    except OSError:
        return set()


class _DriverHelper:
    """The driver extracts images itself, from the end of the list, while the Ray workers start.

    Used only on cores no Ray node was given (``_driver_should_help``).

    A worker needs seconds to start (a process, Ray, torch, the model) while the driver holds
    a built extractor and idles; on a run of a few hundred images that start-up is a large
    part of the time. Before each image the driver adds its key to a claims file (replaced
    atomically, a path on the shared storage named for this run); workers skip claimed keys.
    Each image is on disk (a part chunk) before the progress bar counts it. It stops at the
    first result from the workers. A key the workers took before it was
    claimed is extracted twice with identical numbers (same configuration and thread count);
    the part store keeps one.
    """

    def __init__(self, image_dir: Path, todo: list[str], extractor, config, parts: ff.PartStore, claims: Path,
                 threads: int):
        self.image_dir, self.todo, self.extractor, self.config = image_dir, todo, extractor, config
        self.parts, self.claims, self.threads = parts, claims, threads
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
        from ..extract import _features_of, _load
        from ..files.images import ImageReadError
        from ..runtime import set_num_threads

        set_num_threads(self.threads)  # the workers' thread count: identical numbers
        color = getattr(self.extractor, "color", False)
        try:
            for key in reversed(self.todo[len(self.todo) // 2:]):  # never more than half the run
                if self.stop.is_set():
                    break
                self.claimed.append(key)
                write_atomic(self.claims, "\n".join(self.claimed) + "\n", durable=False)
                try:
                    loaded = _load(self.image_dir / key, self.config.resize_max, color, self.config.max_pixels)
                    self.parts.save(key, _features_of(self.extractor, loaded))
                    self.parts.flush()  # on disk before it counts, as the workers' results
                except ImageReadError as exc:
                    self.errors.append((key, str(exc)))
                self.done += 1
                self.bar.update(1)
        except BaseException as exc:  # noqa: BLE001 - reported by the driver's thread in finish()
            self.failure = exc

    def finish(self, reraise: bool = True) -> None:
        """Stop after the current image and wait; re-raise what went wrong in the helper (with ``reraise``)."""
        self.stop.set()
        if self.thread is not None:
            self.thread.join()
        if reraise and self.failure is not None:
            raise self.failure


class _Collected:
    """A stand-in part store that keeps what ``match._match_and_save`` saves, in order."""

    def __init__(self):
        self.items: list[tuple[str, dict[str, np.ndarray]]] = []

    def save(self, key: str, arrays: dict[str, np.ndarray]) -> None:
        self.items.append((key, arrays))


class _MatchWorker:
    """A Ray actor: opens the feature file once, then matches batches of pairs (``pairs`` column, JSON)."""

    def __init__(self, features: str, binary: bool, described: dict, config, threads: int, output: str):
        from ..runtime import set_num_threads

        set_num_threads(threads)
        self.features, self.binary, self.described, self.config = features, binary, described, config
        self.cache = None
        self.out = _TaskParts(output)

    def _open(self):
        import h5py

        from ..match import DescriptorCache
        from ..runtime import resolve_device

        self.cache = DescriptorCache(h5py.File(self.features, "r"), self.binary,
                                     self.described.get("rootsift", False), resolve_device(self.config.device))

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        from ..files import matches as mf
        from ..match import _match_and_save

        groups = [json.loads(str(text)) for text in batch["pairs"]]
        keys = [mf.pair_key(a, b) for group in groups for a, b in group]
        try:
            if self.cache is None:
                self._open()
        except OSError as exc:  # the node does not see the file: nothing can be matched here
            problem = (f"{self.features}: cannot read the feature file on Ray node {_node()} ({exc}); "
                       "every node must see it at the same path (shared storage)")
            return _rows(keys, [problem] * len(keys), fatal=True)
        collected = _Collected()
        for group in groups:  # the same batches as the local loop: identical padding, identical numbers
            _match_and_save(group, self.cache, self.binary, self.described, self.config, collected)
        if [key for key, _ in collected.items] != keys:  # cannot happen unless match.py changes its keys
            raise RuntimeError("match results out of order")
        chunk, problem = self.out.write(collected.items)
        if problem:
            return _rows(keys, [problem] * len(keys), fatal=True)
        return _rows(keys, [""] * len(keys), chunk)


@contextmanager
def _stream(ray, items: list[dict], worker, args: tuple, base: int, options: RayOptions) -> Iterator[Iterator[dict]]:
    """Start the actors; gives the result batches of ``worker`` over ``items`` as tasks finish (any order).

    Each batch holds the columns of ``_rows``, one row per image or pair. ``base``: items per
    task on a small cluster (see ``task_size``); ``options.images_per_task`` overrides it.
    Leaving the context stops the actors, which frees their CPUs and GPUs for the next stage
    of the same connection (``session``).
    """
    fit = _workers(ray, options)
    per_task = options.images_per_task or task_size(base, fit)
    tasks = [_columns(items[i:i + per_task]) for i in range(0, len(items), per_task)]
    workers = min(fit, len(tasks))  # an actor with nothing to do only costs its start-up
    logger.info("Ray: %d workers x %d threads%s, %d tasks of %d", workers, options.threads_per_worker,
                f" x {options.gpus_per_worker:g} GPU" if options.gpus_per_worker else "", len(tasks), per_task)
    # A killed worker process is restarted (its constructor runs again) whenever the cluster has
    # room; its unfinished calls fail at once (no retries at the same actor) and go to whichever
    # worker is free (_pool_results): a node that leaves for good holds nothing up.
    actor_class = ray.remote(worker).options(num_cpus=options.threads_per_worker,
                                             num_gpus=options.gpus_per_worker or None,
                                             max_restarts=-1, max_task_retries=0)
    actors = [actor_class.remote(*args) for _ in range(workers)]
    try:
        yield _pool_results(ray, actors, tasks, _warn_worker_lost)
    finally:
        for actor in actors:
            ray.kill(actor)


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

    An actor gets its first ``TASKS_IN_FLIGHT`` tasks once it is up (``__ray_ready__``
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
        """Fill ``actor`` up to ``TASKS_IN_FLIGHT`` tasks from the queue."""
        while self.todo and self.load[actor] < TASKS_IN_FLIGHT:
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


def _drain(batches: Iterable[dict], total: int, unit: str, desc: str, output: Path, parts: ff.PartStore,
           on_error: Callable[[str, str], None], write_group, progress: bool, folder: Path | None = None,
           shard_meta: dict[str, dict] | None = None, helper: _DriverHelper | None = None,
           merge: ff.Merge | None = None) -> None:
    """Count the keys the workers report as written, report failures, then check their chunks are visible here.

    ``shard_meta`` collects the workers' shard descriptions (``chunk -> key -> arrays``).
    ``merge``: a merge begun for this run; each reported chunk is written into it at once, so
    the driver copies while the workers compute, instead of all of it after them.

    Logs the driver's load: the bytes it received per result, and the CPU time of the driver
    process (its Ray threads included) per result, i.e. how many results per second it could
    absorb (docs/cluster.md, "Measured scaling").
    """
    bar = tqdm(total=total, unit=unit, desc=desc, disable=not progress, dynamic_ncols=True)
    start, first, received, done = time.monotonic(), None, 0, 0
    chunks: set[str] = set()
    if helper is not None:
        helper.start(bar)
    try:
        for batch in batches:
            if first is None:
                if helper is not None:  # the workers are up: the driver goes back to absorbing results
                    helper.finish()
                first, cpu0 = time.monotonic(), time.process_time()  # from here on the driver only absorbs results
            received += len(pickle.dumps(batch, protocol=pickle.HIGHEST_PROTOCOL))
            for key, error, chunk, fatal, meta in zip(batch["key"], batch["error"], batch["chunk"], batch["fatal"],
                                                      batch["meta"]):
                if error and fatal:
                    raise SekdError(str(error))
                if error:
                    on_error(str(key), str(error))
                elif chunk != BY_DRIVER and meta and shard_meta is not None:  # (BY_DRIVER: the helper counts it)
                    shard_meta.setdefault(str(chunk), {})[str(key)] = json.loads(str(meta))
            reported = {str(chunk) for chunk in batch["chunk"] if chunk and chunk != BY_DRIVER}  # ("": failed rows)
            chunks |= reported
            fresh = int(sum(1 for chunk in batch["chunk"] if chunk != BY_DRIVER))
            done += fresh
            bar.update(fresh)
            if merge is not None:
                merge.add(parts.root / chunk for chunk in reported)
        if helper is not None:
            helper.finish()  # a run so short that no worker result came back
            for key, error in helper.errors:
                on_error(key, error)
        _check_visible(folder or parts.root, chunks)
    except KeyboardInterrupt:
        bar.close()
        if helper is not None:
            helper.finish(reraise=False)  # its saved images go into this merge
        saved = merge.finish() if merge is not None else ff.merge_parts(output, parts, write_group=write_group)
        raise Interrupted(f"interrupted: {saved} more {'images' if unit == 'img' else unit + 's'} saved in {output}; "
                          "run the same command again to resume") from None
    finally:
        bar.close()
        if helper is not None:  # a failure (a worker's fatal error, no cluster) stops the helper before it surfaces
            helper.finish(reraise=False)
    end = time.monotonic()
    if merge is not None:
        logger.info("Ray: %d of the %d %ss were in the output's copy when the workers finished", len(merge.written),
                    done, unit)
    if helper is not None and helper.done:
        logger.info("Ray: the driver extracted %d of the %d images itself while the workers started; the workers "
                    "the other %d", helper.done, total, done)
    if first is not None and done:
        cpu = time.process_time() - cpu0
        rate = f"; then {(done - 1) / (end - first):.2f} {unit}/s" if done > 1 and end > first else ""
        logger.info("Ray: %d %ss in %.1f s (first after %.1f s: worker start-up%s); driver received "
                    "%.0f B per %s, %d chunks; driver CPU %.2f ms per %s (%.1f%% of a core)",
                    done, unit, end - start, first - start, rate, received / done, unit, len(chunks),
                    1000 * cpu / done, unit, 100 * cpu / max(end - first, 1e-3))


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


def _claims_path(output: Path) -> Path:
    """This run's claims file (``_DriverHelper``): beside the output, named for a fresh id and the driver's PID
    (``<output>.claims-ID.PID.tmp``: a killed driver's file is removed by the next run, ``remove_stale_temps``)."""
    output = Path(output)
    return output.with_name(f"{output.name}.claims-{uuid.uuid4().hex[:8]}.{os.getpid()}.tmp")


def _free_cores_here(ray) -> float:
    """Cores of the driver's machine that no live Ray node on it was given (by ``ray start --num-cpus``).

    Ray nodes on the driver's machine are those at the driver's node IP address (several raylets
    on one host share it; inside a network namespace all of them are 127.0.0.1).
    """
    here = ray.util.get_node_ip_address()
    given = sum(node.get("Resources", {}).get("CPU", 0.0) for node in ray.nodes()
                if node.get("Alive") and node.get("NodeManagerAddress") == here)
    from ..runtime import usable_cores

    return usable_cores() - given


def driver_merges_while_running(options: RayOptions | None = None) -> bool:
    """Whether the driver writes the workers' chunks into the output as they arrive (``featurefile.Merge``).

    With ``--ray-merge copy``, and only where the driver's machine has a core that no Ray node
    on it was given (a login node, a head node started with ``--num-cpus 0``): there the copy
    overlaps the workers' work, and the merge left at the end is the last tasks' chunks. Where
    Ray holds every core (a one-machine cluster), copying during the run slowed the workers by
    more than it saved at the end (docs/cluster.md, run M). Call it connected (``session``).
    """
    options = options or RayOptions()
    ray = _import_ray()
    return ray.is_initialized() and _merges_while_running(ray, options)


def _merges_while_running(ray, options: RayOptions) -> bool:
    if options.merge != "copy" or options.merge_while_running is False:
        return False
    return options.merge_while_running is True or _free_cores_here(ray) >= 1


def _driver_should_help(ray, options: RayOptions, extractor) -> bool:
    """Whether the driver extracts images itself while the workers start (``_DriverHelper``).

    Only where it takes no core from a worker: CPU workers, and (by default) at least a
    worker's threads of cores on the driver's machine that Ray was not given. Where Ray holds
    every core of the driver's machine (a one-machine cluster), the driver's extraction slows
    the workers' start-up more than it adds: docs/cluster.md, run L.
    """
    if options.gpus_per_worker or not _on_cpu(extractor) or options.driver_helps is False:
        return False
    return options.driver_helps is True or _free_cores_here(ray) >= options.threads_per_worker


def _on_cpu(extractor) -> bool:
    """Whether ``extractor`` runs on the CPU (the driver's helper must compute exactly what CPU workers do)."""
    device = getattr(getattr(extractor, "model", None), "device", None) or getattr(extractor, "device", "cpu")
    return str(device) == "cpu"


def _driver_config(config, extractor):
    """The configuration workers build: ``auto`` precision and relative paths resolved on the driver."""
    weights = str(Path(config.weights).resolve()) if config.weights else None
    if config.feature == "sekd":
        return replace(config, weights=weights, sekd=replace(config.sekd, precision=extractor.model.precision))
    return replace(config, weights=weights)


def extract_on_ray(image_dir: Path, todo: list[str], config, described: dict, extractor, parts: ff.PartStore,
                   output: Path, *, strict: bool = False, progress: bool = True,
                   options: RayOptions | None = None, merge: ff.Merge | None = None) -> list[str]:
    """Extract the images ``todo`` (keys below ``image_dir``) on Ray into ``parts``; returns the unreadable keys.

    ``described`` is the driver's ``extract.describe_config``; every worker must build the same.
    ``merge``: a merge of the output begun for this run (``--ray-merge copy``), fed as chunks arrive.
    """
    options = options or RayOptions()
    failed: list[str] = []
    if not todo:
        return failed

    def on_error(key: str, error: str) -> None:
        if strict:
            raise SekdError(f"{error} (--strict)")
        failed.append(key)
        tqdm.write(f"warning: {error}; skipped", file=sys.stderr)

    claims = _claims_path(output)
    import torch

    from ..runtime import set_num_threads

    threads = torch.get_num_threads()  # the helper switches to the workers' count; restored below
    ray, owned = _connect(options)
    try:
        helper = None
        if _driver_should_help(ray, options, extractor):
            helper = _DriverHelper(Path(image_dir), todo, extractor, config, parts, claims, options.threads_per_worker)
        args = (str(Path(image_dir).resolve()), _driver_config(config, extractor), described, options.threads_per_worker,
                str(Path(output).resolve()), options.merge, str(claims.resolve()) if helper else "")
        folder = shards.shard_root(output) if options.merge == "virtual" else None
        shard_meta: dict[str, dict] = {}
        try:
            with _stream(ray, [{"key": key} for key in todo], _ExtractWorker, args, 4, options) as results:
                _drain(results, len(todo), "img", f"extract {config.feature} (ray)", output, parts, on_error, None,
                       progress, folder, shard_meta, helper, merge)
        finally:  # also when interrupted: the merge then references these shards without opening them
            if shard_meta:
                shards.write_manifest(output, shard_meta)
    finally:
        claims.unlink(missing_ok=True)
        set_num_threads(threads)
        if owned:
            ray.shutdown()
    order = {key: i for i, key in enumerate(todo)}
    return sorted(failed, key=order.__getitem__)  # the order of a local run, whatever order tasks finished in


def match_on_ray(features: Path, todo: list[tuple[str, str]], sizes: dict[str, int], binary: bool, described: dict,
                 config, parts: ff.PartStore, output: Path, *, progress: bool = True,
                 options: RayOptions | None = None) -> None:
    """Match the pairs ``todo`` on Ray into ``parts``, in the same batches as the local loop (``match.batches``)."""
    from ..files import matches as mf
    from ..match import batches

    options = replace(options or RayOptions(), images_per_task=None)  # a matching task is pair batches, not images
    if not todo:
        return

    def on_error(key: str, error: str) -> None:  # workers report only fatal errors for pairs
        raise SekdError(error)

    ray, owned = _connect(options)
    try:
        items = [{"pairs": json.dumps(group)} for group in batches(todo, sizes, config.max_elements)]
        args = (str(Path(features).resolve()), binary, described, config, options.threads_per_worker,
                str(Path(output).resolve()))
        with _stream(ray, items, _MatchWorker, args, 1, options) as results:
            _drain(results, len(todo), "pair", "match (ray)", output, parts, on_error, mf.write_pair_group, progress)
    finally:
        if owned:
            ray.shutdown()
