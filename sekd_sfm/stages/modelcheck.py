"""The model check, after mapping: verified pairs that the model's own poses contradict.

A folded model (look-alikes joined, part of the cameras turned round) is consistent with the
pairs it was built from, not with the right pairs across the fold. So every verified pair of two
photos of one model with ``min_inliers`` or more inliers is checked against the model's cameras
(poses, intrinsics, distortion): a pair with under ``min_agreement`` of its inliers within
``max_error_px`` (Sampson) contradicts it. The model is ``suspect`` when ``min_strong`` or more
contradicting pairs have at least the tested pairs' lower-quartile inlier count (the wrong pairs
a correct model leaves out are weak). Measured: docs/experiments.md, section 32.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..evaluation.metrics import essential_matrix
from .colmap import open_database, require_pycolmap


@dataclass
class ModelCheckConfig:
    """Settings of the model check (``check_model``)."""

    enabled: bool = True
    #: Pairs with fewer inliers are not tested (their share of agreement is noise).
    min_inliers: int = 30
    #: Distance (px, Sampson) within which an inlier fits the model's epipolar geometry: COLMAP's verification's.
    max_error_px: float = 4.0
    #: A pair whose inliers fit the model's poses less than this share contradicts the model.
    min_agreement: float = 0.5
    #: A model is flagged when at least this many contradicting pairs have as many inliers as the lower quartile
    #: of the tested pairs (folded models measured: 5 and more; correct ones: none).
    min_strong: int = 2
    #: Contradicting pairs listed in the record (strongest first).
    listed: int = 10


def model_essential(reconstruction, image1: int, image2: int) -> np.ndarray:
    """The 3 x 3 essential matrix (normalized camera coordinates of image1 -> epipolar lines in image2's) of two
    registered images as ``reconstruction`` poses them."""
    a, b = reconstruction.images[image1], reconstruction.images[image2]
    relative = b.cam_from_world() * a.cam_from_world().inverse()
    return essential_matrix(relative.rotation.matrix(), relative.translation)


def sampson2(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Squared Sampson distances of the matches ``x1`` <-> ``x2`` (N x 2 each) to ``F`` (in x's units squared)."""
    h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    numerator = np.sum(h2 * Fx1, axis=1) ** 2
    return numerator / np.maximum(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2, 1e-30)


def pair_agreement(reconstruction, image1: int, image2: int, x1: np.ndarray, x2: np.ndarray,
                   max_error_px: float) -> float:
    """The share of the matches ``x1`` <-> ``x2`` (pixels, N x 2 each) within ``max_error_px`` of the epipolar
    geometry the model gives the two images. The keypoints are undistorted by their cameras first and the
    distance measured in normalized coordinates, then scaled by the mean focal length back to pixels."""
    camera1 = reconstruction.cameras[reconstruction.images[image1].camera_id]
    camera2 = reconstruction.cameras[reconstruction.images[image2].camera_id]
    n1, n2 = np.asarray(camera1.cam_from_img(x1)), np.asarray(camera2.cam_from_img(x2))
    focal = 0.5 * (camera1.mean_focal_length() + camera2.mean_focal_length())
    distances = sampson2(model_essential(reconstruction, image1, image2), n1, n2) * focal ** 2
    return float(np.mean(distances <= max_error_px ** 2))


def matched_points(db, keypoints: dict[int, np.ndarray], image1: int, image2: int,
                   matches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pixel positions (N x 2 each) of ``matches`` (keypoint indices, N x 2) between two images of the open
    database ``db``; ``keypoints`` caches each image's keypoints across calls."""
    for image_id in (image1, image2):
        if image_id not in keypoints:
            keypoints[image_id] = np.asarray(db.read_keypoints(image_id), np.float64)[:, :2]
    return keypoints[image1][matches[:, 0]], keypoints[image2][matches[:, 1]]


def check_model(reconstruction, database: str | Path, config: ModelCheckConfig | None = None) -> dict:
    """The verified pairs of ``database`` between images of ``reconstruction`` that its poses contradict (module
    doc). Returns the record: pairs tested and their inliers, contradicting pairs and their inliers, the share,
    ``suspect`` (the model may be folded), the strongest contradicting pairs (names, inliers, agreement)."""
    pycolmap = require_pycolmap()
    config = config or ModelCheckConfig()
    names = {image_id: image.name for image_id, image in reconstruction.images.items() if image.has_pose}
    by_name = {name: image_id for image_id, name in names.items()}
    counts: list[int] = []
    listed: list[dict] = []
    with open_database(database) as db:
        db_names = {image.image_id: image.name for image in db.read_all_images()}
        keypoints: dict[int, np.ndarray] = {}
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            matches = np.asarray(geometry.inlier_matches).reshape(-1, 2)
            if len(matches) < config.min_inliers:
                continue
            id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
            model1, model2 = by_name.get(db_names[id1]), by_name.get(db_names[id2])
            if model1 is None or model2 is None:
                continue
            agreement = pair_agreement(reconstruction, model1, model2,
                                       *matched_points(db, keypoints, id1, id2, matches), config.max_error_px)
            counts.append(len(matches))
            if agreement < config.min_agreement:
                listed.append({"pair": [db_names[id1], db_names[id2]], "inliers": len(matches),
                               "agreement": round(agreement, 3)})
    listed.sort(key=lambda p: -p["inliers"])
    quartile = float(np.percentile(counts, 25)) if counts else 0.0
    strong = sum(p["inliers"] >= quartile for p in listed)
    contradicting_inliers = sum(p["inliers"] for p in listed)
    return {"pairs": len(counts), "inliers": int(sum(counts)), "contradicting": len(listed),
            "contradicting_inliers": contradicting_inliers,
            "contradicting_share": round(contradicting_inliers / sum(counts), 5) if counts else 0.0,
            "lower_quartile_inliers": quartile, "strong_contradicting": strong, "suspect": strong >= config.min_strong,
            "strongest": listed[:config.listed], "config": asdict(config)}
