"""``sekd triangulate``: photos + known camera poses -> 3D points, the poses and intrinsics held fixed.

The poses come from a COLMAP model (text or binary; its 3D points are only used to choose
pairs) or from an hloc-style poses file, one ``NAME qw qx qy qz tx ty tz`` line per photo
(world-to-camera, COLMAP's convention), with the intrinsics of ``--camera-params`` or, failing
those, the EXIF / default prior (COLMAP's: focal 1.2 x the long side without EXIF), which is
then kept as it is (it is not refined unless ``refine_intrinsics``).

Pipeline, as ``sekd reconstruct`` up to the database: extract (the same defaults), pair from
the poses (``covisibility_pairs``) or by retrieval, match, refine keypoints, then a COLMAP
database whose rigs, cameras, frames and images carry the ids of the given model, geometric
verification, and ``pycolmap.triangulate_points`` (COLMAP's point_triangulator: triangulation,
track completion and merging, bundle adjustment of the points with every pose constant).
COLMAP normalises each rotation quaternion in bundle adjustment; the given values (unchanged
up to that normalisation, which is checked) are written back before the model is saved, so
the model holds exactly the poses it was given. ``TRIANGULATE`` lists the steps; each is
``step(run, state) -> state`` over a ``Triangulation`` (``run.py``), and the files they write are
named in ``record.py``.

Files in the output folder::

    features.h5, pairs.txt, matches.h5   the stages before triangulation (reused when made with the same settings)
    features-refined.h5                  keypoints moved to where their matches agree (``refine.py``)
    database.db                          COLMAP database (made again on every run)
    colmap.log                           COLMAP's log
    photos/                              links to the posed photos, only when PHOTOS holds others (extracted alone)
    model/                               COLMAP binary model: the given poses and intrinsics, the new points
    record (``record.STATS``)            points, track lengths, reprojection error, pairs, timings, configuration
    .lock                                held for the run: a second run on the same folder is refused
"""
from __future__ import annotations

import logging
import os
import shutil
import tempfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..errors import SekdError
from ..execution import RayOptions
from ..features import FeatureConfig
from ..files import matches as mf
from ..files.atomic import remove_folder
from ..files.images import list_images
from ..files.poses import read_poses
from ..runtime import package_versions
from ..stages.colmap import (
    clean_logs,
    colmap_log,
    open_database,
    require_pycolmap,
    set_options,
)
from ..stages.database import (
    COLMAP_PIXEL_OFFSET,
    camera_groups,
    camera_key,
    parse_camera_params,
    two_view_options,
    verify_matches,
)
from ..stages.export import model_folder, read_model
from ..stages.extract import extract_features
from ..stages.match import MatchConfig, match_features
from ..stages.pairs import (
    Pair,
    PairsConfig,
    read_pairs,
    retrieval_pairs,
    split_writable,
    unique_pairs,
    warn_skipped,
    write_pairs,
)
from ..stages.refine import RefineConfig, refine_keypoints, refine_summary
from . import record
from .config import DEFAULT_FILE_NAMES, DEFAULT_RESIZE_MAX, config_dict
from .run import Run, RunOptions, Step, run_steps

logger = logging.getLogger("sekd")

#: Where pairs come from: the known poses (``covisibility_pairs``) or global descriptors (``pairs.py``).
PAIR_SOURCES = ("covisibility", "retrieval")
#: Partners per photo (as retrieval's K in ``pairs.py``).
DEFAULT_NEIGHBORS = 20
#: Cameras whose optical axes differ more than this see a surface too obliquely for local features to match it.
DEFAULT_MAX_ANGLE_DEG = 60.0
#: Rotation (deg) and translation (relative to the camera's distance from the origin) a pose may differ from
#: the given one after COLMAP's bundle adjustment: quaternion normalisation only. More means it moved.
POSE_TOLERANCE = 1e-6
#: Photos named in a message at most.
NAMES_SHOWN = 10


@dataclass
class TriangulateConfig:
    """Every stage's settings; ``mapper`` / ``verification`` are ``key=value`` pycolmap option overrides
    (IncrementalPipelineOptions, whose ``triangulation.*`` and ``ba_*`` fields drive the triangulator)."""

    features: FeatureConfig = field(default_factory=lambda: FeatureConfig(resize_max=DEFAULT_RESIZE_MAX))
    matching: MatchConfig = field(default_factory=MatchConfig)
    pairs: str = "covisibility"
    num_neighbors: int = DEFAULT_NEIGHBORS
    max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG
    #: Intrinsics of a poses file (ignored for a model, whose cameras give them): a COLMAP model name and
    #: "f,cx,cy,..." in COLMAP pixels (centre of the first pixel at 0.5), or None for the EXIF / default prior.
    camera_model: str = "SIMPLE_RADIAL"
    camera_params: str | None = None
    refine_intrinsics: bool = False
    mapper: list[str] = field(default_factory=list)
    verification: list[str] = field(default_factory=list)
    refine: RefineConfig = field(default_factory=RefineConfig)
    seed: int = 0
    file_names: tuple[str, str] = DEFAULT_FILE_NAMES


# ----------------------------------------------------------------------------- known poses

def _names(kind: str, names: list[str]) -> str:
    shown = ", ".join(names[:NAMES_SHOWN])
    return f"{len(names)} {kind}: {shown}" + (", ..." if len(names) > NAMES_SHOWN else "")


def common_photos(posed: list[str], photos: list[str], poses: Path, image_dir: Path) -> list[str]:
    """The posed names that are photos below ``image_dir`` (sorted); warns about the others, SekdError if none."""
    common = sorted(set(posed) & set(photos))
    if not common:
        raise SekdError(f"{poses}: none of its {len(posed)} posed photos (e.g. {min(posed)}) is among the "
                        f"{len(photos)} photos of {image_dir} (e.g. {min(photos)}); names must be paths "
                        "relative to PHOTOS")
    missing = sorted(set(posed) - set(photos))
    if missing:
        logger.warning("warning: %s: %s; left out", poses, _names(f"posed photo(s) not in {image_dir}", missing))
    unposed = sorted(set(photos) - set(posed))
    if unposed:
        logger.warning("warning: %s: %s; left out", image_dir, _names(f"photo(s) without a pose in {poses}", unposed))
    return common


def read_pose_model(folder: Path):
    """The COLMAP model in ``folder`` (``export.read_model``); a model without a points3D file (poses given as
    cameras + images only) is read as one without points."""
    folder = model_folder(folder)
    for ext in ("bin", "txt"):
        if (folder / f"images.{ext}").is_file() and not (folder / f"points3D.{ext}").exists():
            with tempfile.TemporaryDirectory(prefix="sekd-poses-") as tmp:
                for path in folder.glob(f"*.{ext}"):
                    shutil.copy(path, tmp)
                # An empty points file: no line of text, or a binary count of 0 (uint64).
                Path(tmp, f"points3D.{ext}").write_bytes(b"" if ext == "txt" else bytes(8))
                return read_model(tmp)
    return read_model(folder)


def _model_subset(model, names: set[str]):
    """A new Reconstruction with the rigs, cameras, posed frames and images of ``model`` whose names are in
    ``names``, ids kept, no 2D or 3D points (the triangulator makes its own from the database)."""
    pycolmap = require_pycolmap()
    keep = sorted((im for im in model.images.values() if im.name in names and im.has_pose), key=lambda im: im.image_id)
    subset = pycolmap.Reconstruction()
    frames = {im.frame_id: model.frame(im.frame_id) for im in keep}
    rigs = {frame.rig_id: model.rig(frame.rig_id) for frame in frames.values()}
    camera_ids = {im.camera_id for im in keep} | {s.id for rig in rigs.values() for s in rig.sensor_ids()
                                                    if s.type == pycolmap.SensorType.CAMERA}
    for camera_id in sorted(camera_ids):
        subset.add_camera(model.camera(camera_id))
    for rig_id in sorted(rigs):
        subset.add_rig(rigs[rig_id])
    for frame_id in sorted(frames):
        frame = pycolmap.Frame()
        frame.frame_id, frame.rig_id = frame_id, frames[frame_id].rig_id
        frame.rig_from_world = frames[frame_id].rig_from_world
        for image in keep:
            if image.frame_id == frame_id:
                frame.add_data_id(image.data_id)
        subset.add_frame(frame)
    for image in keep:
        copy = pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id)
        copy.frame_id = image.frame_id
        subset.add_image(copy)
    return subset


def _check_sizes(reference, image_dir: Path) -> None:
    """SekdError when a model camera's size is not its photo's: keypoints would land in the wrong pixels."""
    wrong = []
    for image in reference.images.values():
        camera = reference.camera(image.camera_id)
        key = camera_key(image_dir / image.name)
        if len(key) > 1 and (key[0], key[1]) != (camera.width, camera.height):
            wrong.append(f"{image.name} ({key[0]}x{key[1]}, camera {camera.camera_id} {camera.width}x{camera.height})")
    if wrong:
        raise SekdError(f"{image_dir}: photos differ in size from their cameras in the poses: {', '.join(wrong[:5])}; "
                        "give the photos the poses were made for (or scale the cameras to these photos)")


def _file_cameras(image_dir: Path, names: list[str], model_name: str, params: str | None) -> dict[str, object]:
    """One pycolmap Camera per photo group (``camera_groups``: size and EXIF), ids from 1: ``params`` when given
    (all photos must then share a size), else COLMAP's EXIF prior (focal 1.2 x the long side without EXIF)."""
    pycolmap = require_pycolmap()
    groups = camera_groups(image_dir, names)
    cameras: dict[str, object] = {}
    if params is not None:
        sizes = {camera_key(image_dir / n)[:2] for n in names}
        if len(sizes) != 1 or len(next(iter(sizes))) != 2:
            raise SekdError(f"--camera-params {params}: one set of intrinsics for photos of {len(sizes)} sizes in "
                            f"{image_dir}; give a COLMAP model with one camera per size as --poses")
        width, height = next(iter(sizes))
        camera = pycolmap.Camera.create_from_model_name(1, model_name, 1.0, width, height)
        camera.params = parse_camera_params(model_name, params, width, height)
        return dict.fromkeys(names, camera)
    options = pycolmap.ImageReaderOptions()
    options.camera_model = model_name
    for camera_id, group in enumerate(groups, 1):
        camera = pycolmap.infer_camera_from_image(str(image_dir / group[0]), options)
        camera.camera_id = camera_id
        cameras.update(dict.fromkeys(group, camera))
    logger.warning("warning: no --camera-params: the intrinsics are COLMAP's prior (EXIF focal length, else 1.2 x "
                   "the long side; principal point at the centre; no distortion) and are NOT refined; the points are "
                   "only as good as that guess: give --camera-params, or --refine-intrinsics")
    return cameras


def _from_poses_file(poses: dict[str, tuple[np.ndarray, np.ndarray]], names: list[str], image_dir: Path,
                     config: TriangulateConfig):
    """A Reconstruction of the posed ``names`` (image ids 1.. in name order, trivial rigs and frames)."""
    pycolmap = require_pycolmap()
    reference = pycolmap.Reconstruction()
    cameras = _file_cameras(image_dir, names, config.camera_model, config.camera_params)
    for camera in {c.camera_id: c for c in cameras.values()}.values():
        reference.add_camera_with_trivial_rig(camera)
    for image_id, name in enumerate(names, 1):
        quat, translation = poses[name]
        image = pycolmap.Image(name=name, camera_id=cameras[name].camera_id, image_id=image_id)
        reference.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(quat), translation))
    return reference


def read_known_poses(poses: str | Path, image_dir: Path, photos: list[str], config: TriangulateConfig):
    """``(input, reference)``: the Reconstruction read from ``poses`` (a model folder, or a poses file made
    into one) and the one to triangulate: its posed photos present below ``image_dir``, ids kept, no points."""
    poses = Path(poses)
    if poses.is_dir():
        if config.camera_params is not None:
            raise SekdError(f"--camera-params: {poses} is a COLMAP model, whose cameras give the intrinsics; "
                            "leave --camera-params out (or give a poses file)")
        model = read_pose_model(poses)
        posed = [im.name for im in model.images.values() if im.has_pose]
        if not posed:
            raise SekdError(f"{poses}: the model has no posed images; give a model with registered images")
        names = common_photos(posed, photos, poses, image_dir)
        reference = _model_subset(model, set(names))
        _check_sizes(reference, image_dir)
        return model, reference
    if not poses.is_file():
        raise SekdError(f"--poses {poses}: no such file or folder; give a COLMAP model folder or a poses file")
    parse_camera_params(config.camera_model, config.camera_params)
    table = read_poses(poses)
    names = common_photos(list(table), photos, poses, image_dir)
    reference = _from_poses_file(table, names, image_dir, config)
    return reference, reference


# ----------------------------------------------------------------------------- pairs

def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(a @ b.T, -1.0, 1.0)))


def pose_pairs(reference, k: int, max_angle_deg: float) -> list[Pair]:
    """Each photo with its ``k`` nearest cameras (centre distance) among those whose optical axis is within
    ``max_angle_deg`` of its own: cameras close together looking the same way see the same surfaces."""
    images = sorted(reference.images.values(), key=lambda im: im.name)
    if len(images) < 2:
        return []
    centres = np.array([im.projection_center() for im in images])
    axes = np.array([im.viewing_direction() for im in images])
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    distance[_angle_deg(axes, axes) > max_angle_deg] = np.inf
    np.fill_diagonal(distance, np.inf)
    pairs = []
    for i, row in enumerate(distance):
        for j in np.argsort(row, kind="stable")[:k]:
            if np.isfinite(row[j]):
                pairs.append((images[i].name, images[j].name))
    return unique_pairs(sorted(tuple(sorted(p)) for p in pairs))


def covisibility_pairs(model, reference, k: int, max_angle_deg: float) -> list[Pair]:
    """The pairs of the known poses. ``model`` with 3D points: each photo with the ``k`` photos sharing the most
    points with it (hloc's pairs_from_covisibility); photos of no such pair (and every photo when the model has no
    points, or for a poses file) get ``pose_pairs`` instead."""
    names = {im.image_id: im.name for im in model.images.values()}
    wanted = {im.name for im in reference.images.values()}
    shared: dict[str, Counter] = {}
    for point in model.points3D.values():
        seen = sorted({names[e.image_id] for e in point.track.elements} & wanted)
        for i, a in enumerate(seen):
            for b in seen[i + 1:]:
                shared.setdefault(a, Counter())[b] += 1
                shared.setdefault(b, Counter())[a] += 1
    pairs = [tuple(sorted((a, b))) for a, counts in shared.items() for b, _ in counts.most_common(k)]
    lonely = wanted - {n for p in pairs for n in p}
    pairs += [p for p in pose_pairs(reference, k, max_angle_deg) if p[0] in lonely or p[1] in lonely]
    return unique_pairs(sorted(pairs))


# ----------------------------------------------------------------------------- database and triangulation

def create_pose_database(reference, keypoints: Path, matches: Path, pairs: list[Pair], database: Path) -> Path:
    """A fresh COLMAP database holding ``reference``'s rigs, cameras, frames and images under their own ids,
    the keypoints of ``keypoints`` (+0.5 px: COLMAP's pixel convention) and the raw matches of ``pairs``.

    Cameras are marked as known (prior focal length), so verification estimates essential matrices.
    """
    for suffix in ("", "-wal", "-shm"):
        database.with_name(database.name + suffix).unlink(missing_ok=True)
    ids = {im.name: im.image_id for im in reference.images.values()}
    with open_database(database) as db:
        for camera in reference.cameras.values():
            known = require_pycolmap().Camera(camera.todict())
            known.has_prior_focal_length = True
            db.write_camera(known, use_camera_id=True)
        for rig in reference.rigs.values():
            db.write_rig(rig, use_rig_id=True)
        for frame in reference.frames.values():
            db.write_frame(frame, use_frame_id=True)
        for image in reference.images.values():
            db.write_image(image, use_image_id=True)
        with h5py.File(keypoints, "r") as f:
            lacking = sorted(n for n in ids if n not in f)
            if lacking:
                raise SekdError(f"{keypoints}: no features of {_names('posed photo(s)', lacking)} (unreadable? see the "
                                "warnings of extraction); remove their poses or fix the photos")
            for name, image_id in ids.items():
                db.write_keypoints(image_id, f[name]["keypoints"][()].astype(np.float32) + COLMAP_PIXEL_OFFSET)
        for name0, name1, idx, _ in mf.iter_matches(matches, pairs):
            db.write_matches(ids[name0], ids[name1], idx.astype(np.uint32))
    return database


def triangulator_options(assignments: list[str], seed: int):
    """pycolmap IncrementalPipelineOptions of the triangulator: seeded, on one thread (the same points on every
    run, as the mapper of ``mapping.mapper_options``; ``num_threads=-1`` for speed), ``key=value`` overrides applied."""
    options = require_pycolmap().IncrementalPipelineOptions()
    options.random_seed = seed
    options.num_threads = 1
    return set_options(options, assignments, "--mapper")


def pose_change(given, result) -> tuple[float, float]:
    """Largest rotation (deg) and relative translation change of ``result``'s images against ``given``'s."""
    rotation, translation = 0.0, 0.0
    for image_id, image in given.images.items():
        a, b = image.cam_from_world(), result.image(image_id).cam_from_world()
        qa, qb = a.rotation.quat / np.linalg.norm(a.rotation.quat), b.rotation.quat / np.linalg.norm(b.rotation.quat)
        chord = min(np.linalg.norm(qa - qb), np.linalg.norm(qa + qb))  # q and -q: the same rotation
        rotation = max(rotation, float(np.degrees(4 * np.arcsin(min(1.0, chord / 2)))))  # exact near zero, unlike acos
        scale = max(1.0, float(np.linalg.norm(a.translation)))
        translation = max(translation, float(np.linalg.norm(a.translation - b.translation)) / scale)
    return rotation, translation


def restore_poses(given, result) -> None:
    """Write ``given``'s frame and rig poses into ``result`` bit for bit (COLMAP normalised the quaternions);
    SekdError if a pose moved beyond normalisation (then the triangulator did not hold it fixed)."""
    rotation, translation = pose_change(given, result)
    if rotation > POSE_TOLERANCE or translation > POSE_TOLERANCE:
        raise SekdError(f"COLMAP's triangulator moved a camera ({rotation:.3g} deg, {translation:.3g} relative); "
                        "the poses were not held fixed: report this with colmap.log")
    for frame_id, frame in given.frames.items():
        result.frame(frame_id).rig_from_world = frame.rig_from_world
    for rig_id, rig in given.rigs.items():
        for sensor in rig.non_ref_sensors:
            result.rig(rig_id).set_sensor_from_rig(sensor, rig.sensor_from_rig(sensor))
    for image_id, image in given.images.items():
        a, b = image.cam_from_world(), result.image(image_id).cam_from_world()
        if not (np.array_equal(a.rotation.quat, b.rotation.quat) and np.array_equal(a.translation, b.translation)):
            raise SekdError(f"{image.name}: its pose could not be written back exactly; report this with colmap.log")
    result.update_point_3d_errors()  # the errors under the poses as written


def triangulate_known(reference, database: Path, image_dir: Path, out: Path, options, refine_intrinsics: bool):
    """``pycolmap.triangulate_points`` on ``reference`` (left unchanged), the given poses written back, the model
    saved to ``out``/model (replacing an earlier one only once complete). Returns the new Reconstruction."""
    pycolmap = require_pycolmap()
    scratch = out / "triangulation.tmp"
    remove_folder(scratch)
    scratch.mkdir()
    result = pycolmap.triangulate_points(pycolmap.Reconstruction(reference), str(database), str(image_dir),
                                         str(scratch), clear_points=True, options=options,
                                         refine_intrinsics=refine_intrinsics)
    restore_poses(reference, result)
    if not refine_intrinsics:
        for camera_id, camera in reference.cameras.items():
            if not np.array_equal(camera.params, result.camera(camera_id).params):
                raise SekdError(f"camera {camera_id}: its intrinsics changed although fixed; report this with colmap.log")
    shutil.rmtree(scratch)
    scratch.mkdir()
    result.write_binary(str(scratch))
    remove_folder(out / record.MODEL)
    os.replace(scratch, out / record.MODEL)
    return result


def triangulation_stats(result) -> dict:
    """Points, observations, mean/median track length, mean reprojection error (px), photos with points."""
    lengths = np.array([p.track.length() for p in result.points3D.values()], dtype=np.int64)
    seen = sum(1 for im in result.images.values() if im.num_points3D > 0)
    return {"images": int(result.num_reg_images()), "images_with_points": seen,
            "points3D": int(result.num_points3D()), "observations": int(lengths.sum()),
            "mean_track_length": float(lengths.mean()) if len(lengths) else 0.0,
            "median_track_length": float(np.median(lengths)) if len(lengths) else 0.0,
            "mean_reprojection_error_px": float(result.compute_mean_reprojection_error())}


# ----------------------------------------------------------------------------- the command

def _photo_view(image_dir: Path, photos: list[str], names: list[str], out: Path) -> Path:
    """The folder to extract from: ``image_dir`` when it holds just the posed photos, else ``out``/photos with
    links to them (extraction reads every photo of its folder; the others would cost time for nothing)."""
    view = out / "photos"
    remove_folder(view)
    if set(photos) == set(names):
        return image_dir
    for name in names:
        link = view / name
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to((image_dir / name).resolve())
    return view


def _make_pairs(config: TriangulateConfig, model, reference, features: Path, out: Path, progress: bool) -> Path:
    names, bad = split_writable(sorted(im.name for im in reference.images.values()))
    warn_skipped(bad)
    if config.pairs == "retrieval":
        pairs = retrieval_pairs(features, names, PairsConfig(mode="retrieval", num_neighbors=config.num_neighbors),
                                config.num_neighbors, progress)
    else:
        pairs = covisibility_pairs(model, reference, config.num_neighbors, config.max_angle_deg)
    pairs = [p for p in pairs if p[0] not in bad and p[1] not in bad]
    alone = sorted(set(names) - {n for p in pairs for n in p})
    if alone:
        logger.warning("warning: %s; they get no points (raise --max-angle or use --pairs retrieval)",
                       _names("photo(s) in no pair", alone))
    if not pairs:
        raise SekdError(f"{out}: no pairs among the {len(names)} posed photos; raise --max-angle or use --pairs retrieval")
    return write_pairs(pairs, out / record.PAIRS)


@dataclass
class Triangulation:
    """What the steps of ``TRIANGULATE`` have made so far, and the record they fill (``stats``).

    ``model``: the Reconstruction the poses were read from (its points choose pairs); ``reference``: the one
    triangulated (its posed photos below ``image_dir``, no points); ``options`` / ``two_view``: pycolmap's
    triangulator and verification options; ``keypoints``: what the database gets (the refined keypoints, or the
    features); ``result``: the triangulated Reconstruction.
    """

    image_dir: Path
    photos: list[str]
    model: Any
    reference: Any
    config: TriangulateConfig
    options: Any
    two_view: Any
    stats: dict
    features: Path | None = None
    pairs_file: Path | None = None
    pairs: list[Pair] = field(default_factory=list)
    matches: Path | None = None
    keypoints: Path | None = None
    database: Path | None = None
    result: Any = None

    @property
    def names(self) -> list[str]:
        """The posed photos triangulated, sorted."""
        return sorted(im.name for im in self.reference.images.values())


def triangulate(image_dir: str | Path, poses: str | Path, output_dir: str | Path,
                config: TriangulateConfig | None = None, *, overwrite: bool = False, num_threads: int | None = None,
                progress: bool = True, executor: str = "local", ray_options: RayOptions | None = None,
                options: RunOptions | None = None) -> Path:
    """Triangulate the photos below ``image_dir`` with the poses of ``poses`` into ``output_dir``; returns the
    model folder (``output_dir``/model). Holds the folder's lock; features and matches of an earlier run with
    the same settings are reused. How the run runs: ``options`` (a RunOptions), or its fields ``overwrite``,
    ``num_threads``, ``progress``, ``executor`` and ``ray_options`` as keywords. SekdError for bad input (one
    clear sentence)."""
    require_pycolmap()
    config = config or TriangulateConfig()
    options = options or RunOptions(overwrite=overwrite, num_threads=num_threads, progress=progress,
                                    executor=executor, ray_options=ray_options)
    if config.pairs not in PAIR_SOURCES:
        raise SekdError(f"unknown pair source {config.pairs!r}; choose from {', '.join(PAIR_SOURCES)}")
    image_dir, out = Path(image_dir), Path(output_dir)
    if not image_dir.is_dir():
        raise SekdError(f"{image_dir}: not a folder of images; give the folder holding the photos")
    # Options and poses are checked first: a typo or a bad line fails in a second, before OUT is made.
    triangulator = triangulator_options(config.mapper, config.seed)
    two_view = two_view_options(config.verification, config.seed)
    photos = list_images(image_dir)
    model, reference = read_known_poses(Path(poses), image_dir, photos, config)
    stats: dict = {"status": "running", "images_dir": str(image_dir), "poses": str(poses),
                   "poses_kind": "model" if Path(poses).is_dir() else "poses file", "config": config_dict(config),
                   "versions": package_versions(), "photos": len(photos), "posed": reference.num_images()}
    state = Triangulation(image_dir, photos, model, reference, config, triangulator, two_view, stats)
    with Run(out, options, lock="triangulation folder") as run:
        clean_logs(out / record.COLMAP_LOG)  # left by a killed run: nobody else uses them while we hold the lock
        state = run_steps(run, TRIANGULATE, state)
        stats.update(status="ok", model=triangulation_stats(state.result), output=str(out / record.MODEL),
                     timings_s=run.timings(), stages=run.stage_table())
        record.write_record(stats, out)
    return out / record.MODEL


# ----------------------------------------------------------------------------- the steps, in order

def extract(run: Run, s: Triangulation) -> Triangulation:
    """OUT's feature file of the posed photos (made or resumed)."""
    photos = _photo_view(s.image_dir, s.photos, s.names, run.out)
    s.features = extract_features(photos, run.out / s.config.file_names[0], s.config.features,
                                  overwrite=run.options.overwrite, num_threads=run.num_threads, progress=run.progress,
                                  executor=run.executor)
    return s


def pairs(run: Run, s: Triangulation) -> Triangulation:
    """OUT's pairs file: from the known poses, or by retrieval (``config.pairs``)."""
    s.pairs_file = _make_pairs(s.config, s.model, s.reference, s.features, run.out, run.progress)
    return s


def match(run: Run, s: Triangulation) -> Triangulation:
    """OUT's match file (made or resumed); the record counts the pairs."""
    s.matches = match_features(s.features, s.pairs_file, run.out / s.config.file_names[1], s.config.matching,
                               overwrite=run.options.overwrite, num_threads=run.num_threads, progress=run.progress,
                               executor=run.executor)
    s.pairs = read_pairs(s.pairs_file)
    s.stats["pairs"] = len(s.pairs)
    return s


def refine(run: Run, s: Triangulation) -> Triangulation:
    """The keypoints moved to where their matches agree (``stages.refine``)."""
    s.keypoints = refine_keypoints(s.features, s.matches, s.pairs, s.image_dir,
                                   run.out / record.refined_name(s.config.file_names[0]), s.config.refine,
                                   progress=run.progress, executor=run.executor)
    s.stats["refine"] = refine_summary(s.keypoints)
    return s


def verification(run: Run, s: Triangulation) -> Triangulation:
    """COLMAP's database of the given rigs, cameras, frames and images, the keypoints and the matches, verified
    geometrically; COLMAP's log goes to OUT from here to the run's end."""
    run.hold(colmap_log(run.out / record.COLMAP_LOG))
    s.database = run.out / record.DATABASE
    s.keypoints = s.keypoints or s.features
    create_pose_database(s.reference, s.keypoints, s.matches, s.pairs, s.database)
    verify_matches(s.database, s.two_view, run.num_threads or -1)
    with open_database(s.database) as db:
        s.stats["verified_pairs"] = int(db.num_verified_image_pairs())
    return s


def triangulation(run: Run, s: Triangulation) -> Triangulation:
    """The points triangulated with every pose (and, unless refined, every intrinsic) fixed; OUT/model."""
    logger.info("triangulating %d photos with their poses fixed", len(s.names))
    s.result = triangulate_known(s.reference, s.database, s.image_dir, run.out, s.options, s.config.refine_intrinsics)
    return s


#: ``sekd triangulate``, step by step; the record's ``timings_s`` has one entry per step run, and their total.
TRIANGULATE: tuple[Step, ...] = (
    Step("extract", extract),
    Step("pairs", pairs),
    Step("match", match),
    Step("refine", refine, when=lambda s: s.config.refine.enabled),
    Step("verification", verification),
    Step("triangulation", triangulation),
)


def format_triangulation(stats: dict) -> str:
    """One line for the console: what the run's record says of the model."""
    m = stats["model"]
    return (f"{stats['output']}: {m['points3D']:,} points from {m['images_with_points']}/{m['images']} posed photos, "
            f"{m['observations']:,} observations, mean track length {m['mean_track_length']:.2f}, "
            f"mean reprojection error {m['mean_reprojection_error_px']:.3f} px ({stats['pairs']} pairs, "
            f"{stats['verified_pairs']} verified)")
