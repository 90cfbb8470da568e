"""Camera rigs (``--rig-config rig.json``): cameras fixed to each other, exposed together.

``rig.json`` is COLMAP's ``rig_configurator`` format: a list of rigs, each ``{"cameras": [...]}``, a camera
``{"image_prefix": "cam0/", "ref_sensor": true}`` or with its pose in the rig, ``cam_from_rig_rotation``
([w, x, y, z]) and ``cam_from_rig_translation`` (the rig's units), optionally ``camera_model_name`` and
``camera_params``. An instant (COLMAP's frame) is one file name under each prefix: ``cam0/0001.jpg`` and
``cam1/0001.jpg``. Each prefix gets a camera of its own (``database._import_images``).

Poses in the rig that are given are kept; those left out are estimated: the photos are mapped once as free
photos, each camera's pose relative to the reference camera taken where most instants agree
(``estimate_cam_from_rig``), and the photos mapped again as one rig (pipelines/reconstruct.py).
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..evaluation.metrics import rotation_angles_deg
from .colmap import open_database, require_pycolmap

logger = logging.getLogger("sekd")
#: Instants whose relative camera rotation lies within this of the candidate's agree with it (deg).
AGREEMENT_DEG = 2.0


@dataclass
class RigCamera:
    """One camera of a rig: its ``prefix``; ``cam_from_rig`` (4x4, None: to estimate) unless ``ref``."""

    prefix: str
    ref: bool = False
    cam_from_rig: np.ndarray | None = None
    extra: dict = field(default_factory=dict)  # camera_model_name / camera_params, passed on to COLMAP


Rig = list[RigCamera]


def read_rigs(path: str | Path) -> list[Rig]:
    """The rigs of a ``rig_configurator`` file, checked (one ``SekdError`` naming what is wrong)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise SekdError(f"--rig-config {path}: cannot read it as JSON ({exc})") from None
    if not isinstance(data, list) or not data:
        raise SekdError(f"--rig-config {path}: expected a list of rigs, each {{\"cameras\": [...]}}")
    rigs = [_parse_rig(entry, f"--rig-config {path}: rig {k + 1}") for k, entry in enumerate(data)]
    prefixes = [camera.prefix for rig in rigs for camera in rig]
    for a in prefixes:
        clash = [b for b in prefixes if b != a and b.startswith(a)]
        if clash or prefixes.count(a) > 1:
            raise SekdError(f"--rig-config {path}: image prefix {a!r} is given twice or contains {clash[0]!r}")
    return rigs


def _parse_rig(entry, where: str) -> Rig:
    cameras = entry.get("cameras") if isinstance(entry, dict) else None
    if not isinstance(cameras, list) or len(cameras) < 2:
        raise SekdError(f"{where}: needs \"cameras\", a list of at least two cameras")
    rig = [_parse_camera(camera, f"{where}, camera {k + 1}") for k, camera in enumerate(cameras)]
    if sum(camera.ref for camera in rig) != 1:
        raise SekdError(f"{where}: exactly one camera must have \"ref_sensor\": true")
    return rig


def _parse_camera(entry, where: str) -> RigCamera:
    if not isinstance(entry, dict) or not isinstance(entry.get("image_prefix"), str) or not entry["image_prefix"]:
        raise SekdError(f"{where}: needs \"image_prefix\", the start of its photos' names (e.g. \"cam0/\")")
    rotation, translation = entry.get("cam_from_rig_rotation"), entry.get("cam_from_rig_translation")
    camera = RigCamera(entry["image_prefix"], bool(entry.get("ref_sensor", False)),
                       extra={k: entry[k] for k in ("camera_model_name", "camera_params") if k in entry})
    if (rotation is None) != (translation is None):
        raise SekdError(f"{where}: give both cam_from_rig_rotation and cam_from_rig_translation, or neither")
    if rotation is not None and not camera.ref:
        try:
            q = np.asarray(rotation, np.float64).reshape(4)
            t = np.asarray(translation, np.float64).reshape(3)
        except (TypeError, ValueError):
            raise SekdError(f"{where}: cam_from_rig_rotation is [w, x, y, z], cam_from_rig_translation [x, y, z]") from None
        if not np.isfinite(q).all() or not np.isfinite(t).all() or abs(np.linalg.norm(q) - 1) > 1e-3:
            raise SekdError(f"{where}: cam_from_rig_rotation must be a unit quaternion [w, x, y, z]")
        camera.cam_from_rig = make_pose(quat_to_matrix(q), t)
    return camera


def quat_to_matrix(wxyz: np.ndarray) -> np.ndarray:
    """3 x 3 rotation of a quaternion [w, x, y, z] (normalised first)."""
    w, x, y, z = np.asarray(wxyz, np.float64) / np.linalg.norm(wxyz)
    return np.asarray(require_pycolmap().Rotation3d(np.array([x, y, z, w])).matrix())


def matrix_to_quat(R: np.ndarray) -> list[float]:
    """[w, x, y, z] of a rotation matrix (w >= 0)."""
    xyzw = require_pycolmap().Rotation3d(np.asarray(R, np.float64)).quat
    w, x, y, z = xyzw[3], *xyzw[:3]
    sign = 1.0 if w >= 0 else -1.0
    return [float(sign * v) for v in (w, x, y, z)]


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R, t
    return pose


def poses_known(rigs: list[Rig]) -> bool:
    """Whether every camera's pose in its rig is given (then the mapper keeps them)."""
    return all(camera.ref or camera.cam_from_rig is not None for rig in rigs for camera in rig)


def sensor_prefix(rigs: list[Rig], name: str) -> str | None:
    """The rig camera (its prefix) that took the photo ``name``, None if no rig's."""
    return next((camera.prefix for rig in rigs for camera in rig if name.startswith(camera.prefix)), None)


def check_photos(rigs: list[Rig], names: list[str], path: str | Path) -> dict:
    """SekdError when a prefix names no photo, or shares no instant (file name) with its rig's reference camera;
    a warning for instants some camera lacks. Returns {prefix: photos}."""
    counts = {}
    for rig in rigs:
        ref = next(camera for camera in rig if camera.ref)
        instants = {camera.prefix: {n[len(camera.prefix):] for n in names if n.startswith(camera.prefix)}
                    for camera in rig}
        for prefix, found in instants.items():
            if not found:
                raise SekdError(f"--rig-config {path}: image prefix {prefix!r} names no photo (photos are named like "
                                f"{names[0]!r})" if names else f"--rig-config {path}: no photos")
            if prefix != ref.prefix and not found & instants[ref.prefix]:
                raise SekdError(f"--rig-config {path}: {prefix!r} and {ref.prefix!r} share no file name (e.g. "
                                f"{prefix}{min(found)} has no {ref.prefix}{min(found)}): an instant is the same "
                                "file name under each prefix")
            counts[prefix] = len(found)
        every = set.union(*instants.values())
        partial = sorted(f for f in every if any(f not in found for found in instants.values()))
        if partial:
            logger.warning("warning: %d of %d instants of the rig of %s lack a camera's photo (e.g. %s)", len(partial),
                           len(every), ref.prefix, partial[0])
    return counts


def apply_rigs(database: str | Path, rigs: list[Rig]) -> dict[str, int]:
    """The rigs and their instants (frames) written into ``database`` (every camera's pose in its rig known), with
    the intrinsics a rig file gives; returns the camera id of each prefix whose intrinsics were given."""
    pycolmap = require_pycolmap()
    configs, given = [], {}
    with open_database(database) as db:
        first = {}
        for image in db.read_all_images():
            prefix = sensor_prefix(rigs, image.name)
            if prefix is not None and prefix not in first:
                first[prefix] = db.read_camera(image.camera_id)
        for rig in rigs:
            cameras = []
            for camera in rig:
                entry = pycolmap.RigConfigCamera(image_prefix=camera.prefix, ref_sensor=camera.ref)
                if camera.cam_from_rig is not None and not camera.ref:
                    pose = camera.cam_from_rig
                    entry.cam_from_rig = pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:3, :3]), pose[:3, 3])
                if "camera_model_name" in camera.extra and camera.prefix in first:
                    known = first[camera.prefix]
                    entry.camera = pycolmap.Camera(model=camera.extra["camera_model_name"], width=known.width,
                                                   height=known.height, params=camera.extra["camera_params"])
                    given[camera.prefix] = known.camera_id
                cameras.append(entry)
            configs.append(pycolmap.RigConfig(cameras=cameras))
        pycolmap.apply_rig_config(configs, db)
    return given


def write_rigs(rigs: list[Rig], path: Path) -> Path:
    """``rigs`` as a ``rig_configurator`` file (what a later run can take with ``--rig-config``)."""
    out = []
    for rig in rigs:
        cameras = []
        for camera in rig:
            entry = {"image_prefix": camera.prefix, **({"ref_sensor": True} if camera.ref else {}), **camera.extra}
            if camera.cam_from_rig is not None and not camera.ref:
                entry["cam_from_rig_rotation"] = matrix_to_quat(camera.cam_from_rig[:3, :3])
                entry["cam_from_rig_translation"] = [float(v) for v in camera.cam_from_rig[:3, 3]]
            cameras.append(entry)
        out.append({"cameras": cameras})
    path.write_text(json.dumps(out, indent=2) + "\n")
    return path


def _world_to_camera(reconstruction) -> dict[str, np.ndarray]:
    """4x4 world-to-camera pose of each registered photo of a model, by name."""
    poses = {}
    for image in reconstruction.images.values():
        if image.has_pose:
            pose = image.cam_from_world()
            poses[image.name] = make_pose(pose.rotation.matrix(), pose.translation)
    return poses


def calibration_photos(rigs: list[Rig], names: list[str], instants: int) -> list[str]:
    """The photos of each rig's first ``instants`` instants (in natural name order), every camera's."""
    from .pairs import natural_key

    chosen, known = [], set(names)
    for rig in rigs:
        ref = next(camera for camera in rig if camera.ref)
        frames = sorted((n[len(ref.prefix):] for n in names if n.startswith(ref.prefix)), key=natural_key)[:instants]
        chosen += [name for camera in rig for name in (camera.prefix + f for f in frames) if name in known]
    return chosen


def estimate_cam_from_rig(rigs: list[Rig], reconstruction) -> tuple[list[Rig], dict]:
    """Each unknown camera pose in its rig from a model of the photos mapped freely; (rigs, record by prefix).

    For every instant with both photos registered, cam_from_ref = cam_from_world * ref_from_world^-1. The instant
    with the most others within AGREEMENT_DEG of its rotation wins; its agreeing instants are averaged (rotation:
    the projected mean; translation: the median), so instants the free model got wrong do not pull the pose.
    SekdError when a camera has no instant registered together with the reference camera (or no model is given).
    """
    poses = _world_to_camera(reconstruction) if reconstruction is not None else {}
    record = {}
    out = []
    for rig in rigs:
        ref = next(camera for camera in rig if camera.ref)
        estimated = []
        for camera in rig:
            if camera.ref or camera.cam_from_rig is not None:
                estimated.append(camera)
                continue
            relative = [poses[camera.prefix + n[len(ref.prefix):]] @ np.linalg.inv(poses[n]) for n in poses
                        if n.startswith(ref.prefix) and camera.prefix + n[len(ref.prefix):] in poses]
            if not relative:
                raise SekdError(f"rig: no photo of {camera.prefix!r} was registered together with {ref.prefix!r}'s "
                                "photo of the same instant, so its pose in the rig cannot be estimated; give "
                                "cam_from_rig_rotation and cam_from_rig_translation in the rig file")
            pose, agree = _consensus(np.stack(relative))
            if agree < max(2, len(relative) / 2):
                raise SekdError(f"rig: the photos mapped as free photos disagree on {camera.prefix!r}'s pose in the rig "
                                f"(at most {agree} of {len(relative)} instants within {AGREEMENT_DEG} deg of each "
                                "other); give cam_from_rig_rotation and cam_from_rig_translation in the rig file")
            estimated.append(RigCamera(camera.prefix, False, pose, camera.extra))
            record[camera.prefix] = {"instants": len(relative), "agreeing": agree}
        out.append(estimated)
    return out, record


def _consensus(poses: np.ndarray) -> tuple[np.ndarray, int]:
    """The pose most of ``poses`` (N x 4 x 4) agree with: (4 x 4, how many agree)."""
    R = poses[:, :3, :3]
    angles = rotation_angles_deg(R[:, None] @ np.swapaxes(R, 1, 2)[None])  # N x N: angle of R_i R_j^T
    inliers = angles[int(np.argmax((angles < AGREEMENT_DEG).sum(1)))] < AGREEMENT_DEG
    u, _, vt = np.linalg.svd(R[inliers].mean(0))
    mean = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
    return make_pose(mean, np.median(poses[inliers, :3, 3], axis=0)), int(inliers.sum())


def rig_record(reconstruction) -> list[dict]:
    """The model's rigs of more than one camera: each camera's pose in its rig ([w, x, y, z], translation) and the
    instants registered."""
    out = []
    frames_of: dict[int, int] = {}
    for frame in reconstruction.frames.values():
        if frame.has_pose:
            frames_of[frame.rig_id] = frames_of.get(frame.rig_id, 0) + 1
    names = {image.camera_id: image.name for image in reconstruction.images.values()}
    for rig_id, rig in reconstruction.rigs.items():
        if rig.num_sensors() < 2:
            continue
        cameras = [{"camera_id": rig.ref_sensor_id.id, "example": names.get(rig.ref_sensor_id.id), "ref": True}]
        for sensor, pose in rig.non_ref_sensors.items():
            cameras.append({"camera_id": sensor.id, "example": names.get(sensor.id),
                            "cam_from_rig_rotation": matrix_to_quat(pose.rotation.matrix()),
                            "cam_from_rig_translation": [round(float(v), 6) for v in pose.translation]})
        out.append({"rig_id": int(rig_id), "cameras": cameras, "instants_registered": frames_of.get(rig_id, 0)})
    return out
