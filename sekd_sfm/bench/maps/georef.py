"""``sekd bench maps georef``: camera-centre error of a georeferenced model against the GPS noise.

For a scene with known cameras in metres (Strecha layout: ``images/``, ``gt_dense_cameras/``;
fountain-P11, or a ``sekd bench scale`` scene), the true camera centres are turned by a random
rotation (seeded) about their centroid, placed at a WGS84 origin (default 46.5 N, 6.6 E, 400 m),
perturbed by isotropic Gaussian noise of ``sigma`` metres per axis (the same seeded draw at every level,
scaled by ``sigma``: levels differ in the noise's size only), and written as EXIF GPS into
copies of the photos (JPEG bytes kept: ``files.gps.write_gps``). Each noise level is
reconstructed end to end (``reconstruct`` with ``--gps auto``: GPS pairs + alignment); the
aligned model's camera centres are compared with the true centres in the same ENU frame (that of
georef.json's origin). Reported per level: the GPS error itself (what using the GPS positions as
the camera centres would give), the camera-centre error after alignment (median, mean, max;
3D and horizontal), the residuals and inliers; and, from ``repeats`` further noise draws aligned
to the same model (alignment only, no reconstruction), the mean of the median errors.

Files: ``OUTPUT/<scene>/sigma_<s>/images`` (the GPS copies), ``.../out`` (the reconstruction),
``OUTPUT/results.json`` and ``results.md``. Features and matches of the first level are
copied into the later levels' folders, where ``reconstruct`` reuses them (same pixels).
"""
from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ...evaluation.strecha import read_cameras
from ...files.atomic import write_json
from ...files.gps import GPSPosition, write_gps
from ...pipelines.reconstruct import ReconstructConfig, ReconstructionError, reconstruct
from ...pipelines.record import GEOREF, read_record
from ...runtime import package_versions, run_record
from ...stages.georef import (
    GpsConfig,
    camera_centres,
    enu_from_geodetic,
    geodetic_from_enu,
    robust_similarity,
)
from ..sfm import resolve_scene

logger = logging.getLogger("sekd")
DEFAULT_ORIGIN = GPSPosition(46.5, 6.6, 400.0)
DEFAULT_NOISE_M = (0.0, 0.1, 0.5, 2.0, 5.0)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random 3x3 rotation (QR of a Gaussian matrix, signs fixed)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def true_positions(scene: Path, seed: int) -> dict[str, np.ndarray]:
    """The scene's true camera centres (metres) turned by a seeded random rotation about their centroid:
    their ENU coordinates (3,) about the GPS origin, by image name."""
    cameras = read_cameras(scene / "gt_dense_cameras")
    names = sorted(cameras)
    centres = np.array([cameras[n].C for n in names])
    rotation = random_rotation(np.random.default_rng(seed))
    return dict(zip(names, (centres - centres.mean(0)) @ rotation.T))


def gps_copy(scene: Path, target: Path, truth: dict[str, np.ndarray], sigma_m: float, seed: int,
             origin: GPSPosition = DEFAULT_ORIGIN, altitude: bool = True) -> dict[str, np.ndarray]:
    """Copy ``scene``/images to ``target`` with EXIF GPS = ``truth`` + N(0, sigma_m^2) per axis (metres, ENU
    about ``origin``); photos without a true camera are copied without GPS. Returns the noisy ENU positions."""
    target.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    noisy = {name: p + rng.normal(0, sigma_m, 3) for name, p in truth.items()}
    lla = dict(zip(noisy, geodetic_from_enu(np.array(list(noisy.values())), origin)))
    for source in sorted((scene / "images").iterdir()):
        if source.name in lla:
            lat, lon, alt = lla[source.name]
            write_gps(source, target / source.name, GPSPosition(float(lat), float(lon), float(alt) if altitude else None))
        elif source.is_file():
            shutil.copyfile(source, target / source.name)
    return noisy


def centre_errors(model_centres: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> dict:
    """Distances (metres) between the model's camera centres and the true ones (same frame), 3D and horizontal."""
    names = sorted(set(model_centres) & set(truth))
    diff = np.array([model_centres[n] - truth[n] for n in names]).reshape(-1, 3)
    error, horizontal = np.linalg.norm(diff, axis=1), np.linalg.norm(diff[:, :2], axis=1)
    return {"images": len(names), "median_m": float(np.median(error)), "mean_m": float(error.mean()),
            "max_m": float(error.max()), "median_horizontal_m": float(np.median(horizontal)),
            "median_vertical_m": float(np.median(np.abs(diff[:, 2])))}


def _truth_in_model_frame(truth: dict[str, np.ndarray], origin: GPSPosition, georef: dict) -> dict[str, np.ndarray]:
    """``truth`` (ENU about ``origin``) in the ENU frame of georef.json's origin."""
    model_origin = GPSPosition(**georef["origin"])
    enu = enu_from_geodetic(geodetic_from_enu(np.array(list(truth.values())), origin), model_origin)
    return dict(zip(truth, enu))


def repeated_alignments(centres: dict[str, np.ndarray], truth: dict[str, np.ndarray], sigma_m: float, repeats: int,
                        seed: int, config: GpsConfig) -> dict:
    """The model's centres aligned to ``repeats`` fresh noisy GPS draws (alignment only): mean / spread of the
    median camera-centre error (metres) over the draws."""
    names = sorted(set(centres) & set(truth))
    src, tgt = np.array([centres[n] for n in names]), np.array([truth[n] for n in names])
    rng, medians = np.random.default_rng(seed + 1000), []
    for _ in range(repeats):
        fit = robust_similarity(src, tgt + rng.normal(0, sigma_m, tgt.shape), config.max_error_m)
        if fit is not None:
            medians.append(float(np.median(np.linalg.norm(np.asarray(fit[0] * src) - tgt, axis=1))))
    return {"repeats": repeats, "aligned": len(medians), "mean_median_m": float(np.mean(medians)) if medians else None,
            "std_median_m": float(np.std(medians)) if medians else None}


def run_level(scene: Path, work: Path, truth: dict[str, np.ndarray], sigma_m: float, config: ReconstructConfig,
              seed: int, repeats: int, reuse: Path | None, altitude: bool, num_threads: int | None) -> dict:
    """One noise level: GPS copies, reconstruction, errors. ``reuse``: an earlier level's output folder."""
    images, out = work / "images", work / "out"
    noisy = gps_copy(scene, images, truth, sigma_m, seed, altitude=altitude)
    gps_error = np.linalg.norm(np.array([noisy[n] - truth[n] for n in truth]), axis=1)
    if reuse is not None and not out.exists():
        out.mkdir(parents=True)
        for name in (*config.file_names, "features.global.h5"):
            if (reuse / name).is_file():
                shutil.copyfile(reuse / name, out / name)
    start, failure, row = time.perf_counter(), None, {"sigma_m": sigma_m}
    try:
        reconstruct(images, out, config, num_threads=num_threads, progress=False)
    except ReconstructionError as exc:
        failure = str(exc).splitlines()[0]
    row.update(wall_time_s=round(time.perf_counter() - start, 1), failure=failure,
               gps_error={"median_m": float(np.median(gps_error)), "mean_m": float(gps_error.mean())})
    stats = read_record(out) or {}
    row["registered_images"] = stats.get("model", {}).get("registered_images", 0)
    row["georeference"] = stats.get("georeference")
    georef_file = out / GEOREF
    if failure is None and georef_file.is_file():
        georef = json.loads(georef_file.read_text())
        from ...stages.colmap import require_pycolmap

        centres = camera_centres(require_pycolmap().Reconstruction(str(out / "model")))
        in_frame = _truth_in_model_frame(truth, DEFAULT_ORIGIN, georef)
        row["camera_centre_error"] = centre_errors(centres, in_frame)
        row["residuals"] = {k: georef[k] for k in ("median_residual_m", "max_residual_m", "inliers", "aligned_images",
                                                   "inlier_threshold_m", "scale", "residuals")}
        row["alignment_only"] = repeated_alignments(centres, in_frame, sigma_m, repeats, seed, config.gps)
    return row


def benchmark_georef(scenes: list[str], output_dir: str | Path, config: ReconstructConfig, *,
                     noise_m: tuple[float, ...] = DEFAULT_NOISE_M, repeats: int = 20, seed: int = 0,
                     altitude: bool = True, num_threads: int | None = None) -> dict:
    """Every scene at every noise level (``run_level``); writes results.json and results.md in ``output_dir``."""
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    config = replace(config, gps=replace(config.gps, mode="auto"))
    report = {"origin": DEFAULT_ORIGIN.__dict__, "noise_m": list(noise_m), "repeats": repeats, "seed": seed,
              "altitude": altitude, "resize_max": config.features.resize_max, "gps_config": config.gps.__dict__,
              "scenes": [], "versions": package_versions(), "record": run_record()}
    for scene_name in scenes:
        scene = resolve_scene(scene_name)
        truth, rows, reuse = true_positions(scene, seed), [], None
        for sigma in noise_m:
            work = out / scene.name / f"sigma_{sigma:g}"
            logger.info("georef benchmark: %s, GPS noise %g m", scene.name, sigma)
            rows.append(run_level(scene, work, truth, sigma, config, seed, repeats, reuse, altitude, num_threads))
            reuse = reuse or work / "out"
        spread = np.linalg.svd(np.array(list(truth.values())) - np.mean(list(truth.values()), 0), compute_uv=False)
        report["scenes"].append({"scene": str(scene), "cameras": len(truth),
                                 "camera_spread_m": [round(float(s / np.sqrt(len(truth))), 2) for s in spread],
                                 "levels": rows})
        write_json(report, out / "results.json")
    (out / "results.md").write_text(georef_markdown(report))
    return report


def _fmt(value, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _row(label: str, cameras: int, row: dict) -> str:
    err, geo = row.get("camera_centre_error", {}), row.get("georeference") or {}
    res, only = row.get("residuals", {}), row.get("alignment_only", {})
    state = "yes" if geo.get("georeferenced") else f"no: {geo.get('reason') or row.get('failure')}"
    cells = [label, f"{row['sigma_m']:g}", _fmt(row["gps_error"]["median_m"]), f"{row['registered_images']}/{cameras}",
             state, f"{res.get('inliers', '-')}/{res.get('aligned_images', '-')}", _fmt(err.get("median_m")),
             _fmt(err.get("mean_m")), _fmt(err.get("max_m")), _fmt(err.get("median_horizontal_m")),
             _fmt(only.get("mean_median_m")), str(row["wall_time_s"])]
    return "| " + " | ".join(cells) + " |"


def georef_markdown(report: dict) -> str:
    """The results as a Markdown table, one row per scene and noise level."""
    origin = report["origin"]
    intro = (f"EXIF GPS = true camera centres (randomly rotated, seed {report['seed']}) + Gaussian noise of sigma "
             f"metres per axis, origin {origin['latitude']} N {origin['longitude']} E {origin['altitude']} m, "
             f"altitude {'written' if report['altitude'] else 'left out'}; --resize-max {report['resize_max']}. "
             "Errors in metres against the true centres in the model's ENU frame; GPS error = distance of the "
             "written GPS position from the true centre.")
    header = ["scene (spread m)", "sigma", "GPS error median", "registered", "georeferenced", "inliers",
              "centre error median", "mean", "max", "horizontal median",
              f"alignment only: mean of medians ({report['repeats']} draws)", "wall (s)"]
    lines = [intro, "", "| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for scene in report["scenes"]:
        path = Path(scene["scene"])
        name = path.name if path.name != "scene" else f"{path.parent.name}/{path.name}"  # a bench scale folder
        label = f"{name} ({'/'.join(f'{s:g}' for s in scene['camera_spread_m'])})"
        lines += [_row(label, scene["cameras"], row) for row in scene["levels"]]
    return "\n".join(lines) + "\n"
