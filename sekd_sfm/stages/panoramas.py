"""360-degree photos: each equirectangular panorama mapped as a rig of perspective views.

    panoramas -> views/pano<k>/<name> + masks + a rig of VIEW_YAWS_DEG views -> model -> panoramas.txt

A panorama (a 2:1 photo, or every photo with ``--camera-model EQUIRECTANGULAR``) is resampled into
``len(VIEW_YAWS_DEG)`` pinhole views that share its centre, ``VIEW_FOV_DEG`` wide and high, at the
panorama's own pixels per degree at their centres. Each pixel of the sphere belongs to the view whose axis is
nearest (a mask per view), so a feature is found once, while the views' overlap gives keypoints near a
boundary their whole neighbourhood. The views are one rig whose poses and intrinsics are known and kept;
its reference view looks at the panorama's centre, so the rig's pose is the panorama's: ``panoramas.txt``
gives ``NAME qw qx qy qz tx ty tz`` (world-to-panorama; x right, y down, z the direction at the image's
centre), hloc's format. Views of one panorama share no pixel, so they are never matched with each other.
Other photos of the folder are linked next to the views and mapped with them.
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..files.atomic import write_atomic
from ..files.poses import pose_line
from .rig import RigCamera, make_pose

logger = logging.getLogger("sekd")

#: Directions of the views about the panorama's vertical axis (deg; 0 = the panorama's centre).
VIEW_YAWS_DEG = (0.0, 90.0, 180.0, 270.0)
#: Field of view of each view (deg): 10 deg more than 90 so each view overlaps its neighbours.
VIEW_FOV_DEG = 100.0
PREFIX = "pano{}/"
RECORD = "panoramas.json"
FORMAT = "sekd-panoramas/1"


def is_panorama(size: tuple[int, int]) -> bool:
    """Whether a photo of ``size`` (width, height px) is an equirectangular panorama: exactly 2:1."""
    return size[0] == 2 * size[1] and size[1] >= 64


def find_panoramas(image_dir: Path, names: list[str], forced: bool) -> list[str]:
    """The panoramas among ``names``: the 2:1 photos, or all of them when ``forced`` (``--camera-model
    EQUIRECTANGULAR``; a photo that is not 2:1 is then a SekdError naming its size)."""
    from PIL import Image

    found = []
    for name in names:
        try:
            with Image.open(image_dir / name) as image:
                size = image.size
        except OSError:
            continue  # unreadable: extraction reports it
        if is_panorama(size):
            found.append(name)
        elif forced:
            raise SekdError(f"{image_dir / name}: {size[0]}x{size[1]} px is not a 360-degree panorama (2:1); "
                            "--camera-model EQUIRECTANGULAR takes equirectangular photos only")
    return found


def rotation_y(angle: float) -> np.ndarray:
    """3 x 3 rotation by ``angle`` (rad) about y: turns +z towards +x."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def view_rotations() -> list[np.ndarray]:
    """cam_from_panorama rotation (3 x 3) of each view: a turn of its yaw about the panorama's y (down) axis."""
    return [rotation_y(yaw).T for yaw in np.radians(VIEW_YAWS_DEG)]  # panorama_from_cam turns z to the yaw


def view_intrinsics(panorama_width: int) -> tuple[int, float]:
    """(size px, focal length px) of the square views of a panorama ``panorama_width`` px wide."""
    focal = panorama_width / (2 * math.pi)  # the panorama's pixels per radian, kept at the views' centres
    return int(round(2 * focal * math.tan(math.radians(VIEW_FOV_DEG) / 2))), focal


def equirectangular_pixels(rays: np.ndarray, width: int) -> np.ndarray:
    """Pixel (u, v) (OpenCV: integer = pixel centre) of directions ``rays`` (... x 3, panorama frame) in a
    ``width`` x ``width / 2`` panorama."""
    x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]
    yaw, pitch = np.arctan2(x, z), -np.arctan2(y, np.hypot(x, z))
    return np.stack([(0.5 + yaw / (2 * math.pi)) * width - 0.5, (0.5 - pitch / math.pi) * (width / 2) - 0.5], -1)


def _view_maps(width: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per view: remap coordinates (size x size x 2, float32) into the panorama, and its mask (uint8, 255 = own)."""
    size, focal = view_intrinsics(width)
    c = (size - 1) / 2
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float64)
    rays = np.stack([(xs - c) / focal, (ys - c) / focal, np.ones_like(xs)], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    rotations = view_rotations()
    axes = np.array([R[2] for R in rotations])  # each view's axis in the panorama frame (row 2 of cam_from_pano)
    maps, masks = [], []
    for k, R in enumerate(rotations):
        in_pano = rays @ R  # cam -> panorama: R^T ray, for row vectors
        maps.append(equirectangular_pixels(in_pano, width).astype(np.float32))
        masks.append(np.where(np.argmax(in_pano @ axes.T, -1) == k, 255, 0).astype(np.uint8))
    return maps, masks


def render_views(image_dir: Path, panoramas: list[str], views_dir: Path, masks_dir: Path,
                 progress: bool = True) -> dict:
    """Each panorama's views written as ``views_dir/pano<k>/<name>`` (JPEG 95) with their masks
    (``masks_dir/pano<k>/<name>.png``); resumes where the record says the views exist. Returns the record."""
    import cv2
    from tqdm import tqdm

    record_path = views_dir / RECORD
    old = json.loads(record_path.read_text()) if record_path.is_file() else {}
    done = set(old.get("panoramas", [])) if old.get("views") == _views_entry(old.get("width", 0)) else set()
    widths, cache = {}, {}
    for name in tqdm(panoramas, desc="panorama views", unit="pano", disable=not progress):
        image = cv2.imread(str(image_dir / name), cv2.IMREAD_COLOR)
        if image is None:
            logger.warning("warning: %s: cannot be read; left out", name)
            continue
        width = image.shape[1]
        widths[name] = width
        if len(set(widths.values())) > 1:
            raise SekdError(f"{image_dir / name}: {width} px wide, other panoramas {min(widths.values())} px: "
                            "panoramas of one run must have one size")
        if name in done:
            continue
        maps, masks = cache.setdefault(width, _view_maps(width))
        for k, (xy, mask) in enumerate(zip(maps, masks)):
            view = cv2.remap(image, xy[..., 0], xy[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            target = views_dir / (PREFIX.format(k) + name)
            target.parent.mkdir(parents=True, exist_ok=True)
            ok, data = cv2.imencode(".jpg", view, [cv2.IMWRITE_JPEG_QUALITY, 95])
            write_atomic(target, data.tobytes())
            mask_path = masks_dir / (PREFIX.format(k) + name + ".png")
            mask_path.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(mask_path, cv2.imencode(".png", mask)[1].tobytes())
        done.add(name)
        record = {"format": FORMAT, "width": width, "views": _views_entry(width), "panoramas": sorted(done)}
        write_atomic(record_path, json.dumps(record, indent=1).encode())
    if not widths:
        raise SekdError(f"{image_dir}: none of its panoramas can be read")
    return json.loads(record_path.read_text())


def _views_entry(width: int) -> dict:
    size, focal = view_intrinsics(width) if width else (0, 0.0)
    return {"yaws_deg": list(VIEW_YAWS_DEG), "fov_deg": VIEW_FOV_DEG, "size": size, "focal": focal}


def panorama_rig(width: int) -> list[RigCamera]:
    """The views as one rig of known poses and PINHOLE intrinsics (COLMAP's pixel convention), view 0 the reference."""
    size, focal = view_intrinsics(width)
    intrinsics = {"camera_model_name": "PINHOLE", "camera_params": [focal, focal, size / 2, size / 2]}
    return [RigCamera(PREFIX.format(k), k == 0, make_pose(R, np.zeros(3)) if k else None, dict(intrinsics))
            for k, R in enumerate(view_rotations())]


def same_panorama(name0: str, name1: str) -> bool:
    """Whether two view names are views of one panorama (they share no pixel: never a pair)."""
    a, b = name0.split("/", 1), name1.split("/", 1)
    return len(a) == len(b) == 2 and a[1] == b[1] and a[0] != b[0] and a[0].startswith("pano") and b[0].startswith("pano")


def write_panorama_poses(reconstruction, path: Path) -> int:
    """``path`` = one line per posed panorama: ``NAME qw qx qy qz tx ty tz`` (world-to-panorama); returns the count."""
    reference = PREFIX.format(0)
    lines = ["# panorama qw qx qy qz tx ty tz (world-to-panorama: x right, y down, z the image's centre)"]
    for image in sorted(reconstruction.images.values(), key=lambda i: i.name):
        if not image.name.startswith(reference) or not image.has_pose:
            continue
        lines.append(pose_line(image.name[len(reference):], image.frame.rig_from_world))
    write_atomic(path, ("\n".join(lines) + "\n").encode())
    return len(lines) - 1
