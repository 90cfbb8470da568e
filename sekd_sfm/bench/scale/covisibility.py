"""Co-visibility ground truth of a scene's photos: which pairs see the same surface, and how much of it.

Co-visibility is measured on points sampled over every face (about one per 0.5 m, at
most 600 per face): a point is seen by a camera when it falls in the image and the face
drawn at its pixel is its own face (so occlusion counts). A surface point seen from two
directions far apart (a facade from both ends of a street, a corner from two sides) is
co-visible but not matchable by local features. On these scenes (N = 250, both SIFT and
SEKD) pairs whose shared points are seen within 60 degrees of each other (median ray angle)
verify 97-100 % of the time, pairs beyond 90 degrees 0-2 %; hence the pixel overlap
(points seen within MATCHABLE_ANGLE_DEG, MegaDepth-style depth reprojection) that the
retrieval ground truth uses.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import SekdError
from .geometry import NEAR, Camera

#: Largest angle (deg) between the two viewing rays of a surface point for the point to count
#: as matchable between two photos (see the module docstring).
MATCHABLE_ANGLE_DEG = 60.0


def visible_points(camera: Camera, face_id: np.ndarray, samples: list[np.ndarray], offsets: np.ndarray,
                   drawn: np.ndarray) -> np.ndarray:
    """Global ids of the sample points whose pixel shows their own face.

    ``face_id``: the photo's face index per pixel (H x W, -1 = none); ``samples[f]``: face f's
    ``M_f x 3`` sample points (``Face.samples``), numbered from ``offsets[f]`` (cumulative counts);
    ``drawn``: the faces the photo shows. Returns int64 ids.
    """
    ids = []
    for index in drawn:
        pix, z = camera.project(samples[index])
        col, row = np.round(pix[:, 0]), np.round(pix[:, 1])
        inside = (z > NEAR) & (col >= 0) & (row >= 0) & (col < camera.width) & (row < camera.height)
        k = np.flatnonzero(inside)
        seen = face_id[row[k].astype(int), col[k].astype(int)] == index
        ids.append(offsets[index] + k[seen])
    return np.concatenate(ids) if ids else np.zeros(0, np.int64)


def covisibility_counts(visible: list[np.ndarray], num_points: int):
    """``(shared, seen)``: shared[i, j] = points seen by both i and j (sparse, symmetric); seen[i] per image."""
    from scipy import sparse

    rows = np.concatenate([np.full(len(v), i) for i, v in enumerate(visible)]) if visible else np.zeros(0, int)
    cols = np.concatenate(visible) if visible else np.zeros(0, int)
    matrix = sparse.csr_matrix((np.ones(len(cols), np.int32), (rows, cols)), shape=(len(visible), num_points))
    matrix.data[:] = 1  # a point counts once per image
    return (matrix @ matrix.T).tocoo(), np.asarray(matrix.sum(axis=1)).ravel()


@dataclass
class SurfaceView:
    """What one photo sees: surface points on a pixel grid, and which face each pixel shows.

    ``points``: M x 3 world points, one per 8 x 8 pixel cell centre showing a face;
    ``point_faces``: M face indices of those points; ``faces``: the face index at every
    ``step``-th pixel (-1 = sky), (H / step) x (W / step) int32.
    """

    points: np.ndarray
    point_faces: np.ndarray
    faces: np.ndarray
    step: int

    @classmethod
    def of(cls, camera: Camera, face_id: np.ndarray, depth: np.ndarray, grid: int = 8, step: int = 2) -> SurfaceView:
        d, f = depth[grid // 2::grid, grid // 2::grid], face_id[grid // 2::grid, grid // 2::grid]
        rows, cols = np.nonzero(f >= 0)
        z = d[rows, cols].astype(np.float64)
        pix = np.stack([cols * grid + grid // 2, rows * grid + grid // 2, np.ones_like(z)], 1)
        cam = (pix @ np.linalg.inv(camera.K).T) * z[:, None]
        points = (cam - camera.t) @ camera.R  # R^T (x - t), row by row
        return cls(points, f[rows, cols], np.ascontiguousarray(face_id[step // 2::step, step // 2::step]), step)


def pixel_overlap(view_a: SurfaceView, camera_a: Camera, view_b: SurfaceView, camera_b: Camera,
                  max_angle: float = MATCHABLE_ANGLE_DEG) -> float:
    """Fraction of photo a's surface pixels that photo b sees unoccluded (b's pixel there shows the
    point's own face) from a direction at most ``max_angle`` deg from a's (the two viewing rays)."""
    if len(view_a.points) == 0:
        return 0.0
    pix, z = camera_b.project(view_a.points)
    col, row = np.floor(pix[:, 0] / view_b.step), np.floor(pix[:, 1] / view_b.step)
    h, w = view_b.faces.shape
    inside = (z > NEAR) & (col >= 0) & (row >= 0) & (col < w) & (row < h)
    k = np.flatnonzero(inside)
    k = k[view_b.faces[row[k].astype(int), col[k].astype(int)] == view_a.point_faces[k]]
    angles = pair_ray_angles(view_a.points[k], camera_a.center, camera_b.center)
    return float((angles <= max_angle).sum() / len(view_a.points))


def pair_ray_angles(points: np.ndarray, center_a: np.ndarray, center_b: np.ndarray) -> np.ndarray:
    """Angle (deg) between the viewing rays from ``center_a`` and ``center_b`` to each of ``points`` (M x 3)."""
    ra, rb = points - center_a, points - center_b
    cos = (ra * rb).sum(1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def write_covisibility(path: Path, names: list[str], visible: list[np.ndarray], num_points: int,
                       cameras: list[Camera], views: list[SurfaceView]) -> Path:
    """Write "name0 name1 shared overlap overlap01 overlap10" for every pair sharing a sample point.

    ``visible[i]``: ids of the face sample points photo i sees (of ``num_points``);
    ``overlap01``: ``pixel_overlap`` of photo 0 in photo 1, ``overlap10`` the converse.
    """
    shared, seen = covisibility_counts(visible, num_points)
    lines = []
    for i, j, count in sorted(zip(shared.row.tolist(), shared.col.tolist(), shared.data.tolist())):
        if i < j and count > 0:
            o01 = pixel_overlap(views[i], cameras[i], views[j], cameras[j])
            o10 = pixel_overlap(views[j], cameras[j], views[i], cameras[i])
            lines.append(f"{names[i]} {names[j]} {count} {count / max(1, min(seen[i], seen[j])):.4f} "
                         f"{o01:.4f} {o10:.4f}\n")
    path.write_text("".join(lines))
    return path


def read_covisibility(scene_dir: str | Path, min_overlap: float = 0.1,
                      matchable: bool = False) -> dict[frozenset, float]:
    """Ground-truth pairs ``{frozenset((a, b)): overlap}`` with overlap >= ``min_overlap``.

    ``matchable=False``: every co-visible pair (shared face sample points over the smaller
    view's); ``matchable=True``: the pixel overlap, the smaller of the two directions: the
    fraction of each photo's surface pixels that the other sees from at most
    MATCHABLE_ANGLE_DEG away (the pairs local features can match; the retrieval ground truth).
    """
    path = Path(scene_dir) / "covisibility.txt"
    try:
        pairs = {}
        for line in path.read_text().splitlines():
            fields = line.split()
            if len(fields) != 6:
                raise ValueError(f"{len(fields)} columns, expected 6")
            overlap = min(float(fields[4]), float(fields[5])) if matchable else float(fields[3])
            if overlap >= min_overlap:
                pairs[frozenset(fields[:2])] = overlap
    except (OSError, ValueError) as exc:
        raise SekdError(f"{path}: cannot read the co-visibility file ({exc}); generate the scene again") from None
    return pairs
