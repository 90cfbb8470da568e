"""The chance check (``sekd_sfm.stages.chance``): verified pairs whose inliers random matches would reach."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from sekd_sfm.execution import LocalExecutor
from sekd_sfm.stages.chance import (
    ChanceConfig,
    chance_inliers,
    check_chance,
    read_weak_pairs,
)
from sekd_sfm.stages.colmap import open_database, require_pycolmap

pycolmap = require_pycolmap()
WIDTH, HEIGHT = 640, 480


def test_random_matches_reach_colmaps_floor_of_15_inliers():
    """The mechanism the check answers: 100 random matches in a 640 px photo give a fundamental matrix with 15+
    inliers within 4 px, COLMAP's verification floor."""
    rng = np.random.default_rng(0)
    points1 = rng.uniform((0, 0), (WIDTH, HEIGHT), (100, 2))
    points2 = rng.uniform((0, 0), (WIDTH, HEIGHT), (100, 2))
    found = chance_inliers(points1, points2, ChanceConfig(), seed=1)
    assert len(found) == 4 and min(found) >= 13 and max(found) >= 15
    assert found == chance_inliers(points1, points2, ChanceConfig(), seed=1)  # seeded: the same every time


def _true_matches(rng, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` projections of random points seen by two cameras 20 deg apart (f 500 px): right matches."""
    K = np.array([[500.0, 0, WIDTH / 2], [0, 500.0, HEIGHT / 2], [0, 0, 1]])
    points = rng.uniform((-2, -1.5, 6), (2, 1.5, 9), (n, 3))
    angle = np.radians(20)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    t = np.array([-2.5, 0.0, 0.5])
    x1 = (K @ points.T).T
    x2 = (K @ (R @ points.T + t[:, None])).T
    return x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]


def _write_database(path, pairs: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, int]]) -> None:
    """A COLMAP database of three photos; per pair (ids 1-3): its matched keypoints (N x 2 each, px) and how many of
    the first matches verification kept."""
    with open_database(path) as db:
        camera = pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId.SIMPLE_PINHOLE, 500.0, WIDTH, HEIGHT)
        camera_id = db.write_camera(camera)
        ids = [db.write_image(pycolmap.Image(name=f"photo{i}.jpg", camera_id=camera_id)) for i in range(1, 4)]
        keypoints: dict[int, list[np.ndarray]] = {i: [] for i in ids}
        rows = []
        for (a, b), (x1, x2, kept) in pairs.items():
            start1, start2 = sum(map(len, keypoints[a])), sum(map(len, keypoints[b]))
            keypoints[a].append(x1)
            keypoints[b].append(x2)
            index = np.arange(len(x1))
            rows.append((a, b, np.stack([start1 + index, start2 + index], 1).astype(np.uint32), kept))
        for image_id, parts in keypoints.items():
            points = np.concatenate(parts) if parts else np.zeros((0, 2))
            db.write_keypoints(image_id, points.astype(np.float32))
        for a, b, matches, kept in rows:
            db.write_matches(a, b, matches)
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            geometry.inlier_matches = matches[:kept]
            db.write_two_view_geometry(a, b, geometry)


@pytest.fixture
def database(tmp_path):
    """Pair 1-2: 100 random matches "verified" at 17 inliers (chance); pair 1-3: 40 right matches among 100 verified
    at 40; pair 2-3: 150 right matches (not tested: 100 inliers or more)."""
    rng = np.random.default_rng(3)
    noise1 = rng.uniform((0, 0), (WIDTH, HEIGHT), (60, 2))
    noise2 = rng.uniform((0, 0), (WIDTH, HEIGHT), (60, 2))
    right1, right2 = _true_matches(rng, 40)
    path = tmp_path / "database.db"
    _write_database(path, {
        (1, 2): (rng.uniform((0, 0), (WIDTH, HEIGHT), (100, 2)), rng.uniform((0, 0), (WIDTH, HEIGHT), (100, 2)), 17),
        (1, 3): (np.concatenate([right1, noise1]), np.concatenate([right2, noise2]), 40),
        (2, 3): (*_true_matches(rng, 150), 150)})
    return path


def test_chance_pairs_are_dropped_and_right_ones_kept(database, tmp_path):
    weak, verified = read_weak_pairs(database, 15, 100)
    assert verified == 3 and sorted((p.image1, p.image2) for p in weak) == [(1, 2), (1, 3)]
    copy = tmp_path / "copy.db"
    shutil.copy(database, copy)
    record = check_chance(database, 15, executor=LocalExecutor(2))
    assert record["verified"] == 3 and record["tested"] == 2 and record["dropped"] == 1
    (dropped,) = record["dropped_pairs"]
    assert dropped["pair"] == ["photo1.jpg", "photo2.jpg"] and dropped["inliers"] == 17 and dropped["matches"] == 100
    assert dropped["chance_inliers"] * ChanceConfig().margin > 17
    with open_database(database) as db:
        inliers = {pycolmap.pair_id_to_image_pair(pair_id): len(geometry.inlier_matches)
                   for pair_id, geometry in zip(*db.read_two_view_geometries())}
        assert inliers.get((1, 2), 0) == 0 and len(db.read_matches(1, 2)) == 100  # raw matches stay
        assert inliers[(1, 3)] == 40 and inliers[(2, 3)] == 150
    assert not list(tmp_path.glob("database-chance.h5*"))  # the shuffles' results go once decided
    # The decisions depend on the pairs only: this process, another run, the same record.
    assert check_chance(copy, 15, executor=LocalExecutor(1)) == record


def test_a_stricter_margin_and_the_inlier_cap(database):
    record = check_chance(database, 15, ChanceConfig(max_inliers=18))
    assert record["tested"] == 1 and record["dropped"] == 1  # pair 1-3 (40 inliers) not tested
    record = check_chance(database, 15, ChanceConfig(margin=100.0))
    assert record["tested"] == 1 and record["dropped"] == 1  # only 1-3 left to test (1-2 already dropped): dropped too
