"""`sekd triangulate` on fountain-P11 (6 photos at 768 x 512) with its ground-truth cameras: the given poses and ids
come back bit for bit, with many accurate points; bad poses input is one Error line."""
import json
import re
import shutil

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sekd_sfm.cli.main import sekd
from sekd_sfm.evaluation.strecha import read_cameras
from sekd_sfm.pipelines.triangulate import pose_pairs, read_pose_model
from sekd_sfm.stages.colmap import require_pycolmap

pycolmap = require_pycolmap()
NAMES = [f"{i:04d}.jpg" for i in range(2, 8)]
SCALE = 0.25  # 3072 x 2048 -> 768 x 512, an exact 4 x 4 pixel average
IMAGE_IDS = {name: 10 + 3 * i for i, name in enumerate(NAMES)}  # not 1..N: the ids must be kept, not renumbered
CAMERA_ID = 7
FAST = ["--resize-max", "640", "--no-progress"]


def run(*args):
    result = CliRunner().invoke(sekd, [str(a) for a in args])
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    return result, errors


@pytest.fixture(scope="module")
def scene(shared, tmp_path_factory):
    """Photos (reduced copies), the ground truth as a COLMAP text model (one shared PINHOLE camera; Strecha's K puts
    the first pixel's centre at 0, COLMAP at 0.5) and as a poses file; the model triangulated once."""
    root = shared / "data/sfm/fountain-P11"
    truth = read_cameras(root / "gt_dense_cameras")
    work = tmp_path_factory.mktemp("triangulate")
    photos, model = work / "photos", work / "gt_model"
    photos.mkdir()
    model.mkdir()
    for name in NAMES:
        image = cv2.imread(str(root / "images" / name))
        cv2.imwrite(str(photos / name), cv2.resize(image, None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_AREA))
    K = truth[NAMES[0]].K
    params = [K[0, 0] * SCALE, K[1, 1] * SCALE, (K[0, 2] + 0.5) * SCALE, (K[1, 2] + 0.5) * SCALE]
    (model / "cameras.txt").write_text(f"{CAMERA_ID} PINHOLE 768 512 {' '.join(repr(float(p)) for p in params)}\n")
    lines = []
    for name in NAMES:
        R, t = truth[name].cam_from_world
        x, y, z, w = (float(v) for v in pycolmap.Rotation3d(R).quat)
        lines.append(f"{name} {w!r} {x!r} {y!r} {z!r} {' '.join(repr(float(v)) for v in t)}")
    (model / "images.txt").write_text("".join(f"{IMAGE_IDS[line.split()[0]]} {' '.join(line.split()[1:])} "
                                              f"{CAMERA_ID} {line.split()[0]}\n\n" for line in lines))
    (work / "poses.txt").write_text("# NAME qw qx qy qz tx ty tz\n" + "\n".join(lines) + "\n")
    out = work / "out_model"
    result, _ = run("triangulate", photos, "--poses", model, "-o", out, *FAST)
    assert result.exit_code == 0, result.output
    return work, photos, model, out, ",".join(repr(float(p)) for p in params), result.output


def assert_poses_equal(given, result):
    for image_id, image in given.images.items():
        a, b = image.cam_from_world(), result.image(image_id).cam_from_world()
        assert result.image(image_id).name == image.name
        assert np.array_equal(a.rotation.quat, b.rotation.quat) and np.array_equal(a.translation, b.translation)


def assert_good_points(stats, model, minimum=1000):
    assert stats["status"] == "ok" and stats["model"]["points3D"] >= minimum
    assert stats["model"]["mean_reprojection_error_px"] < 1.5 and stats["model"]["mean_track_length"] > 3
    assert stats["model"]["points3D"] == model.num_points3D()
    assert stats["model"]["images_with_points"] == model.num_reg_images()


def test_model_poses_ids_and_intrinsics_kept_bitwise(scene):
    _, _, gt, out, _, output = scene
    given, result = read_pose_model(gt), pycolmap.Reconstruction(str(out / "model"))  # gt: no points3D.txt
    assert (out / "model" / "images.bin").is_file() and not (out / "model" / "images.txt").exists()
    assert sorted(result.images) == sorted(IMAGE_IDS.values()) and sorted(result.cameras) == [CAMERA_ID]
    assert_poses_equal(given, result)
    assert np.array_equal(given.camera(CAMERA_ID).params, result.camera(CAMERA_ID).params)
    stats = json.loads((out / "stats.json").read_text())
    assert_good_points(stats, result)
    # Every point reprojects within a few pixels under the ground-truth cameras (the errors COLMAP keeps).
    errors = np.array([p.error for p in result.points3D.values()])
    assert np.median(errors) < 1.0 and errors.max() < 4.0
    assert stats["poses_kind"] == "model" and stats["pairs"] == 15 and stats["config"]["features"]["resize_max"] == 640
    assert "points from 6/6 posed photos" in output
    for name in ("features.h5", "matches.h5", "pairs.txt", "database.db", "features-refined.h5"):
        assert (out / name).is_file()


def test_poses_file_with_intrinsics_and_photo_lists(scene, caplog):
    work, photos, _, _, params, _ = scene
    # One pose names a photo that is not there; one photo has no pose: both are listed, the rest triangulated.
    lines = (work / "poses.txt").read_text().splitlines()
    (work / "poses5.txt").write_text("\n".join(lines[:-1]) + "\nnot_here.jpg 1 0 0 0 0 0 0\n")
    out = work / "out_file"
    out.mkdir()
    shutil.copy(scene[3] / "features.h5", out / "features.h5")  # reused as reconstruct reuses it: same settings
    result, errors = run("triangulate", photos, "--poses", work / "poses5.txt", "-o", out, "--camera-model",
                         "PINHOLE", "--camera-params", params, *FAST)
    assert result.exit_code == 0 and not errors, result.output
    assert "1 posed photo(s) not in" in caplog.text and "not_here.jpg" in caplog.text
    assert f"1 photo(s) without a pose in {work / 'poses5.txt'}: {NAMES[-1]}" in caplog.text
    model = pycolmap.Reconstruction(str(out / "model"))
    assert sorted(im.name for im in model.images.values()) == NAMES[:-1]
    for line in lines[1:-1]:
        name, *values = line.split()
        pose = model.find_image_with_name(name).cam_from_world()
        w, x, y, z, *t = (float(v) for v in values)
        assert pose.rotation.quat.tolist() == [x, y, z, w] and pose.translation.tolist() == t
    assert model.camera(1).params.tolist() == [float(p) for p in params.split(",")]
    assert_good_points(json.loads((out / "stats.json").read_text()), model, minimum=800)


def test_a_model_with_points_pairs_by_shared_points(scene):
    """The binary model written above, points and all, as POSES: its own ids and poses come back."""
    work, photos, _, out, _, _ = scene
    again = work / "out_again"
    again.mkdir()
    shutil.copy(out / "features.h5", again / "features.h5")
    result, errors = run("triangulate", photos, "--poses", out / "model", "-o", again, "--num-neighbors", "2", *FAST)
    assert result.exit_code == 0 and not errors, result.output
    given, model = pycolmap.Reconstruction(str(out / "model")), pycolmap.Reconstruction(str(again / "model"))
    assert_poses_equal(given, model)
    pairs = (again / "pairs.txt").read_text().split("\n")
    assert 6 <= len([p for p in pairs if p]) < 15  # two partners each (by shared points), not all 15 pairs
    assert_good_points(json.loads((again / "stats.json").read_text()), model, minimum=800)


def test_pose_pairs_follow_centres_and_viewing_directions(scene):
    reference = read_pose_model(scene[2])
    # The fountain cameras stand on an arc, each turned towards the fountain: neighbours along the arc.
    pairs = pose_pairs(reference, 2, 60.0)
    steps = {NAMES.index(b) - NAMES.index(a) for a, b in pairs}
    assert steps == {1, 2} and {(NAMES[i], NAMES[i + 1]) for i in range(len(NAMES) - 1)} <= set(pairs)
    assert len(pose_pairs(reference, 20, 60.0)) == 15  # all within 60 degrees of each other
    assert pose_pairs(reference, 1, 0.5) == []  # no two optical axes within half a degree


def test_no_posed_photo_is_one_error(scene, tmp_path):
    _, photos, _, _, _, _ = scene
    (tmp_path / "poses.txt").write_text("elsewhere/a.jpg 1 0 0 0 0 0 0\nelsewhere/b.jpg 1 0 0 0 1 0 0\n")
    result, errors = run("triangulate", photos, "--poses", tmp_path / "poses.txt", "-o", tmp_path / "out", *FAST)
    assert result.exit_code == 1 and len(errors) == 1
    assert "none of its 2 posed photos (e.g. elsewhere/a.jpg)" in errors[0] and str(photos) in errors[0]


@pytest.mark.parametrize("line,message", [
    ("0002.jpg 1 0 0 0 0 0", r"line 2: expected 'NAME qw qx qy qz tx ty tz'"),
    ("0002.jpg 1 0 0 zero 0 0 0", r"line 2: expected 'NAME qw qx qy qz tx ty tz'"),
    ("0002.jpg 0 0 0 0 0 0 0", "line 2: the quaternion is zero"),
])
def test_malformed_poses_line_is_one_error_naming_file_and_line(scene, tmp_path, line, message):
    _, photos, _, _, _, _ = scene
    poses = tmp_path / "poses.txt"
    poses.write_text(f"# header\n{line}\n")
    result, errors = run("triangulate", photos, "--poses", poses, "-o", tmp_path / "out", *FAST)
    assert result.exit_code == 1 and len(errors) == 1, result.output
    assert errors[0].startswith(f"Error: {poses}, line 2:") and re.search(message, errors[0])
    assert not (tmp_path / "out").exists()  # checked before the output folder is made


def test_camera_params_with_a_model_and_wrong_sizes_are_errors(scene, tmp_path):
    _, photos, gt, _, params, _ = scene
    result, errors = run("triangulate", photos, "--poses", gt, "-o", tmp_path / "a", "--camera-params", params, *FAST)
    assert result.exit_code == 1 and "leave --camera-params out" in errors[0]
    small = tmp_path / "small"
    small.mkdir()
    for name in NAMES:
        cv2.imwrite(str(small / name), cv2.resize(cv2.imread(str(photos / name)), (384, 256)))
    result, errors = run("triangulate", small, "--poses", gt, "-o", tmp_path / "b", *FAST)
    assert result.exit_code == 1 and "differ in size from their cameras" in errors[0] and "384x256" in errors[0]


def test_a_folder_in_use_is_refused(scene, tmp_path):
    from sekd_sfm.files.locking import exclusive_lock

    _, photos, gt, _, _, _ = scene
    (tmp_path / "busy").mkdir()
    with exclusive_lock(tmp_path / "busy"):
        result, errors = run("triangulate", photos, "--poses", gt, "-o", tmp_path / "busy", *FAST)
    assert result.exit_code == 1 and "in use by another sekd process" in errors[0]
