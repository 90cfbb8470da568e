"""``sekd bench maps triangulate``: points triangulated from the true poses of a scene against a free reconstruction.

The scene's ground-truth cameras (Strecha ``.camera`` files: K with the first pixel's centre at 0, OpenCV's
convention) become a COLMAP text model (one PINHOLE camera per photo, principal point + 0.5 px: COLMAP's
convention) and an hloc poses file in the work folder. ``sekd triangulate`` runs on both (the same points
are expected), then ``sekd reconstruct`` on the same photos with the same extraction, matching and keypoint
refinement (features and matches copied from the triangulation, so both start from the same matches).
Reported per run: points, observations, mean / median track length, mean reprojection error; for the free
model also its pose errors against the ground truth (``bench.sfm.evaluate``).
"""
from __future__ import annotations

import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ...evaluation.strecha import StrechaCamera, read_cameras
from ...files.atomic import write_json
from ...pipelines.reconstruct import ReconstructConfig, reconstruct
from ...pipelines.record import Record
from ...pipelines.triangulate import TriangulateConfig, triangulate, triangulation_stats
from ...runtime import cpu_text, package_versions, run_record
from ...stages.colmap import require_pycolmap
from ..sfm import evaluate, resolve_scene


def _number(value: float) -> str:
    return repr(float(value))  # the shortest text that reads back as the same double


def write_ground_truth(truth: dict[str, StrechaCamera], folder: Path) -> tuple[Path, Path, str]:
    """``folder``/gt_model (COLMAP text: cameras.txt, images.txt, an empty points3D.txt; ids 1.. in name order)
    and ``folder``/gt_poses.txt (``NAME qw qx qy qz tx ty tz``). Also returns the first camera's PINHOLE
    parameters as --camera-params text (COLMAP pixels), for the poses file."""
    pycolmap = require_pycolmap()
    model = folder / "gt_model"
    model.mkdir(parents=True, exist_ok=True)
    cameras, images, poses = [], [], []
    for image_id, (name, camera) in enumerate(sorted(truth.items()), 1):
        K = camera.K
        params = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]  # COLMAP: first pixel's centre at 0.5
        cameras.append(f"{image_id} PINHOLE {camera.width} {camera.height} {' '.join(map(_number, params))}")
        R, t = camera.cam_from_world
        x, y, z, w = pycolmap.Rotation3d(R).quat
        pose = " ".join(map(_number, (w, x, y, z, *t)))
        images.append(f"{image_id} {pose} {image_id} {name}\n")  # and an empty line: no 2D points
        poses.append(f"{name} {pose}")
    (model / "cameras.txt").write_text("\n".join(cameras) + "\n")
    (model / "images.txt").write_text("\n".join(images) + "\n")
    (model / "points3D.txt").write_text("")
    (folder / "gt_poses.txt").write_text("\n".join(poses) + "\n")
    first = truth[min(truth)].K
    return model, folder / "gt_poses.txt", ",".join(map(_number, (first[0, 0], first[1, 1], first[0, 2] + 0.5,
                                                                  first[1, 2] + 0.5)))


def _run_triangulation(images: Path, poses: Path, work: Path, config: TriangulateConfig,
                       num_threads: int | None, label: str) -> dict:
    start = time.perf_counter()
    triangulate(images, poses, work, config, num_threads=num_threads, progress=False)
    wall = time.perf_counter() - start
    stats = Record.from_record(work, needs="model").data
    return {"method": label, "wall_time_s": round(wall, 1), "stage_times_s": stats["timings_s"],
            "core_stage_s": stats["timings_s"]["triangulation"],
            "pairs": stats["pairs"], "verified_pairs": stats["verified_pairs"], **stats["model"]}


def _run_free(images: Path, work: Path, config: ReconstructConfig, num_threads: int | None,
              truth: dict[str, StrechaCamera]) -> dict:
    start = time.perf_counter()
    model_path = reconstruct(images, work, config, num_threads=num_threads, progress=False)
    wall = time.perf_counter() - start
    model = require_pycolmap().Reconstruction(str(model_path))
    stats = Record.from_record(work, needs="model").data
    errors = evaluate(model, truth)
    return {"method": "free reconstruction (sekd reconstruct)", "wall_time_s": round(wall, 1),
            "stage_times_s": stats.get("timings_s", {}), "core_stage_s": stats.get("timings_s", {}).get("mapping"),
            "pairs": stats.get("matches", {}).get("pairs_with_matches"), **triangulation_stats(model),
            **{k: errors[k] for k in ("median_rotation_deg", "median_translation_deg", "auc1", "auc5")}}


def benchmark_triangulation(scene: str | Path, output_dir: str | Path, config: TriangulateConfig, *,
                            num_threads: int | None = None) -> dict:
    """Triangulate ``scene`` from its true poses (model and poses file) and reconstruct it freely; write
    results.json and results.md into ``output_dir`` (work folders beside them). Returns the report."""
    scene, out = resolve_scene(scene), Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    truth = read_cameras(scene / "gt_dense_cameras")
    images = scene / "images"
    model, poses, params = write_ground_truth(truth, out)
    runs = [_run_triangulation(images, model, out / "triangulated", config, num_threads,
                               "triangulated from the true poses (COLMAP model)")]
    by_file = replace(config, camera_model="PINHOLE", camera_params=params)
    shutil.rmtree(out / "triangulated_file", ignore_errors=True)
    _copy_inputs(out / "triangulated", out / "triangulated_file", config.file_names)
    runs.append(_run_triangulation(images, poses, out / "triangulated_file", by_file, num_threads,
                                   "triangulated from the true poses (poses file + --camera-params)"))
    free = ReconstructConfig(features=config.features, matching=config.matching, refine=config.refine,
                             seed=config.seed, file_names=config.file_names)
    free.pairs.mode = "exhaustive"
    shutil.rmtree(out / "free", ignore_errors=True)
    _copy_inputs(out / "triangulated", out / "free", config.file_names)
    runs.append(_run_free(images, out / "free", free, num_threads, truth))
    # The free reconstruction matched every pair; triangulating from those same pairs isolates the poses' effect.
    shutil.rmtree(out / "triangulated_all_pairs", ignore_errors=True)
    _copy_inputs(out / "free", out / "triangulated_all_pairs", config.file_names)
    runs.append(_run_triangulation(images, model, out / "triangulated_all_pairs", replace(config, max_angle_deg=180.0),
                                   num_threads, "triangulated from the true poses, every pair (--max-angle 180)"))
    report = {"scene": str(scene), "images": len(truth), "resize_max": config.features.resize_max,
              "config": Record.from_record(out / "triangulated").config_data,
              "results": runs, "versions": package_versions(), "record": run_record()}
    write_json(report, out / "results.json")
    (out / "results.md").write_text(triangulation_markdown(report))
    return report


def _copy_inputs(source: Path, target: Path, names: tuple[str, str]) -> None:
    """The features and matches of ``source`` into ``target``: reused there, so both runs share them."""
    target.mkdir(parents=True, exist_ok=True)
    for name in names:
        shutil.copy(source / name, target / name)


def _fmt(value, digits: int = 3) -> str:
    return "-" if value is None or (isinstance(value, float) and np.isnan(value)) else f"{value:,.{digits}f}"


def triangulation_markdown(report: dict) -> str:
    """The benchmark as a Markdown table."""
    record = report["record"]
    lines = [(f"# Triangulation from known poses: {Path(report['scene']).name} ({report['images']} photos, "
              f"long side {report['resize_max']} px)"), "",
             f"sekd {record['sekd_sfm']} ({record['commit']}), {record['date']}, {cpu_text(record['cpu'])}", "",
             ("| run | pairs | photos with points | points | observations | mean track | median track "
              "| mean reproj. (px) | median rot. err. (deg) | median transl. err. (deg) | triangulation / mapping (s) "
              "| wall (s) |"),
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["results"]:
        lines.append(f"| {r['method']} | {r.get('pairs') or '-'} | {r['images_with_points']}/{report['images']} "
                     f"| {r['points3D']:,} "
                     f"| {r['observations']:,} | {_fmt(r['mean_track_length'], 2)} | {_fmt(r['median_track_length'], 1)} "
                     f"| {_fmt(r['mean_reprojection_error_px'])} | {_fmt(r.get('median_rotation_deg'))} "
                     f"| {_fmt(r.get('median_translation_deg'))} | {_fmt(r.get('core_stage_s'), 1)} "
                     f"| {r['wall_time_s']:.1f} |")
    lines += ["", ("Pose errors: the free model's pairwise relative poses against the ground truth (the triangulated "
                   "models hold the ground truth itself). The free reconstruction reuses the triangulation's features "
                   "and matches (plus the pairs the poses left out: cameras more than 60 degrees apart); the last run "
                   "triangulates from the free run's matches, every pair. Wall times include extraction in the first "
                   "run only (the others reuse its features) and keypoint refinement in every run.")]
    return "\n".join(lines) + "\n"
