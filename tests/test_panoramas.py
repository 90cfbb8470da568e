"""360-degree photos (``sekd_sfm.stages.panoramas``): views of an equirectangular panorama, masks, poses."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from sekd_sfm.errors import SekdError
from sekd_sfm.stages.panoramas import (
    PREFIX,
    VIEW_YAWS_DEG,
    equirectangular_pixels,
    find_panoramas,
    panorama_rig,
    render_views,
    same_panorama,
    view_intrinsics,
    view_rotations,
)

WIDTH = 512


def direction_panorama(width: int = WIDTH) -> np.ndarray:
    """A panorama whose pixel shows its own direction: B, G = cos, sin of its yaw, R its pitch, scaled to 0..255."""
    h = width // 2
    v, u = np.mgrid[0:h, 0:width].astype(np.float64)
    yaw = np.radians((u + 0.5) / width * 360 - 180)
    pitch = 90 - (v + 0.5) / h * 180
    return np.stack([(np.cos(yaw) + 1) * 127.5, (np.sin(yaw) + 1) * 127.5, (pitch + 90) / 180 * 255], -1).astype(np.uint8)


def test_equirectangular_pixels_follow_the_panorama_frame():
    # z: the image's centre; x: right (a quarter turn right of the centre); -y: up (the top row)
    px = equirectangular_pixels(np.array([[0, 0, 1.0], [1.0, 0, 0], [0, -1.0, 1e-9]]), WIDTH)
    assert np.allclose(px[0], [WIDTH / 2 - 0.5, WIDTH / 4 - 0.5])
    assert np.allclose(px[1], [3 * WIDTH / 4 - 0.5, WIDTH / 4 - 0.5])
    assert px[2][1] == pytest.approx(-0.5, abs=1e-6)


def test_views_look_where_the_rig_says_and_masks_share_out_the_sphere(tmp_path):
    cv2.imwrite(str(tmp_path / "pano.png"), direction_panorama())
    made = render_views(tmp_path, ["pano.png"], tmp_path / "views", tmp_path / "masks", progress=False)
    size, focal = view_intrinsics(WIDTH)
    assert made["panoramas"] == ["pano.png"] and made["views"]["size"] == size
    masks = []
    for k, yaw in enumerate(VIEW_YAWS_DEG):
        view = cv2.imread(str(tmp_path / "views" / (PREFIX.format(k) + "pano.png")))
        centre = view[size // 2, size // 2].astype(float)
        seen_yaw = math.degrees(math.atan2(centre[1] / 127.5 - 1, centre[0] / 127.5 - 1))
        assert abs((seen_yaw - yaw + 180) % 360 - 180) < 2  # the view's centre looks at its yaw, on the horizon
        assert abs(centre[2] / 255 * 180 - 90) < 2
        masks.append(cv2.imread(str(tmp_path / "masks" / (PREFIX.format(k) + "pano.png.png")), cv2.IMREAD_GRAYSCALE))
    assert all(0.3 < (m > 0).mean() < 0.9 for m in masks)  # each view owns its middle, not its overlap
    rig = panorama_rig(WIDTH)
    assert rig[0].ref and all(np.allclose(c.cam_from_rig[:3, :3], R) for c, R in zip(rig[1:], view_rotations()[1:]))
    assert rig[0].extra["camera_params"] == [focal, focal, size / 2, size / 2]
    assert focal == pytest.approx(WIDTH / (2 * math.pi))


def test_resumes_and_refuses_what_is_not_a_panorama(tmp_path):
    cv2.imwrite(str(tmp_path / "pano.jpg"), direction_panorama())
    cv2.imwrite(str(tmp_path / "photo.jpg"), np.zeros((300, 400, 3), np.uint8))
    assert find_panoramas(tmp_path, ["pano.jpg", "photo.jpg"], forced=False) == ["pano.jpg"]
    with pytest.raises(SekdError, match="400x300 px is not a 360-degree panorama"):
        find_panoramas(tmp_path, ["pano.jpg", "photo.jpg"], forced=True)
    render_views(tmp_path, ["pano.jpg"], tmp_path / "v", tmp_path / "m", progress=False)
    view = tmp_path / "v" / (PREFIX.format(1) + "pano.jpg")
    stamp = view.stat().st_mtime_ns
    render_views(tmp_path, ["pano.jpg"], tmp_path / "v", tmp_path / "m", progress=False)
    assert view.stat().st_mtime_ns == stamp  # done views are not rendered again
    assert same_panorama("pano0/a.jpg", "pano2/a.jpg") and not same_panorama("pano0/a.jpg", "pano0/b.jpg")


def test_generated_panoramas_are_posed_against_the_truth(shared, tmp_path):
    from sekd_sfm import reconstruct
    from sekd_sfm.bench.scale.captures import render_panoramas
    from sekd_sfm.bench.scale.scene import SceneConfig
    from sekd_sfm.evaluation.metrics import rotation_angle_deg
    from sekd_sfm.stages.rig import quat_to_matrix

    scene = json.loads(render_panoramas(tmp_path / "scene", SceneConfig(), count=3, width=1024, progress=False)
                       .read_text())
    out = tmp_path / "out"
    reconstruct(tmp_path / "scene/images", out, progress=False)
    lines = [line.split() for line in (out / "panoramas.txt").read_text().splitlines() if not line.startswith("#")]
    poses = {f[0]: (quat_to_matrix([float(v) for v in f[1:5]]), np.array([float(v) for v in f[5:]])) for f in lines}
    truth = {c["name"]: (np.array(c["R"]), np.array(c["t"])) for c in scene["images"]}
    assert sorted(poses) == sorted(truth)
    names = sorted(truth)
    for a, b in zip(names, names[1:]):  # relative rotation and translation direction of neighbours
        Rt, Re = truth[b][0] @ truth[a][0].T, poses[b][0] @ poses[a][0].T
        tt, te = truth[b][1] - Rt @ truth[a][1], poses[b][1] - Re @ poses[a][1]
        assert rotation_angle_deg(Re @ Rt.T) < 1.0
        assert np.degrees(np.arccos(np.clip(tt @ te / np.linalg.norm(tt) / np.linalg.norm(te), -1, 1))) < 3.0
    stats = json.loads((out / "stats.json").read_text())
    assert stats["panoramas"]["posed"] == 3 and (out / "views/pano3").is_dir()
    assert not any(p.count("pano") == 2 and p.split()[0].split("/", 1)[1] == p.split()[1].split("/", 1)[1]
                   for p in (out / "pairs.txt").read_text().splitlines())  # no pair within a panorama
