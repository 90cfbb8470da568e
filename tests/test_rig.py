"""Camera rigs (``sekd_sfm.stages.rig``): the rig file checked, poses estimated where most instants agree."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sekd_sfm import ReconstructConfig, reconstruct
from sekd_sfm.errors import SekdError
from sekd_sfm.evaluation.metrics import rotation_angle_deg
from sekd_sfm.stages.rig import (
    _consensus,
    check_photos,
    make_pose,
    matrix_to_quat,
    poses_known,
    quat_to_matrix,
    read_rigs,
    sensor_prefix,
    write_rigs,
)

NAMES = [f"cam{c}/{k:04d}.jpg" for c in (0, 1) for k in range(5)]


def yaw(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rig_file(tmp_path, cameras, name="rig.json"):
    path = tmp_path / name
    path.write_text(cameras if isinstance(cameras, str) else json.dumps([{"cameras": cameras}]))
    return path


def test_reads_colmap_rig_file_with_and_without_poses(tmp_path):
    q = matrix_to_quat(yaw(40))
    rigs = read_rigs(rig_file(tmp_path, [{"image_prefix": "cam0/", "ref_sensor": True},
                                         {"image_prefix": "cam1/", "cam_from_rig_rotation": q,
                                          "cam_from_rig_translation": [-0.3, 0, 0]}]))
    assert poses_known(rigs) and q[0] > 0
    assert rotation_angle_deg(rigs[0][1].cam_from_rig[:3, :3] @ yaw(40).T) < 1e-6
    assert sensor_prefix(rigs, "cam1/0001.jpg") == "cam1/" and sensor_prefix(rigs, "other.jpg") is None
    unknown = read_rigs(rig_file(tmp_path, [{"image_prefix": "cam0/", "ref_sensor": True}, {"image_prefix": "cam1/"}]))
    assert not poses_known(unknown)
    again = read_rigs(write_rigs(rigs, tmp_path / "again.json"))  # what a run writes, a later run reads
    assert np.allclose(again[0][1].cam_from_rig, rigs[0][1].cam_from_rig)


@pytest.mark.parametrize("content, words", [
    ("{not json", "cannot read it as JSON"),
    ("[]", "a list of rigs"),
    ([{"image_prefix": "cam0/", "ref_sensor": True}], "at least two cameras"),
    ([{"image_prefix": "cam0/"}, {"image_prefix": "cam1/"}], "exactly one camera"),
    ([{"image_prefix": "cam0/", "ref_sensor": True}, {"ref_sensor": False}], "image_prefix"),
    ([{"image_prefix": "cam/", "ref_sensor": True}, {"image_prefix": "cam/1/"}], "given twice or contains"),
    ([{"image_prefix": "cam0/", "ref_sensor": True}, {"image_prefix": "cam1/", "cam_from_rig_rotation": [1, 0, 0, 0]}],
     "give both"),
    ([{"image_prefix": "cam0/", "ref_sensor": True},
      {"image_prefix": "cam1/", "cam_from_rig_rotation": [2, 0, 0, 0], "cam_from_rig_translation": [0, 0, 0]}],
     "unit quaternion"),
])
def test_bad_rig_files_are_one_clear_error(tmp_path, content, words):
    with pytest.raises(SekdError, match=words):
        read_rigs(rig_file(tmp_path, content))


def test_photos_are_checked_against_the_prefixes(tmp_path, caplog):
    path = rig_file(tmp_path, [{"image_prefix": "cam0/", "ref_sensor": True}, {"image_prefix": "cam1/"}])
    rigs = read_rigs(path)
    assert check_photos(rigs, NAMES, path) == {"cam0/": 5, "cam1/": 5}
    with pytest.raises(SekdError, match="'cam1/' names no photo"):
        check_photos(rigs, [n for n in NAMES if n.startswith("cam0/")], path)
    renamed = [n.replace("cam1/", "cam1/IMG_") for n in NAMES]
    with pytest.raises(SekdError, match="share no file name"):
        check_photos(rigs, renamed, path)
    check_photos(rigs, NAMES[:-1], path)  # one instant without cam1's photo: a warning
    assert "1 of 5 instants" in caplog.text


def test_consensus_ignores_instants_the_free_model_got_wrong():
    rng = np.random.default_rng(0)
    truth = make_pose(yaw(40), np.array([-0.3, 0, 0]))
    poses = [make_pose(yaw(40 + rng.normal(0, 0.1)), truth[:3, 3] + rng.normal(0, 0.002, 3)) for _ in range(12)]
    poses += [make_pose(yaw(90), np.array([1.0, 0, 0])), make_pose(yaw(-50), np.array([0, 0, 2.0]))]  # folded
    pose, agree = _consensus(np.stack(poses))
    assert agree == 12
    assert rotation_angle_deg(pose[:3, :3] @ yaw(40).T) < 0.1
    assert np.abs(pose[:3, 3] - truth[:3, 3]).max() < 0.005
    assert np.allclose(quat_to_matrix(matrix_to_quat(pose[:3, :3])), pose[:3, :3])


@pytest.fixture(scope="module")
def rig_scene(shared, tmp_path_factory):
    """8 instants of the generated two-camera rig (320 px) and a first run with the rig's pose left out."""
    from sekd_sfm.bench.scale.captures import render_rig
    from sekd_sfm.bench.scale.scene import SceneConfig

    root = tmp_path_factory.mktemp("rig")
    scene = json.loads(render_rig(root / "scene", SceneConfig(image_size=320), instants=8, progress=False).read_text())
    out = root / "estimated"
    reconstruct(root / "scene/images", out, ReconstructConfig(rig=str(root / "scene/rig.json")), progress=False)
    return root, scene, out


def _rig_pose(model) -> np.ndarray:
    (rig,) = [r for r in model.rigs.values() if r.num_sensors() == 2]
    (pose,) = rig.non_ref_sensors.values()
    return make_pose(pose.rotation.matrix(), pose.translation)


def test_rig_pose_left_out_is_estimated_and_kept_rigid(rig_scene):
    import pycolmap

    root, scene, out = rig_scene
    model = pycolmap.Reconstruction(str(out / "model"))
    assert model.num_reg_images() == 16 and len([f for f in model.frames.values() if f.has_pose]) == 8
    truth = quat_to_matrix(scene["rig"]["cam_from_rig_rotation"])
    assert rotation_angle_deg(_rig_pose(model)[:3, :3] @ truth.T) < 0.5
    written = read_rigs(out / "rig.json")  # the rig file with the estimated pose, for later runs
    assert poses_known(written)
    stats = json.loads((out / "stats.json").read_text())
    assert stats["rig"]["estimated"]["cam1/"]["agreeing"] >= 6 and stats["rig"]["model"][0]["instants_registered"] == 8


def test_rig_pose_given_is_kept(rig_scene, tmp_path):
    import pycolmap

    root, scene, out = rig_scene
    given = read_rigs(root / "scene/rig_known.json")
    config = ReconstructConfig(rig=str(root / "scene/rig_known.json"))
    reconstruct(root / "scene/images", tmp_path / "known", config, features=out / "features.h5",
                matches=out / "matches.h5", progress=False)
    model = pycolmap.Reconstruction(str(tmp_path / "known/model"))
    assert model.num_reg_images() == 16
    assert np.allclose(_rig_pose(model), given[0][1].cam_from_rig, atol=1e-6)  # neither rotation nor baseline moved
    assert not (tmp_path / "known/rig.json").exists()


def test_rig_model_exports_as_any_other(rig_scene, tmp_path):
    import pycolmap

    from sekd_sfm.stages.export import export_model
    from sekd_sfm.stages.export_nerfstudio import export_nerfstudio

    root, scene, out = rig_scene
    text = export_model(out / "model", tmp_path / "text")
    assert (text / "rigs.txt").is_file() and (text / "frames.txt").is_file()
    export_nerfstudio(out / "model", tmp_path / "splat", root / "scene/images")
    transforms = json.loads((tmp_path / "splat/transforms.json").read_text())
    assert sorted(f["file_path"] for f in transforms["frames"]) == sorted(f"images/{n}" for n in scene_names(scene))
    model = pycolmap.Reconstruction(str(tmp_path / "splat/sparse/0"))
    assert model.num_reg_images() == 16


def scene_names(scene) -> list[str]:
    return [image["name"] for image in scene["images"]]
