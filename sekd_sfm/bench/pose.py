"""``sekd bench pose``: relative pose on every image pair of scenes with ground-truth cameras.

Protocol (docs/method.md, the IMC stereo task the paper uses): up to 2,000 keypoints per image,
ratio test (float descriptors, with the feature type's measured default ratio) or mutual
nearest neighbours (binary), essential matrix by RANSAC on points normalised with the known
intrinsics, ``cv2.recoverPose``; rotation error = angle of R_est R_gt^T, translation error
= angle between translation directions, pose error = the larger. Reported: mAA@1:10 deg
and AUC@5/10/20 deg.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from itertools import combinations
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..errors import SekdError
from ..evaluation import metrics
from ..evaluation.datasets import PoseScene, read_pose_scene
from ..files import features as ff
from ..runtime import package_versions, run_record, timing_context
from ..stages.match import (
    DEFAULT_RATIO,
    FALLBACK_RATIO,
    ROOTSIFT_FEATURES,
    match_descriptors,
)
from .methods import Method, cached_features, evaluate_each

logger = logging.getLogger("sekd")


@dataclass
class PoseConfig:
    max_keypoints: int = 2000
    resize_max: int | None = 1600   # extraction size; keypoints are mapped back to original pixels
    precision: str = "fp32"
    ransac_px: float = 1.0          # RANSAC threshold in pixels (of the mean focal length)
    confidence: float = 0.99999
    #: RANSAC runs per pair: run 0 on the matches in the matcher's order (the mAA / AUC columns),
    #: the others on seeded shuffles of the same matches (``metrics.ransac_order``); their mean
    #: and sd show how much of a difference between methods is RANSAC's luck.
    ransac_runs: int = 10
    num_threads: int | None = None  # CPU threads of the extraction (None: every usable core)


def match_pair(f0: dict, f1: dict, feature: str, binary: bool) -> np.ndarray:
    """``M x 2`` indices: ratio test for float descriptors (measured default ratio; RootSIFT for SIFT,
    as ``sekd match`` does), mutual NN for binary ones."""
    mode, ratio = ("mnn", None) if binary else ("ratio", DEFAULT_RATIO["ratio"].get(feature, FALLBACK_RATIO))
    matches0, _ = match_descriptors(f0["descriptors"], f1["descriptors"], mode=mode, ratio=ratio,
                                    rootsift=feature in ROOTSIFT_FEATURES, device="cpu")
    keep = matches0 >= 0
    return np.stack([np.nonzero(keep)[0], matches0[keep]], 1)


def _normalise(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    return (points - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])


def estimate_relative_pose(kp0, kp1, K0, K1, config: PoseConfig):
    """``(R, t, inliers)`` of camera 1 from camera 0, or None when fewer than 5 matches or RANSAC fails."""
    if len(kp0) < 5:
        return None
    p0, p1 = _normalise(kp0, K0), _normalise(kp1, K1)
    threshold = config.ransac_px / np.mean([K0[0, 0], K0[1, 1], K1[0, 0], K1[1, 1]])
    E, mask = cv2.findEssentialMat(p0, p1, np.eye(3), method=cv2.RANSAC, prob=config.confidence, threshold=threshold)
    if E is None or E.shape != (3, 3):
        return None
    inliers, R, t, mask = cv2.recoverPose(E, p0, p1, np.eye(3), mask=mask)
    return R, t.ravel(), int(inliers)


def pose_errors(estimate, truth0, truth1) -> tuple[float, float]:
    """(rotation, translation-direction) errors in degrees; (inf, inf) for a failed estimate."""
    if estimate is None:
        return float("inf"), float("inf")
    (_, R0, t0), (_, R1, t1) = truth0, truth1
    R_gt = R1 @ R0.T
    t_gt = t1 - R_gt @ t0
    R, t, _ = estimate
    return metrics.rotation_error_deg(R, R_gt), metrics.translation_error_deg(t, t_gt)


def evaluate_scene(features: Path, scene: PoseScene, feature: str, binary: bool, config: PoseConfig) -> list[dict]:
    names = sorted(n for n in scene.cameras if n in set(ff.list_keys(features)))
    if len(names) < 2:
        raise SekdError(f"{scene.name}: fewer than 2 images have both features and ground-truth cameras")
    loaded = {n: ff.read_features(features, n) for n in names}
    results = []
    for a, b in tqdm(list(combinations(names, 2)), desc=f"pose {scene.name}", unit="pair", leave=False):
        matches = match_pair(loaded[a], loaded[b], feature, binary)
        runs = []
        for run in range(max(1, config.ransac_runs)):
            ordered = matches[metrics.ransac_order(len(matches), run)]
            kp0, kp1 = loaded[a]["keypoints"][ordered[:, 0]], loaded[b]["keypoints"][ordered[:, 1]]
            estimate = estimate_relative_pose(kp0.astype(np.float64), kp1.astype(np.float64),
                                              scene.cameras[a][0], scene.cameras[b][0], config)
            runs.append((estimate, pose_errors(estimate, scene.cameras[a], scene.cameras[b])))
        estimate, (rot, trans) = runs[0]
        results.append({"scene": scene.name, "pair": [a, b], "matches": len(matches),
                        "inliers": estimate[2] if estimate else 0, "rotation_deg": rot, "translation_deg": trans,
                        "pose_deg": max(rot, trans), "pose_deg_runs": [max(errors) for _, errors in runs]})
    return results


def summarise(pairs: list[dict]) -> dict:
    """mAA@1:10 and AUC@5/10/20 of run 0, their mean and sd over the RANSAC runs, median errors, matches."""
    errors = [p["pose_deg"] for p in pairs]
    runs = min((len(p["pose_deg_runs"]) for p in pairs), default=1)
    per_run = [[p["pose_deg_runs"][r] for p in pairs] for r in range(runs)]
    maa_mean, maa_sd = metrics.mean_and_sd([metrics.mean_average_accuracy(e) for e in per_run])
    auc5_mean, auc5_sd = metrics.mean_and_sd([metrics.pose_auc(e, 5) for e in per_run])
    return {"pairs": len(pairs), "maa": metrics.mean_average_accuracy(errors), "ransac_runs": runs,
            "maa_mean": maa_mean, "maa_sd": maa_sd, "auc5_mean": auc5_mean, "auc5_sd": auc5_sd,
            "accuracy": metrics.accuracy_curve(errors).tolist(),
            **{f"auc{t}": metrics.pose_auc(errors, t) for t in (5, 10, 20)},
            "median_rotation_deg": float(np.median([p["rotation_deg"] for p in pairs])),
            "median_translation_deg": float(np.median([p["translation_deg"] for p in pairs])),
            "matches": float(np.mean([p["matches"] for p in pairs])),
            "inliers": float(np.mean([p["inliers"] for p in pairs]))}


def run_pose_benchmark(scene_dirs: list[Path], methods: list[Method], output: Path,
                       config: PoseConfig | None = None) -> Path:
    """Evaluate every method on every scene; writes results.json, results.md, pose_accuracy.png."""
    config = config or PoseConfig()
    scenes = [read_pose_scene(d) for d in scene_dirs]
    results = {"config": asdict(config), "scenes": [s.name for s in scenes], "versions": package_versions(),
               "record": run_record(), "methods": {}}

    def evaluate(method: Method) -> dict:
        pairs = _evaluate_method(method, scenes, Path(output) / "cache", config)
        return {"method": asdict(method), "summary": summarise(pairs), "pairs": pairs}

    results["methods"] = evaluate_each(methods, evaluate)
    results["timing"] = timing_context()  # after the extraction, which set the threads
    return _write(results, Path(output))


def _evaluate_method(method: Method, scenes: list[PoseScene], cache: Path, config: PoseConfig) -> list[dict]:
    feature_config = method.feature_config(config.max_keypoints, config.precision)
    feature_config.resize_max = config.resize_max
    pairs = []
    for scene in scenes:
        features, _ = cached_features(method, feature_config, scene.image_dir, cache / scene.name,
                                      num_threads=config.num_threads)
        binary = ff.read_attrs(features)["descriptor_dtype"] == "uint8"
        pairs += evaluate_scene(features, scene, method.feature, binary, config)
    return pairs


def _write(results: dict, output: Path) -> Path:
    from .report import plot_pose, pose_markdown, write_results

    return write_results(results, output, pose_markdown, plot_pose)
