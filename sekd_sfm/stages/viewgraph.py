"""The view-graph check, between geometric verification and mapping: verified pairs that disagree with the rest.

On repeated or symmetric structure (rows of like columns, facades that show the same subject)
two photos of different places can share enough look-alike matches to pass verification: the
pair is geometrically consistent, and wrong. One such pair is enough to fold or split a model.
What betrays it is the rest of the graph (Zach et al., CVPR 2010; GLOMAP's relative-pose
filter): the relative rotations of correct pairs compose consistently around every loop of the
view graph, a wrong pair's does not. So:

1. every verified pair's relative rotation, from its own two-view geometry and the database's
   cameras (``pycolmap.estimate_two_view_geometry_pose``: E, or F with the cameras' prior
   focal lengths, or H);
2. one rotation per photo by robust rotation averaging: a maximum spanning tree over the pairs
   weighted by their inlier counts to start, then iteratively reweighted chordal averaging (a
   Cauchy weight per pair, so a few wrong pairs cannot pull the rest);
3. pairs whose rotation disagrees with the averaged ones by more than ``threshold`` (the larger
   of ``min_error_deg`` and ``sigmas`` robust standard deviations of all pairs' disagreements: a
   prior focal length that is off bends every pair a little, a wrong pair a lot) are dropped from
   the database's verified pairs (their raw matches stay), and the averaging is repeated without
   them until no pair is dropped.

The check changes nothing where the graph has no loops (a pair or a chain), and it keeps at
least one pair for each photo that has a pair the averaging agrees with.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..evaluation.metrics import rotation_angles_deg
from .colmap import delete_verified_pairs, open_database, require_pycolmap

logger = logging.getLogger("sekd")


@dataclass
class ViewGraphConfig:
    """Settings of the view-graph check (``check_view_graph``); angles in degrees. Off by default: on the scenes
    measured it removed the wrong pairs but also right ones (planar pairs whose rotation is ambiguous) and made no
    model better (docs/experiments.md, section 31)."""

    enabled: bool = False
    #: Smallest disagreement (deg) between a pair's rotation and the averaged rotations that drops it.
    min_error_deg: float = 5.0
    #: ... or this many robust standard deviations of all pairs' disagreements, when that is larger.
    sigmas: float = 4.0
    #: Rounds of reweighted averaging per pass.
    iterations: int = 40
    #: Passes (averaging, then dropping) at most; a pass that drops nothing ends the check.
    passes: int = 4


@dataclass
class Edge:
    """A verified pair: image ids and names, ``rotation`` = cam2_from_cam1's 3 x 3 matrix, its inlier count."""

    image1: int
    image2: int
    name1: str
    name2: str
    rotation: np.ndarray
    inliers: int


#: The verified configurations a relative rotation can be read from.
_POSED = ("CALIBRATED", "UNCALIBRATED", "PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC")


def read_edges(database: str | Path, min_inliers: int,
               calibrate: bool = True) -> tuple[list[Edge], dict[int, FocalEstimate]]:
    """Every verified pair of ``database`` with at least ``min_inliers`` inliers whose relative pose can be
    estimated, with its relative rotation (pair order as COLMAP stores it), and the focal lengths estimated.
    ``calibrate``: the focal lengths of cameras without a prior (no EXIF: COLMAP guesses 1.2 x the long side) are
    first estimated from the pairs' fundamental matrices (``calibrate_focal_lengths``), so that F's rotations are
    not bent by the guess."""
    pycolmap = require_pycolmap()
    posed = {getattr(pycolmap.TwoViewGeometryConfiguration, name) for name in _POSED}
    with open_database(database) as db:
        images = {image.image_id: image for image in db.read_all_images()}
        cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
        verified = [(pycolmap.pair_id_to_image_pair(pair_id), geometry)
                    for pair_id, geometry in zip(*db.read_two_view_geometries())
                    if len(geometry.inlier_matches) >= min_inliers and geometry.config in posed]
        keypoints = {image_id: np.asarray(db.read_keypoints(image_id), np.float64)[:, :2]
                     for image_id in sorted({i for pair, _ in verified for i in pair})}
    camera_of = {image_id: image.camera_id for image_id, image in images.items()}
    uncalibrated = [(camera_of[i1], camera_of[i2], g.F) for (i1, i2), g in verified
                    if g.config == pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED]
    estimates = calibrate_focal_lengths(cameras, uncalibrated) if calibrate and uncalibrated else {}
    edges: list[Edge] = []
    for (id1, id2), geometry in verified:
        camera1, camera2 = cameras[camera_of[id1]], cameras[camera_of[id2]]
        if not pycolmap.estimate_two_view_geometry_pose(camera1, keypoints[id1], camera2, keypoints[id2], geometry):
            continue
        rotation = np.asarray(geometry.cam2_from_cam1.rotation.matrix(), np.float64)
        edges.append(Edge(id1, id2, images[id1].name, images[id2].name, rotation,
                          len(geometry.inlier_matches)))
    return edges, estimates


def essential_cost(F: np.ndarray, K1: np.ndarray, K2: np.ndarray, scale: float = 0.1) -> np.ndarray:
    """How far ``K2^T F K1`` is from an essential matrix, per pair (``F``: ``P x 3 x 3``, ``K1``/``K2``: ``P x 3 x 3``):
    a robust (Cauchy) cost of its two non-zero singular values' relative difference, which is 0 for E."""
    s = np.linalg.svd(K2.transpose(0, 2, 1) @ F @ K1, compute_uv=False)
    r = (s[:, 0] - s[:, 1]) / np.maximum(s[:, 0] + s[:, 1], 1e-12)
    return r ** 2 / (r ** 2 + scale ** 2)


#: The focal lengths tried, as factors of the camera's current one: 0.3x to 3x on a log grid, then +-10 % finer.
_FOCAL_FACTORS = np.exp(np.linspace(np.log(0.3), np.log(3.0), 241))
_FINE_FACTORS = np.exp(np.linspace(np.log(0.9), np.log(1.1), 81))


#: A camera's focal length counts as determined by its pairs when the median cost 10 % away from the best focal
#: length is at least this many times the best's. Measured: fountain-P11 (no EXIF) 17-18x, its estimate 1.3 % from
#: the truth; a turntable under a 24 deg lens 1.1-1.2x (rotation about one axis is a critical motion for
#: self-calibration), its estimate 4 % off, enough to bend correct pairs' rotations past the check's threshold.
MIN_FOCAL_SHARPNESS = 2.0


@dataclass
class FocalEstimate:
    """A camera's focal length from its pairs (px), and how sharply the pairs determine it (``MIN_FOCAL_SHARPNESS``)."""

    focal: float
    sharpness: float

    @property
    def determined(self) -> bool:
        return self.sharpness >= MIN_FOCAL_SHARPNESS


def calibrate_focal_lengths(cameras: dict, pairs: list[tuple[int, int, np.ndarray]],
                            sweeps: int = 8) -> dict[int, FocalEstimate]:
    """Set the focal length of each camera of ``cameras`` (id -> pycolmap.Camera, changed in place) that has no
    prior to the one that makes the fundamental matrices of ``pairs`` (camera id 1, camera id 2, F) most nearly
    essential, by the median over its pairs (GLOMAP's view-graph calibration, as a grid search per camera: first
    over its pairs with itself, where it has some, then coordinate sweeps over all pairs until nothing moves).
    Cameras with a prior focal length (EXIF), or in no pair, keep theirs. Returns id -> FocalEstimate."""
    free = sorted({c for c1, c2, _ in pairs for c in (c1, c2) if not cameras[c].has_prior_focal_length})
    if not free:
        return {}
    focal = {c: float(cameras[c].mean_focal_length()) for c in cameras}
    F = np.stack([f for _, _, f in pairs])
    first, second = np.array([c1 for c1, _, _ in pairs]), np.array([c2 for _, c2, _ in pairs])
    centre = {c: (cameras[c].principal_point_x, cameras[c].principal_point_y) for c in cameras}

    def calibrations(ids: np.ndarray, focals: np.ndarray) -> np.ndarray:
        K = np.zeros((len(ids), 3, 3))
        K[:, 0, 0] = K[:, 1, 1] = focals
        K[:, :2, 2] = [centre[c] for c in ids]
        K[:, 2, 2] = 1.0
        return K

    def costs(camera_id: int, rows: np.ndarray, trials: np.ndarray) -> np.ndarray:
        ids1, ids2 = first[rows], second[rows]
        f1, f2 = np.array([focal[c] for c in ids1]), np.array([focal[c] for c in ids2])
        return np.array([np.median(essential_cost(F[rows], calibrations(ids1, np.where(ids1 == camera_id, f, f1)),
                                                  calibrations(ids2, np.where(ids2 == camera_id, f, f2))))
                         for f in trials])

    def best(camera_id: int, rows: np.ndarray, factors: np.ndarray) -> float:
        trials = focal[camera_id] * factors
        return float(trials[int(np.argmin(costs(camera_id, rows, trials)))])

    for camera_id in free:  # a start from the camera's own pairs, free of the other cameras' guesses
        own = (first == camera_id) & (second == camera_id)
        if own.sum() >= 3:
            focal[camera_id] = best(camera_id, own, _FOCAL_FACTORS)
    # One camera: a coarse sweep, then a fine one. Several: sweeps until nothing moves (each fine after the first).
    for sweep in range(sweeps if len(free) > 1 else 2):
        before = dict(focal)
        for camera_id in free:
            mine = (first == camera_id) | (second == camera_id)
            focal[camera_id] = best(camera_id, mine, _FOCAL_FACTORS if sweep == 0 else _FINE_FACTORS)
        if all(abs(focal[c] / before[c] - 1) < 1e-3 for c in free):
            break
    estimates = {}
    for camera_id in free:
        mine = (first == camera_id) | (second == camera_id)
        at, *near = costs(camera_id, mine, focal[camera_id] * np.array([1.0, 0.9, 1 / 0.9]))
        estimates[camera_id] = FocalEstimate(focal[camera_id], float(min(near) / max(at, 1e-12)))
        cameras[camera_id].focal_length = focal[camera_id]  # SIMPLE_* / RADIAL models: the one focal parameter
    return estimates


def _project(M: np.ndarray) -> np.ndarray:
    """The nearest rotation to each 3 x 3 matrix of ``M`` (``... x 3 x 3``), by SVD."""
    U, _, Vt = np.linalg.svd(M)
    D = np.ones(M.shape[:-1])
    D[..., -1] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def spanning_rotations(n: int, a: np.ndarray, b: np.ndarray, Rab: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """World-to-camera rotations of ``n`` photos chained along the maximum spanning forest of the pairs
    (``a[k], b[k]``: photo indices, ``Rab[k]``: b's rotation times a's transposed, ``weights[k]``: its strength).
    Each tree's first photo gets the identity."""
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    tree: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(n)]
    for k in np.argsort(-weights, kind="stable"):
        ra, rb = root(int(a[k])), root(int(b[k]))
        if ra != rb:
            parent[ra] = rb
            tree[a[k]].append((int(b[k]), Rab[k]))        # R_b = Rab R_a
            tree[b[k]].append((int(a[k]), Rab[k].T))      # R_a = Rab^T R_b
    R = np.tile(np.eye(3), (n, 1, 1))
    seen = np.zeros(n, bool)
    for start in range(n):
        if seen[start]:
            continue
        seen[start], stack = True, [start]
        while stack:
            i = stack.pop()
            for j, Rij in tree[i]:
                if not seen[j]:
                    R[j], seen[j] = Rij @ R[i], True
                    stack.append(j)
    return R


def average_rotations(R: np.ndarray, a: np.ndarray, b: np.ndarray, Rab: np.ndarray, weights: np.ndarray,
                      scale_deg: float, iterations: int) -> np.ndarray:
    """Refine rotations ``R`` (``n x 3 x 3``) to agree with the pairs: iteratively reweighted chordal averaging,
    each pair weighted by ``weights`` times a Cauchy weight of its disagreement (``scale_deg``)."""
    for _ in range(iterations):
        residual = rotation_angles_deg(Rab @ R[a] @ R[b].transpose(0, 2, 1))
        w = weights / (1 + (residual / scale_deg) ** 2)
        M = np.zeros_like(R)
        np.add.at(M, a, w[:, None, None] * (Rab.transpose(0, 2, 1) @ R[b]))  # a's rotation as b's pair sees it
        np.add.at(M, b, w[:, None, None] * (Rab @ R[a]))
        has = np.abs(M).sum(axis=(1, 2)) > 0
        R[has] = _project(M[has])
    return R


def disagreements(edges: list[Edge], config: ViewGraphConfig) -> np.ndarray:
    """Each pair's disagreement (deg) with rotations averaged over all ``edges``."""
    ids = sorted({e.image1 for e in edges} | {e.image2 for e in edges})
    index = {image_id: i for i, image_id in enumerate(ids)}
    a = np.array([index[e.image1] for e in edges], np.int64)
    b = np.array([index[e.image2] for e in edges], np.int64)
    Rab = np.stack([e.rotation for e in edges])
    weights = np.sqrt(np.array([e.inliers for e in edges], np.float64))  # many inliers: a surer rotation
    R = spanning_rotations(len(ids), a, b, Rab, weights)
    R = average_rotations(R, a, b, Rab, weights, config.min_error_deg, config.iterations)
    return rotation_angles_deg(Rab @ R[a] @ R[b].transpose(0, 2, 1))


def _threshold(residual: np.ndarray, config: ViewGraphConfig) -> float:
    sigma = 1.4826 * float(np.median(residual)) if len(residual) else 0.0
    return max(config.min_error_deg, config.sigmas * sigma)


def find_inconsistent(edges: list[Edge], config: ViewGraphConfig) -> tuple[list[tuple[Edge, float]], dict]:
    """The pairs of ``edges`` to drop, with their disagreement (deg), and the check's record."""
    kept, dropped = list(edges), []
    threshold, residual = config.min_error_deg, np.zeros(0)
    for _ in range(config.passes):
        if len(kept) < 3:
            break
        residual = disagreements(kept, config)
        threshold = _threshold(residual, config)
        worse = residual > threshold
        if not worse.any():
            break
        dropped += [(e, float(r)) for e, r, w in zip(kept, residual, worse) if w]
        kept = [e for e, w in zip(kept, worse) if not w]
    record = {"pairs": len(edges), "dropped": len(dropped), "threshold_deg": round(threshold, 3),
              "median_disagreement_deg": round(float(np.median(residual)), 3) if len(residual) else None}
    return dropped, record


def check_view_graph(database: str | Path, min_inliers: int, config: ViewGraphConfig | None = None) -> dict:
    """Drop from ``database``'s verified pairs those whose rotation disagrees with the view graph (module doc);
    their raw matches stay. Returns the record: pairs checked, dropped (with names, inliers, disagreement), the
    threshold, the median disagreement, the focal lengths estimated, the settings; or why the check was skipped
    (a camera without EXIF whose focal length its pairs do not determine: its rotations could not be trusted)."""
    config = config or ViewGraphConfig()
    edges, estimates = read_edges(database, min_inliers)
    focal = {str(c): {"focal_px": round(e.focal, 2), "sharpness": round(e.sharpness, 3)} for c, e in estimates.items()}
    undetermined = sorted(c for c, e in estimates.items() if not e.determined)
    if undetermined:
        logger.info("view graph: not checked: the focal length of camera %d (no EXIF) is not determined by its pairs "
                    "(a turntable or a narrow lens); pass --camera-params to check it", undetermined[0])
        return {"pairs": len(edges), "dropped": 0, "dropped_pairs": [], "focal_lengths": focal,
                "skipped": f"the focal length of camera(s) {undetermined} is not determined by their pairs",
                "config": asdict(config)}
    dropped, record = find_inconsistent(edges, config)
    if dropped:
        delete_verified_pairs(database, [(edge.image1, edge.image2) for edge, _ in dropped])
        logger.info("view graph: %d of %d verified pairs dropped, their rotation %.1f deg or more from the "
                    "others' (repeated or symmetric structure)", len(dropped), len(edges), record["threshold_deg"])
    record["dropped_pairs"] = [{"pair": [e.name1, e.name2], "inliers": e.inliers, "disagreement_deg": round(r, 2)}
                               for e, r in sorted(dropped, key=lambda d: -d[1])]
    record["focal_lengths"] = focal
    record["config"] = asdict(config)
    return record
