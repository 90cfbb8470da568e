"""Localize new photos against a reconstruction (``sekd localize``): queries + OUT of ``sekd reconstruct`` -> poses.

For each query photo: features with the reference's extraction settings, the K reference images
most similar by the reference's global descriptors (VLAD, ``retrieval.py``), matches with the
reference's matching settings, the matched reference keypoints lifted to the model's 3D points
(``points2D[j].point3D_id``: the model's observations are indexed like the feature file's
keypoints), then pycolmap's ``estimate_and_refine_absolute_pose`` (LO-RANSAC on the 2D-3D
correspondences, then a non-linear refinement of the inliers).

Retrieval rule: the reference's global file (``<features>.global.h5``, written by retrieval pairs)
when it exists; else, for a reference of at most ``2K + 1`` registered images (where
``sekd reconstruct`` pairs exhaustively and writes no global file), every registered image;
else a vocabulary and global descriptors of the reference are made in the work folder (never in OUT).

Camera of a query, first that applies: ``camera_params`` (COLMAP convention, ``camera_model``); the
reference's calibrated camera when the query has the same ``database.camera_key`` (size and EXIF
make, model, focal length) as a registered photo of that camera (read from the photo folder
recorded in OUT's record); else a prior, SIMPLE_RADIAL-like model of the reference's
``config.camera.model``, focal length from EXIF's 35 mm equivalent (``f35 / 36 * max(w, h)``) or
``1.2 * max(w, h)`` (COLMAP's default prior), with the focal length estimated (P4Pf) and refined.

Files written (``-o results.txt``; nothing is ever written into OUT)::

    results.txt            one line per localized query: ``NAME qw qx qy qz tx ty tz`` (world-to-camera,
                           COLMAP's convention, hloc's format), in query order
    results_log.json       per query: retrieved images, matches per image, 2D-3D correspondences, inliers,
                           camera used, pose, seconds, or why it failed; the configuration, versions, reference
    results-localize/      work folder: features.h5 (the queries' features; resumable), queries/ (links to the
                           photos of a list file), reference.global.h5 (only under the third retrieval rule)
    results.txt.lock       held for the run: a second run on the same output is refused

Resumable: queries localized in an earlier run with the same configuration and reference are
kept, not recomputed (failed ones are tried again). A query that fails (unreadable photo, too
few matches or inliers) is logged with its reason; the others go on. ``LOCALIZE`` lists the
run's steps, each ``step(run, state) -> state`` over a ``Localization`` (``run.py``).
"""
from __future__ import annotations

import copy
import hashlib
import json
import logging
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from tqdm import tqdm

from ..errors import SekdError
from ..execution import RayOptions
from ..features import FeatureConfig
from ..files import features as ff
from ..files.atomic import write_atomic
from ..files.images import ImageReadError, list_images, read_image
from ..files.locking import writer_lock
from ..files.poses import pose_line
from ..runtime import package_versions
from ..stages.colmap import require_pycolmap
from ..stages.database import COLMAP_PIXEL_OFFSET, camera_key, parse_camera_params
from ..stages.extract import extract_features
from ..stages.match import describe_config, match_descriptors
from ..stages.retrieval import compute_global_descriptors, global_path, query_neighbors
from .config import ReconstructConfig
from .record import MODEL, Record
from .run import Run, RunOptions, Step, run_steps

logger = logging.getLogger("sekd")
#: Reference images retrieved per query (hloc's localization pipelines use 10 to 50 with NetVLAD).
DEFAULT_NUM_NEIGHBORS = 10
#: RANSAC inlier threshold in pixels (hloc's and pycolmap's default for localization).
DEFAULT_MAX_ERROR_PX = 12.0
#: Fewest pose inliers for a query to count as localized: below, a pose from a dozen points is a guess.
DEFAULT_MIN_INLIERS = 12
#: Focal length prior without EXIF, times the long side (COLMAP's ImageReader default).
DEFAULT_FOCAL_FACTOR = 1.2
#: EXIF tags: the Exif sub-IFD and its FocalLengthIn35mmFilm.
_EXIF_IFD, _EXIF_FOCAL_35MM = 0x8769, 0xA405
#: Seconds between checkpoints of the results (what a kill loses at most).
CHECKPOINT_SECONDS = 10.0


@dataclass
class LocalizeConfig:
    """How queries are localized: ``num_neighbors`` K, camera (``camera_model``: None = the reference's
    ``config.camera.model``; ``camera_params`` "f,cx,cy,k" in COLMAP pixels, None = reuse or estimate),
    RANSAC threshold ``max_error_px`` (pixels), ``min_inliers``, RANSAC ``seed``."""

    num_neighbors: int = DEFAULT_NUM_NEIGHBORS
    camera_model: str | None = None
    camera_params: str | None = None
    max_error_px: float = DEFAULT_MAX_ERROR_PX
    min_inliers: int = DEFAULT_MIN_INLIERS
    seed: int = 0


@dataclass
class Reference:
    """A ``sekd reconstruct`` output, read only: its model, feature file and the settings it was made with."""

    folder: Path
    record: Record
    features: Path
    model: Any  # pycolmap.Reconstruction
    ids: dict[str, int]  # registered image name -> image id
    images_dir: Path | None
    fingerprint: str
    point3D_ids: dict[str, np.ndarray] = field(default_factory=dict)  # per image: N (keypoints) int64, -1 = none

    @property
    def stats(self) -> dict:
        """The record as written."""
        return self.record.data

    @property
    def config(self) -> dict:
        """The recorded configuration (JSON types; ``settings`` types it)."""
        return self.record.config_data

    @property
    def settings(self) -> ReconstructConfig:
        """The configuration the reference was made with, typed (a new object on every call)."""
        return self.record.config()

    @property
    def camera_model(self) -> str:
        """The reference's camera model (``config.camera.model``)."""
        return self.settings.camera.model or "SIMPLE_RADIAL"

    def observed(self, name: str) -> np.ndarray:
        """The model's 3D point id of each keypoint of reference image ``name`` (N int64, -1 where none)."""
        if name not in self.point3D_ids:
            image = self.model.image(self.ids[name])
            ids = np.full(image.num_points2D(), -1, dtype=np.int64)
            for idx in image.get_observation_point2D_idxs():
                ids[idx] = image.points2D[idx].point3D_id
            self.point3D_ids[name] = ids
        return self.point3D_ids[name]


def load_reference(folder: str | Path) -> Reference:
    """Read and check the reference folder OUT; SekdError (one sentence) when it is not a usable sekd output."""
    pycolmap = require_pycolmap()
    folder = Path(folder)
    if not folder.is_dir():
        raise SekdError(f"{folder}: no such folder; give --reference the output folder of `sekd reconstruct`")
    record = Record.from_record(folder, option="--reference")  # SekdError (one sentence) when it is no `sekd reconstruct` output
    model_dir = folder / MODEL
    if not (model_dir / "images.bin").is_file() and not (model_dir / "images.txt").is_file():
        raise SekdError(f"{folder}: has no model (model/ missing; the reconstruction "
                        f"{record.data.get('status', 'failed')}); localize against a folder where `sekd reconstruct` "
                        "succeeded")
    features = _reference_features(record)
    try:
        model = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # noqa: BLE001 - pycolmap raises bare RuntimeErrors for torn files
        raise SekdError(f"{model_dir}: cannot read the COLMAP model ({exc}); rerun `sekd reconstruct`") from None
    ids = {model.image(i).name: i for i in model.reg_image_ids()}
    if not ids:
        raise SekdError(f"{model_dir}: the model has no registered image; nothing to localize against")
    _check_keypoints(features, model, ids)
    return Reference(folder, record, features, model, ids, record.photo_folder(), _fingerprint(model_dir))


def _reference_features(record: Record) -> Path:
    """The feature file the model's keypoints index: the one given to reconstruct (``inputs.features``) or made in OUT."""
    path = record.features
    if not path.is_file():
        raise SekdError(f"{path}: the reference's feature file is missing (the model alone cannot be matched); "
                        "localize against a complete `sekd reconstruct` output")
    ff.read_attrs(path)
    return path


def _check_keypoints(features: Path, model, ids: dict[str, int]) -> None:
    """SekdError when a registered image's observations do not index the feature file's keypoints."""
    with h5py.File(features, "r") as f:
        for name, image_id in ids.items():
            count = f[name]["keypoints"].shape[0] if name in f and "keypoints" in f[name] else None
            if count != model.image(image_id).num_points2D():
                have = "no features" if count is None else f"{count} keypoints"
                raise SekdError(f"{features}: has {have} for '{name}' but the model has "
                                f"{model.image(image_id).num_points2D()} observations slots; the model was not made "
                                "from this feature file (rerun `sekd reconstruct`)")


def _fingerprint(model_dir: Path) -> str:
    """SHA-1 of the model's cameras and images files: a rebuilt reference invalidates earlier results."""
    digest = hashlib.sha1()
    for name in ("cameras.bin", "images.bin", "cameras.txt", "images.txt"):
        if (model_dir / name).is_file():
            digest.update((model_dir / name).read_bytes())
    return digest.hexdigest()


def feature_config(reference: Reference, weights: str | None = None) -> FeatureConfig:
    """The reference's extraction settings (its record's ``config.features``, typed; a new object on every call);
    ``weights``: its SEKD checkpoint."""
    return reference.record.config(weights).features


def matching_config(reference: Reference) -> dict:
    """The reference's matching (mode, ratio, metric, rootsift) as its match file recorded it, defaults resolved."""
    recorded = reference.record.matching
    if {"mode", "ratio", "rootsift"} <= set(recorded):
        return recorded
    attrs = ff.read_attrs(reference.features)
    return describe_config(reference.settings.matching, str(attrs["feature_type"]),
                           str(attrs["descriptor_dtype"]) == "uint8")


# ----------------------------------------------------------------------------- queries

def query_images(queries: str | Path, work: Path) -> tuple[Path, list[str]]:
    """The folder to extract from and the query names, for a folder of photos or a list file of paths.

    A list file holds one path per line (blank lines and ``#`` comments ignored); relative paths
    are relative to the list file's folder and keep that relative path as their name, absolute
    ones are named by their file name. Their photos are linked into ``work/queries/``.
    """
    queries = Path(queries)
    if queries.is_dir():
        return queries, list_images(queries)
    if not queries.is_file():
        raise SekdError(f"{queries}: no such folder or file; give a folder of photos or a text file listing them")
    try:
        lines = [s.strip() for s in queries.read_text(encoding="utf-8").splitlines()]
    except (OSError, UnicodeDecodeError) as exc:
        raise SekdError(f"{queries}: not a text list of photo paths ({exc}); give a folder or one path per line") from None
    links, names = work / "queries", []
    for line in (s for s in lines if s and not s.startswith("#")):
        source = Path(line) if Path(line).is_absolute() else queries.parent / line
        name = Path(line).name if Path(line).is_absolute() else Path(line).as_posix()
        if name in names or ".." in Path(name).parts:
            raise SekdError(f"{queries}: '{line}' gives a query name twice or outside the list's folder; "
                            "list each photo once, by a path below the list's folder or an absolute path")
        _link(links / name, source.resolve())
        names.append(name)
    if not names:
        raise SekdError(f"{queries}: lists no photo; give one path per line")
    return links, names


def _link(link: Path, target: Path) -> None:
    link.parent.mkdir(parents=True, exist_ok=True)
    if link.is_symlink() and Path(os.readlink(link)) == target:
        return
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(target)


def work_folder(output: Path) -> Path:
    """The work folder of ``output``: ``results.txt`` -> ``results-localize/`` beside it."""
    return output.with_name(output.stem + "-localize")


def log_path(output: Path) -> Path:
    """The JSON log of ``output``: ``results.txt`` -> ``results_log.json`` beside it."""
    return output.with_name(output.stem + "_log.json")


# ----------------------------------------------------------------------------- retrieval and matching

def retrieve(reference: Reference, query_features: Path, names: list[str], config: LocalizeConfig, work: Path,
             progress: bool) -> tuple[dict[str, list[str]], str]:
    """The reference images to match with each query (best first) and the rule used (module docstring)."""
    registered = sorted(reference.ids)
    k = config.num_neighbors
    with h5py.File(query_features, "r") as f:
        present = [n for n in names if n in f and "descriptors" in f[n]]  # failed extractions have none
    stored = global_path(reference.features)
    if not stored.is_file():
        if len(registered) <= 2 * k + 1:
            return {n: list(registered) for n in present}, "all registered images (no global file, <= 2K+1 images)"
        stored = compute_global_descriptors(reference.features, reference.settings.pairs.retrieval,
                                            work / "reference.global.h5", progress)
        rule = f"global descriptors learned in {stored}"
    else:
        rule = f"reference global descriptors {stored}"
    result: dict[str, list[str]] = {}
    for i in range(0, len(present), 64):  # 64 queries' VLADs at a time: bounded memory
        chunk = {n: ff.read_features(query_features, n)["descriptors"] for n in present[i:i + 64]}
        result.update(query_neighbors(stored, chunk, k, registered))
    return result, rule


def correspondences(reference: Reference, query: dict[str, np.ndarray], retrieved: list[str], matching: dict,
                    cache: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """2D-3D correspondences of a query: M x 2 keypoints (COLMAP pixels), M x 3 model points, matches per image.

    A query keypoint matched to several reference keypoints of one 3D point counts once.
    """
    pairs: set[tuple[int, int]] = set()
    counts = {}
    for name in retrieved:
        if name not in cache:
            if len(cache) > 64:
                cache.pop(next(iter(cache)))
            cache[name] = ff.read_features(reference.features, name)["descriptors"]
        matches, _ = match_descriptors(query["descriptors"], cache[name], matching["mode"], matching["ratio"],
                                       bool(matching.get("rootsift")))
        found = np.flatnonzero(matches >= 0)
        counts[name] = len(found)
        point_ids = reference.observed(name)[matches[found]]
        pairs.update(zip(found[point_ids >= 0].tolist(), point_ids[point_ids >= 0].tolist()))
    if not pairs:
        return np.zeros((0, 2)), np.zeros((0, 3)), counts
    idx, pids = map(np.array, zip(*sorted(pairs)))
    points2D = query["keypoints"][idx].astype(np.float64) + COLMAP_PIXEL_OFFSET
    points3D = np.array([reference.model.point3D(int(p)).xyz for p in pids], dtype=np.float64)
    return points2D, points3D, counts


# ----------------------------------------------------------------------------- camera and pose

def query_camera(reference: Reference, photo: Path, size: tuple[int, int], config: LocalizeConfig,
                 key_cache: dict) -> tuple[Any, str, bool]:
    """The camera of a query photo (module docstring): ``(pycolmap.Camera, where it comes from, estimate focal)``."""
    pycolmap = require_pycolmap()
    width, height = size
    model = config.camera_model or reference.camera_model
    if config.camera_params:
        params = parse_camera_params(model, config.camera_params, width, height)
        camera = pycolmap.Camera.create_from_model_name(0, model, 1.0, width, height)
        camera.params = params
        return camera, "--camera-params", False
    key = camera_key(photo)
    for camera_id, ref_key in _reference_camera_keys(reference, key_cache).items():
        if ref_key == key and len(key) > 1:
            return copy.copy(reference.model.camera(camera_id)), f"reference camera {camera_id} (same camera key)", False
    focal, source = _focal_prior(photo, width, height)
    camera = pycolmap.Camera.create_from_model_name(0, model, focal, width, height)
    return camera, f"prior: focal {focal:.1f} px from {source}, estimated", True


def _reference_camera_keys(reference: Reference, cache: dict) -> dict[int, tuple]:
    """``camera_key`` of one registered photo per reference camera (empty without the reference's photo folder)."""
    if "keys" not in cache:
        keys = {}
        if reference.images_dir is not None and reference.images_dir.is_dir():
            for name, image_id in sorted(reference.ids.items()):
                camera_id = reference.model.image(image_id).camera_id
                if camera_id not in keys and (reference.images_dir / name).is_file():
                    keys[camera_id] = camera_key(reference.images_dir / name)
        cache["keys"] = keys
    return cache["keys"]


def _focal_prior(photo: Path, width: int, height: int) -> tuple[float, str]:
    """Focal length prior in pixels: EXIF FocalLengthIn35mmFilm (36 mm = the long side), else 1.2 x the long side."""
    from PIL import Image

    try:
        with Image.open(photo) as image:
            f35 = float(image.getexif().get_ifd(_EXIF_IFD).get(_EXIF_FOCAL_35MM) or 0)
    except (OSError, ValueError, TypeError, ZeroDivisionError, SyntaxError):
        f35 = 0.0
    if f35 > 0:
        return f35 / 36.0 * max(width, height), "EXIF 35 mm equivalent"
    return DEFAULT_FOCAL_FACTOR * max(width, height), f"{DEFAULT_FOCAL_FACTOR} x the long side"


def estimate_pose(points2D: np.ndarray, points3D: np.ndarray, camera, estimate_focal: bool,
                  config: LocalizeConfig) -> dict | None:
    """pycolmap's LO-RANSAC + refinement on M x 2 / M x 3 correspondences; refines ``camera`` in place when
    ``estimate_focal``. Returns pycolmap's dict (cam_from_world, num_inliers, inlier_mask) or None."""
    pycolmap = require_pycolmap()
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.estimate_focal_length = estimate_focal
    estimation.ransac.max_error = config.max_error_px
    estimation.ransac.random_seed = config.seed
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    refinement.refine_focal_length = estimate_focal
    refinement.refine_extra_params = estimate_focal
    return pycolmap.estimate_and_refine_absolute_pose(points2D, points3D, camera, estimation, refinement)


# ----------------------------------------------------------------------------- the run

@dataclass
class Localization:
    """What the steps of ``LOCALIZE`` have made so far, and the log they fill (``log``: the results of an earlier run
    with the same ``identity`` resumed, else new).

    ``image_dir`` / ``names``: the folder the queries are extracted from and their names; ``features``: their
    feature file in the work folder; ``todo``: the queries not localized yet; ``neighbours``: the reference images
    retrieved for each of them, best first.
    """

    queries: str | Path
    reference: Reference
    output: Path
    config: LocalizeConfig
    features_config: FeatureConfig
    identity: dict = field(default_factory=dict)
    log: dict = field(default_factory=dict)
    image_dir: Path | None = None
    names: list[str] = field(default_factory=list)
    features: Path | None = None
    matching: dict = field(default_factory=dict)
    todo: list[str] = field(default_factory=list)
    neighbours: dict[str, list[str]] = field(default_factory=dict)

    @property
    def work(self) -> Path:
        return work_folder(self.output)


def localize(queries: str | Path, reference: str | Path, output: str | Path, config: LocalizeConfig | None = None, *,
             weights: str | None = None, overwrite: bool = False, num_threads: int | None = None,
             progress: bool = True, executor: str = "local", ray_options: RayOptions | None = None,
             options: RunOptions | None = None) -> Path:
    """Localize the photos of ``queries`` (folder or list file) against the reconstruction folder ``reference``.

    Writes ``output`` (hloc poses), its log and work folder (module docstring); returns ``output``.
    ``weights``: the reference's SEKD checkpoint when it was not the default model. SekdError for
    a reference that is not a usable sekd output, or an output made with other settings (unless
    ``overwrite``). How the run runs: ``options`` (a RunOptions), or its fields ``overwrite``, ``num_threads``,
    ``progress``, ``executor`` and ``ray_options`` as keywords (the executor: where the queries' extraction runs).
    """
    config = config or LocalizeConfig()
    options = options or RunOptions(overwrite=overwrite, num_threads=num_threads, progress=progress,
                                    executor=executor, ray_options=ray_options)
    if config.num_neighbors < 1:
        raise SekdError(f"--num-neighbors {config.num_neighbors}: retrieve at least 1 reference image per query")
    output = Path(output)
    ref = load_reference(reference)
    if output.resolve().is_relative_to(ref.folder.resolve()):
        raise SekdError(f"{output}: inside the reference folder {ref.folder}, which localize never writes into; "
                        "choose an output elsewhere")
    if config.camera_params:
        parse_camera_params(config.camera_model or ref.camera_model, config.camera_params)
    state = Localization(queries, ref, output, config, feature_config(ref, weights))
    # One writer per results file (its own lock beside it: OUTPUT is a file, not a run folder); the run's
    # executor, open from the queries' extraction to the end, works in the work folder.
    with writer_lock(output, "localization results file"), Run(work_folder(output), options) as run:
        run_steps(run, LOCALIZE, state)
    return output


def _identity(ref: Reference, config: LocalizeConfig, features: dict) -> dict:
    """What must agree for earlier results to be kept."""
    return {"reference": str(ref.folder.resolve()), "reference_model_sha1": ref.fingerprint,
            "localize": asdict(config), "features": features}


# ----------------------------------------------------------------------------- the steps, in order

def resume(run: Run, s: Localization) -> Localization:
    """The work folder, the log of an earlier run to resume (SekdError when made with other settings), the queries."""
    s.work.mkdir(parents=True, exist_ok=True)
    s.identity = _identity(s.reference, s.config,
                           {k: v for k, v in asdict(s.features_config).items() if k != "weights"})
    s.log = _previous_log(s.output, s.identity, run.options.overwrite)
    s.image_dir, s.names = query_images(s.queries, s.work)
    return s


def extract(run: Run, s: Localization) -> Localization:
    """The queries' features (made or resumed in the work folder) with the reference's settings, checked against
    the reference's."""
    s.features = extract_features(s.image_dir, s.work / "features.h5", s.features_config,
                                  overwrite=run.options.overwrite, num_threads=run.num_threads, progress=run.progress,
                                  executor=run.executor)
    _check_same_features(s.features, s.reference.features)
    return s


def plan(run: Run, s: Localization) -> Localization:
    """The log's settings, and the queries still to localize (those an earlier run localized are kept)."""
    s.matching = matching_config(s.reference)
    s.log.update({"identity": s.identity, "queries_source": str(s.queries), "matching": s.matching,
                  "versions": package_versions(), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
    records = s.log.setdefault("queries", {})
    s.todo = [n for n in s.names if (records.get(n) or {}).get("status") != "localized"]
    return s


def retrieval(run: Run, s: Localization) -> Localization:
    """The reference images to match with each query to localize (``retrieve``)."""
    s.neighbours, s.log["retrieval"] = retrieve(s.reference, s.features, s.todo, s.config, s.work, run.progress)
    return s


def localize_queries(run: Run, s: Localization) -> Localization:
    """Each query localized in turn (``_localize_one``), the results saved every CHECKPOINT_SECONDS and at the end."""
    records = s.log["queries"]
    caches = {"cache": {}, "keys": {}}
    saved = time.monotonic()
    for name in tqdm(s.todo, desc="localize", unit="query", disable=not run.progress or not s.todo):
        records[name] = _localize_one(s.reference, s.image_dir, s.features, name, s.neighbours.get(name), s.matching,
                                      s.config, caches)
        if time.monotonic() - saved > CHECKPOINT_SECONDS:
            _save(s.output, s.log, s.names)
            saved = time.monotonic()
    _save(s.output, s.log, s.names)
    summary = s.log["summary"]
    logger.info("%s: %d of %d queries localized (%d failed)", s.output, summary["localized"], summary["queries"],
                summary["failed"])
    return s


#: ``sekd localize``, step by step (untimed steps are checks and bookkeeping).
LOCALIZE: tuple[Step, ...] = (
    Step("queries", resume, timed=False),
    Step("extract", extract),
    Step("plan", plan, timed=False),
    Step("retrieve", retrieval, when=lambda s: bool(s.todo)),
    Step("localize", localize_queries),
)


def _previous_log(output: Path, identity: dict, overwrite: bool) -> dict:
    """The log of an earlier run on ``output`` to resume, or a new one; SekdError if made with other settings."""
    path = log_path(output)
    if overwrite or not path.is_file():
        return {}
    try:
        log = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}  # torn by hand: start again (the file is only ever replaced whole)
    if log.get("identity") != identity:
        raise SekdError(f"{path}: records a localization with another reference or other settings; "
                        "pass --overwrite to start again, or choose another output")
    return log


def _check_same_features(query: Path, reference: Path) -> None:
    """SekdError when the queries' features were made otherwise than the reference's (another model or setting)."""
    mine, theirs = ff.read_attrs(query), ff.read_attrs(reference)
    settings = [_without_precision(a.get("config")) for a in (mine, theirs)]
    for key, a, b in [(k, mine.get(k), theirs.get(k)) for k in ("feature_type", "descriptor_dim", "descriptor_dtype",
                                                                 "model_sha256")] + [("config", *settings)]:
        if str(a) != str(b):
            raise SekdError(f"{query}: the queries' features differ from the reference's {reference} in {key} "
                            f"({a} vs {b}); give the reference's SEKD model with --weights/--model, or delete "
                            "the work folder if the reference was rebuilt")
    if str(mine.get("config")) != str(theirs.get("config")):  # bf16 here, fp32 there: the same network, rounded
        logger.warning("warning: %s: extracted at another precision than the reference's %s", query, reference)


def _without_precision(config: Any) -> Any:
    """A feature file's recorded configuration without SEKD's arithmetic precision (which CPUs differ in)."""
    try:
        data = json.loads(str(config))
    except ValueError:
        return config
    if isinstance(data, dict) and isinstance(data.get("sekd"), dict):
        data["sekd"].pop("precision", None)
    return json.dumps(data, sort_keys=True)


def _localize_one(ref: Reference, image_dir: Path, features: Path, name: str, retrieved: list[str] | None,
                  matching: dict, config: LocalizeConfig, caches: dict) -> dict:
    """One query's record for the log: localized with its pose, or failed with the reason. ``caches``: the reference
    descriptors (``cache``) and camera keys (``keys``) read so far, kept from one query to the next."""
    start = time.perf_counter()
    record: dict[str, Any] = {"status": "failed", "reason": None}
    try:
        if retrieved is None:
            record["reason"] = _unreadable_reason(image_dir / name)
            return record
        query = ff.read_features(features, name)
        record["retrieved"] = retrieved
        points2D, points3D, record["matches"] = correspondences(ref, query, retrieved, matching, caches["cache"])
        record["correspondences"] = len(points2D)
        size = tuple(int(v) for v in query["image_size"])
        camera, record["camera_source"], estimate_focal = query_camera(ref, image_dir / name, size, config, caches["keys"])
        if len(points2D) < max(config.min_inliers, 6):
            record["reason"] = (f"{len(points2D)} 2D-3D correspondences (fewer than {max(config.min_inliers, 6)}): "
                                "the photo shares too little with the reference images retrieved")
            return record
        result = estimate_pose(points2D, points3D, camera, estimate_focal, config)
        record["camera"] = {"model": camera.model_name, "width": camera.width, "height": camera.height,
                            "params": [float(v) for v in camera.params]}
        record["inliers"] = int(result["num_inliers"]) if result else 0
        if result is None or record["inliers"] < config.min_inliers:
            record["reason"] = f"{record['inliers']} pose inliers (fewer than {config.min_inliers})"
            return record
        record.update(status="localized", pose=pose_line(name, result["cam_from_world"]))
    except SekdError as exc:
        record["reason"] = str(exc)
    except (ValueError, RuntimeError, OSError, KeyError) as exc:  # one photo's trouble must not stop the others
        record["reason"] = f"{type(exc).__name__}: {exc}"
    finally:
        record["seconds"] = round(time.perf_counter() - start, 3)
    return record


def _unreadable_reason(photo: Path) -> str:
    try:
        read_image(photo)
    except ImageReadError as exc:
        return f"not extracted: {exc}"
    except OSError as exc:
        return f"not extracted: {photo}: {exc}"
    return "not extracted (see the warnings of the extraction)"


def _save(output: Path, log: dict, names: list[str]) -> None:
    """The log, then the poses file from it (a kill between the two leaves a log the next run rewrites it from)."""
    records = log.get("queries", {})
    localized = [n for n in names if (records.get(n) or {}).get("status") == "localized"]
    failed = [n for n in names if n in records and n not in localized]
    log["summary"] = {"queries": len(names), "localized": len(localized), "failed": len(failed),
                      "failed_queries": {n: records[n].get("reason") for n in failed}}
    write_atomic(log_path(output), json.dumps(log, indent=1))
    write_atomic(output, "".join(records[n]["pose"] + "\n" for n in localized))
