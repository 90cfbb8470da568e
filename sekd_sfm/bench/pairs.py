"""``sekd bench pairs``: are the pairs geometric verification accepts *right*? Measured against the true cameras.

A verified pair (a two-view geometry in COLMAP's database with at least ``MIN_INLIERS`` inlier
matches) can pass verification and still be wrong: on repeated or symmetric structure the
matches of two photos of *different* surfaces can agree with some epipolar geometry, and the
mapper then folds or splits the model. Per verified pair (``score_verified_pairs``,
``score_matches``): the relative pose its OWN inlier matches give with the TRUE intrinsics
(essential matrix, 5-point LO-RANSAC, pycolmap) against the true relative pose: rotation error
and translation-direction error in degrees; the pose is off when either exceeds
``max_error_deg`` (or no essential matrix fits). The pair is ``wrong`` when its pose is off AND
the true pose explains clearly fewer of its inliers than the estimated one (fewer than
``MIN_TRUTH_SUPPORT`` of them, epipolar distance within ``max_error_px``). Without the second
condition, true matches on one plane (facades, the ground) or through a long lens, which fit
several poses, would count as wrong: on a generated city block every "wrong" pair of pycolmap's
SIFT, up to 1,045 inliers, had all its inliers within 0.2 px of the true epipolar lines; those
pairs are counted apart (``ambiguous``). A pair with a distractor of a generated scene (a photo
that shares no surface with any other) is wrong. Also per pair: its inliers, COLMAP's
configuration (calibrated, uncalibrated, planar_or_panoramic, ...) and, for generated scenes,
the true overlap of the two photos (``covisibility.txt``).

Pixel conventions: the database holds COLMAP pixels (the first pixel's centre at 0.5; already in
the original photo's pixels when the photos were resized for extraction); the ``.camera`` files,
as those ``sekd bench scale`` writes, use OpenCV's (integer = pixel centre), so keypoints lose
0.5 before they meet the true K.

The summary (``summarize``): verified pairs, wrong pairs, wrong among near and far pairs (the
photos' separation: their index distance in the sequence of names for a walk, cyclic for a ring,
else the rank of one camera centre among the other's nearest, halved; ``sequence_order`` tells
which from the true centres), median inliers of right and wrong pairs, and a histogram of the
inliers of wrong pairs (wrong pairs with many inliers are the ones a threshold cannot remove);
then which wrong and right pairs the chance check (``stages.chance``) drops from each method's
database and how many wrong pairs are left for the mapper.

The runner (``run_pairs_benchmark``) verifies the pairs of a scene once per method: ``sekd``,
our pipeline (``pipelines.reconstruct``) stopped after its verification step (features, pairs,
matches, refinement, database: what the mapper would get before the checks); ``sift``, pycolmap's SIFT
extraction, matching and verification (``bench.scale.run.run_pycolmap`` without its mapping
stage) on the same pairs as ``sekd`` (every pair when ``sekd`` did not run), and scores each
database. Files::

    OUT/<method>/              the method's work folder (database.db, features, ...)
    OUT/<method>/pair_scores.json   one row per verified pair
    OUT/results.json           settings, machine and versions, each method's summary
    OUT/results.md             the table
"""
from __future__ import annotations

import itertools
import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..evaluation.metrics import fundamental_matrix, rotation_angle_deg
from ..evaluation.strecha import angle_between_deg, read_cameras, relative_pose
from ..files.atomic import write_atomic

logger = logging.getLogger("sekd")

#: Pairs with fewer inlier matches are not verified (COLMAP's ``min_num_inliers`` and the mapper's ``min_num_matches``).
MIN_INLIERS = 15
#: A pair whose rotation or translation direction is off by more than this (deg) has its pose off (``score_matches``).
MAX_ERROR_DEG = 10.0
#: RANSAC threshold (px) of the essential matrix on a pair's inliers, and the epipolar distance within which a
#: match fits a pose: COLMAP's verification threshold.
MAX_ERROR_PX = 4.0
#: A pair whose pose is off is still right when the true pose keeps at least this share of the matches the
#: estimated one keeps (``score_matches``): planar and long-lens pairs fit several poses.
MIN_TRUTH_SUPPORT = 0.8
#: A pair is near when its photos' separation is at most this (``Separation``).
NEAR = 2
#: Lower edges of the inlier histogram's bins (the last bin is open).
INLIER_BINS = (15, 20, 30, 50, 100, 200, 500, 1000)
METHODS = ("sekd", "sift")
#: pycolmap's SIFT ``max_image_size`` for "full size" (no photo is that large).
FULL_SIZE = 1 << 16
#: How far apart the photos of a pair are: index distance on a walk / ring, nearest-centre rank otherwise.
ORDERS = ("walk", "ring", "centres")
#: COLMAP's pixel convention puts the centre of the first pixel at 0.5; the .camera files' K at 0.
COLMAP_PIXEL_OFFSET = 0.5

#: name -> (K 3x3, R world-to-camera 3x3, t (3,)): x ~ K (R X + t).
Truth = dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]


# ----------------------------------------------------------------------------- the truth

@dataclass
class SceneTruth:
    """What a scene folder knows: the true cameras, and for generated scenes the overlap and distractors.

    ``overlap``: ``frozenset((a, b)) -> (co-visible share, matchable overlap)`` of every co-visible pair
    (``covisibility.txt``), None when the scene has none (a pair absent from it shares nothing).
    ``order``: how the photos follow each other (``ORDERS``).
    """

    cameras: Truth
    overlap: dict[frozenset, tuple[float, float]] | None = None
    distractors: frozenset[str] = frozenset()
    order: str = "centres"
    source: str = ""

    def separation(self) -> Separation:
        return Separation(self.cameras, self.order)


def read_truth(scene_dir: str | Path) -> SceneTruth:
    """The truth of a scene folder: ``gt_dense_cameras/*.camera`` (Strecha format), plus ``scene.json`` and
    ``covisibility.txt`` when ``sekd bench scale`` generated it; SekdError when the cameras are missing."""
    scene_dir = Path(scene_dir)
    cameras = {name: (cam.K, *cam.cam_from_world) for name, cam in read_cameras(scene_dir / "gt_dense_cameras").items()}
    overlap, distractors, layout = None, frozenset(), None
    if (scene_dir / "scene.json").is_file():
        data = json.loads((scene_dir / "scene.json").read_text())
        distractors = frozenset(data.get("distractors") or ())
        layout = (data.get("config") or {}).get("layout")
    if (scene_dir / "covisibility.txt").is_file():
        from .scale.covisibility import read_covisibility

        shared = read_covisibility(scene_dir, min_overlap=0.0)
        matchable = read_covisibility(scene_dir, min_overlap=0.0, matchable=True)
        overlap = {pair: (share, matchable.get(pair, 0.0)) for pair, share in shared.items()}
    order = "ring" if layout == "ring" else sequence_order(cameras)
    return SceneTruth(cameras, overlap, distractors, order, str(scene_dir))


def camera_centre(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return -R.T @ t


def sequence_order(cameras: Truth, factor: float = 2.5) -> str:
    """``walk`` when the photos, in name order, step from each camera to a near one (every step at most ``factor``
    times the median nearest-centre distance), ``ring`` when the last also steps back to the first, else
    ``centres`` (no sequence: separations by nearest-centre rank)."""
    names = sorted(cameras)
    if len(names) < 3:
        return "walk"
    centres = np.array([camera_centre(*cameras[n][1:]) for n in names])
    distances = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    np.fill_diagonal(distances, np.inf)
    limit = factor * float(np.median(distances.min(axis=1)))
    if np.diag(distances, 1).max() > limit:
        return "centres"
    return "ring" if distances[0, -1] <= limit else "walk"


class Separation:
    """How far apart the photos of a pair are (1 = neighbours): ``separation(a, b)``, None for a photo without truth.

    ``walk``: the index distance in name order; ``ring``: the same, cyclic; ``centres``: the smaller of the two
    ranks of one camera centre among the other's nearest (1 = nearest), halved and rounded up, so that on a
    walk it is about the index distance (each photo has two neighbours at each distance).
    """

    def __init__(self, cameras: Truth, order: str):
        if order not in ORDERS:
            raise SekdError(f"unknown order {order!r}; choose one of {', '.join(ORDERS)}")
        names = sorted(cameras)
        self.order, self.index = order, {name: k for k, name in enumerate(names)}
        self.rank = None
        if order == "centres":
            centres = np.array([camera_centre(*cameras[name][1:]) for name in names]).reshape(-1, 3)
            distances = np.linalg.norm(centres[:, None] - centres[None], axis=2)
            np.fill_diagonal(distances, -1.0)  # the camera itself ranks 0
            self.rank = np.argsort(np.argsort(distances, axis=1, kind="stable"), axis=1)

    def __call__(self, a: str, b: str) -> int | None:
        i, j = self.index.get(a), self.index.get(b)
        if i is None or j is None:
            return None
        if self.rank is not None:
            return math.ceil(min(self.rank[i, j], self.rank[j, i]) / 2)
        apart = abs(i - j)
        return min(apart, len(self.index) - apart) if self.order == "ring" else apart


# ----------------------------------------------------------------------------- scoring one database

def _calibrated(points: np.ndarray, K: np.ndarray):
    """``points`` (OpenCV pixels) in a pinhole camera with K's mean focal length and no offset or skew, and that
    camera: what pycolmap's estimator needs to use K exactly (skew included) with a threshold in pixels."""
    import pycolmap

    focal = (K[0, 0] + K[1, 1]) / 2
    rays = np.linalg.solve(K, np.c_[points, np.ones(len(points))].T).T
    camera = pycolmap.Camera(model="PINHOLE", width=1, height=1, params=[focal, focal, 0.0, 0.0])
    return focal * rays[:, :2] / rays[:, 2:], camera


def relative_pose_of_matches(x0: np.ndarray, x1: np.ndarray, K0: np.ndarray, K1: np.ndarray,
                             max_error_px: float = MAX_ERROR_PX, seed: int = 0):
    """``(R, t, inliers)`` of camera 1 from camera 0 (x1 = R x0 + t, |t| = 1) from matched OpenCV pixel points
    ``x0``, ``x1`` (``M x 2``) with the intrinsics K0, K1: essential matrix by 5-point LO-RANSAC and its
    decomposition by cheirality (pycolmap); None when no essential matrix fits."""
    from ..stages.colmap import require_pycolmap

    pycolmap = require_pycolmap()
    if len(x0) < 5:
        return None
    (p0, camera0), (p1, camera1) = _calibrated(x0, K0), _calibrated(x1, K1)
    options = pycolmap.RANSACOptions()
    options.max_error, options.random_seed = max_error_px, seed
    found = pycolmap.estimate_essential_matrix(p0, p1, camera0, camera1, options)
    if not found:
        return None
    pose = found["cam2_from_cam1"]
    return np.asarray(pose.rotation.matrix()), np.asarray(pose.translation), int(found["num_inliers"])


def _config_name(config) -> str:
    """COLMAP's two-view configuration by name (``calibrated``, ``planar``, ...); the database gives a number."""
    from ..stages.colmap import require_pycolmap

    try:
        return require_pycolmap().TwoViewGeometryConfiguration(int(config)).name.lower()
    except (TypeError, ValueError):
        return str(getattr(config, "name", config)).lower()


def score_verified_pairs(database: str | Path, truth: Truth, *, max_error_deg: float = MAX_ERROR_DEG,
                         min_inliers: int = MIN_INLIERS, max_error_px: float = MAX_ERROR_PX,
                         min_truth_support: float = MIN_TRUTH_SUPPORT, overlap: dict | None = None,
                         distractors=frozenset(), seed: int = 0) -> list[dict]:
    """One row per verified pair of ``database`` (two-view geometry with ``min_inliers`` inlier matches or more).

    ``truth``: name -> (K, R world-to-camera, t). Row: ``image0``, ``image1`` (COLMAP's pair order), ``inliers``,
    ``config`` (COLMAP's two-view configuration), the scores of ``score_matches`` (``wrong`` None when a photo has
    no truth), and with ``overlap`` (``SceneTruth``) ``overlap`` / ``matchable_overlap`` (0 for pairs that share
    nothing). A pair with a photo of ``distractors`` is wrong (``reason`` "distractor").
    """
    from ..stages.colmap import open_database, require_pycolmap

    pycolmap = require_pycolmap()
    if not Path(database).is_file():
        raise SekdError(f"{database}: no such COLMAP database")
    rows, keypoints = [], {}
    with open_database(Path(database)) as db:
        names = {image.image_id: image.name for image in db.read_all_images()}

        def points(image_id: int, index: np.ndarray) -> np.ndarray:
            if image_id not in keypoints:
                keypoints[image_id] = np.asarray(db.read_keypoints(image_id), np.float64)[:, :2] - COLMAP_PIXEL_OFFSET
            return keypoints[image_id][index]

        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            matches = np.asarray(geometry.inlier_matches).reshape(-1, 2)
            if len(matches) < min_inliers:
                continue
            id0, id1 = pycolmap.pair_id_to_image_pair(pair_id)
            name0, name1 = names[id0], names[id1]
            row = {"image0": name0, "image1": name1, "inliers": len(matches), "config": _config_name(geometry.config),
                   **dict.fromkeys(SCORES), "wrong": None, "reason": None}
            if overlap is not None:
                row["overlap"], row["matchable_overlap"] = overlap.get(frozenset((name0, name1)), (0.0, 0.0))
            if name0 in distractors or name1 in distractors:
                row.update(wrong=True, reason="distractor")
            elif name0 in truth and name1 in truth:
                row.update(score_matches(points(id0, matches[:, 0]), points(id1, matches[:, 1]), truth[name0],
                                         truth[name1], max_error_deg=max_error_deg, max_error_px=max_error_px,
                                         min_truth_support=min_truth_support, seed=seed))
            rows.append(row)
    return sorted(rows, key=lambda r: (r["image0"], r["image1"]))


#: What ``score_matches`` measures of a pair, besides ``wrong`` and ``reason``.
SCORES = ("rotation_error_deg", "translation_error_deg", "pose_off", "pose_inliers", "true_inliers",
          "true_inlier_fraction", "truth_support", "median_true_epipolar_px")


def score_matches(x0: np.ndarray, x1: np.ndarray, truth0, truth1, *, max_error_deg: float = MAX_ERROR_DEG,
                  max_error_px: float = MAX_ERROR_PX, min_truth_support: float = MIN_TRUTH_SUPPORT,
                  seed: int = 0) -> dict:
    """Whether the matches ``x0`` <-> ``x1`` (OpenCV pixels, ``M x 2``) of two photos with true cameras
    ``(K, R, t)`` are a wrong pair.

    ``rotation_error_deg`` / ``translation_error_deg``: of the pose the matches give with the true K
    (``relative_pose_of_matches``) against the true one; ``pose_off``: either above ``max_error_deg`` (or no
    essential matrix). ``pose_inliers``: matches within ``max_error_px`` of their epipolar lines under the
    estimated pose (symmetric distance), ``true_inliers`` under the true pose, ``truth_support`` the ratio of
    the two. ``wrong``: the pose is off AND the truth keeps fewer than ``min_truth_support`` of the matches the
    estimate keeps. A pose off while the truth explains the matches as well is ``reason`` "ambiguous", not
    wrong: matches on one plane, or seen through a long lens, fit several poses (5-point RANSAC then may
    return another than the true one), which says nothing against the matches.
    """
    from .sfm import epipolar_distances

    (K0, R0, t0), (K1, R1, t1) = truth0, truth1
    R_true, t_true = relative_pose((R0, t0), (R1, t1))
    distances = epipolar_distances(x0, x1, fundamental_matrix(K0, K1, R_true, t_true))
    true_inliers = int(np.sum(distances <= max_error_px))
    result = {"true_inliers": true_inliers, "true_inlier_fraction": round(true_inliers / len(x0), 4),
              "median_true_epipolar_px": round(float(np.median(distances)), 3)}
    estimated = relative_pose_of_matches(x0, x1, K0, K1, max_error_px, seed)
    if estimated is None:
        rotation = translation = None
        pose_inliers, pose_off = len(x0), True
    else:
        R_est, t_est, _ = estimated
        pose_inliers = int(np.sum(epipolar_distances(x0, x1, fundamental_matrix(K0, K1, R_est, t_est)) <= max_error_px))
        rotation, translation = rotation_angle_deg(R_est.T @ R_true), angle_between_deg(t_est, t_true)
        pose_off = not (rotation <= max_error_deg and translation <= max_error_deg)  # nan (no baseline): off
    support = true_inliers / max(pose_inliers, 1)
    wrong = pose_off and support < min_truth_support
    if not pose_off:
        reason = None
    elif not wrong:
        reason = "ambiguous"
    elif estimated is None:
        reason = "no essential matrix"
    else:
        reason = "rotation" if not rotation <= max_error_deg else "translation"
    return {**result, "rotation_error_deg": None if rotation is None else round(rotation, 4),
            "translation_error_deg": None if translation is None else round(translation, 4), "pose_off": pose_off,
            "pose_inliers": pose_inliers, "truth_support": round(support, 4), "wrong": wrong, "reason": reason}


# ----------------------------------------------------------------------------- summary

def _median(values) -> float | None:
    return float(np.median(values)) if len(values) else None


def _fraction(part: int, whole: int) -> float | None:
    return part / whole if whole else None


def inlier_histogram(inliers, bins=INLIER_BINS) -> dict[str, int]:
    """Counts of ``inliers`` per bin ``"lo-hi"`` (hi excluded; the last ``"lo+"``); below the first edge: ``"<lo"``."""
    labels = [f"{lo}-{hi - 1}" for lo, hi in itertools.pairwise(bins)] + [f"{bins[-1]}+"]
    counts = dict.fromkeys(labels, 0)
    below = 0
    for count in inliers:
        k = int(np.searchsorted(bins, count, side="right")) - 1
        if k < 0:
            below += 1
        else:
            counts[labels[k]] += 1
    return ({f"<{bins[0]}": below} if below else {}) | counts


def summarize(rows: list[dict], near: int = NEAR) -> dict:
    """Counts over the scored rows (``wrong`` not None) of ``score_verified_pairs``.

    Rows with a ``separation`` (``Separation``; the runner adds it) add ``near`` / ``far`` (separation <= ``near``
    or above) and the counts per separation; rows with an ``overlap`` the wrong pairs among the truly overlapping
    and the others.
    """
    scored = [r for r in rows if r["wrong"] is not None]
    wrong = [r for r in scored if r["wrong"]]
    right = [r for r in scored if not r["wrong"]]
    accurate = [r for r in right if r.get("pose_off") is False]
    summary = {"verified": len(scored), "unscored": len(rows) - len(scored), "wrong": len(wrong),
               "wrong_fraction": _fraction(len(wrong), len(scored)),
               "wrong_reasons": {reason: sum(r["reason"] == reason for r in wrong)
                                 for reason in sorted({r["reason"] for r in wrong})},
               "pose_off": sum(bool(r.get("pose_off")) for r in scored),
               "ambiguous": sum(r["reason"] == "ambiguous" for r in scored),
               "median_inliers_right": _median([r["inliers"] for r in right]),
               "median_inliers_wrong": _median([r["inliers"] for r in wrong]),
               "max_inliers_wrong": max((r["inliers"] for r in wrong), default=None),
               "median_rotation_error_right_deg": _median([r["rotation_error_deg"] for r in accurate]),
               "median_translation_error_right_deg": _median([r["translation_error_deg"] for r in accurate]),
               "inlier_histogram_wrong": inlier_histogram([r["inliers"] for r in wrong]),
               "inlier_histogram_right": inlier_histogram([r["inliers"] for r in right]),
               "configs": {c: [sum(r["config"] == c for r in right), sum(r["config"] == c for r in wrong)]
                           for c in sorted({r["config"] for r in scored})}}
    if any("chance" in r for r in scored):  # what the chance check removes, and the wrong pairs the mapper still gets
        summary["chance"] = {"dropped_wrong": sum(bool(r.get("chance")) for r in wrong),
                             "dropped_right": sum(bool(r.get("chance")) for r in right),
                             "wrong_left": sum(not r.get("chance") for r in wrong),
                             "verified_left": sum(not r.get("chance") for r in scored)}
    if any(r.get("separation") is not None for r in scored):
        by_distance: dict[int, list[int]] = {}
        for r in scored:
            if r.get("separation") is not None:
                counts = by_distance.setdefault(r["separation"], [0, 0])
                counts[0] += 1
                counts[1] += bool(r["wrong"])
        for label, test in (("near", lambda d: d <= near), ("far", lambda d: d > near)):
            group = [r for r in scored if r.get("separation") is not None and test(r["separation"])]
            bad = sum(bool(r["wrong"]) for r in group)
            summary[label] = {"verified": len(group), "wrong": bad, "wrong_fraction": _fraction(bad, len(group))}
        summary["near_max_separation"] = near
        summary["by_separation"] = {str(d): {"verified": v, "wrong": w} for d, (v, w) in sorted(by_distance.items())}
    if any("overlap" in r for r in scored):
        for label, test in (("overlapping", lambda r: r["overlap"] > 0), ("not_overlapping", lambda r: r["overlap"] == 0)):
            group = [r for r in scored if r.get("overlap") is not None and test(r)]
            bad = sum(bool(r["wrong"]) for r in group)
            summary[label] = {"verified": len(group), "wrong": bad, "wrong_fraction": _fraction(bad, len(group))}
    return summary


# ----------------------------------------------------------------------------- the benchmark

@dataclass
class PairsBenchConfig:
    """What ``sekd bench pairs`` runs: the methods, their extraction size and network, and the scoring."""

    methods: tuple[str, ...] = METHODS
    #: Long side (px) of the photos for extraction, both methods; None: full size.
    resize_max: int | None = 1600
    #: SEKD network file (None: the default embedded model).
    weights: str | None = None
    max_keypoints: int | None = None
    max_error_deg: float = MAX_ERROR_DEG
    min_truth_support: float = MIN_TRUTH_SUPPORT
    min_inliers: int = MIN_INLIERS
    near: int = NEAR
    num_threads: int | None = None
    seed: int = 0
    #: Score the databases an earlier run left in the output folder instead of running the methods again.
    score_only: bool = False


def verification_steps():
    """``RECONSTRUCT`` up to and including its verification step: the database the mapper would get."""
    from ..pipelines.reconstruct import RECONSTRUCT

    names = [step.name for step in RECONSTRUCT]
    return RECONSTRUCT[:names.index("verification") + 1]


def run_sekd(scene_dir: Path, work: Path, config: PairsBenchConfig) -> dict:
    """Our pipeline with its defaults (``config``'s size, network and keypoints) up to verification."""
    from ..pipelines.reconstruct import ReconstructConfig, reconstruct
    from ..pipelines.record import read_record

    rc = ReconstructConfig(seed=config.seed)
    rc.features.resize_max = config.resize_max
    if config.weights:
        rc.features.weights = config.weights
    if config.max_keypoints:
        rc.features.max_keypoints = config.max_keypoints
    start = time.perf_counter()
    reconstruct(scene_dir / "images", work, rc, num_threads=config.num_threads, progress=False,
                steps=verification_steps())
    stats = read_record(work) or {}
    features = {}
    if (work / "features.h5").is_file():
        from ..files.features import read_attrs

        attrs = read_attrs(work / "features.h5")
        features = {"weights": Path(str(attrs.get("weights", ""))).name,
                    "model_sha256": str(attrs.get("model_sha256", ""))}
    return {"wall_s": round(time.perf_counter() - start, 1), "stages_s": {k: v for k, v in
                                                                          stats.get("timings_s", {}).items()},
            "pairs_mode": ((stats.get("config") or {}).get("pairs") or {}).get("mode"), "features": features,
            "failure": stats.get("failure")}


def run_sift(scene_dir: Path, work: Path, config: PairsBenchConfig, pairs: list[tuple[str, str]] | None) -> dict:
    """pycolmap's SIFT extraction, matching and verification (``bench.scale.run.run_pycolmap``, no mapping) on
    ``pairs`` (None: every pair)."""
    from ..files.images import list_images
    from ..stages.pairs import exhaustive_pairs
    from .scale.run import run_pycolmap

    names = list_images(scene_dir / "images")
    pairs = pairs if pairs is not None else exhaustive_pairs(names)
    size = config.resize_max or FULL_SIZE
    record = run_pycolmap(scene_dir, work, pairs, len(names), config.seed, config.num_threads, size, map_stage=False)
    return {"wall_s": record["wall_s"], "stages_s": {k: v["time_s"] for k, v in record["stages"].items()},
            "matcher": record["matcher"], "max_image_size": size, "failure": record["failure"]}


def score_method(work: Path, truth: SceneTruth, config: PairsBenchConfig) -> dict:
    """Score ``work``'s database; writes ``work/pair_scores.json``; returns the summary."""
    from ..pipelines.record import DATABASE

    rows = score_verified_pairs(work / DATABASE, truth.cameras, max_error_deg=config.max_error_deg,
                                min_inliers=config.min_inliers, min_truth_support=config.min_truth_support,
                                overlap=truth.overlap,
                                distractors=truth.distractors, seed=config.seed)
    separation = truth.separation()
    for row in rows:
        row["separation"] = separation(row["image0"], row["image1"])
    mark_chance_pairs(work / DATABASE, rows, config)
    write_atomic(work / "pair_scores.json", json.dumps(rows, indent=0))
    return summarize(rows, config.near)


def mark_chance_pairs(database: Path, rows: list[dict], config: PairsBenchConfig) -> None:
    """Set each row's ``chance``: whether the chance check (``stages.chance``, its defaults) drops the pair. The
    check runs on the database as verification left it, for every method, and changes nothing in it: what it
    would remove is scored, not applied."""
    from ..execution import LocalExecutor
    from ..stages.chance import find_chance_pairs

    processes = config.num_threads if config.num_threads and config.num_threads > 0 else None  # None: every core
    dropped, _ = find_chance_pairs(database, config.min_inliers, seed=config.seed, executor=LocalExecutor(processes))
    names = {frozenset((pair.name1, pair.name2)) for pair in dropped}
    for row in rows:
        row["chance"] = frozenset((row["image0"], row["image1"])) in names


def run_pairs_benchmark(scene: str | Path, output_dir: str | Path, config: PairsBenchConfig | None = None) -> Path:
    """Verify SCENE's pairs with every method of ``config`` and score them; writes results.json and results.md."""
    from ..pipelines.record import DATABASE
    from ..runtime import package_versions, run_record
    from .sfm import resolve_scene

    config = config or PairsBenchConfig()
    unknown = sorted(set(config.methods) - set(METHODS))
    if unknown or not config.methods:
        raise SekdError(f"methods {', '.join(unknown) or '(none)'}: choose among {', '.join(METHODS)}")
    scene_dir = resolve_scene(scene)
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    truth = read_truth(scene_dir)
    report = {"scene": str(scene_dir), "images": len(truth.cameras), "order": truth.order,
              "distractors": len(truth.distractors), "overlap_known": truth.overlap is not None,
              "settings": asdict(config), "versions": package_versions(), "record": run_record(), "methods": {}}
    earlier = _earlier_report(out) if config.score_only else {}
    if earlier:  # what the databases were made with
        report["settings"].update({k: v for k, v in earlier.get("settings", {}).items() if k in EXTRACTION})
    for method in config.methods:
        work = out / method
        if config.score_only:
            if not (work / DATABASE).is_file():
                raise SekdError(f"{work / DATABASE}: no database to score; run without --score-only first")
            run = earlier.get("methods", {}).get(method, {}).get("run", {})
        elif method == "sekd":
            logger.info("%s: verifying the pairs of %s", method, scene_dir)
            run = run_sekd(scene_dir, work, config)
        else:
            from ..stages.pairs import read_pairs

            logger.info("%s: verifying the pairs of %s", method, scene_dir)
            ours = out / "sekd" / "pairs.txt"
            run = run_sift(scene_dir, work, config, read_pairs(ours) if "sekd" in config.methods and ours.is_file()
                           else None)
        if not config.score_only:
            run["pairs"] = "sekd's" if method == "sift" and run.get("matcher") == "imported pairs" else "own"
        if run.get("failure"):
            report["methods"][method] = {"run": run}
            logger.warning("%s failed: %s", method, run["failure"])
            continue
        report["methods"][method] = {"run": run, **score_method(work, truth, config)}
    path = out / "results.json"
    write_atomic(path, json.dumps(report, indent=1, default=str))
    write_atomic(out / "results.md", pairs_markdown(report))
    return path


#: The settings that made the databases (kept from the earlier run by ``score_only``).
EXTRACTION = ("resize_max", "weights", "max_keypoints")


def _earlier_report(out: Path) -> dict:
    """``out``'s results.json (empty without one)."""
    try:
        report = json.loads((out / "results.json").read_text())
    except (OSError, ValueError):
        return {}
    return report if isinstance(report, dict) else {}


def _pct(value) -> str:
    return "-" if value is None else f"{100 * value:.1f}"


def _n(value, digits: int = 0) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _split(part: dict | None) -> str:
    return "-" if not part else f"{part['wrong']}/{part['verified']}"


def pairs_markdown(report: dict) -> str:
    """The table: per method verified pairs, wrong (count, %), wrong among near / far pairs, median inliers."""
    settings = report["settings"]
    near = settings["near"]
    lines = [(f"Verified pairs of {Path(report['scene']).name} ({report['images']} photos with true cameras, "
              f"order: {report['order']}) scored against the true cameras. Pose off: the pose a pair's own "
              f"inliers give with the true intrinsics is off by more than {settings['max_error_deg']:g} deg in "
              f"rotation or translation direction; wrong: pose off and the true pose keeps fewer than "
              f"{settings['min_truth_support']:.0%} of the inliers the estimated one keeps (the others, "
              f"ambiguous, are right matches that fit several poses: planar, long lens). Near: separation <= "
              f"{near} (index distance for a walk / ring, nearest-centre rank / 2 otherwise). Extraction at "
              f"{settings['resize_max'] or 'full'} px."), "",
             ("| method | verified pairs | wrong | wrong % | wrong near | wrong far | pose off (ambiguous) "
              "| median inliers right | median inliers wrong | max inliers wrong |"),
             "|---|---|---|---|---|---|---|---|---|---|"]
    for method, entry in report["methods"].items():
        if "verified" not in entry:
            lines.append(f"| {method} | failed: {entry['run'].get('failure')} |||||||||")
            continue
        lines.append(f"| {method} | {entry['verified']} | {entry['wrong']} | {_pct(entry['wrong_fraction'])} "
                     f"| {_split(entry.get('near'))} | {_split(entry.get('far'))} "
                     f"| {entry['pose_off']} ({entry['ambiguous']}) "
                     f"| {_n(entry['median_inliers_right'])} | {_n(entry['median_inliers_wrong'])} "
                     f"| {_n(entry['max_inliers_wrong'])} |")
    checked = [(m, e) for m, e in report["methods"].items() if "chance" in e]
    if checked:
        lines += ["", ("The chance check (`stages.chance`: a pair is dropped when RANSAC on its matches shuffled "
                       "reaches more than 1/1.25 of its inliers), applied to each method's verified pairs:"), "",
                  "| method | dropped: wrong | dropped: right | left: wrong / verified |", "|---|---|---|---|"]
        lines += [f"| {m} | {e['chance']['dropped_wrong']} | {e['chance']['dropped_right']} "
                  f"| {e['chance']['wrong_left']} / {e['chance']['verified_left']} |" for m, e in checked]
    overlap = [(m, e) for m, e in report["methods"].items() if "overlapping" in e]
    if overlap:
        lines += ["", "| method | wrong among truly overlapping | wrong among not overlapping |", "|---|---|---|"]
        lines += [f"| {m} | {_split(e['overlapping'])} | {_split(e['not_overlapping'])} |" for m, e in overlap]
    scored = [(m, e) for m, e in report["methods"].items() if "verified" in e]
    if scored:
        bins = list(dict.fromkeys(b for _, e in scored for key in ("inlier_histogram_right", "inlier_histogram_wrong")
                                  for b in e[key]))
        lines += ["", "Inliers of the wrong pairs (right pairs in brackets):", "",
                  "| method | " + " | ".join(bins) + " |", "|---|" + "---|" * len(bins)]
        lines += [f"| {m} | " + " | ".join(f"{e['inlier_histogram_wrong'].get(b, 0)} "
                                           f"({e['inlier_histogram_right'].get(b, 0)})" for b in bins) + " |"
                  for m, e in scored]
        distances = sorted({int(d) for _, e in scored for d in e.get("by_separation", {})})
        if distances:
            lines += ["", "Wrong / verified pairs by separation:", "",
                      "| method | " + " | ".join(map(str, distances)) + " |", "|---|" + "---|" * len(distances)]
            for m, e in scored:
                per = e.get("by_separation", {})
                lines.append(f"| {m} | " + " | ".join(f"{per[str(d)]['wrong']}/{per[str(d)]['verified']}"
                                                      if str(d) in per else "-" for d in distances) + " |")
    record = report.get("record", {})
    lines += ["", (f"sekd_sfm {record.get('sekd_sfm', '?')}, commit {record.get('commit') or '?'}, pycolmap "
                  f"{report['versions'].get('pycolmap')}, {record.get('cpu', {}).get('model', '?')}, "
                  f"{record.get('date', '')}.")]
    return "\n".join(lines) + "\n"
