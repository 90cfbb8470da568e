"""Strecha et al. (2008) ground-truth cameras: the ``.camera`` text format and pose errors.

A ``<image>.camera`` file has 9 lines: rows 1-3 the intrinsic matrix K; row 4 radial
distortion (zeros); rows 5-7 the rotation R, *camera-to-world* (its columns are the
camera axes in world coordinates); row 8 the camera centre C in world coordinates;
row 9 the image width and height. A world point X projects as ``x ~ K R^T (X - C)``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SekdError
from .metrics import rotation_angle_deg


@dataclass(frozen=True)
class StrechaCamera:
    """One ground-truth camera. ``K`` 3x3 (pixels), ``R`` 3x3 camera-to-world, ``C`` (3,) world units, size (w, h)."""

    K: np.ndarray
    R: np.ndarray
    C: np.ndarray
    width: int
    height: int

    @property
    def cam_from_world(self) -> tuple[np.ndarray, np.ndarray]:
        """``(R_cw, t_cw)`` with x_cam = R_cw X + t_cw, COLMAP's convention: R_cw = R^T, t_cw = -R^T C."""
        return self.R.T, -self.R.T @ self.C


def read_camera(path: str | Path) -> StrechaCamera:
    """Parse a Strecha ``.camera`` file; SekdError naming the file when it is malformed."""
    path = Path(path)
    try:
        rows = [[float(v) for v in line.split()] for line in path.read_text().splitlines() if line.strip()]
        matrix = np.array(rows[:8], dtype=np.float64)
        if len(rows) < 9 or matrix.shape != (8, 3) or len(rows[8]) != 2:
            raise ValueError("expected 8 rows of 3 numbers and a row 'width height'")
    except (OSError, ValueError) as exc:
        raise SekdError(f"{path}: not a Strecha .camera file ({exc})") from None
    return StrechaCamera(K=matrix[:3], R=matrix[4:7], C=matrix[7], width=int(rows[8][0]), height=int(rows[8][1]))


def read_cameras(folder: str | Path) -> dict[str, StrechaCamera]:
    """All cameras of a ``gt_dense_cameras`` folder, keyed by image name (``0000.jpg.camera`` -> ``0000.jpg``)."""
    folder = Path(folder)
    cameras = {p.name.removesuffix(".camera"): read_camera(p) for p in sorted(folder.glob("*.camera"))}
    if not cameras:
        raise SekdError(f"{folder}: no .camera files found")
    return cameras


def relative_pose(cam_from_world0: tuple[np.ndarray, np.ndarray], cam_from_world1: tuple[np.ndarray, np.ndarray]):
    """``(R, t)`` of camera 1 from camera 0: x1 = R x0 + t, given both world-to-camera poses."""
    (R0, t0), (R1, t1) = cam_from_world0, cam_from_world1
    R = R1 @ R0.T
    return R, t1 - R @ t0


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two 3-vectors in degrees (translation direction error); nan for a zero vector."""
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return float("nan")
    return float(np.degrees(np.arccos(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def pairwise_errors(estimated: dict[str, tuple[np.ndarray, np.ndarray]], truth: dict[str, StrechaCamera]) -> dict:
    """Relative rotation and translation-direction errors (degrees) over all pairs of estimated images.

    ``estimated`` maps image name -> world-to-camera ``(R, t)``; scale and world frame are
    irrelevant because only relative poses are compared. Returns lists per pair and medians.
    """
    names = sorted(n for n in estimated if n in truth)
    rot, trans = [], []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            R_est, t_est = relative_pose(estimated[a], estimated[b])
            R_gt, t_gt = relative_pose(truth[a].cam_from_world, truth[b].cam_from_world)
            rot.append(rotation_angle_deg(R_est.T @ R_gt))
            trans.append(angle_between_deg(t_est, t_gt))
    median = (lambda v: float(np.median(v)) if v else float("nan"))
    return {"pairs": len(rot), "rotation_deg": rot, "translation_deg": trans,
            "median_rotation_deg": median(rot), "median_translation_deg": median(trans)}
