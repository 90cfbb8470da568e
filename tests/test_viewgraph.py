"""The view-graph check (``sekd_sfm.stages.viewgraph``): focal lengths from fundamental matrices, rotation averaging,
and the wrong pairs it drops, on exact synthetic graphs."""
from __future__ import annotations

import numpy as np
import pytest

from sekd_sfm.evaluation.metrics import fundamental_matrix, rotation_angles_deg
from sekd_sfm.stages.colmap import require_pycolmap
from sekd_sfm.stages.viewgraph import (
    Edge,
    ViewGraphConfig,
    calibrate_focal_lengths,
    find_inconsistent,
)

pycolmap = require_pycolmap()


def _rotation(rng, max_deg: float = 180.0) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(0, max_deg))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _ring(n: int, rng) -> list[np.ndarray]:
    """World-to-camera rotations of ``n`` cameras on a circle looking at its centre, with some jitter."""
    rotations = []
    for i in range(n):
        yaw = 2 * np.pi * i / n
        c, s = np.cos(yaw), np.sin(yaw)
        rotations.append(_rotation(rng, 2.0) @ np.array([[c, s, 0], [0, 0, -1], [-s, c, 0]]))
    return rotations


def _edges(rotations, pairs, rng, noise_deg: float = 0.5, inliers: int = 200) -> list[Edge]:
    return [Edge(i, j, f"{i:02d}", f"{j:02d}", _rotation(rng, noise_deg) @ rotations[j] @ rotations[i].T, inliers)
            for i, j in pairs]


def test_wrong_pairs_on_a_ring_are_dropped_and_only_they():
    rng = np.random.default_rng(0)
    rotations = _ring(24, rng)
    near = [(i, (i + d) % 24) for i in range(24) for d in (1, 2, 3)]
    edges = _edges(rotations, near, rng)
    # Look-alike matches across the ring: few inliers, a rotation like a neighbour's, the wrong place.
    wrong = [Edge(i, (i + 12) % 24, f"{i:02d}", f"{(i + 12) % 24:02d}", _rotation(rng, 20.0), 25) for i in range(0, 24, 3)]
    dropped, record = find_inconsistent(edges + wrong, ViewGraphConfig())
    assert sorted((e.image1, e.image2) for e, _ in dropped) == sorted((e.image1, e.image2) for e in wrong)
    assert record["pairs"] == 80 and record["dropped"] == 8 and record["median_disagreement_deg"] < 1.0
    assert min(r for _, r in dropped) > record["threshold_deg"] >= 5.0


def test_a_half_turned_group_is_outvoted_by_the_correct_pairs():
    """Wrong pairs that agree with each other (symmetric structure: a facade matched to its twin across the block)
    still lose against the many correct pairs around the loop."""
    rng = np.random.default_rng(1)
    rotations = _ring(30, rng)
    edges = _edges(rotations, [(i, (i + d) % 30) for i in range(30) for d in (1, 2)], rng)
    flip = np.diag([-1.0, 1.0, -1.0])  # 180 degrees about the camera's y axis
    wrong = _edges([flip @ R if i >= 15 else R for i, R in enumerate(rotations)],
                   [(i, i + 15) for i in range(0, 15, 2)], rng, inliers=120)
    dropped, _ = find_inconsistent(edges + wrong, ViewGraphConfig())
    assert sorted((e.image1, e.image2) for e, _ in dropped) == sorted((e.image1, e.image2) for e in wrong)


def test_consistent_graphs_and_graphs_without_loops_lose_nothing():
    rng = np.random.default_rng(2)
    rotations = _ring(12, rng)
    loops = _edges(rotations, [(i, j) for i in range(12) for j in range(i + 1, 12) if j - i <= 4], rng, noise_deg=1.5)
    assert find_inconsistent(loops, ViewGraphConfig())[0] == []
    chain = _edges(rotations, [(i, i + 1) for i in range(11)], rng, noise_deg=30.0)  # no loop: nothing to compare
    assert find_inconsistent(chain, ViewGraphConfig())[0] == []


def test_rotation_angle():
    rng = np.random.default_rng(3)
    R = _rotation(rng, 30.0)
    assert rotation_angles_deg(np.eye(3)) == pytest.approx(0.0, abs=1e-6)
    assert rotation_angles_deg(np.diag([1.0, -1.0, -1.0])) == pytest.approx(180.0)
    assert rotation_angles_deg(R @ R.T) == pytest.approx(0.0, abs=1e-5)


def test_focal_lengths_are_recovered_from_fundamental_matrices():
    """COLMAP's guess for a photo without EXIF is 1.2 x its long side; the fundamental matrices of its pairs say
    better (the true focal length here is 500 px, the guess 768)."""
    rng = np.random.default_rng(4)
    truth = {1: 500.0, 2: 900.0}
    cameras = {cid: pycolmap.Camera.create_from_model_id(cid, pycolmap.CameraModelId.SIMPLE_RADIAL, 768.0, 640, 480)
               for cid in truth}
    K = {cid: np.array([[f, 0, 320.0], [0, f, 240.0], [0, 0, 1]]) for cid, f in truth.items()}
    pairs = []
    for k in range(30):
        c1, c2 = (1, 1) if k < 10 else (1, 2) if k < 20 else (2, 2)
        R, t = _rotation(rng, 25.0), rng.normal(size=3)
        pairs.append((c1, c2, fundamental_matrix(K[c1], K[c2], R, t / np.linalg.norm(t))))
    found = calibrate_focal_lengths(cameras, pairs)
    assert found[1].focal == pytest.approx(500, rel=0.02) and found[2].focal == pytest.approx(900, rel=0.02)
    assert cameras[1].mean_focal_length() == pytest.approx(found[1].focal)
    assert found[1].determined and found[2].determined  # general motion: a sharp minimum
    with_exif = {1: pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId.SIMPLE_RADIAL, 768.0, 640, 480)}
    with_exif[1].has_prior_focal_length = True
    assert calibrate_focal_lengths(with_exif, [p for p in pairs if p[:2] == (1, 1)]) == {}
    assert with_exif[1].mean_focal_length() == 768.0  # EXIF's focal length is kept


def test_the_check_as_a_step_of_reconstruct_keeps_every_right_pair(tmp_path):
    """``--view-graph`` on the synthetic views of test_reconstruct (every pair right, calibrated cameras): all 28
    pairs checked, none dropped, the step timed and recorded."""
    from test_reconstruct import CALIBRATED, SIFT, write_arc_scene

    from sekd_sfm.pipelines.reconstruct import ReconstructConfig, reconstruct
    from sekd_sfm.pipelines.record import read_record

    _, images, out = write_arc_scene(tmp_path)
    config = ReconstructConfig(features=SIFT, camera=CALIBRATED)
    config.view_graph.enabled = True
    reconstruct(images, out, config, progress=False)
    stats = read_record(out)
    assert stats["status"] == "ok" and stats["model"]["registered_images"] == 8
    assert stats["view_graph"]["pairs"] == 28 and stats["view_graph"]["dropped"] == 0
    assert "view graph" in stats["timings_s"] and stats["view_graph"]["focal_lengths"] == {}  # calibrated: no estimate
