"""`sekd relpose` on a fountain-P11 pair against the ground-truth cameras, and its errors."""
import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sekd_sfm.bench.strecha import (
    angle_between_deg,
    read_cameras,
    relative_pose,
    rotation_angle_deg,
)
from sekd_sfm.cli.main import sekd

PAIR = ("0004.jpg", "0006.jpg")


def run(*args):
    result = CliRunner().invoke(sekd, ["-q", "relpose", *map(str, args)])
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    return result, errors


@pytest.fixture(scope="module")
def fountain(shared):
    root = shared / "data/sfm/fountain-P11"
    truth = read_cameras(root / "gt_dense_cameras")
    R, t = relative_pose(truth[PAIR[0]].cam_from_world, truth[PAIR[1]].cam_from_world)
    return root / "images", truth, R, t


def test_known_intrinsics_within_2_degrees(fountain, tmp_path):
    images, truth, R_gt, t_gt = fountain
    K = truth[PAIR[0]].K
    # The ground-truth K puts pixel centres at integers; COLMAP at +0.5.
    params = f"{K[0, 0]},{K[1, 1]},{K[0, 2] + 0.5},{K[1, 2] + 0.5}"
    result, errors = run(images / PAIR[0], images / PAIR[1], "--feature", "sift", "--max-keypoints", "4000",
                         "--resize-max", "1024", "--camera-model", "PINHOLE", "--camera-params", params,
                         "-o", tmp_path / "pose.json")
    assert result.exit_code == 0 and not errors, result.output
    pose = json.loads(result.output)
    assert pose == json.loads((tmp_path / "pose.json").read_text())
    R, t = np.array(pose["R"]), np.array(pose["t"])
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.norm(t) == pytest.approx(1)
    assert rotation_angle_deg(R.T @ R_gt) < 2.0
    assert angle_between_deg(t, t_gt) < 5.0
    assert 100 < pose["num_inliers"] <= pose["num_matches"] <= min(pose["num_keypoints"])
    assert pose["cameras"][0] == {"model": "PINHOLE", "params": [float(v) for v in params.split(",")],
                                  "focal_from": "given"}


def test_default_focal_length_is_reported(fountain):
    images, _, R_gt, _ = fountain
    result, errors = run(images / PAIR[0], images / PAIR[1], "--feature", "sift", "--resize-max", "800")
    assert result.exit_code == 0 and not errors, result.output
    pose = json.loads(result.output)
    # No EXIF in these files: COLMAP's 1.2 x 3072 px guess, 34% above the true 2760 px.
    assert pose["cameras"][0]["focal_from"] == "default"
    assert pose["cameras"][0]["params"][0] == pytest.approx(1.2 * 3072)
    assert rotation_angle_deg(np.array(pose["R"]).T @ R_gt) < 15  # a wrong focal length costs accuracy


def test_too_few_matches(tmp_path):
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(tmp_path / name), np.full((64, 80), 128, np.uint8))
    result, errors = run(tmp_path / "a.png", tmp_path / "b.png", "--feature", "sift")
    assert result.exit_code == 1
    assert errors == [("Error: too few matches for a relative pose: 0 and 0 keypoints, 0 matches (need 15); "
                       "try more keypoints, a looser --ratio, or images with more overlap")]


def test_bad_inputs(tmp_path, fountain):
    images = fountain[0]
    result, errors = run(images / PAIR[0], tmp_path / "missing.jpg", "--feature", "sift", "--resize-max", "400")
    assert result.exit_code == 1 and len(errors) == 1 and "missing.jpg: cannot read file" in errors[0]
    result, errors = run(images / PAIR[0], images / PAIR[1], "--feature", "orb", "--resize-max", "400",
                         "--camera-params", "1,2")
    assert result.exit_code == 1 and len(errors) == 1 and "SIMPLE_PINHOLE model takes 3" in errors[0]


def test_strecha_camera_file_and_conventions(tmp_path):
    from sekd_sfm.bench.strecha import read_camera
    from sekd_sfm.errors import SekdError

    # A camera at C = (1, 2, 3) turned 90 degrees about the world z axis (columns = camera axes).
    text = "100 0 50\n0 100 40\n0 0 1\n0 0 0\n0 -1 0\n1 0 0\n0 0 1\n1 2 3\n100 80\n"
    (tmp_path / "c.camera").write_text(text)
    camera = read_camera(tmp_path / "c.camera")
    assert (camera.width, camera.height) == (100, 80) and camera.C.tolist() == [1, 2, 3]
    R_cw, t_cw = camera.cam_from_world
    X = np.array([1.0, 2.0, 13.0])  # 10 units along the camera's z axis (= world z)
    x = camera.K @ (R_cw @ X + t_cw)
    assert (x[:2] / x[2]).tolist() == pytest.approx([50, 40])  # on the optical axis: the principal point
    # The first column of R, world +y, is the camera's x axis: one unit along it is x_cam = (1, 0, 0).
    assert (R_cw @ np.array([1.0, 3.0, 3.0]) + t_cw).tolist() == pytest.approx([1, 0, 0])
    (tmp_path / "bad.camera").write_text("1 2 3\n")
    with pytest.raises(SekdError, match="not a Strecha .camera file"):
        read_camera(tmp_path / "bad.camera")
