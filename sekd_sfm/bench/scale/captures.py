"""Generated captures with known cameras on the city block of ``scene.py`` (its layout, textures
and renderer): a two-camera rig (``render_rig``), 360-degree panoramas (``render_panoramas``) and a
video (``render_video``), all along the block walk of ``make_cameras`` (no distractors).

Each folder's scene.json is in ``read_scene``'s format (per image K, world-to-camera R, t, width,
height; K null for panoramas, whose pixels follow ``EQUIRECT``; ``distractors`` empty) plus ``capture`` (kind and settings) and the kind's truth. There is no
covisibility.txt: captures are scored on all pairs. scene.json is written last; a folder holding a
finished capture of the same settings is reused.
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ...errors import SekdError
from ...evaluation.samplers import expose_u8
from ...files.atomic import write_atomic
from ...stages.panoramas import rotation_y
from .geometry import Camera
from .rendering import candidate_faces, render
from .scene import (
    FORMAT,
    Layout,
    SceneConfig,
    _config_record,
    _write_image,
    layout_scene,
)

#: Walk length (m) between panoramas: a panorama every few steps; each facade point is seen by three or more of them
#: (at 6-9 m from the facades, 5 m leaves neighbours 30-40 deg apart and most points in two panoramas only).
PANORAMA_SPACING_M = 2.5
#: Walk length (m) between video frames; the poses are interpolated between the walk's photos.
VIDEO_STEP_M = 0.25
#: Motion blur kernel lengths (px), inclusive.
BLUR_PX = (9, 24)
#: The panorama pixel convention scene.json records.
EQUIRECT = ("equirectangular, frame x right, y down, z at the centre column; yaw = atan2(x, z), "
            "pitch = -atan2(y, hypot(x, z)); u = (0.5 + yaw / 2pi) W - 0.5, v = (0.5 - pitch / pi) H - 0.5")


def walk_layout(config: SceneConfig, count: int, **changes) -> Layout:
    """The block of ``config`` with ``count`` walk cameras (the layout's one distractor slot is never rendered)."""
    return layout_scene(replace(config, num_images=count + 1, distractor_fraction=0.0, **changes))


def face_renderer(layout: Layout):
    """``camera -> BGR image`` of ``layout``'s faces, culled to the faces the camera may see."""
    faces = layout.faces
    centers = np.array([f.corners().mean(0) for f in faces])
    radii = np.array([0.5 * math.hypot(f.width, f.height) for f in faces])
    origins, normals = np.array([f.origin for f in faces]), np.array([f.normal for f in faces])
    return lambda camera: render(camera, faces, layout.textures,
                                 candidate_faces(camera, centers, radii, origins, normals))[0]


def _reuse(out: Path, config: SceneConfig, capture: dict) -> Path | None:
    """scene.json of ``out`` when it holds this capture, None when there is none; SekdError for another one."""
    done = out / "scene.json"
    if not done.is_file():
        return None
    try:
        previous = json.loads(done.read_text())
    except (OSError, ValueError) as exc:
        raise SekdError(f"{done}: unreadable ({exc}); delete the folder {out} to generate it again") from None
    if previous.get("config") == _config_record(config) and previous.get("capture") == capture:
        return done
    raise SekdError(f"{out}: holds a capture of other settings; choose another folder or delete it")


def _finish(out: Path, config: SceneConfig, capture: dict, images: list[dict], start: float, **truth) -> Path:
    record = {"format": FORMAT, "config": _config_record(config), "capture": capture, "distractors": [],
              "pixel_convention": "OpenCV (integer = pixel centre); COLMAP principal point = ours + 0.5",
              **truth, "images": images, "generation_s": round(time.perf_counter() - start, 2)}
    return write_atomic(out / "scene.json", json.dumps(record, indent=1))


def _entry(name: str, camera: Camera, K: bool = True) -> dict:
    return {"name": name, "K": camera.K.tolist() if K else None, "R": camera.R.tolist(), "t": camera.t.tolist(),
            "width": camera.width, "height": camera.height}


# ----------------------------------------------------------------------------- rig

def cam1_from_rig(yaw_deg: float, baseline_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``(R 3 x 3, t 3)``: rig (= camera 0) coordinates to camera 1's, ``R = R_y(yaw)``, camera 1's centre
    ``baseline_m`` along the rig's x axis (so it looks ``yaw_deg`` to the rig's left, from its right)."""
    R = rotation_y(math.radians(yaw_deg))
    return R, -R @ np.array([baseline_m, 0.0, 0.0])


def render_rig(output_dir: str | Path, config: SceneConfig, instants: int = 50, yaw_deg: float = 40.0,
               baseline_m: float = 0.3, progress: bool = True) -> Path:
    """A two-camera rig along the walk (``instants`` walk cameras as rig poses; ``config.num_images`` unused):
    images/cam0|cam1/NNNNN.jpg, rig.json (COLMAP rig_configurator, relative pose unknown), rig_known.json (with
    camera 1's ``cam_from_rig``), scene.json (``rig``: the truth). Returns scene.json's path."""
    out = Path(output_dir)
    capture = {"kind": "rig", "instants": instants, "yaw_deg": yaw_deg, "baseline_m": baseline_m}
    if done := _reuse(out, config, capture):
        return done
    start = time.perf_counter()
    layout = walk_layout(config, instants)
    draw = face_renderer(layout)
    R1, t1 = cam1_from_rig(yaw_deg, baseline_m)
    for folder in ("cam0", "cam1"):
        (out / "images" / folder).mkdir(parents=True, exist_ok=True)
    images = []
    for k, cam0 in enumerate(tqdm(layout.cameras, desc="rig", unit="instant", disable=not progress)):
        cam1 = Camera(cam0.K, R1 @ cam0.R, R1 @ cam0.t + t1, cam0.width, cam0.height)
        for j, camera in enumerate((cam0, cam1)):
            name = f"cam{j}/{k:05d}.jpg"
            _write_image(out / "images" / name, expose_u8(draw(camera), np.random.default_rng([config.seed, 2, k, j])),
                         config.jpeg_quality)
            images.append(_entry(name, camera))
    half = math.radians(yaw_deg) / 2
    truth = {"cam_from_rig_rotation": [math.cos(half), 0.0, math.sin(half), 0.0],  # [w, x, y, z] of R_y(yaw)
             "cam_from_rig_translation": t1.tolist()}
    sensors = [{"image_prefix": "cam0/", "ref_sensor": True}, {"image_prefix": "cam1/"}]
    write_atomic(out / "rig.json", json.dumps([{"cameras": sensors}], indent=1))
    write_atomic(out / "rig_known.json", json.dumps([{"cameras": [sensors[0], {**sensors[1], **truth}]}], indent=1))
    return _finish(out, config, capture, images, start, rig=truth)


# ----------------------------------------------------------------------------- panoramas

#: Cube faces as (forward, down) in the panorama frame: front, right, back, left, up, down.
CUBE = (((0, 0, 1), (0, 1, 0)), ((1, 0, 0), (0, 1, 0)), ((0, 0, -1), (0, 1, 0)), ((-1, 0, 0), (0, 1, 0)),
        ((0, -1, 0), (0, 0, 1)), ((0, 1, 0), (0, 0, -1)))


def cube_rotations() -> np.ndarray:
    """6 x 3 x 3 face-from-panorama rotations of ``CUBE`` (rows: right = down x forward, down, forward)."""
    return np.array([[np.cross(d, f), d, f] for f, d in np.array(CUBE, np.float64)])


def cube_intrinsics(size: int) -> np.ndarray:
    """K of a cube face rendered with a 1 px margin: 90 deg over the inner ``size`` px of ``size + 2``."""
    c = (size + 1) / 2
    return np.array([[size / 2, 0, c], [0, size / 2, c], [0, 0, 1]])


def equirect_directions(width: int) -> np.ndarray:
    """``width/2 x width x 3`` float32 unit directions (panorama frame) of the pixel centres (``stages.panoramas.equirectangular_pixels``)."""
    yaw = ((np.arange(width) + 0.5) / width - 0.5) * 2 * np.pi
    pitch = (0.5 - (np.arange(width // 2) + 0.5) / (width // 2)) * np.pi
    yaw, pitch = np.meshgrid(yaw, pitch)
    return np.stack([np.cos(pitch) * np.sin(yaw), -np.sin(pitch), np.cos(pitch) * np.cos(yaw)], -1).astype(np.float32)


@lru_cache(maxsize=1)
def _equirect_maps(width: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (``width/2 x width`` float32) from the panorama into the atlas of six ``n x n`` faces."""
    K, rotations = cube_intrinsics(n - 2), cube_rotations().astype(np.float32)
    d = equirect_directions(width)
    face = (d @ rotations[:, 2].T).argmax(-1)  # the face whose axis is nearest
    map_x, map_y = np.empty(face.shape, np.float32), np.empty(face.shape, np.float32)
    for k, R in enumerate(rotations):
        inside = face == k
        p = d[inside] @ R.T
        map_x[inside] = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2] + k * n
        map_y[inside] = K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]
    return map_x, map_y


def cube_to_equirect(faces: list[np.ndarray], width: int) -> np.ndarray:
    """Six ``(s+2) x (s+2)`` cube faces (``CUBE`` order, ``cube_intrinsics``) resampled (linear) to ``width/2 x width``.

    The faces side by side form one atlas for cv2.remap; each direction reads the face it meets,
    within 0.5 px of the inner square, so the margin keeps the interpolation off the neighbour's pixels.
    """
    return cv2.remap(np.concatenate(faces, 1), *_equirect_maps(width, faces[0].shape[0]), cv2.INTER_LINEAR)


def render_panorama(draw, R: np.ndarray, t: np.ndarray, width: int) -> np.ndarray:
    """``width/2 x width`` BGR panorama of world-to-panorama ``R``, ``t`` (``draw``: camera -> image)."""
    size = round(width / 4)
    K = cube_intrinsics(size)
    faces = [draw(Camera(K, Rf @ R, Rf @ t, size + 2, size + 2)) for Rf in cube_rotations()]
    return cube_to_equirect(faces, width)


def render_panoramas(output_dir: str | Path, config: SceneConfig, count: int = 30, width: int = 2048,
                     progress: bool = True, spacing_m: float = PANORAMA_SPACING_M) -> Path:
    """``count`` equirectangular panoramas ``width x width/2`` along the walk, ``spacing_m`` apart
    (``config.num_images`` / ``spacing`` unused): images/NNNNN.jpg, scene.json (per name world-to-panorama R, t;
    K null). Each is oriented like its walk camera, turned by a random yaw about its own y axis. Returns
    scene.json's path."""
    if width < 16 or width % 2:
        raise SekdError(f"panorama width {width}: give an even number of pixels, at least 16")
    out = Path(output_dir)
    capture = {"kind": "panorama", "count": count, "width": width, "spacing_m": spacing_m}
    if done := _reuse(out, config, capture):
        return done
    start = time.perf_counter()
    layout = walk_layout(config, count, spacing=spacing_m)
    draw = face_renderer(layout)
    (out / "images").mkdir(parents=True, exist_ok=True)
    images = []
    for i, camera in enumerate(tqdm(layout.cameras, desc="panoramas", unit="panorama", disable=not progress)):
        rng = np.random.default_rng([config.seed, 6, i])
        turn = rotation_y(rng.uniform(-np.pi, np.pi))
        pano = Camera(None, turn @ camera.R, turn @ camera.t, width, width // 2)
        _write_image(out / "images" / f"{i:05d}.jpg", expose_u8(render_panorama(draw, pano.R, pano.t, width), rng), 95)
        images.append(_entry(f"{i:05d}.jpg", pano, K=False))
    return _finish(out, config, capture, images, start, panorama=EQUIRECT)


# ----------------------------------------------------------------------------- video

def interpolate_camera(cameras: list[Camera], x: float) -> Camera:
    """The pose at ``x`` (in walk-camera indices) between cameras ``floor(x)`` and the next: rotation along the
    geodesic, centre along the line; the walk's jitter becomes a smooth sway instead of a shake per frame."""
    a = min(int(x), len(cameras) - 2)
    w, ca, cb = x - a, cameras[a], cameras[a + 1]
    turn, _ = cv2.Rodrigues(cb.R @ ca.R.T)
    R = cv2.Rodrigues(w * turn)[0] @ ca.R
    return Camera(ca.K, R, -R @ ((1 - w) * ca.center + w * cb.center), ca.width, ca.height)


def motion_blur(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``image`` smeared along a line of ``BLUR_PX`` length (px) at a random angle."""
    length, angle = int(rng.integers(BLUR_PX[0], BLUR_PX[1] + 1)), rng.uniform(0, np.pi)
    n = length | 1
    half = (length - 1) / 2 * np.array([math.cos(angle), math.sin(angle)])
    kernel = np.zeros((n, n), np.float32)
    ends = [tuple(np.round(16 * ((n - 1) / 2 + s * half)).astype(int)) for s in (-1, 1)]
    cv2.line(kernel, *ends, 1.0, 1, cv2.LINE_AA, shift=4)  # shift 4: sub-pixel end points
    return cv2.filter2D(image, -1, kernel / kernel.sum())


def render_video(output_dir: str | Path, config: SceneConfig, frames: int = 600, fps: int = 30,
                 blur_fraction: float = 0.15, progress: bool = True) -> Path:
    """The walk as a video walk.avi (MJPG, ``fps``): ``frames`` poses ``VIDEO_STEP_M`` apart, interpolated
    between the walk cameras of ``config`` (``config.num_images`` unused); ``blur_fraction`` of the frames motion
    blurred; exposure drifting slowly, fresh noise per frame. scene.json: per frame ``walk/NNNNNN.jpg`` (the
    names of ``sekd reconstruct``'s keyframes), ``video`` (fps, frames, ``blurred`` frame indices). Frames are
    rendered and written one at a time. Returns scene.json's path."""
    if frames < 2 or fps < 1 or not 0 <= blur_fraction <= 1:
        raise SekdError(f"a video needs at least 2 frames, fps >= 1 and a blur fraction in 0..1; got {frames}, "
                        f"{fps}, {blur_fraction}")
    out = Path(output_dir)
    capture = {"kind": "video", "frames": frames, "fps": fps, "blur_fraction": blur_fraction, "step_m": VIDEO_STEP_M}
    if done := _reuse(out, config, capture):
        return done
    start = time.perf_counter()
    per_camera = VIDEO_STEP_M / config.spacing
    layout = walk_layout(config, int((frames - 1) * per_camera) + 2)
    draw = face_renderer(layout)
    rng = np.random.default_rng([config.seed, 7])
    blurred = set(rng.choice(frames, round(blur_fraction * frames), replace=False).tolist())
    phase = rng.uniform(0, 2 * np.pi, 2)
    out.mkdir(parents=True, exist_ok=True)
    partial = out / "walk.partial.avi"  # the extension tells FFmpeg the container
    camera = layout.cameras[0]
    writer = cv2.VideoWriter(str(partial), cv2.VideoWriter_fourcc(*"MJPG"), fps, (camera.width, camera.height))
    if not writer.isOpened():
        raise SekdError(f"{partial}: OpenCV cannot write an MJPG video here")
    images = []
    try:
        for i in tqdm(range(frames), desc="video", unit="frame", disable=not progress):
            camera = interpolate_camera(layout.cameras, i * per_camera)
            image, frame_rng = draw(camera), np.random.default_rng([config.seed, 2, i])
            if i in blurred:
                image = motion_blur(image, frame_rng)
            # Auto exposure drifts over seconds; an exposure drawn per frame would flicker.
            gain = 1 + 0.15 * math.sin(2 * math.pi * i / fps / 9 + phase[0])
            gamma = 1 + 0.1 * math.sin(2 * math.pi * i / fps / 13 + phase[1])
            writer.write(expose_u8(image, frame_rng, (gain, gain), (gamma, gamma)))
            images.append(_entry(f"walk/{i:06d}.jpg", camera))
    finally:
        writer.release()
    os.replace(partial, out / "walk.avi")
    return _finish(out, config, capture, images, start, video={"fps": fps, "frames": frames, "blurred": sorted(blurred)})
