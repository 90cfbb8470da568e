"""Process-level settings for fast CPU inference and training: threads, allocator, device, precision.

Also the facts ``sekd doctor`` reports (library versions, CPU features).
"""
from __future__ import annotations

import ctypes
import importlib.metadata
import os
import platform
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import SekdError

if TYPE_CHECKING:  # torch is imported where it is used: workers that never touch it start without it
    import torch

PRECISIONS = ("auto", "fp32", "bf16", "int8")  # int8: optional extra, sekd_sfm/int8.py
DEVICES = ("auto", "cpu", "cuda")

# glibc mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: glibc's own ceilings (mallopt(3)): its dynamic mmap threshold rises to 32 MiB at most on 64-bit,
#: and the trim threshold follows it at twice that.
_GLIBC_MMAP_THRESHOLD_MAX = 32 << 20
_GLIBC_TRIM_THRESHOLD_MAX = 64 << 20


@lru_cache(maxsize=1)
def tune_allocator() -> bool:
    """Keep freed activation buffers in the heap instead of returning them to the OS.

    By default glibc serves every allocation above 32 MB with a fresh ``mmap``; a
    480x640 forward allocates several such buffers, and the kernel then zeroes every
    page on first touch. Raising the thresholds doubles fp32 throughput on a 2-core
    CPU (``sekd bench speed`` measures it). Returns False where glibc is absent.
    """
    return sys.platform.startswith("linux") and _set_heap_thresholds(1 << 30, (1 << 31) - 1)


def tuning_requested() -> bool:
    """True when ``tune_allocator`` has been called since the last ``untune_allocator`` (glibc or not)."""
    return tune_allocator.cache_info().currsize > 0


def _set_heap_thresholds(mmap_bytes: int, trim_bytes: int, trim_now: bool = False) -> bool:
    """glibc's ``M_MMAP_THRESHOLD`` and ``M_TRIM_THRESHOLD`` (and ``malloc_trim`` with ``trim_now``); False without glibc."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(_M_MMAP_THRESHOLD, mmap_bytes) == 1 and libc.mallopt(_M_TRIM_THRESHOLD, trim_bytes) == 1
        if ok and trim_now:
            release_free_memory()
        return ok
    except (OSError, AttributeError):
        return False


def release_free_memory() -> bool:
    """Give the heap's free pages back to the OS (glibc's ``malloc_trim``); False without glibc.

    Below glibc's 32 MB mmap threshold (where ``untune_allocator`` leaves it after extraction) a stage's
    temporaries come from the heap, which returns memory only from its top: what a stage freed in the middle stays
    in the process's resident set for the rest of the run, and every worker process forked later starts from it
    (refinement of the generated 1,000-photo walk: 751 MB resident after it, 322 MB once trimmed; a whole
    ``sekd reconstruct`` of that walk held ~4.7 GB from refinement through mapping). The pipelines call it after
    each stage.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        return True
    except (OSError, AttributeError):
        return False


def untune_allocator() -> bool:
    """Undo ``tune_allocator`` once the network's work is done, and give the freed heap back to the OS.

    With the network's thresholds every allocation under 1 GB comes from the heap, which is
    never trimmed: what extraction, the retrieval vocabulary or the matching free stays in the
    process, and the matching's distance matrices (up to 128 MB, of shapes that change from
    batch to batch) no longer fit the holes they leave, so the heap grows for as long as the
    matching runs (2,000 generated photos in one ``sekd reconstruct``: 17 GB peak in the
    matching stage, against 2.3 GB for ``sekd match`` alone). Back at glibc's ceilings, large
    arrays are mapped and unmapped again. A later ``tune_allocator`` call tunes anew.
    Returns True when the allocator had been tuned in this process.
    """
    tuned = tuning_requested() and tune_allocator()  # cached: glibc is not called again
    tune_allocator.cache_clear()
    return tuned and _set_heap_thresholds(_GLIBC_MMAP_THRESHOLD_MAX, _GLIBC_TRIM_THRESHOLD_MAX, trim_now=True)


@contextmanager
def allocator_tuned() -> Iterator[bool]:
    """``tune_allocator`` for the block, then glibc's defaults again unless the caller had tuned it before.

    For training on the CPU: at 512 px crops a step allocates many activation and gradient
    buffers above glibc's 32 MB ceiling, each one a fresh ``mmap`` whose pages the kernel zeroes
    on first touch, so a third or more of a training process's CPU time went to page faults in
    the kernel. Yields whether the allocator is tuned inside the block.
    """
    tuned_before = tuning_requested()
    tuned = tune_allocator()
    try:
        yield tuned
    finally:
        if not tuned_before:
            untune_allocator()


def shared_dir() -> Path:
    """The project's data folder (benchmark data, peer weights): the one place that says where it is.

    ``$SEKD_SHARED`` when set; otherwise ``shared/`` beside the source checkout (so a command
    finds it from any working directory), then ``../shared`` from the working directory.
    """
    if "SEKD_SHARED" in os.environ:
        return Path(os.environ["SEKD_SHARED"])
    beside_checkout = Path(__file__).resolve().parents[2] / "shared"
    return beside_checkout if beside_checkout.is_dir() else Path("../shared")


def usable_cores() -> int:
    """CPU cores this process may run on: its affinity mask (a container's or ``taskset``'s share), else all."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def set_num_threads(num_threads: int | None) -> int:
    """Use ``num_threads`` intra-op threads (None or 0: one per available core); SekdError if negative."""
    import torch

    if num_threads is not None and int(num_threads) < 0:
        raise SekdError(f"--num-threads must be a positive number of CPU threads, got {num_threads}")
    if not num_threads:
        num_threads = usable_cores()
    torch.set_num_threads(int(num_threads))
    return torch.get_num_threads()


def exact_sqrt(squared: torch.Tensor) -> torch.Tensor:
    """Correctly rounded square roots of ``squared`` (negatives read as 0), same dtype and device.

    torch's float32 ``sqrt`` on an AVX-512 CPU is 1 ulp off for ~0.5 % of values, and in some processes for
    nearly half of them (measured on matching's distances: 131 or 10,880 of 23,580 in the same batch, from one
    run to the next); at the ratio test's border that flipped matches, so two runs of the same command on two
    threads wrote different matches. NumPy's is IEEE's.
    """
    import numpy as np
    import torch

    roots = np.sqrt(np.maximum(squared.detach().cpu().numpy(), 0))
    return torch.from_numpy(roots).to(squared.device)


def resolve_device(device: str = "auto") -> torch.device:
    """``auto`` picks CUDA when a GPU is present, else the CPU."""
    import torch

    if device not in DEVICES:
        raise SekdError(f"--device must be one of {', '.join(DEVICES)}, got {device!r}")
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        reason = ("this torch build has no CUDA support" if torch.version.cuda is None
                  else "no CUDA GPU is visible (check the driver and CUDA_VISIBLE_DEVICES)")
        raise SekdError(f"--device cuda: {reason}; use --device cpu or --device auto")
    return torch.device(device)


@lru_cache(maxsize=1)
def cpu_flags() -> frozenset[str]:
    """CPU feature flags from /proc/cpuinfo (empty where unavailable)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


#: The CPU features that decide which precision is fast (``sekd doctor``, ``sekd bench speed``).
CPU_FEATURES = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "amx_tile", "amx_bf16", "amx_int8")


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` knows."""
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")),
                        platform.processor() or "unknown")
    except OSError:
        return platform.processor() or "unknown"


def cpu_description() -> dict:
    """The machine type a speed figure belongs to: model name, ``CPU_FEATURES`` present, torch's kernel level."""
    import torch

    flags = cpu_flags()
    return {"model": cpu_model(), "features": {name: name in flags for name in CPU_FEATURES},
            "torch_kernels": torch.backends.cpu.get_cpu_capability(), "cores": os.cpu_count()}


def source_commit() -> str:
    """The git commit of this package's source, with ``+dirty`` for uncommitted changes; "" for an installed copy."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    if not (root / ".git").exists():
        return ""

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10,
                              check=True).stdout.strip()

    try:
        commit = git("rev-parse", "--short=12", "HEAD")
        return commit + ("+dirty" if git("status", "--porcelain", "--untracked-files=no", "--", "sekd_sfm") else "")
    except (OSError, subprocess.SubprocessError):
        return ""


def cpu_text(cpu) -> str:
    """A ``cpu_description()`` (as a record keeps it) in a few words: model, torch's kernels, cores."""
    if not isinstance(cpu, dict):
        return str(cpu)
    return f"{cpu.get('model', '?')}, {cpu.get('torch_kernels', '?')}, {cpu.get('cores', '?')} cores"


def run_record() -> dict:
    """What every benchmark result records, so no table mixes machines or versions silently: the sekd version, the
    source commit, the CPU (model, features, torch's kernels, cores), the command line and the date."""
    import time

    from . import __version__

    return {"sekd_sfm": __version__, "commit": source_commit(), "cpu": cpu_description(),
            "command": " ".join(["sekd" if Path(sys.argv[0]).name == "sekd" else sys.argv[0], *sys.argv[1:]]),
            "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


def timing_context() -> dict:
    """What a benchmark's wall-clock columns (ms per image) depend on: the CPU and torch's intra-op threads."""
    import torch

    return {"cpu": cpu_description(), "threads": torch.get_num_threads()}


def cpu_reports_bf16() -> bool:
    """True when the CPU's flags name a native bf16 unit (AVX512-BF16 or AMX), whether or not it is usable."""
    flags = cpu_flags()
    return "avx512_bf16" in flags or "amx_bf16" in flags


def cpu_has_fast_bf16() -> bool:
    """True when the CPU computes bf16 natively (AVX512-BF16 or AMX) and oneDNN may use it.

    The CPU flags alone are not enough: oneDNN can be held below the CPU (``ONEDNN_MAX_CPU_ISA``,
    set by some containers or to reproduce another machine), and then its bf16 convolutions fall
    back to reference kernels ~70x slower than fp32 (measured: 543 against 14.6 ms per 3x3
    convolution at ONEDNN_MAX_CPU_ISA=AVX2 on an AMX CPU).
    """
    import torch

    if not cpu_reports_bf16():
        return False
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # a torch without the query: trust the flags
        return True


def resolve_precision(precision: str, device: torch.device) -> str:
    """``auto``: bf16 on CPUs with native bf16, fp32 elsewhere (including CUDA, for exactness)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision != "auto":
        return precision
    return "bf16" if device.type == "cpu" and cpu_has_fast_bf16() else "fp32"


def stop_cleanly_on_sigterm() -> None:
    """Make SIGTERM (``kill``, job schedulers) and Ctrl-C raise KeyboardInterrupt once, so stages stop
    cleanly: each saves what is done and says how to resume.

    Further SIGTERM/SIGINT are ignored from the first one on: a second signal (a scheduler that
    repeats its SIGTERM, Ctrl-C pressed twice) arriving while the interrupt is handled would
    otherwise cut the saving short or kill the process during shutdown (exit by signal, not the
    one ``Error:`` line and exit code 1). SIGKILL still ends a stuck process. Calling this again
    (the next command in the same process) re-arms both signals.
    """
    signal.signal(signal.SIGTERM, _raise_interrupt)
    current = signal.getsignal(signal.SIGINT)
    if current is signal.default_int_handler or current is _raise_interrupt or (
            current == signal.SIG_IGN and _STATE["ignoring"]):  # not a handler the embedding program chose
        signal.signal(signal.SIGINT, _raise_interrupt)
    _STATE["ignoring"] = False


_STATE = {"ignoring": False}  # True once an interrupt made us ignore SIGTERM/SIGINT


def _raise_interrupt(signum, frame) -> None:
    for other in (signal.SIGTERM, signal.SIGINT):
        if signal.getsignal(other) is _raise_interrupt:
            signal.signal(other, signal.SIG_IGN)
    _STATE["ignoring"] = True
    raise KeyboardInterrupt


def forget_handled_interrupt() -> None:
    """After a command has handled an interrupt, keep ``python -m`` from exiting by SIGINT anyway.

    CPython (3.8-3.13) marks a KeyboardInterrupt that escapes source text run by ``exec()`` or
    ``PyRun_String`` as "unhandled", even when a caller catches it later; under ``python -m``
    the interpreter then ends the process with SIGINT (exit -2) after our one ``Error:`` line
    and exit code 1. ``dataclasses`` and ``namedtuple`` build their methods with ``exec()``, so
    a Ctrl-C or SIGTERM during the import of a module defining one hits this. Running empty
    source text through the same entry point clears that mark. Only after our handler raised
    an interrupt.
    """
    if not _STATE["ignoring"]:
        return
    try:
        ctypes.pythonapi.PyRun_SimpleString(b"")
    except AttributeError:  # not CPython: no such mark
        pass


def keep_sigterm_handler(import_module):
    """Import through ``import_module()`` without losing our SIGTERM handler.

    pycolmap's glog installs a crash handler for SIGTERM when it is imported, which would
    kill the process without saving.
    """
    previous = signal.getsignal(signal.SIGTERM)
    module = import_module()
    if previous is _raise_interrupt or (previous == signal.SIG_IGN and _STATE["ignoring"]):
        try:
            signal.signal(signal.SIGTERM, previous)
        except ValueError:  # not the main thread: signals cannot be set here
            pass
    return module


def package_versions() -> dict[str, str]:
    """Versions of the libraries that shape the results (recorded in every output file)."""
    import cv2
    import h5py
    import numpy
    import torch

    from . import __version__

    versions = {
        "sekd_sfm": __version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": numpy.__version__,
        "opencv": cv2.__version__,
        "h5py": h5py.__version__,
    }
    for name in ("pycolmap", "kornia"):
        try:  # metadata, not an import: importing pycolmap has side effects (signal handlers)
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions
