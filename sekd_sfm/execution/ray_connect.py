"""Ray connection: where the cluster is, connecting (or starting a local one).

Ray (the optional extra ``sekd-sfm[ray]``) is imported only when a run asks for it.
"""
from __future__ import annotations

import logging
import os
import socket
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from .. import runtime
from ..errors import SekdError

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
    own = not any(os.environ.get(name) for name in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")) \
        and not (Path.home() / ".ray" / "auth_token").exists()
    if own:
        os.environ["RAY_AUTH_TOKEN"] = uuid.uuid4().hex + uuid.uuid4().hex
    # address="local": a new cluster even where Ray's current-cluster file (``ray_current_cluster`` in its temporary
    # folder) still names one that was killed; plain ray.init() would try to join that one and refuse num_cpus.
    ray.init(address="local", num_cpus=runtime.usable_cores(), include_dashboard=False, **init)


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
        # A killed cluster leaves its address in Ray's current-cluster file: nothing to tell the user, a local
        # cluster starts instead (SEKD_DEBUG=1 shows it).
        logger.debug("Ray: a cluster recorded or running on this machine does not answer from here (%s)", silent)
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


def _free_cores_here(ray) -> float:
    """Cores of the driver's machine that no live Ray node on it was given (by ``ray start --num-cpus``).

    Ray nodes on the driver's machine are those at the driver's node IP address (several raylets
    on one host share it; inside a network namespace all of them are 127.0.0.1).
    """
    here = ray.util.get_node_ip_address()
    given = sum(node.get("Resources", {}).get("CPU", 0.0) for node in ray.nodes()
                if node.get("Alive") and node.get("NodeManagerAddress") == here)
    return runtime.usable_cores() - given


def driver_merges_while_running(options: RayOptions | None = None) -> bool:
    """Whether the driver writes the workers' chunks into the output as they arrive (``files.partstore.Merge``).

    With ``--ray-merge copy``, and only where the driver's machine has a core that no Ray node
    on it was given (a login node, a head node started with ``--num-cpus 0``): there the copy
    overlaps the workers' work, and the merge left at the end is the last tasks' chunks. Where
    Ray holds every core (a one-machine cluster), copying during the run slowed the workers by
    more than it saved at the end (docs/cluster.md, run M). Call it connected (``RayExecutor.run``).
    """
    options = options or RayOptions()
    ray = _import_ray()
    return ray.is_initialized() and _merges_while_running(ray, options)


def _merges_while_running(ray, options: RayOptions) -> bool:
    if options.merge != "copy" or options.merge_while_running is False:
        return False
    return options.merge_while_running is True or _free_cores_here(ray) >= 1


