"""Geometric verification: the RANSAC trial budget, hand-made pairs with known inliers."""
import time

import numpy as np

from sekd_sfm.evaluation.metrics import fundamental_matrix
from sekd_sfm.stages.colmap import open_database, require_pycolmap
from sekd_sfm.stages.database import VERIFY_MAX_TRIALS, two_view_options, verify_matches

pycolmap = require_pycolmap()
W, H, F = 640, 480, 500.0


def _camera():
    return pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", F, W, H)


def _project(points: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of camera-frame points (N, 3) through the pinhole (F, W/2, H/2)."""
    return F * points[:, :2] / points[:, 2:] + [W / 2, H / 2]


def _true_pair(rng: np.random.Generator, num_inliers: int, num_outliers: int):
    """Keypoints (N, 2) of two views of random 3D points, matches (N, 2) (inliers first, outliers after), F (3, 3)."""
    points = rng.uniform([-2, -1.5, 4], [2, 1.5, 8], size=(num_inliers, 3))
    angle = np.deg2rad(8)
    rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    translation = np.array([-0.8, 0.05, 0.1])
    second = points @ rotation.T + translation
    keypoints0 = np.vstack([_project(points), rng.uniform([0, 0], [W, H], size=(num_outliers, 2))])
    keypoints1 = np.vstack([_project(second), rng.uniform([0, 0], [W, H], size=(num_outliers, 2))])
    matches = np.repeat(np.arange(num_inliers + num_outliers, dtype=np.uint32)[:, None], 2, axis=1)
    return keypoints0, keypoints1, matches, _fundamental(rotation, translation)


def _fundamental(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """F (3, 3) with x1^T F x0 = 0 for pixels x0, x1 of the two views."""
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])
    return fundamental_matrix(K, K, rotation, translation)


def _sampson_px(fundamental: np.ndarray, keypoints0: np.ndarray, keypoints1: np.ndarray) -> np.ndarray:
    """Sampson distance (N,) in pixels of each correspondence, the error COLMAP's F RANSAC thresholds."""
    x0 = np.hstack([keypoints0, np.ones((len(keypoints0), 1))])
    x1 = np.hstack([keypoints1, np.ones((len(keypoints1), 1))])
    line1, line0 = x0 @ fundamental.T, x1 @ fundamental
    numerator = np.sum(x1 * line1, axis=1) ** 2
    return np.sqrt(numerator / (line1[:, 0] ** 2 + line1[:, 1] ** 2 + line0[:, 0] ** 2 + line0[:, 1] ** 2))


def _random_pair(rng: np.random.Generator, num: int):
    """Two views sharing no surface: ``num`` matches between unrelated random keypoints."""
    keypoints = rng.uniform([0, 0], [W, H], size=(2, num, 2))
    return keypoints[0], keypoints[1], np.repeat(np.arange(num, dtype=np.uint32)[:, None], 2, axis=1)


def test_options_cap_trials_and_user_overrides_win():
    options = two_view_options()
    assert options.ransac.max_num_trials == VERIFY_MAX_TRIALS == 2000 and options.ransac.random_seed == 0
    restored = two_view_options(["ransac.max_num_trials=10000"], seed=3)
    assert restored.ransac.max_num_trials == 10000 and restored.ransac.random_seed == 3


def test_cap_bounds_the_cost_of_a_pair_that_cannot_verify():
    """40 unrelated matches: RANSAC runs every trial; 2000 trials cost a fraction of COLMAP's 10000."""
    keypoints0, keypoints1, matches = _random_pair(np.random.default_rng(0), 40)
    cpu, results = {}, {}
    for trials in (VERIFY_MAX_TRIALS, 10000):
        options = two_view_options([f"ransac.max_num_trials={trials}"])
        start = time.thread_time()  # CPU time of this thread: robust on a loaded machine
        results[trials] = pycolmap.estimate_two_view_geometry(_camera(), keypoints0, _camera(), keypoints1,
                                                              matches, options)
        cpu[trials] = time.thread_time() - start
    assert all(len(r.inlier_matches) == 0 for r in results.values())
    assert cpu[10000] > 2.5 * cpu[VERIFY_MAX_TRIALS], cpu


def _database_with(tmp_path, pairs: list[tuple[np.ndarray, np.ndarray, np.ndarray]]):
    """A COLMAP database with one camera and two images per pair (keypoints in COLMAP pixels)."""
    database = tmp_path / "database.db"
    ids = []
    with open_database(database) as db:
        camera_id = db.write_camera(_camera())
        for index, (keypoints0, keypoints1, matches) in enumerate(pairs):
            image_ids = [db.write_image(pycolmap.Image(name=f"{index}_{side}.jpg", camera_id=camera_id))
                         for side in (0, 1)]
            db.write_keypoints(image_ids[0], keypoints0.astype(np.float32))
            db.write_keypoints(image_ids[1], keypoints1.astype(np.float32))
            db.write_matches(image_ids[0], image_ids[1], matches)
            ids.append(image_ids)
    return database, ids


def test_verify_matches_keeps_true_inliers_and_rejects_the_rest(tmp_path):
    """With the capped budget: a pair with 40% inliers keeps all its inliers (plus the random outliers that
    happen to lie near their epipolar line); unrelated matches and a pair below min_num_inliers (15) get none."""
    rng = np.random.default_rng(1)
    *true, fundamental = _true_pair(rng, 40, 60)
    *few, _ = _true_pair(rng, 14, 0)
    database, ids = _database_with(tmp_path, [true, _random_pair(rng, 45), few])
    assert verify_matches(database, two_view_options(), num_threads=1) == database
    with open_database(database) as db:
        inliers = [db.read_two_view_geometry(*pair).inlier_matches for pair in ids]
    # F is fitted to every inlier of the best model, random ones too, so an outlier a little past the
    # 4 px threshold of the true F may pass; one far from its epipolar line may not.
    near_line = set(np.flatnonzero(_sampson_px(fundamental, true[0], true[1]) < 8).tolist())
    found = set(inliers[0][:, 0].tolist())
    assert set(range(40)) <= found <= near_line and len(found) <= 43, found - set(range(40))
    assert len(inliers[1]) == 0 and len(inliers[2]) == 0


def test_verify_matches_empty_database(tmp_path):
    database, _ = _database_with(tmp_path, [])
    assert verify_matches(database, two_view_options(), num_threads=1) == database
    with open_database(database) as db:
        assert db.num_verified_image_pairs() == 0
