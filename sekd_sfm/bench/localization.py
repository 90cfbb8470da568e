"""``sekd bench localization``: how closely matched keypoints follow the surface, with and without refinement.

Each photo is warped by a random homography (rotation, scale, mild perspective, a sub-pixel
shift; bilinear interpolation), so the true position of every keypoint in the warped photo is
known exactly. Per method: features of both photos as ``extract`` makes them (the product's
settings: sub-pixel SEKD keypoints), mutual-nearest-neighbour matches, and the distance
between each match's keypoint in the warped photo and its partner mapped by the homography,
over the correct matches (under ``correct_px``). Then the same after keypoint refinement
(``sfm.refine``) on the pair. Reports per method: correct matches, median and RMS distance,
share under 0.5 px, before and after refinement.
"""
from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..evaluation.samplers import random_centred_homography
from ..files.atomic import write_atomic
from ..runtime import package_versions, run_record, shared_dir, timing_context
from .methods import Method, evaluate_each

logger = logging.getLogger("sekd")


@dataclass
class LocalizationConfig:
    """Photos, keypoints, and the range of the random homographies."""

    num_images: int = 20
    max_keypoints: int = 2000
    seed: int = 0
    max_rotation_deg: float = 15.0
    scale_range: tuple[float, float] = (0.85, 1.15)
    perspective: float = 2e-4       # largest |h31|, |h32| (1/px) about the photo's centre
    correct_px: float = 2.0         # a match is correct when its distance is under this
    num_threads: int | None = None  # CPU threads of the extraction (None: every usable core)


def random_homography(rng: np.random.Generator, width: int, height: int, config: LocalizationConfig) -> np.ndarray:
    """A 3x3 homography about the photo's centre (rotation, scale, perspective) plus a sub-pixel shift
    (``samplers.random_centred_homography`` with the benchmark's ranges)."""
    return random_centred_homography(rng, width, height, config.max_rotation_deg, config.scale_range,
                                     config.perspective)


def match_distances(keypoints0: np.ndarray, keypoints1: np.ndarray, matches: np.ndarray, H: np.ndarray,
                    correct_px: float) -> np.ndarray:
    """Distances (px) between ``H``-mapped keypoints of photo 0 and their matches in photo 1, correct ones only.

    ``matches``: ``M x 2`` indices (photo 0, photo 1).
    """
    if len(matches) == 0:
        return np.zeros(0)
    points = np.concatenate([keypoints0[matches[:, 0]].astype(np.float64), np.ones((len(matches), 1))], 1) @ H.T
    distances = np.linalg.norm(points[:, :2] / points[:, 2:] - keypoints1[matches[:, 1]], axis=1)
    return distances[distances < correct_px]


def summarize(distances: np.ndarray) -> dict:
    """Count, median, RMS and share under 0.5 px of the distances."""
    if distances.size == 0:
        return {"correct": 0, "median_px": None, "rms_px": None, "under_0_5px": None}
    return {"correct": int(distances.size), "median_px": round(float(np.median(distances)), 4),
            "rms_px": round(float(np.sqrt((distances ** 2).mean())), 4),
            "under_0_5px": round(float((distances < 0.5).mean()), 4)}


def warp_photos(photos: list[Path], folder: Path, config: LocalizationConfig) -> dict[str, np.ndarray]:
    """Each photo (grayscale, PNG) and its warp into ``folder``; returns ``"i/0.png i/1.png" -> H``."""
    import cv2

    from ..files.images import read_image

    rng = np.random.default_rng(config.seed)
    folder.mkdir(parents=True, exist_ok=True)
    homographies = {}
    for i, photo in enumerate(photos):
        image = read_image(photo)
        height, width = image.shape
        H = random_homography(rng, width, height, config)
        (folder / f"{i:03d}").mkdir(exist_ok=True)
        cv2.imwrite(str(folder / f"{i:03d}/0.png"), image)
        cv2.imwrite(str(folder / f"{i:03d}/1.png"), cv2.warpPerspective(image, H, (width, height), flags=cv2.INTER_LINEAR))
        homographies[f"{i:03d}/0.png {i:03d}/1.png"] = H
    return homographies


def _evaluate(method: Method, images: Path, work: Path, homographies: dict, config: LocalizationConfig) -> dict:
    import h5py

    from ..features import FeatureConfig
    from ..files import matches as mf
    from ..model.inference import SEKDConfig
    from ..stages.extract import extract_features
    from ..stages.match import MatchConfig, match_features
    from ..stages.pairs import write_pairs
    from ..stages.refine import refine_keypoints, refine_summary

    folder = work / method.label
    feature_config = FeatureConfig(feature=method.feature, max_keypoints=config.max_keypoints, weights=method.weights,
                                   sekd=SEKDConfig(max_keypoints=config.max_keypoints))
    # overwrite: a rerun with other settings recomputes (cheap here) instead of refusing the old files
    features = extract_features(images, folder / "features.h5", feature_config, overwrite=True, progress=False,
                                num_threads=config.num_threads)
    pairs = [tuple(key.split(" ")) for key in homographies]
    pairs_file = write_pairs(pairs, folder / "pairs.txt")
    matches = match_features(features, pairs_file, folder / "matches.h5", MatchConfig(mode="mnn"), overwrite=True,
                             progress=False)
    refined = refine_keypoints(features, matches, pairs, images, folder / "features-refined.h5", progress=False)
    result = {}
    for label, keypoints_file in (("detected", features), ("refined", refined)):
        distances = []
        with h5py.File(keypoints_file, "r") as f:
            for (name0, name1, idx, _), H in zip(mf.iter_matches(matches, pairs), homographies.values()):
                distances.append(match_distances(f[name0]["keypoints"][()], f[name1]["keypoints"][()], idx, H,
                                                 config.correct_px))
        result[label] = summarize(np.concatenate(distances))
    result["refinement"] = refine_summary(refined)
    return result


def run_localization_benchmark(output: str | Path, methods: list[Method], config: LocalizationConfig | None = None,
                               photos: list[Path] | None = None) -> Path:
    """Every method on the warped photo pairs; writes results.json and results.md in ``output``. Returns results.json."""
    config = config or LocalizationConfig()
    out = Path(output)
    if photos is None:
        photos = sorted((shared_dir() / "data/train/coco").glob("*.jpg"))[: config.num_images]
    if not photos:
        raise SekdError("no photos to warp: give photos, or set SEKD_SHARED to the shared data folder")
    homographies = warp_photos(photos, out / "images", config)
    results = evaluate_each(methods, lambda m: _evaluate(m, out / "images", out / "work", homographies, config))
    report = {"config": asdict(config), "photos": [p.name for p in photos], "versions": package_versions(),
              "record": run_record(),
              "timing": timing_context(),
              "results": results}
    path = write_atomic(out / "results.json", json.dumps(report, indent=1))
    write_atomic(out / "results.md", localization_markdown(report))
    return path


def localization_markdown(report: dict) -> str:
    """The results as a Markdown table."""
    def cell(entry: dict, key: str) -> str:
        value = entry.get(key)
        return "-" if value is None else f"{value:.3f}" if isinstance(value, float) else str(value)

    intro = (f"Keypoint localisation on {len(report['photos'])} photos warped by known homographies: distance (px) "
             f"between matched keypoints and the true position, correct mutual-NN matches "
             f"(< {report['config']['correct_px']} px), as detected and after `sekd reconstruct`'s keypoint refinement.")
    lines = [intro, "", "| method | correct matches | median | RMS | < 0.5 px | refined: median | RMS | < 0.5 px |",
             "|---|---|---|---|---|---|---|---|"]
    for label, result in report["results"].items():
        if "error" in result:
            lines.append(f"| {label} | error: {result['error']} |" + " |" * 6)
            continue
        d, r = result["detected"], result["refined"]
        lines.append(f"| {label} | {d['correct']} | {cell(d, 'median_px')} | {cell(d, 'rms_px')} | "
                     f"{cell(d, 'under_0_5px')} | {cell(r, 'median_px')} | {cell(r, 'rms_px')} | {cell(r, 'under_0_5px')} |")
    return "\n".join(lines) + "\n"
