"""The hierarchical mapper's merge (``hierarchical``, step 3), in the mapper's child process (``mapper_worker``):
the clusters' models joined by similarities from the cameras they share, then the points triangulated again
from the whole database with the merged poses held, at a tolerance that lets tracks cross the seams
(``SEAM_MAX_ERROR_PX``). NumPy, pycolmap (the module passed in) and ``colmap``'s
database opener only: no torch, as the child.
"""
from __future__ import annotations

import copy
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .colmap import open_database

#: Cameras shared with what is merged a model needs to join it (fewer: it stays a model of its own).
MIN_SHARED = 3
#: A shared camera agrees with the similarity when its rotation is within this angle (deg) ...
MAX_ROTATION_DEG = 5.0
#: ... and its centre within this share of the shared cameras' spread (median distance to their centroid).
MAX_CENTER_SHARE = 0.1
#: Where two clusters meet, their poses disagree by a few pixels (each drifted its own way): more than COLMAP's
#: 4 px, so with its tolerances no track crossed the seam, the adjustment could not close it and the model kept a
#: kink there (a generated 1,000-photo walk: 3 points shared across one seam by the 10 photos on either side,
#: ~1,400 across every other cut). Tracks are made and kept up to this error (px) instead; the merged model's
#: robust adjustment pulls the seams in and drops what stays beyond 4 px (``mapper_worker.bundle_adjust_merged``):
#: pose AUC@5 0.933 -> 0.958 on that walk, 0.780 -> 0.913 on a 2,000-photo one. A seam off by much more than this
#: keeps few tracks; the merge's later passes (``mapper_worker.MERGE_PASS_TOLERANCES_PX``) triangulate again once
#: the first pass's adjustment has pulled it in (docs/experiments.md, sections 41 to 44).
SEAM_MAX_ERROR_PX = 16.0


@dataclass
class Piece:
    """One model of one cluster (or what has been merged): photo id -> ``cam_from_world`` (3 x 4), camera id ->
    parameters."""

    poses: dict[int, np.ndarray]
    cameras: dict[int, np.ndarray] = field(default_factory=dict)


def pieces_of(arrays: dict[str, np.ndarray]) -> list[Piece]:
    """The models of one cluster's ``model_arrays``, largest first."""
    pieces = [Piece({}) for _ in range(int(arrays["model"].max()) + 1 if len(arrays["model"]) else 0)]
    for image_id, k, pose in zip(arrays["image_ids"], arrays["model"], arrays["cam_from_world"]):
        pieces[int(k)].poses[int(image_id)] = pose
    for row in arrays["cameras"]:
        params = row[2:]
        pieces[int(row[0])].cameras[int(row[1])] = params[~np.isnan(params)]
    return pieces


def centers(poses: list[np.ndarray]) -> np.ndarray:
    """Camera centres ``(K, 3)`` of ``cam_from_world`` poses ``(K, 3, 4)``."""
    stacked = np.asarray(poses)
    return -np.einsum("kji,kj->ki", stacked[:, :, :3], stacked[:, :, 3])


def _mean_rotation(rotations: np.ndarray) -> np.ndarray:
    """The rotation nearest the mean of ``rotations (K, 3, 3)`` (chordal L2 mean)."""
    u, _, vt = np.linalg.svd(rotations.mean(axis=0))
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (deg) between rotations ``a (K, 3, 3)`` and ``b (3, 3)``."""
    cos = (np.einsum("kij,ij->k", a, b) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def similarity(source: dict[int, np.ndarray], target: dict[int, np.ndarray]):
    """``(scale, R, t)`` taking ``source``'s world to ``target``'s (``x_t = scale * R @ x_s + t``) from the photos
    both hold, and the ids that agree with it; None with fewer than MIN_SHARED agreeing.

    Rotation: the candidate (one per shared camera) most others agree with, averaged over those; scale and offset
    first robustly (the median ratio of distances between shared centres, the median offset) to drop the centres
    that disagree, then by least squares over the others. Orientations make it well posed even where the shared
    centres lie on a line (a walk's clusters meet along the path)."""
    shared = sorted(set(source) & set(target))
    if len(shared) < MIN_SHARED:
        return None
    src, tgt = np.array([source[i] for i in shared]), np.array([target[i] for i in shared])
    candidates = np.einsum("kji,kjl->kil", tgt[:, :, :3], src[:, :, :3])  # R_k = R_tgt_k^T R_src_k
    votes = [int((_angle_deg(candidates, c) < MAX_ROTATION_DEG).sum()) for c in candidates]
    best = candidates[int(np.argmax(votes))]
    agree = _angle_deg(candidates, best) < MAX_ROTATION_DEG
    if agree.sum() < MIN_SHARED:
        return None
    rotation = _mean_rotation(candidates[agree])
    c_src, c_tgt = centers(src), centers(tgt)
    a, b = np.triu_indices(len(shared), 1)
    d_src = np.linalg.norm(c_src[a] - c_src[b], axis=1)
    d_tgt = np.linalg.norm(c_tgt[a] - c_tgt[b], axis=1)
    usable = (d_src > 1e-9) & agree[a] & agree[b]
    if not usable.any():
        return None
    scale = float(np.median(d_tgt[usable] / d_src[usable]))
    offset = c_tgt - scale * c_src @ rotation.T
    translation = np.median(offset[agree], axis=0)
    spread = float(np.median(np.linalg.norm(c_tgt - c_tgt.mean(axis=0), axis=1)))
    error = np.linalg.norm(c_src @ rotation.T * scale + translation - c_tgt, axis=1)
    agree &= error <= MAX_CENTER_SHARE * max(spread, 1e-9)
    if agree.sum() < MIN_SHARED:
        return None
    # The robust estimates found the agreeing cameras; least squares over them is the precise scale and offset.
    rotated, target = c_src[agree] @ rotation.T, c_tgt[agree]
    rotated_mean, target_mean = rotated.mean(axis=0), target.mean(axis=0)
    spread_src = float(((rotated - rotated_mean) ** 2).sum())
    if spread_src > 1e-18:
        scale = float(((rotated - rotated_mean) * (target - target_mean)).sum()) / spread_src
        translation = target_mean - scale * rotated_mean
    return scale, rotation, translation, [shared[k] for k in np.flatnonzero(agree)]


def moved(pose: np.ndarray, scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """``cam_from_world`` (3 x 4) of a camera of the source world, in the target world of ``similarity``."""
    r = pose[:, :3] @ rotation.T
    return np.c_[r, scale * pose[:, 3] - r @ translation]


def merge_pieces(pieces: list[Piece]) -> list[Piece]:
    """The pieces joined into models: the largest first, then repeatedly the piece sharing most photos with it,
    moved by their ``similarity`` (photos it already holds keep their pose); pieces that join nothing start models
    of their own. Largest model first."""
    left = sorted(pieces, key=lambda p: -len(p.poses))
    models: list[Piece] = []
    while left:
        merged = Piece(dict(left[0].poses), dict(left[0].cameras))
        left = left[1:]
        while (joined := _next_to_join(left, merged)) is not None:
            k, (scale, rotation, translation, _) = joined
            piece = left.pop(k)
            for image_id, pose in piece.poses.items():
                merged.poses.setdefault(image_id, moved(pose, scale, rotation, translation))
            for camera_id, params in piece.cameras.items():
                merged.cameras.setdefault(camera_id, params)
        models.append(merged)
    return sorted(models, key=lambda p: -len(p.poses))


def _next_to_join(left: list[Piece], merged: Piece):
    """``(index in left, similarity)`` of the piece sharing most photos with ``merged`` that aligns with it (at
    least MIN_SHARED shared), or None."""
    shared = [len(merged.poses.keys() & piece.poses.keys()) for piece in left]
    for k in sorted(range(len(left)), key=lambda k: -shared[k]):
        if shared[k] < MIN_SHARED:
            return None
        found = similarity(left[k].poses, merged.poses)
        if found is not None:
            return k, found
    return None


def seam_options(options, tolerance_px: float = SEAM_MAX_ERROR_PX):
    """A copy of ``options`` (IncrementalPipelineOptions) whose triangulation makes and keeps tracks up to
    ``tolerance_px`` (merging, completing and filtering), at least the given tolerances."""
    relaxed = copy.deepcopy(options)
    tolerance = relaxed.triangulation
    tolerance.merge_max_reproj_error = max(tolerance.merge_max_reproj_error, tolerance_px)
    tolerance.complete_max_reproj_error = max(tolerance.complete_max_reproj_error, tolerance_px)
    relaxed.mapper.filter_max_reproj_error = max(relaxed.mapper.filter_max_reproj_error, tolerance_px)
    return relaxed


def assemble(piece: Piece, database: str, image_dir: str, options, scratch: Path, pycolmap, triangulate: bool = True):
    """A Reconstruction of ``piece``'s photos at its poses and intrinsics, its points triangulated from
    ``database`` with the poses held (``triangulate_held``); ``triangulate=False``: the poses alone, no point."""
    cache_options = pycolmap.DatabaseCacheOptions()
    with open_database(database) as db:
        names = {image.name for image in db.read_all_images() if image.image_id in piece.poses}
        cache_options.image_names = names
        cache = pycolmap.DatabaseCache.create(db, cache_options)
    model = pycolmap.Reconstruction()
    model.load(cache)
    for camera_id, params in piece.cameras.items():
        if model.exists_camera(camera_id):
            model.camera(camera_id).params = params
    for image_id, pose in piece.poses.items():
        if not model.exists_image(image_id):
            continue  # no verified pair left among the merged photos
        image = model.image(image_id)
        model.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(pose)
        model.register_frame(image.frame_id)
    return triangulate_held(model, database, image_dir, options, scratch, pycolmap) if triangulate else model


def triangulate_held(model, database: str, image_dir: str, options, scratch: Path, pycolmap,
                     tolerance_px: float = SEAM_MAX_ERROR_PX):
    """``model`` with its points cleared and triangulated again from ``database``, its poses and intrinsics
    held (COLMAP's point triangulator, ``options``: IncrementalPipelineOptions, its tolerances widened to
    ``tolerance_px`` by ``seam_options``)."""
    scratch.mkdir(parents=True, exist_ok=True)
    result = pycolmap.triangulate_points(model, database, image_dir, str(scratch), clear_points=True,
                                         options=seam_options(options, tolerance_px), refine_intrinsics=False)
    shutil.rmtree(scratch, ignore_errors=True)
    return result
