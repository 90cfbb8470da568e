"""Relative-pose benchmark: pose estimation on synthetic correspondences, scene readers, a tiny run."""
import json

import numpy as np
import pytest

from sekd_sfm.bench.methods import parse_method
from sekd_sfm.bench.pose import (
    PoseConfig,
    estimate_relative_pose,
    pose_errors,
    run_pose_benchmark,
)
from sekd_sfm.errors import SekdError
from sekd_sfm.evaluation.datasets import read_pose_scene


def rotation_y(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def project(K, R, t, X):
    x = (K @ (R @ X.T + t[:, None])).T
    return x[:, :2] / x[:, 2:]


def test_exact_correspondences_give_the_true_pose():
    rng = np.random.default_rng(0)
    X = rng.uniform([-2, -2, 4], [2, 2, 8], size=(200, 3))
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    cam0 = (K, np.eye(3), np.zeros(3))
    cam1 = (K, rotation_y(10), np.array([-1.0, 0.1, 0.2]))
    estimate = estimate_relative_pose(project(*cam0, X), project(*cam1, X), K, K, PoseConfig())
    rot, trans = pose_errors(estimate, cam0, cam1)
    assert rot < 0.01 and trans < 0.05 and estimate[2] == 200
    assert estimate_relative_pose(np.zeros((3, 2)), np.zeros((3, 2)), K, K, PoseConfig()) is None
    assert pose_errors(None, cam0, cam1) == (float("inf"), float("inf"))


def test_strecha_scene_reader(tmp_path):
    (tmp_path / "s/gt_dense_cameras").mkdir(parents=True)
    (tmp_path / "s/images").mkdir()
    camera = "800 0 320\n0 800 240\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 2 3\n640 480\n"
    (tmp_path / "s/gt_dense_cameras/a.jpg.camera").write_text(camera)
    scene = read_pose_scene(tmp_path / "s")
    K, R, t = scene.cameras["a.jpg"]
    assert scene.image_dir == tmp_path / "s/images"
    assert np.allclose(t, [-1, -2, -3]) and np.allclose(R, np.eye(3)) and K[0, 0] == 800
    with pytest.raises(SekdError, match="no ground truth"):
        read_pose_scene(tmp_path)


def test_tiny_run_on_fountain(tmp_path, shared):
    out = run_pose_benchmark([shared / "data/sfm/fountain-P11"], [parse_method("sift")], tmp_path,
                             PoseConfig(max_keypoints=1000, resize_max=640, ransac_runs=3))
    entry = json.loads(out.read_text())["methods"]["sift"]
    summary = entry["summary"]
    assert summary["pairs"] == 55 and summary["ransac_runs"] == 3
    # Run 0 is the single run of the mAA column (the file keeps the runs to 0.01 deg).
    assert all(len(p["pose_deg_runs"]) == 3 and p["pose_deg_runs"][0] == round(p["pose_deg"], 2) for p in entry["pairs"])
    assert summary["maa_sd"] >= 0 and abs(summary["maa_mean"] - summary["maa"]) < 0.1
    assert summary["median_rotation_deg"] < 1.0 and summary["maa"] > 0.3
    assert (tmp_path / "pose_accuracy.png").is_file()


def test_colmap_model_as_ground_truth(tmp_path):
    model = tmp_path / "scene/sparse/0"
    model.mkdir(parents=True)
    (tmp_path / "scene/images").mkdir()
    (model / "cameras.txt").write_text("1 PINHOLE 640 480 500 510 320 240\n")
    # Image 2: 90 deg about z (quaternion w = x = 0, y = 0, z = sin 45 = cos 45), translation (1, 2, 3).
    (model / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.jpg\n\n"
                                      "2 0.7071067811865476 0 0 0.7071067811865476 1 2 3 1 b.jpg\n\n")
    (model / "points3D.txt").write_text("")
    scene = read_pose_scene(tmp_path / "scene")
    assert scene.image_dir == tmp_path / "scene/images" and sorted(scene.cameras) == ["a.jpg", "b.jpg"]
    K, R, t = scene.cameras["b.jpg"]
    assert np.allclose(K, [[500, 0, 319.5], [0, 510, 239.5], [0, 0, 1]])  # OpenCV pixel centres
    assert np.allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-9) and np.allclose(t, [1, 2, 3])
