"""Per-round validation on homography sequences (HPatches layout), small and fast.

For each sequence, pairs (1, k): top-k SEKD keypoints, mutual nearest-neighbour matching,
mean matching accuracy (MMA@t: fraction of matches within t px of the ground truth) and
homography accuracy (HA@t: RANSAC homography, mean corner error <= t px), t = 1..10,
as in docs/method.md but on images resized to ``val_long_side``.
"""
from __future__ import annotations

import glob
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn

from ..errors import SekdError
from ..evaluation import metrics
from ..evaluation.datasets import is_sequence, read_sequence
from ..files.images import read_image, resize_max_side, resized_to_original_matrix
from ..model.inference import SEKDConfig, SEKDExtractor
from ..runtime import shared_dir
from ..stages.match import match_descriptors
from .model import plain_copy

THRESHOLDS = tuple(range(1, 11))


@dataclass(frozen=True)
class Sequence:
    """One resized sequence: grayscale images ``1..N`` and homographies from image 1 to each other image."""

    name: str
    images: tuple[np.ndarray, ...]
    homographies: tuple[np.ndarray, ...]   # H_1_k for k = 2..N, in resized pixels


def find_sequences(patterns: list[str]) -> list[Path]:
    """Sequence folders matching ``patterns`` (absolute, or relative to the shared folder), sorted."""
    found = []
    for pattern in patterns:
        base = pattern if Path(pattern).is_absolute() else str(shared_dir() / pattern)
        found += [Path(p) for p in glob.glob(base) if is_sequence(Path(p))]
    if not found:
        raise SekdError(f"no homography sequences (folders with H_1_2) match val_sets {patterns}; "
                        "set SEKD_SHARED or --set validate=false")
    return sorted(set(found))


def _prepare(path: Path, long_side: int) -> tuple[np.ndarray, np.ndarray]:
    image, sx, sy = resize_max_side(read_image(path), long_side or None)
    h, w = image.shape
    return np.ascontiguousarray(image[: h - h % 16, : w - w % 16]), resized_to_original_matrix(sx, sy)


@lru_cache(maxsize=32)
def load_sequence(folder: Path, long_side: int) -> Sequence:
    """Images ``1..N`` of a sequence, resized, and each ``H_1_k`` re-expressed in resized pixels."""
    files = read_sequence(folder)
    first, s1 = _prepare(files.images[1], long_side)
    images, homographies = [first], []
    for k, h in sorted(files.homographies.items()):
        image, sk = _prepare(files.images[k], long_side)
        images.append(image)
        homographies.append(np.linalg.inv(sk) @ h @ s1)
    return Sequence(folder.name, tuple(images), tuple(homographies))


def mutual_matches(desc1: np.ndarray, desc2: np.ndarray) -> np.ndarray:
    """Index pairs ``M x 2`` of mutual nearest neighbours between descriptors ``N1 x D``, ``N2 x D``."""
    matches0, _ = match_descriptors(desc1, desc2, mode="mnn", device="cpu")
    keep = matches0 >= 0
    return np.stack([np.nonzero(keep)[0], matches0[keep]], axis=1).astype(np.int64)


def pair_scores(kp1: np.ndarray, kp2: np.ndarray, matches: np.ndarray, h_gt: np.ndarray,
                shape1: tuple[int, int]) -> tuple[np.ndarray, float]:
    """(MMA at each threshold, corner error of the RANSAC homography; inf when estimation fails)."""
    p1, p2 = kp1.astype(np.float64), kp2.astype(np.float64)
    mma = metrics.match_accuracy(p1, p2, matches, h_gt, THRESHOLDS)
    if len(matches) < 4:
        return mma, float("inf")
    h_est, _ = cv2.findHomography(p1[matches[:, 0]], p2[matches[:, 1]], cv2.RANSAC)
    return mma, metrics.corner_error(h_est, h_gt, shape1[1], shape1[0])


def evaluate(net: nn.Module, folders: list[Path], long_side: int, max_keypoints: int, threshold: float,
             nms_radius: int, device: torch.device) -> dict:
    """Validation metrics of ``net``: mma3, mma_avg (MMA@1..10), ha3, ha_avg (HA@1..10), per-subset mma3,
    and ``desc_cos``, the descriptors' mean pairwise cosine (collapse shows as a value near 1)."""
    config = SEKDConfig(max_keypoints=max_keypoints, threshold=threshold, nms_radius=nms_radius,
                        precision="fp32", device=device.type, subpixel=False)  # comparable with every past run
    extractor = SEKDExtractor(plain_copy(net), config)
    rows, cosines = [], []
    for folder in folders:
        seq = load_sequence(folder, long_side)
        feats = [extractor.extract(image) for image in seq.images]
        cosines.append(mean_pairwise_cosine(feats[0]["descriptors"]))
        for k, h_gt in enumerate(seq.homographies, start=1):
            matches = mutual_matches(feats[0]["descriptors"], feats[k]["descriptors"])
            mma, corner = pair_scores(feats[0]["keypoints"], feats[k]["keypoints"], matches, h_gt,
                                      seq.images[0].shape)
            rows.append((seq.name, mma, corner, len(matches), len(feats[0]["keypoints"])))
    return {**summarise(rows), "desc_cos": float(np.nanmean(cosines)) if cosines else float("nan")}


def mean_pairwise_cosine(descriptors: np.ndarray) -> float:
    """Mean cosine between distinct rows of ``N x C`` unit descriptors; NaN for fewer than 2.

    Near 0 for spread descriptors (the authors' model: ~0.02), near 1 when they collapse to one
    direction, where matching only sees tiny differences and breaks at the smallest change.
    """
    d = np.asarray(descriptors, dtype=np.float64)
    n = len(d)
    if n < 2:
        return float("nan")
    total = d.sum(axis=0)
    return float((total @ total - (d * d).sum()) / (n * (n - 1)))


def summarise(rows: list[tuple]) -> dict:
    """Average the per-pair results ``(sequence, mma[10], corner_error, matches, keypoints)``."""
    mma = np.array([r[1] for r in rows])
    corner = np.array([r[2] for r in rows])
    ha = np.array([(corner <= t).mean() for t in THRESHOLDS])
    out = {"pairs": len(rows), "mma3": float(mma[:, 2].mean()), "mma_avg": float(mma.mean()),
           "ha3": float(ha[2]), "ha_avg": float(ha.mean()),
           "matches": float(np.mean([r[3] for r in rows])), "keypoints": float(np.mean([r[4] for r in rows]))}
    for prefix in ("i", "v"):
        subset = [r[1][2] for r in rows if r[0].startswith(prefix + "_")]
        if subset:
            out[f"mma3_{prefix}"] = float(np.mean(subset))
    return out
