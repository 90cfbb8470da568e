"""SfM benchmarks on a scene with ground-truth cameras (Strecha layout: ``images/``, ``gt_dense_cameras/``).

* ``benchmark_sfm`` (``sekd bench sfm``): our pipeline (extract -> pairs -> match ->
  COLMAP) and pycolmap's own SIFT pipeline on the same images, side by side: registered
  images, median pairwise rotation / translation-direction error against the ground
  truth, and wall time.
* ``benchmark_ratios`` (``sekd bench ratios``): how the matches' precision and number
  of correct matches change with the ratio-test threshold, per feature type; the
  source of ``match.DEFAULT_RATIO``.
"""
from __future__ import annotations

import logging
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..evaluation.metrics import fundamental_matrix, mean_average_accuracy, pose_auc
from ..features import FeatureConfig
from ..files.atomic import write_json
from ..files.features import read_attrs, read_features
from ..pipelines.reconstruct import ReconstructConfig, ReconstructionError, reconstruct
from ..pipelines.record import read_record
from ..runtime import package_versions, run_record, shared_dir
from ..stages.colmap import colmap_log, log_prefix, require_pycolmap
from ..stages.extract import extract_features
from ..stages.mapping import mapper_options, run_mapper
from ..stages.match import MatchConfig, describe_config, match_descriptors
from .strecha import StrechaCamera, pairwise_errors, read_cameras, relative_pose

logger = logging.getLogger("sekd")
#: Ratio thresholds swept by ``benchmark_ratios``.
RATIO_GRID = tuple(float(round(r, 2)) for r in np.arange(0.60, 1.0001, 0.05))
#: A match is correct when its symmetric epipolar distance under the ground truth is below this (original pixels).
EPIPOLAR_THRESHOLD_PX = 4.0
#: The ratio chosen as default is the one with the most correct matches among those with at least this precision.
MIN_PRECISION = 0.9


def resolve_scene(scene: str | Path) -> Path:
    """A scene folder: ``scene`` itself, or ``$SEKD_SHARED/data/sfm/<scene>``; SekdError if it lacks images/GT."""
    path = Path(scene)
    if not path.is_dir():
        path = shared_dir() / "data/sfm" / str(scene)
    if not (path / "images").is_dir() or not (path / "gt_dense_cameras").is_dir():
        raise SekdError(f"{scene}: not a scene folder with images/ and gt_dense_cameras/ (looked in {path})")
    return path


def poses_of(reconstruction) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World-to-camera ``(R, t)`` of every registered image of a pycolmap reconstruction, by name."""
    poses = {}
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.image(image_id)
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        poses[image.name] = (np.asarray(pose.rotation.matrix()), np.asarray(pose.translation))
    return poses


def evaluate(reconstruction, truth: dict[str, StrechaCamera]) -> dict:
    """Registered images and pairwise pose errors of a reconstruction against ground truth.

    ``maa`` is the mean average accuracy (1..10 deg) of the pose error max(rotation,
    translation direction) over ALL ground-truth pairs: a pair with an unregistered image
    counts as a failure (docs/method.md, Evaluation protocols); ``auc1`` / ``auc5`` the area
    under its accuracy curve up to 1 / 5 deg (``auc1`` still separates maps that ``maa`` rates 1.0).
    """
    if reconstruction is None:
        return {"registered_images": 0, "median_rotation_deg": None, "median_translation_deg": None, "maa": 0.0,
                "auc1": 0.0, "auc5": 0.0}
    errors = pairwise_errors(poses_of(reconstruction), truth)
    all_pairs = len(truth) * (len(truth) - 1) // 2
    pose_errors = [max(r, t) for r, t in zip(errors["rotation_deg"], errors["translation_deg"])]
    pose_errors += [float("inf")] * (all_pairs - len(pose_errors))
    return {
        "registered_images": int(reconstruction.num_reg_images()),
        "points3D": int(reconstruction.num_points3D()),
        "mean_track_length": float(reconstruction.compute_mean_track_length()),
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "median_rotation_deg": errors["median_rotation_deg"],
        "median_translation_deg": errors["median_translation_deg"],
        "max_rotation_deg": max(errors["rotation_deg"], default=None),
        "maa": mean_average_accuracy(pose_errors),
        "auc1": pose_auc(pose_errors, 1.0),
        "auc5": pose_auc(pose_errors, 5.0),
        "pairs_evaluated": errors["pairs"],
    }


def run_ours(scene: Path, work: Path, config: ReconstructConfig, num_threads: int | None, label: str | None = None) -> dict:
    """Our whole pipeline from scratch into ``work``: evaluation, wall time and per-stage times."""
    shutil.rmtree(work, ignore_errors=True)
    start, failure = time.perf_counter(), None
    try:
        reconstruct(scene / "images", work, config, num_threads=num_threads, progress=False)
    except ReconstructionError as exc:
        failure = str(exc).splitlines()[0]
    wall = time.perf_counter() - start
    model = work / "model"
    reconstruction = require_pycolmap().Reconstruction(str(model)) if model.is_dir() else None
    stats = read_record(work) or {}
    return {"method": label or f"sekd pipeline ({config.features.feature}, {config.mapper_type} mapper)",
            "wall_time_s": round(wall, 1),
            "stage_times_s": stats.get("timings_s", {}), "failure": failure,
            **evaluate(reconstruction, read_cameras(scene / "gt_dense_cameras"))}


def run_pycolmap_sift(scene: Path, work: Path, resize_max: int, camera_mode: str, seed: int,
                      num_threads: int | None) -> dict:
    """pycolmap's own pipeline (SIFT extraction, exhaustive matching, incremental mapping) on the same images."""
    pycolmap = require_pycolmap()
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    database, times = work / "database.db", {}
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size, extraction.num_threads = resize_max, num_threads or -1
    mode = getattr(pycolmap.CameraMode, camera_mode.upper().replace("-", "_"))
    start = time.perf_counter()
    with colmap_log(work / "colmap.log"):
        pycolmap.extract_features(str(database), str(scene / "images"), camera_mode=mode,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        times["extract"] = time.perf_counter() - start
        pycolmap.match_exhaustive(str(database), device=pycolmap.Device.cpu)
        times["match+verification"] = time.perf_counter() - start - times["extract"]
        models = run_mapper(database, scene / "images", mapper_options([], seed), progress=False,
                            log_prefix=log_prefix(work / "colmap.log"))
    wall = time.perf_counter() - start
    times["mapping"] = wall - times["extract"] - times["match+verification"]
    return {"method": "pycolmap SIFT pipeline", "wall_time_s": round(wall, 1),
            "stage_times_s": {k: round(v, 1) for k, v in times.items()}, "failure": None if models else "no model",
            **evaluate(models[0] if models else None, read_cameras(scene / "gt_dense_cameras"))}


def benchmark_sfm(scene: str | Path, output_dir: str | Path, config: ReconstructConfig, *, baseline: bool = True,
                  num_threads: int | None = None, methods: list | None = None) -> dict:
    """Run our pipeline (once per ``methods`` entry, else with ``config.features``) and pycolmap's SIFT
    unless ``baseline`` is False on ``scene``; write results.json and results.md.

    ``methods`` are ``bench.methods.Method``; each replaces the feature type and weights of
    ``config``. Images are limited to ``config.features.resize_max`` px for every pipeline.
    """
    scene, out = resolve_scene(scene), Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    truth = read_cameras(scene / "gt_dense_cameras")
    runs = [(None, config)] if not methods else [(m.label, _with_method(config, m)) for m in methods]
    results = [run_ours(scene, out / (label or "ours"), cfg, num_threads, label) for label, cfg in runs]
    if baseline:
        results.append(run_pycolmap_sift(scene, out / "pycolmap", config.features.resize_max or 3200,
                                         config.camera.mode, config.seed, num_threads))
    report = {"scene": str(scene), "images": len(truth), "resize_max": config.features.resize_max,
              "results": results, "versions": package_versions(), "record": run_record()}
    write_json(report, out / "results.json")
    (out / "results.md").write_text(sfm_markdown(report))
    return report


def _with_method(config: ReconstructConfig, method) -> ReconstructConfig:
    features = replace(config.features, feature=method.feature, weights=method.weights)
    return replace(config, features=features)


def _fmt(value, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def sfm_markdown(report: dict) -> str:
    """The benchmark as a Markdown table."""
    lines = [(f"SfM on `{Path(report['scene']).name}` ({report['images']} images, long side <= "
              f"{report['resize_max']} px); pose errors are medians over all pairs of registered images."), "",
             ("| method | registered | pose mAA@1:10 | pose AUC@1 | pose AUC@5 | median rot. err (deg) "
              "| median transl. dir. err (deg) | reproj. err (px) | 3D points | track length | wall time (s) |"),
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["results"]:
        lines.append(f"| {r['method']} | {r['registered_images']}/{report['images']} | {_fmt(r.get('maa'))} "
                     f"| {_fmt(r.get('auc1'))} | {_fmt(r.get('auc5'))} "
                     f"| {_fmt(r['median_rotation_deg'])} | {_fmt(r['median_translation_deg'])} "
                     f"| {_fmt(r.get('mean_reprojection_error_px'))} | {r.get('points3D', 0)} "
                     f"| {_fmt(r.get('mean_track_length'), 2)} | {r['wall_time_s']:.1f} |")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- ratio benchmark

def fundamental(cam0: StrechaCamera, cam1: StrechaCamera) -> np.ndarray:
    """F with ``x1^T F x0 = 0`` for pixel points of the two ground-truth cameras."""
    R, t = relative_pose(cam0.cam_from_world, cam1.cam_from_world)
    return fundamental_matrix(cam0.K, cam1.K, R, t)


def epipolar_distances(x0: np.ndarray, x1: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Symmetric epipolar distance (pixels) of ``M x 2`` point matches: max of the two point-to-line distances."""
    h0, h1 = np.c_[x0, np.ones(len(x0))], np.c_[x1, np.ones(len(x1))]
    l1, l0 = h0 @ F.T, h1 @ F  # epipolar lines in image 1 and image 0
    num = np.abs(np.sum(h1 * l1, axis=1))
    return np.maximum(num / np.linalg.norm(l1[:, :2], axis=1), num / np.linalg.norm(l0[:, :2], axis=1))


def _pair_ratios(f0: dict, f1: dict, F: np.ndarray, mode: str, rootsift: bool) -> tuple[np.ndarray, np.ndarray]:
    """Every match with the ratio test off: its d1/d2 and whether it is correct under the ground truth."""
    matches, scores = match_descriptors(f0["descriptors"], f1["descriptors"], mode, 1.0, rootsift)
    idx = np.flatnonzero(matches >= 0)
    correct = epipolar_distances(f0["keypoints"][idx], f1["keypoints"][matches[idx]], F) < EPIPOLAR_THRESHOLD_PX
    return 1.0 - scores[idx].astype(np.float64), correct


def ratio_curve(features: Path, truth: dict[str, StrechaCamera], pairs: list[tuple[str, str]], mode: str,
                rootsift: bool, grid=RATIO_GRID) -> list[dict]:
    """Matches and correct matches per pair, and precision, at each ratio threshold of ``grid``."""
    cache = {name: read_features(features, name) for name in {n for p in pairs for n in p}}
    per_pair = [_pair_ratios(cache[a], cache[b], fundamental(truth[a], truth[b]), mode, rootsift) for a, b in pairs]
    rows = []
    for r in grid:
        kept = [(ratios < r, correct) for ratios, correct in per_pair]
        total, good = sum(int(k.sum()) for k, _ in kept), sum(int((k & c).sum()) for k, c in kept)
        rows.append({"ratio": r, "matches_per_pair": total / len(pairs), "correct_per_pair": good / len(pairs),
                     "precision": good / total if total else 0.0})
    return rows


def choose_ratio(rows: list[dict], min_precision: float = MIN_PRECISION) -> float | None:
    """The ratio with the most correct matches among those whose precision is at least ``min_precision``."""
    ok = [r for r in rows if r["precision"] >= min_precision]
    return max(ok, key=lambda r: (r["correct_per_pair"], -r["ratio"]))["ratio"] if ok else None


def benchmark_ratios(scene: str | Path, output_dir: str | Path, features: list[str], base: FeatureConfig,
                     max_gap: int = 4, num_threads: int | None = None) -> dict:
    """Sweep the ratio threshold for each feature type on the pairs (i, i+1..i+max_gap) of ``scene``.

    Features are extracted (resumably) into ``output_dir``; writes ratios.json and ratios.md.
    """
    scene, out = resolve_scene(scene), Path(output_dir)
    truth = read_cameras(scene / "gt_dense_cameras")
    names = sorted(truth)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1: i + 1 + max_gap]]
    report = {"scene": str(scene), "pairs": len(pairs), "epipolar_threshold_px": EPIPOLAR_THRESHOLD_PX,
              "min_precision": MIN_PRECISION, "resize_max": base.resize_max, "max_keypoints": base.max_keypoints,
              "features": {}, "versions": package_versions(), "record": run_record()}
    for feature in features:
        # --weights is SEKD's checkpoint; the learned peers load their own local weights.
        config = replace(base, feature=feature, weights=base.weights if feature == "sekd" else None)
        path = extract_features(scene / "images", out / f"features-{feature}.h5", config, num_threads=num_threads,
                                progress=False)
        binary = str(read_attrs(path)["descriptor_dtype"]) == "uint8"
        rootsift = describe_config(MatchConfig(), feature, binary)["rootsift"]
        curves = {mode: ratio_curve(path, truth, pairs, mode, rootsift) for mode in ("both", "ratio")}
        report["features"][feature] = {"curves": curves, "rootsift": rootsift,
                                       "chosen_ratio": {m: choose_ratio(c) for m, c in curves.items()}}
        logger.info("%s: chosen ratio %s", feature, report["features"][feature]["chosen_ratio"])
    write_json(report, out / "ratios.json")
    (out / "ratios.md").write_text(ratios_markdown(report))
    return report


def ratios_markdown(report: dict) -> str:
    """Per feature type: matches, correct matches per pair and precision at each ratio (mutual NN + ratio)."""
    lines = [(f"Ratio sweep on `{Path(report['scene']).name}`, {report['pairs']} pairs, mutual nearest neighbours + "
              f"ratio test; correct = symmetric epipolar distance < {report['epipolar_threshold_px']} px under the "
              "ground truth."), ""]
    for feature, data in report["features"].items():
        lines += [(f"**{feature}** (chosen: {data['chosen_ratio']['both']}; ratio test alone: "
                   f"{data['chosen_ratio']['ratio']})"), "", "| ratio | matches/pair | correct/pair | precision |",
                  "|---|---|---|---|"]
        lines += [f"| {r['ratio']:.2f} | {r['matches_per_pair']:.0f} | {r['correct_per_pair']:.0f} | {r['precision']:.3f} |"
                  for r in data["curves"]["both"]]
        lines.append("")
    return "\n".join(lines)
