"""The mapper's child process: ``python -m sekd_sfm.sfm.mapper_worker`` (started by ``mapping.run_mapper``).

Why a child process: pycolmap's mappers run in C++ with the GIL released; the incremental
mapper looks for Ctrl-C only between its steps (a bundle adjustment runs to its end: up to
3 s on ten photos, far longer on large scenes), the global and hierarchical mappers never
(they run to the end). A child can be killed at once, and its death frees every thread and
every byte the mapper held.

Protocol: the parent writes one pickled request (a dict, see ``main``) to stdin and closes
it. The child writes one line per progress event to stdout (``pair``: an initial pair was
found; ``image``: an image was registered), writes each reconstruction found to
``<output>/<k>`` (largest first, COLMAP binary) and exits 0; on an exception it prints the
traceback to stderr and exits 1. Only pycolmap and the standard library are imported here,
so the child starts in well under a second (no torch).
"""
from __future__ import annotations

import ctypes
import os
import pickle
import signal
import sys
from pathlib import Path

_PR_SET_PDEATHSIG = 1  # prctl(2)


def _die_with_parent(parent_pid: int) -> None:
    """Ask Linux to SIGKILL this process when the parent dies (even by kill -9); no-op elsewhere."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)


def _log_to(prefix: str | None, pycolmap) -> None:
    """COLMAP's log (glog) into files named ``<prefix><date>-<time>.<pid>``, nothing on the console."""
    log = pycolmap.logging
    log.alsologtostderr, log.logtostderr, log.stderrthreshold, log.minloglevel = False, False, 3, 0
    for level in (log.WARNING, log.ERROR):
        log.set_log_destination(level, "")
    log.set_log_destination(log.INFO, prefix or "")


def _event(text: str) -> None:
    os.write(1, (text + "\n").encode())  # unbuffered: the parent's progress bar moves at once


def bundle_adjust_merged(reconstruction, num_threads: int, pycolmap) -> None:
    """One global bundle adjustment of a model the hierarchical mapper merged from clusters.

    COLMAP merges its clusters by similarity transforms and stops there, so each cluster
    keeps its own drift and the seams stay where the merge put them: on the generated
    250-photo block (clusters of 125 photos) pose AUC@5 0.939 as merged, 0.981 after this
    adjustment (the incremental mapper: 0.980).
    """
    if reconstruction.num_reg_images() < 2:
        return
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.ceres.solver_options.num_threads = num_threads
    # Above 1,000 images Ceres would switch to its iterative Schur solver, which took more than 13 minutes on
    # the merged 2,000-photo block; the sparse direct one stays cheap while the camera graph is sparse, as
    # retrieval pairs make it (each photo shares points with a few dozen others).
    options.ceres.max_num_images_direct_sparse_cpu_solver = max(1000, reconstruction.num_reg_images())
    pycolmap.bundle_adjustment(reconstruction, options)


def run(request: dict) -> list:
    """Run the requested mapper; the reconstructions found, largest first."""
    import pycolmap

    _log_to(request.get("log_prefix"), pycolmap)
    options, kind = request["options"], request["mapper_type"]
    pycolmap.set_random_seed(max(0, int(request.get("seed", 0))))
    args = (str(request["database"]), str(request["image_dir"]), str(request["scratch"]), options)
    if kind == "incremental":
        found = pycolmap.incremental_mapping(*args, input_path=request.get("input_path") or "",
                                             initial_image_pair_callback=lambda: _event("pair"),
                                             next_image_callback=lambda: _event("image"))
    elif kind == "global":
        found = pycolmap.global_mapping(*args)
    elif kind == "hierarchical":
        found = pycolmap.hierarchical_mapping(*args)
        for reconstruction in found.values():
            bundle_adjust_merged(reconstruction, options.incremental_options.num_threads, pycolmap)
    else:
        raise ValueError(f"unknown mapper type {kind!r}")
    if request.get("log_prefix"):
        pycolmap.logging.set_log_destination(pycolmap.logging.INFO, "")  # flush and close the log
    return sorted(found.values(), key=lambda r: (-r.num_reg_images(), -r.num_points3D()))


def main() -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides: on Ctrl-C it kills this process
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})  # inherited blocked from the parent's start
    request = pickle.load(sys.stdin.buffer)
    _die_with_parent(int(request["parent_pid"]))
    models = run(request)
    result = Path(request["result"])
    for k, reconstruction in enumerate(models):
        (result / str(k)).mkdir(parents=True, exist_ok=True)
        reconstruction.write_binary(str(result / str(k)))
    _event(f"done {len(models)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
