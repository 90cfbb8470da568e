"""Two-view relative pose (``sekd relpose``): two images -> R, t, inliers.

Convention: ``x1 = R x0 + t`` maps a point from camera 0's frame to camera 1's (COLMAP's
``cam2_from_cam1``); ``t`` has unit length, since two views fix no scale. The essential
matrix is estimated by LO-RANSAC in pycolmap, so intrinsics are needed: given ones
(COLMAP pixel convention), else the EXIF focal length, else COLMAP's default
1.2 x the longer image side (then the pose is only as good as that guess).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..features import FeatureConfig, build_extractor
from ..files.images import (
    ImageReadError,
    read_image,
    resize_max_side,
    to_original_pixels,
)
from ..stages.colmap import require_pycolmap
from ..stages.database import COLMAP_PIXEL_OFFSET, parse_camera_params
from ..stages.match import MatchConfig, describe_config, match_descriptors

#: Fewer matches than this cannot give a trustworthy essential matrix.
MIN_MATCHES = 15


@dataclass
class RelposeConfig:
    """Features and matching; ``camera_model`` + ``camera_params`` ("f,cx,cy", shared by both images) if known."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    matching: MatchConfig = field(default_factory=MatchConfig)
    camera_model: str = "SIMPLE_PINHOLE"
    camera_params: str | None = None
    max_error: float = 4.0
    seed: int = 0


def _features(extractor, path: Path, resize_max: int | None) -> tuple[dict, tuple[int, int]]:
    try:
        image = read_image(path, grayscale=not getattr(extractor, "color", False))
    except ImageReadError as exc:
        raise SekdError(str(exc)) from None
    small, sx, sy = resize_max_side(image, resize_max)
    result = extractor.extract(small)
    result["keypoints"] = to_original_pixels(result["keypoints"], sx, sy)
    return result, (image.shape[1], image.shape[0])


def _camera(path: Path, size: tuple[int, int], config: RelposeConfig):
    """A pycolmap camera and where its focal length came from ("given", "exif" or "default")."""
    pycolmap = require_pycolmap()
    params = parse_camera_params(config.camera_model, config.camera_params, *size)
    if params is not None:
        return pycolmap.Camera(model=config.camera_model, width=size[0], height=size[1], params=params), "given"
    camera = pycolmap.infer_camera_from_image(str(path))
    return camera, "exif" if camera.has_prior_focal_length else "default"


def _matched_points(f0: dict, f1: dict, config: RelposeConfig) -> tuple[np.ndarray, np.ndarray]:
    """Matched keypoints, ``M x 2`` float64 each, in COLMAP's pixel convention."""
    binary = f0["descriptors"].dtype == np.uint8
    described = describe_config(config.matching, config.features.feature, binary)
    matches, _ = match_descriptors(f0["descriptors"], f1["descriptors"], described["mode"], described["ratio"],
                                   described["rootsift"], config.matching.device)
    idx = np.flatnonzero(matches >= 0)
    p0 = f0["keypoints"][idx].astype(np.float64) + COLMAP_PIXEL_OFFSET
    p1 = f1["keypoints"][matches[idx]].astype(np.float64) + COLMAP_PIXEL_OFFSET
    return p0, p1


def relative_pose(image0: str | Path, image1: str | Path, config: RelposeConfig | None = None) -> dict:
    """Relative pose of ``image1`` with respect to ``image0``: R (3x3), unit t (3), inlier count, cameras.

    SekdError when too few matches are found or RANSAC finds no pose (the message gives the counts).
    """
    pycolmap = require_pycolmap()
    config = config or RelposeConfig()
    paths = [Path(image0), Path(image1)]
    parse_camera_params(config.camera_model, config.camera_params)  # fail before the slow part
    extractor, _ = build_extractor(config.features)
    (f0, size0), (f1, size1) = (_features(extractor, p, config.features.resize_max) for p in paths)
    p0, p1 = _matched_points(f0, f1, config)
    counts = f"{len(f0['keypoints'])} and {len(f1['keypoints'])} keypoints, {len(p0)} matches"
    if len(p0) < MIN_MATCHES:
        raise SekdError(f"too few matches for a relative pose: {counts} (need {MIN_MATCHES}); "
                        "try more keypoints, a looser --ratio, or images with more overlap")
    (cam0, source0), (cam1, source1) = _camera(paths[0], size0, config), _camera(paths[1], size1, config)
    options = pycolmap.RANSACOptions(max_error=config.max_error)
    options.random_seed = config.seed
    result = pycolmap.estimate_essential_matrix(p0, p1, cam0, cam1, options)
    if result is None:
        raise SekdError(f"RANSAC found no essential matrix: {counts}; the images may not overlap")
    return {"image0": str(paths[0]), "image1": str(paths[1]), **_pose(result),
            "num_keypoints": [len(f0["keypoints"]), len(f1["keypoints"])],
            "num_matches": len(p0), "num_inliers": int(result["num_inliers"]),
            "cameras": [{"model": c.model_name, "params": np.asarray(c.params).tolist(), "focal_from": s}
                        for c, s in ((cam0, source0), (cam1, source1))]}


def _pose(result: dict) -> dict:
    """R and unit t of pycolmap's ``cam2_from_cam1`` as plain lists."""
    pose = result["cam2_from_cam1"]
    t = np.asarray(pose.translation, dtype=np.float64)
    return {"R": np.asarray(pose.rotation.matrix()).tolist(), "t": (t / max(np.linalg.norm(t), 1e-12)).tolist(),
            "convention": "x1 = R x0 + t (camera 1 from camera 0); t has unit length"}
