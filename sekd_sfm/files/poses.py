"""hloc's poses file: one ``NAME qw qx qy qz tx ty tz`` line per photo (world-to-camera, COLMAP's convention).

``sekd localize`` writes it; ``sekd triangulate --poses`` reads it (as hloc's localization
and triangulation do).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SekdError

Pose = tuple[np.ndarray, np.ndarray]


def pose_line(name: str, cam_from_world) -> str:
    """The line of a pycolmap Rigid3d (its quaternion is stored x, y, z, w; the file says w first)."""
    x, y, z, w = (float(v) for v in cam_from_world.rotation.quat)
    t = [float(v) for v in cam_from_world.translation]
    return " ".join([name] + [repr(v) for v in (w, x, y, z, *t)])


def read_poses(path: str | Path) -> dict[str, Pose]:
    """name -> (quaternion ``[x, y, z, w]`` as pycolmap stores it, translation (3,)), world-to-camera.

    Blank lines and lines starting with ``#`` are skipped; the name may hold spaces (the 7
    numbers are the last fields). A quaternion whose norm is off 1 by more than 1e-6 is
    normalised (same rotation); others are kept bit for bit. SekdError naming the file and
    line for anything else.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise SekdError(f"{path}: cannot read the poses file ({exc})") from None
    poses: dict[str, Pose] = {}
    for number, line in enumerate(lines, 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        name, quat, translation = _parse(line, f"{path}, line {number}")
        if name in poses:
            raise SekdError(f"{path}, line {number}: {name} has a pose on an earlier line already; "
                            "give one pose per photo")
        poses[name] = (quat, translation)
    if not poses:
        raise SekdError(f"{path}: no poses in the file; give one 'NAME qw qx qy qz tx ty tz' line per photo")
    return poses


def _parse(line: str, where: str) -> tuple[str, np.ndarray, np.ndarray]:
    fields = line.strip().rsplit(maxsplit=7)
    try:
        values = [float(v) for v in fields[1:]]
    except ValueError:
        values = []
    if len(fields) != 8 or len(values) != 7 or not np.all(np.isfinite(values)):
        raise SekdError(f"{where}: expected 'NAME qw qx qy qz tx ty tz' (a name and 7 numbers), got {line.strip()!r}")
    quat = np.array(values[1:4] + values[:1])
    norm = float(np.linalg.norm(quat))
    if norm < 1e-12:
        raise SekdError(f"{where}: the quaternion is zero; give qw qx qy qz of a rotation")
    return fields[0], (quat / norm if abs(norm - 1) > 1e-6 else quat), np.array(values[4:])
