"""Localization benchmark (``sekd bench maps localize``): hold out photos of a scene, build a reference from
the rest, localize the held-out ones, score their poses against known cameras.

Protocol, per scene: the photos sorted by name, every third one held out (indices 2, 5, 8, ...:
``names[offset::every]``); the reference is reconstructed from the others, the held-out photos
are localized against it; the reference model is aligned to the known cameras by the similarity
of its camera centres (``pycolmap.estimate_sim3d``, least squares over the reference photos); each
localized query's pose is carried through that similarity and compared with its known camera:
rotation error (deg, angle of R_est R_true^T) and position error (camera centres, the known
cameras' units: metres for fountain-P11) and the same in % of the scene radius = median distance
of all the known camera centres to their centroid.

Methods: sekd (``sekd reconstruct`` + ``sekd localize`` with their defaults) and pycolmap's SIFT
pipeline (reference: pycolmap SIFT extraction, one shared camera, exhaustive matching,
incremental mapping; queries: pycolmap SIFT features matched to every reference image with COLMAP's
matcher rule (mutual nearest neighbours, ratio 0.8), lifted to the SIFT model's 3D points, the
same ``estimate_and_refine_absolute_pose`` with the reference's camera).

Known cameras: fountain-P11's ground truth (``gt_dense_cameras``); a scene without them
(sacre_coeur) is scored against pseudo ground truth: each method's own reconstruction of all the
photos (labelled as such in the results).
"""
from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import SekdError
from ...evaluation.metrics import rotation_angle_deg
from ...evaluation.strecha import read_cameras
from ...features import FeatureConfig
from ...files.atomic import write_json
from ...files.images import list_images
from ...files.poses import pose_line, read_poses
from ...pipelines.localize import (
    LocalizeConfig,
    estimate_pose,
    localize,
)
from ...pipelines.reconstruct import ReconstructConfig, reconstruct
from ...runtime import package_versions, run_record, shared_dir
from ...stages.colmap import colmap_log, log_prefix, open_database, require_pycolmap
from ...stages.database import camera_key
from ...stages.mapping import mapper_options, run_mapper
from ...stages.match import match_descriptors
from ..sfm import poses_of as model_poses

logger = logging.getLogger("sekd")
#: COLMAP's SIFT matcher defaults (SiftMatchingOptions: max_ratio 0.8, cross_check).
SIFT_RATIO = 0.8
#: Targets of issue #43 (docs/benchmarks.md): median rotation error and median position error / scene radius.
TARGET_ROTATION_DEG, TARGET_POSITION_PCT = 0.5, 1.0

Pose = tuple[np.ndarray, np.ndarray]  # world-to-camera (R 3x3, t 3)


@dataclass(frozen=True)
class Split:
    """Photo names of a scene: the reference photos and the held-out queries."""

    reference: list[str]
    queries: list[str]


def split(names: list[str], every: int = 3, offset: int = 2) -> Split:
    """Hold out ``names[offset::every]`` (sorted names; indices 2, 5, 8 of 11 by default)."""
    names = sorted(names)
    held = names[offset::every]
    return Split([n for n in names if n not in held], held)


def link_photos(source: Path, names: list[str], folder: Path) -> Path:
    """A folder of symbolic links to ``source/NAME`` for ``names`` (the shared photos are never copied)."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for name in names:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).symlink_to((source / name).resolve())
    return folder


def centre(pose: Pose) -> np.ndarray:
    """Camera centre (3) of a world-to-camera pose: -R^T t."""
    R, t = pose
    return -R.T @ t


def poses_file(path: Path) -> dict[str, Pose]:
    """An hloc poses file (``sekd localize``'s output) as world-to-camera (R, t) by name."""
    pycolmap = require_pycolmap()
    out = {}
    for name, (quat, t) in read_poses(path).items():
        out[name] = (np.asarray(pycolmap.Rotation3d(quat).matrix()), t)
    return out


def scene_radius(truth: dict[str, Pose]) -> float:
    """Median distance of the known camera centres to their centroid (the scale of the % errors)."""
    centres = np.array([centre(p) for p in truth.values()])
    return float(np.median(np.linalg.norm(centres - centres.mean(0), axis=1)))


def score(reference: dict[str, Pose], localized: dict[str, Pose], truth: dict[str, Pose], queries: list[str]) -> dict:
    """Errors of the ``localized`` queries against ``truth`` after aligning the ``reference`` model's centres to it."""
    pycolmap = require_pycolmap()
    common = sorted(set(reference) & set(truth))
    base = {"queries": len(queries), "localized": len([n for n in queries if n in localized]),
            "reference_registered": len(reference)}
    if len(common) < 3:
        return {**base, "failure": f"{len(common)} reference cameras to align to the known ones (need 3)"}
    src = np.array([centre(reference[n]) for n in common])
    tgt = np.array([centre(truth[n]) for n in common])
    sim = pycolmap.estimate_sim3d(src, tgt)  # truth_from_model
    if sim is None:
        return {**base, "failure": "similarity estimation failed"}
    scale, rotation = float(sim.scale), np.asarray(sim.rotation.matrix())
    translation = np.asarray(sim.translation)

    def to_truth(pose: Pose) -> Pose:  # the pose of the same camera in the known cameras' frame
        R = pose[0] @ rotation.T
        return R, -R @ (scale * rotation @ centre(pose) + translation)

    radius = scene_radius(truth)
    residuals = [float(np.linalg.norm(centre(to_truth(reference[n])) - centre(truth[n]))) for n in common]
    per_query = {}
    for name in queries:
        if name in localized and name in truth:
            pose = to_truth(localized[name])
            err_r = rotation_angle_deg(pose[0] @ truth[name][0].T)
            err_c = float(np.linalg.norm(centre(pose) - centre(truth[name])))
            per_query[name] = {"rotation_deg": err_r, "position": err_c, "position_pct": 100 * err_c / radius}
    rot = [q["rotation_deg"] for q in per_query.values()]
    pos = [q["position"] for q in per_query.values()]
    return {**base, "localized": len(per_query), "scene_radius": radius,
            "alignment_median_residual": float(np.median(residuals)),
            "alignment_median_residual_pct": 100 * float(np.median(residuals)) / radius,
            "median_rotation_deg": float(np.median(rot)) if rot else None,
            "median_position": float(np.median(pos)) if pos else None,
            "median_position_pct": 100 * float(np.median(pos)) / radius if pos else None,
            "max_rotation_deg": max(rot, default=None), "max_position_pct": max(
                (q["position_pct"] for q in per_query.values()), default=None), "per_query": per_query}


# ----------------------------------------------------------------------------- the two methods

def run_sekd(reference_photos: Path, query_photos: Path, work: Path, resize_max: int,
             num_threads: int | None) -> tuple[dict[str, Pose], dict[str, Pose], dict]:
    """``sekd reconstruct`` of the reference photos, then ``sekd localize`` of the queries: (reference, localized, info)."""
    shutil.rmtree(work, ignore_errors=True)
    start = time.perf_counter()
    config = ReconstructConfig(features=FeatureConfig(resize_max=resize_max))
    model = reconstruct(reference_photos, work / "reference", config, num_threads=num_threads, progress=False)
    built = time.perf_counter()
    results = localize(query_photos, work / "reference", work / "results.txt", LocalizeConfig(),
                       num_threads=num_threads, progress=False)
    done = time.perf_counter()
    log = json.loads((work / "results_log.json").read_text())
    info = {"reference_s": round(built - start, 1), "localize_s": round(done - built, 1),
            "queries": {n: {k: r.get(k) for k in ("status", "reason", "correspondences", "inliers", "camera_source")}
                        for n, r in log["queries"].items()}}
    return model_poses(require_pycolmap().Reconstruction(str(model))), poses_file(results), info


def _sift_options(resize_max: int, num_threads: int | None):
    pycolmap = require_pycolmap()
    options = pycolmap.FeatureExtractionOptions()
    options.max_image_size, options.num_threads = resize_max, num_threads or -1
    return options


def one_camera(photos: Path) -> bool:
    """Whether every photo below ``photos`` has the same ``camera_key`` (size, EXIF make/model/focal)."""
    return len({camera_key(photos / n) for n in list_images(photos)}) == 1


def sift_reference(photos: Path, work: Path, resize_max: int, seed: int, num_threads: int | None):
    """pycolmap's SIFT pipeline on ``photos`` (one shared camera when all photos have one camera key, else one
    camera per photo, as sekd's ``auto`` camera mode): the largest model and its database."""
    pycolmap = require_pycolmap()
    work.mkdir(parents=True, exist_ok=True)
    database = work / "database.db"
    mode = pycolmap.CameraMode.SINGLE if one_camera(photos) else pycolmap.CameraMode.PER_IMAGE
    with colmap_log(work / "colmap.log"):
        pycolmap.extract_features(str(database), str(photos), camera_mode=mode,
                                  extraction_options=_sift_options(resize_max, num_threads), device=pycolmap.Device.cpu)
        pycolmap.match_exhaustive(str(database), device=pycolmap.Device.cpu)
        models = run_mapper(database, photos, mapper_options([], seed), progress=False,
                            log_prefix=log_prefix(work / "colmap.log"))
    if not models:
        raise SekdError(f"{photos}: pycolmap's SIFT pipeline made no model")
    return models[0], database


def _sift_features(database: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Keypoints (N x 2, COLMAP pixels) and descriptors (N x 128 float32) of every image of a COLMAP database."""
    out = {}
    with open_database(database) as db:
        for image in db.read_all_images():
            keypoints = np.asarray(db.read_keypoints(image.image_id))[:, :2]
            descriptors = db.read_descriptors(image.image_id)
            descriptors = np.asarray(getattr(descriptors, "data", descriptors), dtype=np.float32)
            camera = db.read_camera(image.camera_id)
            out[image.name] = (keypoints.astype(np.float64), descriptors, camera)
    return out


def run_sift(reference_photos: Path, query_photos: Path, work: Path, resize_max: int, seed: int,
             num_threads: int | None) -> tuple[dict[str, Pose], dict[str, Pose], dict]:
    """The SIFT baseline (module docstring): (reference poses, localized query poses, per-query info)."""
    pycolmap = require_pycolmap()
    shutil.rmtree(work, ignore_errors=True)
    start = time.perf_counter()
    model, database = sift_reference(reference_photos, work / "reference", resize_max, seed, num_threads)
    built = time.perf_counter()
    queries_db = work / "queries.db"
    with colmap_log(work / "colmap-queries.log"):
        pycolmap.extract_features(str(queries_db), str(query_photos), camera_mode=pycolmap.CameraMode.PER_IMAGE,
                                  extraction_options=_sift_options(resize_max, num_threads), device=pycolmap.Device.cpu)
    reference_features, query_features = _sift_features(database), _sift_features(queries_db)
    ids = {model.image(i).name: i for i in model.reg_image_ids()}
    # sekd's camera rule: the reference's calibrated camera for photos of the same camera, else pycolmap's prior
    # (the queries database's camera: 1.2 x the long side without EXIF) with the focal length estimated.
    shared = model.camera(model.image(next(iter(ids.values()))).camera_id) if model.num_cameras() == 1 else None
    same = shared is not None and one_camera(reference_photos) and {
        camera_key(query_photos / n) for n in list_images(query_photos)} == {
        camera_key(reference_photos / n) for n in list_images(reference_photos)}
    localized, info = {}, {}
    lines = []
    for name in list_images(query_photos):
        query = query_features.get(name)
        camera = shared if same else (query[2] if query else None)
        record = _sift_localize_one(model, ids, camera, not same, reference_features, query)
        info[name] = {k: v for k, v in record.items() if k not in ("pose", "line")}
        if record.get("pose") is not None:
            localized[name] = record["pose"]
            lines.append(record["line"].replace("QUERY", name, 1))
    (work / "results.txt").write_text("".join(line + "\n" for line in lines))
    done = time.perf_counter()
    return model_poses(model), localized, {"reference_s": round(built - start, 1), "localize_s": round(done - built, 1),
                                           "queries": info}


def _sift_localize_one(model, ids: dict[str, int], camera, estimate_focal: bool, reference_features: dict,
                       query) -> dict:
    if query is None:
        return {"status": "failed", "reason": "no SIFT features"}
    pairs: set[tuple[int, int]] = set()  # (query keypoint, 3D point), once each as sekd localize counts them
    for name, image_id in ids.items():
        matches, _ = match_descriptors(query[1], reference_features[name][1], "both", SIFT_RATIO)
        image = model.image(image_id)
        for i in np.flatnonzero(matches >= 0):
            point = image.points2D[int(matches[i])]
            if point.has_point3D():
                pairs.add((int(i), int(point.point3D_id)))
    points2D = [query[0][i] for i, _ in sorted(pairs)]
    points3D = [model.point3D(p).xyz for _, p in sorted(pairs)]
    if len(points2D) < LocalizeConfig().min_inliers:
        return {"status": "failed", "reason": f"{len(points2D)} correspondences", "correspondences": len(points2D)}
    result = estimate_pose(np.array(points2D), np.array(points3D), camera, estimate_focal, LocalizeConfig())
    inliers = int(result["num_inliers"]) if result else 0
    record = {"status": "failed", "reason": f"{inliers} pose inliers", "correspondences": len(points2D),
              "inliers": inliers}
    if result is not None and inliers >= LocalizeConfig().min_inliers:
        pose = result["cam_from_world"]
        record.update(status="localized", reason=None, line=pose_line("QUERY", pose),
                      pose=(np.asarray(pose.rotation.matrix()), np.asarray(pose.translation)))
    return record


# ----------------------------------------------------------------------------- the benchmark

def resolve_scene(scene: str | Path) -> Path:
    """A scene folder with images/: ``scene`` itself or ``$SEKD_SHARED/data/sfm/<scene>``."""
    path = Path(scene)
    if not path.is_dir():
        path = shared_dir() / "data/sfm" / str(scene)
    if not (path / "images").is_dir():
        raise SekdError(f"{scene}: not a scene folder with images/ (looked in {path})")
    return path


def benchmark_scene(scene: str | Path, out: Path, resize_max: int = 1600, *, sift: bool = True, seed: int = 0,
                    num_threads: int | None = None, every: int = 3, offset: int = 2) -> dict:
    """One scene: both methods on the same split, scored against ground truth or pseudo ground truth."""
    scene = resolve_scene(scene)
    work = out / scene.name
    names = list_images(scene / "images")
    parts = split(names, every, offset)
    reference_photos = link_photos(scene / "images", parts.reference, work / "photos-reference")
    query_photos = link_photos(scene / "images", parts.queries, work / "photos-queries")
    has_truth = (scene / "gt_dense_cameras").is_dir()
    truth = {n: c.cam_from_world for n, c in read_cameras(scene / "gt_dense_cameras").items()} if has_truth else None
    methods = {"sekd": lambda w: run_sekd(reference_photos, query_photos, w, resize_max, num_threads)}
    if sift:
        methods["pycolmap SIFT"] = lambda w: run_sift(reference_photos, query_photos, w, resize_max, seed, num_threads)
    results = []
    for label, run in methods.items():
        reference, localized, info = run(work / label.replace(" ", "-"))
        row = {"method": label, **info}
        if truth is not None:
            row["ground_truth"] = {"kind": "ground truth", **score(reference, localized, truth, parts.queries)}
        else:
            row["pseudo_ground_truth"] = _pseudo_truth_scores(scene, work, label, reference, localized, parts.queries,
                                                              resize_max, seed, num_threads)
        results.append(row)
    return {"scene": scene.name, "images": len(names), "reference": parts.reference, "queries": parts.queries,
            "holdout": f"names[{offset}::{every}] of the sorted photo names", "ground_truth": has_truth,
            "results": results}


_FULL_CACHE: dict[tuple[str, str], dict[str, Pose]] = {}


def _full_reconstruction(scene: Path, work: Path, method: str, resize_max: int, seed: int,
                         num_threads: int | None) -> dict[str, Pose]:
    """Poses of ``method``'s reconstruction of all the scene's photos (pseudo ground truth)."""
    key = (str(work), method)
    if key not in _FULL_CACHE:
        folder = work / f"full-{method.replace(' ', '-')}"
        shutil.rmtree(folder, ignore_errors=True)
        if method == "sekd":
            config = ReconstructConfig(features=FeatureConfig(resize_max=resize_max))
            model = require_pycolmap().Reconstruction(str(reconstruct(scene / "images", folder, config,
                                                                      num_threads=num_threads, progress=False)))
        else:
            model, _ = sift_reference(scene / "images", folder, resize_max, seed, num_threads)
        _FULL_CACHE[key] = model_poses(model)
    return _FULL_CACHE[key]


def _pseudo_truth_scores(scene: Path, work: Path, label: str, reference: dict, localized: dict, queries: list[str],
                         resize_max: int, seed: int, num_threads: int | None) -> dict:
    """Scores against each method's full reconstruction (no ground truth: pseudo ground truth, labelled)."""
    scores = {}
    for source in ("sekd", "pycolmap SIFT"):
        full = _full_reconstruction(scene, work, source, resize_max, seed, num_threads)
        scores[f"{source} full reconstruction"] = {"kind": f"pseudo ground truth: {source} on all photos",
                                                   **score(reference, localized, full, queries)}
    return scores


def benchmark_localize(output_dir: str | Path, scenes: list[str], resize_max: int = 1600, *, sift: bool = True,
                       seed: int = 0, num_threads: int | None = None) -> dict:
    """Run ``benchmark_scene`` on each scene; write results.json (with the run record) and results.md."""
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = {"benchmark": "localization of held-out photos", "resize_max": resize_max, "seed": seed,
              "targets": {"median_rotation_deg": TARGET_ROTATION_DEG, "median_position_pct": TARGET_POSITION_PCT},
              "scenes": [benchmark_scene(s, out, resize_max, sift=sift, seed=seed, num_threads=num_threads)
                         for s in scenes],
              "versions": package_versions(), "record": run_record()}
    write_json(report, out / "results.json")
    (out / "results.md").write_text(markdown(report))
    return report


def _fmt(value, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def markdown(report: dict) -> str:
    """The benchmark as Markdown tables, one row per scene, method and (pseudo) ground truth."""
    lines = [(f"Localization of held-out photos (every third photo; long side <= {report['resize_max']} px). "
              "Errors after aligning each reference model to the known cameras (similarity of the reference "
              "camera centres); position in the known cameras' units and in % of the scene radius (median "
              "distance of the known camera centres to their centroid)."), "",
             ("| scene | method | scored against | reference registered | localized | median rot. err (deg) "
              "| median pos. err | "
              "median pos. err (% radius) | max rot. (deg) | max pos. (% radius) | alignment residual (% radius) "
              "| reference (s) | localize (s) |"),
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for scene in report["scenes"]:
        for row in scene["results"]:
            scored = ({"ground truth": row["ground_truth"]} if "ground_truth" in row else row["pseudo_ground_truth"])
            for against, s in scored.items():
                lines.append(f"| {scene['scene']} | {row['method']} | {against} "
                             f"| {s.get('reference_registered', '-')}/{len(scene['reference'])} | {s.get('localized', 0)}/"
                             f"{len(scene['queries'])} | {_fmt(s.get('median_rotation_deg'))} "
                             f"| {_fmt(s.get('median_position'), 4)} | {_fmt(s.get('median_position_pct'))} "
                             f"| {_fmt(s.get('max_rotation_deg'))} | {_fmt(s.get('max_position_pct'))} "
                             f"| {_fmt(s.get('alignment_median_residual_pct'))} | {row['reference_s']} "
                             f"| {row['localize_s']} |")
    failures = [f"- {scene['scene']}, {row['method']}, {against}: not scored: {s['failure']}"
                for scene in report["scenes"] for row in scene["results"]
                for against, s in ({"ground truth": row["ground_truth"]} if "ground_truth" in row
                                   else row["pseudo_ground_truth"]).items() if s.get("failure")]
    return "\n".join(lines + ([""] + failures if failures else [])) + "\n"
