"""Benchmark metrics with hand-checkable definitions (docs/method.md, Evaluation protocols).

All pixel coordinates use the OpenCV convention (integer = pixel centre).
"""
from __future__ import annotations

import numpy as np

#: Thresholds in pixels (homography) or degrees (pose) at which accuracies are reported.
THRESHOLDS = np.arange(1, 11)


def warp_points(points: np.ndarray, homography: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to ``N x 2`` points."""
    homogeneous = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ homography.T
    return homogeneous[:, :2] / homogeneous[:, 2:]


def corner_error(estimated: np.ndarray | None, truth: np.ndarray, width: int, height: int) -> float:
    """Mean distance (px, in image k) between image-1 corners mapped by the estimated and true H; inf if none."""
    if estimated is None:
        return float("inf")
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], np.float64)
    return float(np.linalg.norm(warp_points(corners, estimated) - warp_points(corners, truth), axis=1).mean())


def accuracy_curve(errors: list[float], thresholds=THRESHOLDS) -> np.ndarray:
    """Fraction of errors <= t for each threshold (inf counts as wrong everywhere)."""
    errors = np.asarray(errors, np.float64)
    return np.array([(errors <= t).mean() if errors.size else 0.0 for t in thresholds])


def match_accuracy(kp0: np.ndarray, kp1: np.ndarray, matches: np.ndarray, homography: np.ndarray,
                   thresholds=THRESHOLDS) -> np.ndarray:
    """MMA curve of one pair: fraction of matches ``M x 2`` whose reprojection error under H is <= t (0 if none)."""
    if len(matches) == 0:
        return np.zeros(len(thresholds))
    errors = np.linalg.norm(warp_points(kp0[matches[:, 0]], homography) - kp1[matches[:, 1]], axis=1)
    return np.array([(errors <= t).mean() for t in thresholds])


def repeatability(kp0: np.ndarray, kp1: np.ndarray, homography: np.ndarray, size0: tuple[int, int],
                  size1: tuple[int, int], tolerance: float = 3.0) -> float:
    """Share of keypoints, among those visible in both images, with a counterpart within ``tolerance`` px.

    SuperPoint's definition: (repeated in 0 + repeated in 1) / (visible in 0 + visible in 1).
    Sizes are (width, height).
    """
    def visible(points, size):
        return (points[:, 0] >= 0) & (points[:, 1] >= 0) & (points[:, 0] <= size[0] - 1) & (points[:, 1] <= size[1] - 1)

    w01 = warp_points(kp0, homography)
    w10 = warp_points(kp1, np.linalg.inv(homography))
    a, b = w01[visible(w01, size1)], kp1[visible(w10, size0)]
    if len(a) == 0 or len(b) == 0:
        return 0.0
    distances = np.linalg.norm(a[:, None] - b[None], axis=2)
    repeated = (distances.min(1) <= tolerance).sum() + (distances.min(0) <= tolerance).sum()
    return float(repeated / (len(a) + len(b)))


def rotation_angles_deg(rotations: np.ndarray) -> np.ndarray:
    """Angles (degrees) of rotation matrices ``... x 3 x 3`` (robust to rounding outside [-1, 1])."""
    cos = (np.trace(rotations, axis1=-2, axis2=-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees (robust to rounding outside [-1, 1])."""
    return float(rotation_angles_deg(rotation))


def essential_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``[t]x R``: the essential matrix of camera 1 from camera 0 ``(R, t)``, ``x1^T E x0 = 0`` in normalized
    coordinates."""
    t = np.asarray(t, np.float64).ravel()
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]]) @ np.asarray(R)


def fundamental_matrix(K0: np.ndarray, K1: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """F with ``x1^T F x0 = 0`` for pixel points of cameras ``K0``, ``K1``, camera 1 from camera 0 ``(R, t)``."""
    return np.linalg.inv(K1).T @ essential_matrix(R, t) @ np.linalg.inv(K0)


def rotation_error_deg(r_est: np.ndarray, r_gt: np.ndarray) -> float:
    """Angle (degrees) of R_est R_gt^T."""
    return rotation_angle_deg(r_est @ r_gt.T)


def translation_error_deg(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Angle (degrees) between two translation directions (sign matters)."""
    n = np.linalg.norm(t_est) * np.linalg.norm(t_gt)
    if n == 0:
        return 180.0
    return float(np.degrees(np.arccos(np.clip(np.dot(t_est, t_gt) / n, -1.0, 1.0))))


def mean_average_accuracy(errors: list[float], thresholds=THRESHOLDS) -> float:
    """mAA: mean over thresholds (1..10 deg) of the fraction of errors below each (IMC convention)."""
    return float(accuracy_curve(errors, thresholds).mean())


def pose_auc(errors: list[float], limit: float) -> float:
    """Area under the recall-vs-error curve up to ``limit`` degrees, normalised to [0, 1] (SuperGlue's AUC)."""
    errors = np.sort(np.asarray(errors, np.float64))
    if errors.size == 0:
        return 0.0
    recall = np.arange(1, len(errors) + 1) / len(errors)
    errors, recall = np.r_[0.0, errors], np.r_[0.0, recall]
    last = np.searchsorted(errors, limit)
    e = np.r_[errors[:last], limit]
    r = np.r_[recall[:last], recall[last - 1]]
    return float(np.trapezoid(r, x=e) / limit)


def ransac_order(count: int, run: int) -> np.ndarray:
    """Order in which ``count`` matches are given to RANSAC on run ``run`` (0 = as matched).

    OpenCV's RANSAC (``findHomography``, ``findEssentialMat``) seeds its sampler with a fixed
    constant, so the only thing that changes its draws is the order of the input: run 0 keeps
    the matcher's order (the paper's protocol), run ``k > 0`` a permutation seeded by ``k``. The
    spread of a metric over runs is what RANSAC's luck alone does to it.
    """
    if run == 0:
        return np.arange(count)
    return np.random.default_rng(run).permutation(count)


def mean_and_sd(values: list[float]) -> tuple[float, float]:
    """Mean and (population) standard deviation of a metric over RANSAC runs; sd 0 for one run."""
    values = np.asarray(values, np.float64)
    return float(values.mean()), float(values.std())
