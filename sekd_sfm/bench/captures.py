"""``sekd bench captures KIND``: ``sekd reconstruct`` on a generated capture with known cameras
(``scale/captures.py``), scored against the truth. In ``OUT/<kind>/``:

* ``scene/``: the capture; ``ours/``: reconstruct's folder; ``baseline/``: the baseline's (video:
  every ``BASELINE_EVERY``-th frame as photos, from ``frames/``; rig: the same photos without the rig);
  ``<run>-run.json``: a finished run's wall time (a rerun reuses it); ``results.json`` (``run_record()``,
  settings, figures) and ``results.md``.

Pose AUC@5/10/20 is over all pairs (the larger of the relative rotation and translation-direction
errors; a pair with an unregistered image fails). Per kind:

* video: keyframes (``OUT/images/keyframes.json``), the blurred among them, registered, seconds of
  video in gaps of more than ``MAX_GAP_S`` between registered keyframes, models, AUC over keyframe pairs;
* rig: registered photos, AUC, the model's camera 1 from rig against the truth (rotation, translation
  direction; deg), and per instant with both photos registered the relative rotation of its two cameras
  against the truth (median, max; deg): what a free reconstruction (the baseline) gets wrong;
* panorama: panoramas posed (``OUT/panoramas.txt``: ``NAME qw qx qy qz tx ty tz`` world-to-panorama), AUC,
  median rotation error.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass
from itertools import combinations, pairwise
from pathlib import Path

import cv2
import numpy as np

from ..errors import SekdError
from ..evaluation.metrics import pose_auc, rotation_angle_deg, translation_error_deg
from ..files.atomic import write_atomic
from ..stages.rig import quat_to_matrix
from .scale.run import pair_rotation_translation_errors, registered_poses

logger = logging.getLogger("sekd")
KINDS = ("video", "rig", "panorama")
DEFAULT_COUNTS = {"video": 600, "rig": 50, "panorama": 30}
BASELINE_EVERY = 5
MAX_GAP_S = 1.0
COLUMNS = {"video": ("keyframes", "blurred_keyframes_pct", "registered", "gap_s", "models", "auc5", "auc10", "auc20",
                     "wall_s"),
           "rig": ("registered", "images", "auc5", "auc10", "auc20", "rig_rotation_error_deg",
                   "rig_translation_error_deg", "instant_rotation_median_deg", "instant_rotation_max_deg", "models",
                   "wall_s"),
           "panorama": ("posed", "images", "auc5", "auc10", "auc20", "median_rotation_error_deg", "models",
                        "wall_s")}


@dataclass
class CapturesConfig:
    """One benchmark run: ``count`` video frames / rig instants / panoramas (None: ``DEFAULT_COUNTS``),
    ``image_size`` the photos' long side (None: 640) or the panoramas' width (None: 2048)."""

    kind: str
    count: int | None = None
    image_size: int | None = None
    seed: int = 0
    baseline: bool = True
    num_threads: int | None = None
    textures: str | None = None
    #: Metres between panoramas (None: ``scale.captures.PANORAMA_SPACING_M``).
    spacing: float | None = None


def generate(scene_dir: Path, config: CapturesConfig, progress: bool = True) -> Path:
    """The capture of ``config`` in ``scene_dir`` (reused when finished); returns its scene.json."""
    from .scale import captures
    from .scale.scene import SceneConfig

    count = config.count or DEFAULT_COUNTS[config.kind]
    if config.kind == "panorama":
        return captures.render_panoramas(scene_dir, SceneConfig(seed=config.seed, textures=config.textures), count,
                                         config.image_size or 2048, progress,
                                         config.spacing or captures.PANORAMA_SPACING_M)
    scene = SceneConfig(image_size=config.image_size or 640, seed=config.seed, textures=config.textures)
    if config.kind == "rig":
        return captures.render_rig(scene_dir, scene, count, progress=progress)
    return captures.render_video(scene_dir, scene, count, progress=progress)


def run_reconstruct(source: Path, work: Path, config, num_threads: int | None) -> dict:
    """``reconstruct(source, work, config)``: ``{"wall_s", "failure", "models"}``, kept in ``<work>-run.json``;
    a run recorded there with the same configuration is not run again."""
    from ..pipelines.config import config_dict
    from ..pipelines.reconstruct import ReconstructionError, reconstruct
    from ..pipelines.record import read_record

    marker = work.with_name(work.name + "-run.json")
    settings = json.loads(json.dumps(config_dict(config)))  # as read back: tuples become lists
    if marker.is_file() and json.loads(marker.read_text()).get("config") == settings:
        return json.loads(marker.read_text())
    start, failure = time.perf_counter(), None
    logger.info("reconstruct %s -> %s", source, work)
    try:
        reconstruct(source, work, config, num_threads=num_threads, progress=False)
    except ReconstructionError as exc:
        failure = str(exc).splitlines()[0]
    done = {"config": settings, "wall_s": round(time.perf_counter() - start, 1), "failure": failure,
            "models": len((read_record(work) or {}).get("models") or [])}
    write_atomic(marker, json.dumps(done, indent=1))
    return done


# ----------------------------------------------------------------------------- scores

def pose_scores(estimated: dict, truth: dict, names: list[str]) -> dict:
    """Registered ``names``, pose AUC@5/10/20 over all their pairs and the median rotation error (deg) of the
    pairs of registered images. ``estimated``: name -> world-to-camera (R, t); ``truth``: name -> Camera."""
    pairs = np.array(list(combinations(range(len(names)), 2)), np.int64).reshape(-1, 2)
    rotation, translation = pair_rotation_translation_errors(estimated, truth, names, pairs)
    errors = np.maximum(rotation, translation)
    finite = np.isfinite(errors)
    return {"registered": sum(n in estimated for n in names), "images": len(names),
            **{f"auc{k}": round(pose_auc(errors.tolist(), k), 4) for k in (5, 10, 20)},
            "median_rotation_error_deg": round(float(np.median(rotation[finite])), 3) if finite.any() else None}


def frame_scores(names: list[str], estimated: dict, scene: dict) -> dict:
    """Scores of the video frames ``names`` (``walk/NNNNNN.jpg``) a run mapped: keyframes, blurred among them,
    seconds of video in gaps longer than ``MAX_GAP_S`` without a registered one (the ends count), poses."""
    fps, frames, blurred = scene["video"]["fps"], scene["video"]["frames"], set(scene["video"]["blurred"])
    index = [int(Path(n).stem) for n in names]
    times = sorted(i / fps for n, i in zip(names, index) if n in estimated)
    gaps = [b - a for a, b in pairwise([0.0, *times, frames / fps]) if b - a > MAX_GAP_S]
    hit = sum(i in blurred for i in index)
    return {"keyframes": len(names), "blurred_keyframes": hit,
            "blurred_keyframes_pct": round(100 * hit / len(names), 1) if names else None,
            "gap_s": round(sum(gaps), 2), "gaps": len(gaps), **pose_scores(estimated, scene["cameras"], names)}


def keyframe_names(image_dir: Path) -> list[str]:
    """The keyframes ``sekd reconstruct`` chose (``image_dir/keyframes.json``), every video's; [] without it."""
    path = image_dir / "keyframes.json"
    if not path.is_file():
        return []
    return [k["name"] for video in json.loads(path.read_text())["videos"].values() for k in video["keyframes"]]


def model_rig(rec) -> tuple[np.ndarray, np.ndarray] | None:
    """Camera 1 from camera 0 ``(R, t)`` of the model's rig holding the cameras of ``cam0/`` and ``cam1/``, else None."""
    import pycolmap

    cameras = {im.name.split("/")[0]: im.camera_id for im in rec.images.values()}
    if cameras.get("cam0") is None or cameras.get("cam0") == cameras.get("cam1"):
        return None
    sensors = [pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=cameras[c]) for c in ("cam0", "cam1")]
    for rig in rec.rigs.values():
        if all(rig.has_sensor(s) for s in sensors):
            R0, t0, R1, t1 = (x for s in sensors for x in _sensor_pose(rig, s))
            return R1 @ R0.T, t1 - R1 @ R0.T @ t0
    return None


def _sensor_pose(rig, sensor) -> tuple[np.ndarray, np.ndarray]:
    if rig.is_ref_sensor(sensor):
        return np.eye(3), np.zeros(3)
    pose = rig.sensor_from_rig(sensor)
    return np.asarray(pose.rotation.matrix()), np.asarray(pose.translation)


def rig_scores(rec, scene: dict) -> dict:
    """The rig's truth (scene ``rig``) against a pycolmap Reconstruction (None: no model): the model rig's camera 1
    from rig (rotation, translation direction; deg) and, per instant with both photos registered, the deviation of
    ``R_cam1 R_cam0^T`` from the truth (median, max; deg)."""
    from .sfm import poses_of

    R_true, t_true = quat_to_matrix(scene["rig"]["cam_from_rig_rotation"]), np.array(scene["rig"]["cam_from_rig_translation"])
    poses = poses_of(rec) if rec is not None else {}
    deviation = [rotation_angle_deg(poses["cam1" + n[4:]][0] @ R.T @ R_true.T) for n, (R, _) in poses.items()
                 if n.startswith("cam0/") and "cam1" + n[4:] in poses]
    rig = model_rig(rec) if rec is not None else None
    return {"rig_rotation_error_deg": round(rotation_angle_deg(rig[0] @ R_true.T), 3) if rig else None,
            "rig_translation_error_deg": round(translation_error_deg(rig[1], t_true), 3) if rig else None,
            "instants_registered": len(deviation),
            "instant_rotation_median_deg": round(float(np.median(deviation)), 3) if deviation else None,
            "instant_rotation_max_deg": round(max(deviation), 3) if deviation else None}


def read_panoramas(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Name -> world-to-panorama ``(R, t)`` of a panoramas.txt (``NAME qw qx qy qz tx ty tz``; ``#`` comments)."""
    poses = {}
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.rsplit(maxsplit=7)
        try:
            q, t = np.array(parts[1:5], np.float64), np.array(parts[5:8], np.float64)
            if len(parts) != 8 or not np.isfinite([*q, *t]).all():
                raise ValueError
        except ValueError:
            raise SekdError(f"{path}:{number}: expected NAME qw qx qy qz tx ty tz, got {line.strip()!r}") from None
        poses[parts[0]] = (quat_to_matrix(q), t)
    return poses


# ----------------------------------------------------------------------------- runs

def _model(work: Path):
    from ..stages.colmap import require_pycolmap

    return require_pycolmap().Reconstruction(str(work / "model")) if (work / "model").is_dir() else None


def write_frames(video: Path, folder: Path, every: int) -> Path:
    """Every ``every``-th frame of ``video`` as ``folder/<stem>/NNNNNN.jpg`` (quality 95), streamed; kept when all
    are there already. Returns ``folder``."""
    from ..files.video import VideoReader

    with VideoReader(video) as reader:
        wanted = [folder / video.stem / f"{i:06d}.jpg" for i in range(0, reader.frame_count, every)]
        if wanted and all(p.is_file() for p in wanted):
            return folder
        (folder / video.stem).mkdir(parents=True, exist_ok=True)
        for index, _, frame in reader:
            if index % every == 0:
                data = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
                write_atomic(folder / video.stem / f"{index:06d}.jpg", data, durable=False)
    return folder


def _score(kind: str, scene: dict, source: Path, work: Path, run: dict) -> dict:
    estimated = registered_poses(work / "model")
    if kind == "video":
        names = keyframe_names(work / "images") if source.is_file() else sorted(
            p.relative_to(source).as_posix() for p in source.rglob("*.jpg"))
        return {**run, **frame_scores(names, estimated, scene)}
    names = sorted(scene["cameras"])
    if kind == "panorama":
        path = work / "panoramas.txt"
        if not path.is_file():
            logger.warning("%s: missing; does this sekd pose panoramas?", path)
        estimated = read_panoramas(path) if path.is_file() else {}
        return {**run, "posed": sum(n in estimated for n in names), **pose_scores(estimated, scene["cameras"], names)}
    return {**run, **pose_scores(estimated, scene["cameras"], names), **rig_scores(_model(work), scene)}


def _reconstruct_config(config: CapturesConfig, rig: Path | None = None):
    from ..pipelines.config import ReconstructConfig

    reconstruct_config = ReconstructConfig(seed=config.seed)
    if rig is not None:
        reconstruct_config.rig = str(rig)
    return reconstruct_config


def run_captures_benchmark(output: str | Path, config: CapturesConfig, progress: bool = True) -> Path:
    """Generate, reconstruct (ours, and the baseline unless ``config.baseline`` is off) and score the capture of
    ``config`` (module doc); returns ``OUT/<kind>/results.json``."""
    from ..runtime import run_record
    from .scale.scene import read_scene

    if config.kind not in KINDS:
        raise SekdError(f"unknown capture {config.kind!r}; choose from {', '.join(KINDS)}")
    out = Path(output) / config.kind
    scene_dir = generate(out / "scene", config, progress).parent
    scene = read_scene(scene_dir)
    source = {"video": scene_dir / "walk.avi"}.get(config.kind, scene_dir / "images")
    runs = {"ours": (source, _reconstruct_config(config, scene_dir / "rig.json" if config.kind == "rig" else None))}
    if config.baseline and config.kind != "panorama":
        frames = write_frames(source, out / "frames", BASELINE_EVERY) if config.kind == "video" else source
        runs["baseline"] = (frames, _reconstruct_config(config))
    result = {"record": run_record(), "settings": asdict(config), "scene": str(scene_dir), "capture": scene["capture"],
              "generation_s": scene["generation_s"]}
    for name, (images, reconstruct_config) in runs.items():
        run = run_reconstruct(images, out / name, reconstruct_config, config.num_threads)
        result[name] = _score(config.kind, scene, images, out / name, run)
    write_atomic(out / "results.json", json.dumps(result, indent=1, default=str))
    write_atomic(out / "results.md", captures_table(result))
    return out / "results.json"


def captures_table(result: dict) -> str:
    """results.json's figures as a Markdown table, one row per run."""
    columns = COLUMNS[result["settings"]["kind"]]
    lines = ["| run | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for name in ("ours", "baseline"):
        if name in result:
            row = result[name]
            lines.append(f"| {name} | " + " | ".join("-" if row.get(c) is None else str(row[c]) for c in columns) + " |"
                         + (f" failure: {row['failure']}" if row.get("failure") else ""))
    return "\n".join(lines) + "\n"
