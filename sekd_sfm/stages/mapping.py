"""Stage 5: database -> COLMAP model(s), by one of pycolmap's three mappers.

* ``incremental`` (``pycolmap.incremental_mapping``): COLMAP's classic mapper, one image at a time;
* ``global`` (``pycolmap.global_mapping``, GLOMAP): rotation averaging + global positioning,
  then bundle adjustment: all cameras at once;
* ``hierarchical``: the view graph cut into overlapping clusters of at most HIERARCHICAL_LEAF_IMAGES
  photos (``partition``), each mapped incrementally as a task of the run's executor (``hierarchical``:
  worker processes or Ray workers), merged in the child (``cluster_merge``), then one global bundle
  adjustment; photos in camera rigs by ``pycolmap.hierarchical_mapping`` and the same adjustment;
* ``auto`` (the default): incremental up to AUTO_HIERARCHICAL_ABOVE photos, hierarchical above.

The mapper runs in a child process (``mapper_worker``) so that Ctrl-C stops it at once.

Output layout under the output folder::

    model/            the largest model (most registered images), COLMAP binary format
    models/1, ...     the other models, if the images split into several, largest first
"""
from __future__ import annotations

import contextlib
import json
import os
import pickle
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from tqdm import tqdm

from ..errors import Interrupted, SekdError
from .colmap import open_database, require_pycolmap, set_options
from .hierarchical import can_map_clusters, map_clusters

MAIN_MODEL = "model"
MODELS = "models"
#: Folders of older layouts and of killed runs, removed before models are written.
STALE = ("submodels",)
MAPPER_TYPES = ("incremental", "global", "hierarchical")
#: What ``--mapper-type`` accepts: a mapper, or ``auto`` (``resolve_mapper_type``).
MAPPER_CHOICES = ("auto", *MAPPER_TYPES)
#: Photos per cluster of the hierarchical mapper (pycolmap's default is 500). Cost: the
#: clusters are independent, so mapping grows linearly with the photos instead of with a
#: single model's ever longer bundle adjustments. Accuracy: with the final global bundle
#: adjustment, on the generated blocks of `sekd bench scale` (docs/reconstruction.md).
HIERARCHICAL_LEAF_IMAGES = 125
#: ``auto`` maps more photos than this hierarchically (at 250 both mappers are level in time and accuracy).
AUTO_HIERARCHICAL_ABOVE = 250
#: Fewest photos a model keeps (COLMAP's default is 10): a folder that holds several places maps each group of
#: 3+ photos the mapper can build, so a small place (8 photos of one facade among 40) is not dropped silently.
#: The hierarchical mapper's clusters keep COLMAP's 10: a cluster's stray fragments would enter its merge.
MIN_MODEL_SIZE = 3
#: pycolmap's option class of each mapper type.
OPTION_CLASSES = {"incremental": "IncrementalPipelineOptions", "global": "GlobalPipelineOptions",
                  "hierarchical": "HierarchicalPipelineOptions"}
#: The command that starts the mapper's child process (the request goes to its stdin).
WORKER_COMMAND = [sys.executable, "-m", "sekd_sfm.stages.mapper_worker"]
#: Prefix of the mapper's scratch folders in the output folder (removed at the end, or by the next run).
SCRATCH_PREFIX = "mapping-"


def default_options(mapper_type: str = "incremental", seed: int = 0):
    """The pycolmap options object of ``mapper_type``, seeded, on one thread (see ``mapper_options``)."""
    if mapper_type not in MAPPER_TYPES:
        raise SekdError(f"unknown mapper type {mapper_type!r}; choose from {', '.join(MAPPER_TYPES)}")
    pycolmap = require_pycolmap()
    options = getattr(pycolmap, OPTION_CLASSES[mapper_type])()
    options.num_threads = 1
    if mapper_type == "hierarchical":  # no seed of its own: its clusters are mapped incrementally
        options.incremental_options.random_seed = seed
        options.incremental_options.num_threads = 1
        options.num_workers = 1  # one cluster at a time: the same model for a seed (num_workers=-1: faster)
        options.clustering_options.leaf_max_num_images = HIERARCHICAL_LEAF_IMAGES
    else:
        options.random_seed = seed
        options.min_model_size = MIN_MODEL_SIZE
    return options


def mapper_options(assignments: list[str] | None = None, seed: int = 0, mapper_type: str = "incremental"):
    """The options of ``mapper_type`` with validated ``key=value`` overrides, seeded for repeatable runs.

    An option that the chosen mapper does not have is a SekdError naming the closest ones.
    One thread unless ``num_threads=N`` is assigned: COLMAP's mapper repeats its model for a
    seed only on one thread. With all cores, bundle adjustment sums in a varying order and on
    a weak scene that decides what registers (sacre_coeur, same matches: 10/10 images in three
    runs of four, 3/10 in the other; on one thread 10/10 every time). ``--mapper num_threads=-1``
    trades repeatability for speed on large scenes.
    """
    return set_options(default_options(mapper_type, seed), assignments or [], "--mapper")


def resolve_mapper_type(mapper_type: str, num_images: int) -> str:
    """The mapper ``mapper_type`` stands for on ``num_images`` photos: ``auto`` picks by size, others are themselves."""
    if mapper_type == "auto":
        return "hierarchical" if num_images > AUTO_HIERARCHICAL_ABOVE else "incremental"
    if mapper_type not in MAPPER_TYPES:
        raise SekdError(f"unknown mapper type {mapper_type!r}; choose from {', '.join(MAPPER_CHOICES)}")
    return mapper_type


def mapper_type_of(options) -> str:
    """The mapper type whose option class ``options`` is."""
    for kind, cls in OPTION_CLASSES.items():
        if type(options).__name__ == cls:
            return kind
    raise SekdError(f"not a mapper options object: {type(options).__name__}")


def set_principal_point_refinement(options, refine: bool) -> None:
    """Let bundle adjustment refine the cameras' principal points (or keep them fixed) in any mapper's ``options``.

    ``--principal-point auto`` keeps them fixed while mapping and decides afterwards (``principal_point``).
    """
    if mapper_type_of(options) == "global":
        options.mapper.bundle_adjustment.refine_principal_point = refine
    else:  # incremental, or the incremental mapping of each hierarchical cluster
        getattr(options, "incremental_options", options).ba_refine_principal_point = refine


def min_num_matches(options) -> int:
    """The verified inliers a pair needs to link two images in the mapper of ``options``."""
    inner = getattr(options, "incremental_options", options)
    return int(inner.min_num_matches)


def min_model_size(options) -> int:
    """The fewest photos a model keeps in the mapper of ``options`` (hierarchical: its clusters')."""
    inner = getattr(options, "incremental_options", options)
    return int(inner.min_model_size)


def initial_pair_options(options):
    """The incremental mapper's initial-pair settings (``mapper.init_*``), or None for the global mapper."""
    inner = getattr(options, "incremental_options", options)
    return inner.mapper if hasattr(inner.mapper, "init_min_num_inliers") else None


class _MapperProgress:
    """The mapping progress bar.

    The incremental mapper reports events (+2 images at an initial pair, +1 per registered
    image); the others report nothing until they finish, so their bar shows the elapsed time.
    """

    def __init__(self, total: int, mapper_type: str, enabled: bool):
        counted = mapper_type == "incremental"
        self.bar = tqdm(total=total if counted else None, unit="img", desc=f"mapping ({mapper_type})",
                        disable=not enabled, dynamic_ncols=True,
                        bar_format=None if counted else "{desc}: {elapsed} elapsed")
        self.models = 0

    def event(self, line: str) -> None:
        if line == "pair":
            self.models += 1
            self.bar.set_postfix_str(f"model {self.models}")
            self._advance(2)
        elif line == "image":
            self._advance(1)

    def _advance(self, n: int) -> None:
        # Models may share images, so the count can exceed the image total: cap it.
        self.bar.update(max(0, min(n, self.bar.total - self.bar.n)))

    def tick(self) -> None:
        self.bar.refresh()


def clean_scratch(folder: Path) -> None:
    """Remove the scratch folders a killed mapping left in ``folder`` (call it holding the folder's lock)."""
    for stale in Path(folder).glob(SCRATCH_PREFIX + "*"):
        if stale.is_dir():
            shutil.rmtree(stale, ignore_errors=True)


def run_mapper(database: str | Path, image_dir: str | Path, options=None, progress: bool = True,
               log_prefix: str | Path | None = None, input_model: str | Path | None = None,
               final_filter: bool = False, records: list | None = None, executor="local",
               details: dict | None = None, poses_from: list[dict] | None = None,
               merge_passes: int | None = None) -> list:
    """Map ``database`` with the mapper of ``options``; the reconstructions found, largest first (may be empty).

    ``options`` is one of pycolmap's pipeline option objects (``mapper_options``; default:
    incremental). ``image_dir`` is only read for point colours. The random generator is seeded
    from the options, so a run is repeatable. The mapper runs in a child process: Ctrl-C (or
    SIGTERM) kills it within a fraction of a second and raises Interrupted. COLMAP's log of
    the child goes to files ``<log_prefix><date>-<time>.<pid>`` (none without ``log_prefix``).
    ``input_model``: a model to continue from (incremental mapper only; ``sekd reconstruct --extend``),
    its image ids those of ``database``. ``final_filter``: each model's outlying observations dropped and the
    model adjusted again (``mapper_worker.final_filter``); its record per model is appended to ``records``.
    ``executor`` (a name or an open ``execution.Executor``): where the hierarchical mapper's clusters are mapped
    (``stages.hierarchical``); the merge runs in the child. ``details`` gets the hierarchical mapper's record:
    ``clusters`` (``hierarchical.map_clusters``) and ``merge`` (``mapper_worker.merge_clusters``).
    ``poses_from``: no mapping; models already mapped (``hierarchical.model_arrays`` of each, e.g. the capture
    order's chain on fewer pairs) are triangulated again from ``database`` with their poses held and adjusted as
    a whole (incremental or hierarchical options), as the hierarchical mapper's clusters are merged.
    ``merge_passes``: the triangulate-and-adjust passes of that merge (None: ``mapper_worker.MERGE_PASSES``; 0: the
    points triangulated onto the poses as merged, nothing adjusted).
    """
    require_pycolmap()
    options = options if options is not None else mapper_options()
    kind = mapper_type_of(options)
    if poses_from is not None and kind == "global":
        raise SekdError("poses_from needs incremental or hierarchical mapper options (their triangulation)")
    with open_database(database) as db:
        total = db.num_images()
    scratch = Path(tempfile.mkdtemp(prefix=SCRATCH_PREFIX, dir=Path(database).parent))
    request = {"mapper_type": kind, "options": options, "database": str(database), "image_dir": str(image_dir),
               "scratch": str(scratch / "work"), "result": str(scratch / "result"), "parent_pid": os.getpid(),
               "seed": _seed(options), "log_prefix": str(log_prefix) if log_prefix else None,
               "input_path": str(input_model) if input_model else "", "final_filter": final_filter}
    if merge_passes is not None:
        request["merge_passes"] = merge_passes
    details = {} if details is None else details
    if poses_from is not None:
        request["clusters"] = poses_from
    elif kind == "hierarchical" and can_map_clusters(database):
        try:
            details["clusters"] = {}
            request["clusters"] = map_clusters(database, image_dir, options, executor, log_prefix=log_prefix,
                                               progress=progress, record=details["clusters"])
        except BaseException:
            shutil.rmtree(scratch, ignore_errors=True)
            raise
    bar = _MapperProgress(total, kind if poses_from is None else "poses held", progress)
    try:
        _run_child(request, scratch, bar)
        reconstruction = require_pycolmap().Reconstruction
        folder = scratch / "result"
        results = sorted((p for p in folder.iterdir() if p.is_dir()), key=lambda p: int(p.name)) if folder.is_dir() else []
        if (folder / "merge.json").is_file():
            details["merge"] = json.loads((folder / "merge.json").read_text())
        if records is not None:
            records.extend(json.loads(p.with_suffix(".json").read_text()) if p.with_suffix(".json").is_file() else None
                           for p in results)
        return [reconstruction(str(path)) for path in results]
    finally:
        bar.bar.close()
        shutil.rmtree(scratch, ignore_errors=True)  # models are written by write_models, in our layout


def run_child(command: list[str], request: dict, scratch: Path, what: str, progress: bool = True) -> None:
    """Run ``command``, a child of the mapper's protocol (``mapper_worker``), on ``request``; SekdError if it fails.

    The bar shows the elapsed time; Ctrl-C (or SIGTERM) kills the child at once and raises
    Interrupted. ``what`` names the work in the bar and the messages (e.g. "principal point test").
    """
    bar = _MapperProgress(0, what, progress)
    try:
        _run_child({**request, "parent_pid": os.getpid()}, scratch, bar, command, what)
    finally:
        bar.bar.close()


def _seed(options) -> int:
    return int(getattr(options, "incremental_options", options).random_seed)


def _run_child(request: dict, scratch: Path, bar: _MapperProgress, command: list[str] | None = None,
               what: str | None = None) -> None:
    """Start the worker (``command``, default the mapper's), forward its events to ``bar``; kill it on Ctrl-C;
    SekdError if it fails."""
    doing = "mapping" if what is None else f"mapping ({what})"
    command, what = command or WORKER_COMMAND, what or f"the {request['mapper_type']} mapper"
    stderr_path = scratch / "stderr.txt"
    child = None
    try:
        # Ctrl-C / SIGTERM are held back while the child starts and delivered once it is
        # known, so a signal during the start cannot leave a mapper running with no owner.
        with _signals_held(), open(stderr_path, "wb") as stderr:
            child = subprocess.Popen(command, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=stderr, cwd=os.getcwd())
        try:
            child.stdin.write(pickle.dumps(request))
            child.stdin.close()
        except BrokenPipeError:  # the child died at start: its exit code and stderr say why, below
            pass
        _follow(child, bar)
    except KeyboardInterrupt:
        # Ctrl-C, or SIGTERM (raised as KeyboardInterrupt): the mapper's work is worthless
        # without us, so kill it at once rather than wait for it to look for a signal.
        _kill(child)
        kept = f"{request['database']} (features and matches)" if "database" in request else "the database"
        raise Interrupted(f"interrupted while {doing}: {kept} is kept; "
                          "run the same command again to map again") from None
    except BaseException:
        _kill(child)
        raise
    if child.returncode != 0:
        detail = stderr_path.read_text(errors="replace").strip().splitlines()
        how = f"exit code {child.returncode}" if child.returncode > 0 else f"killed by signal {-child.returncode}"
        where = f" on {request['database']}" if "database" in request else ""
        raise SekdError(f"{what} failed{where} ({how}): "
                        f"{detail[-1] if detail else 'no message'}; COLMAP's log has the details (out of memory "
                        "if killed by signal 9)")


def _kill(child: subprocess.Popen | None) -> None:
    if child is not None:
        child.kill()
        child.wait()


@contextlib.contextmanager
def _signals_held():
    """Block SIGINT and SIGTERM in this thread for the block; pending ones are delivered at its end."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _follow(child: subprocess.Popen, bar: _MapperProgress) -> None:
    """Read the child's event lines until it exits, refreshing the bar at least twice a second."""
    stream, pending = child.stdout, b""
    while True:
        ready, _, _ = select.select([stream], [], [], 0.5)
        if ready:
            chunk = os.read(stream.fileno(), 4096)
            if not chunk:
                break
            pending += chunk
            *lines, pending = pending.split(b"\n")
            for line in lines:
                bar.event(line.decode(errors="replace"))
        bar.tick()
    while child.poll() is None:  # stdout closed: the child is exiting
        time.sleep(0.01)


def write_models(reconstructions: list, output_dir: str | Path) -> list[Path]:
    """Write the largest reconstruction to ``output_dir/model`` and the others to ``models/<k>`` (k = 1, 2, ...).

    COLMAP binary format. Models of an earlier run are removed first. Returns the folders written.
    """
    output_dir = Path(output_dir)
    for stale in (output_dir / MAIN_MODEL, output_dir / MODELS, *(output_dir / s for s in STALE)):
        shutil.rmtree(stale, ignore_errors=True)
    paths = [output_dir / MAIN_MODEL] + [output_dir / MODELS / str(k) for k in range(1, len(reconstructions))]
    for reconstruction, path in zip(reconstructions, paths):
        path.mkdir(parents=True, exist_ok=True)
        reconstruction.write_binary(str(path))
    return paths[: len(reconstructions)]


def registered_names(reconstruction) -> list[str]:
    """Names of the images with a pose in ``reconstruction``, sorted."""
    return sorted(reconstruction.image(i).name for i in reconstruction.reg_image_ids())


def model_stats(reconstruction) -> dict:
    """Registered images, 3D points, mean track length (observations per point), mean reprojection error (px)."""
    return {
        "registered_images": int(reconstruction.num_reg_images()),
        "points3D": int(reconstruction.num_points3D()),
        "mean_track_length": float(reconstruction.compute_mean_track_length()),
        "mean_observations_per_image": float(reconstruction.compute_mean_observations_per_reg_image()),
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
    }
