"""`sekd bench captures`: the generated rig, panoramas and video (truth, equirectangular mapping), and the scoring."""
import json
import math

import cv2
import numpy as np
import pycolmap
import pytest
from click.testing import CliRunner

from sekd_sfm.bench.captures import (
    frame_scores,
    pose_scores,
    quat_to_matrix,
    read_panoramas,
    rig_scores,
)
from sekd_sfm.bench.scale.captures import (
    CUBE,
    VIDEO_STEP_M,
    cam1_from_rig,
    cube_intrinsics,
    cube_to_equirect,
    equirect_directions,
    face_renderer,
    render_panorama,
    render_rig,
    render_video,
    rotation_y,
    walk_layout,
)
from sekd_sfm.bench.scale.scene import Camera, SceneConfig, read_scene
from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.files.video import VideoReader
from sekd_sfm.stages.keyframes import sharpness
from sekd_sfm.stages.panoramas import equirectangular_pixels

SMALL = SceneConfig(image_size=160)


def equirect_pixels(directions: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    return tuple(np.moveaxis(equirectangular_pixels(directions, width), -1, 0))


def _xyzw_to_wxyz(R):
    x, y, z, w = pycolmap.Rotation3d(R).quat
    return [w, x, y, z]


def test_rig_truth_is_consistent(tmp_path, shared):
    scene = read_scene(render_rig(tmp_path, SMALL, instants=2, progress=False).parent)
    rig = json.loads((tmp_path / "rig_known.json").read_text())[0]["cameras"]
    assert json.loads((tmp_path / "rig.json").read_text()) == [{"cameras": [rig[0], {"image_prefix": "cam1/"}]}]
    R, t = quat_to_matrix(rig[1]["cam_from_rig_rotation"]), np.array(rig[1]["cam_from_rig_translation"])
    assert np.allclose(R, cam1_from_rig(40, 0.3)[0]) and np.allclose(-R.T @ t, [0.3, 0, 0])
    assert np.allclose(quat_to_matrix(_xyzw_to_wxyz(R)), R)  # our quaternion convention is pycolmap's
    for k in range(2):
        cam0, cam1 = scene["cameras"][f"cam0/{k:05d}.jpg"], scene["cameras"][f"cam1/{k:05d}.jpg"]
        assert (tmp_path / "images" / f"cam1/{k:05d}.jpg").is_file()
        point = cam0.center + cam0.R.T @ np.array([-1.5, 0.3, 8.0])  # ahead of camera 0, within camera 1's view
        composed = Camera(cam0.K, R @ cam0.R, R @ cam0.t + t, cam0.width, cam0.height)
        pixel, depth = cam1.project(point[None])
        assert depth[0] > 0 and 0 <= pixel[0, 0] < cam1.width and 0 <= pixel[0, 1] < cam1.height
        assert np.allclose(composed.project(point[None])[0], pixel)
        assert 0 <= cam0.project(point[None])[0][0, 0] < cam0.width


def test_equirect_pixels_invert_directions_and_top_looks_up():
    d = equirect_directions(64)
    assert d.shape == (32, 64, 3)
    u, v = equirect_pixels(d, 64)
    assert np.allclose(u, np.arange(64)[None], atol=1e-3) and np.allclose(v, np.arange(32)[:, None], atol=1e-3)
    assert (d[0, :, 1] < -0.99).all() and np.allclose(d[16, 32], [0, 0, 1], atol=0.1)  # top: -y; centre: +z
    assert np.allclose(equirect_pixels(np.array([1.0, 0, 0]), 64), (47.5, 15.5))  # +x: three quarters across


def test_cube_to_equirect_reads_the_face_each_direction_meets():
    faces = [np.full((10, 10, 3), 40 * (k + 1), np.uint8) for k in range(6)]  # 8 px faces with their 1 px margin
    pano = cube_to_equirect(faces, 64)
    forwards = np.array([f for f, _ in CUBE], np.float32)
    expected = 40 * ((equirect_directions(64) @ forwards.T).argmax(-1) + 1)
    assert pano.shape == (32, 64, 3) and (pano[..., 0] == expected).all()  # exact: the margin keeps faces apart
    for k, forward in enumerate(forwards):
        u, v = equirect_pixels(forward, 64)
        assert pano[int(v), int(u), 0] == 40 * (k + 1)  # the poles: v = -0.5 or 31.5


def test_panorama_shows_what_a_pinhole_camera_sees(shared):
    layout = walk_layout(SMALL, 3)
    draw = face_renderer(layout)
    camera = layout.cameras[2]
    R, t = rotation_y(0.7) @ camera.R, rotation_y(0.7) @ camera.t  # a panorama turned away from the walk camera
    pano = render_panorama(draw, R, t, 512)
    # A 90 deg pinhole view 46 deg right of the panorama's centre: across the cube's front and right faces.
    K, turn = cube_intrinsics(128), rotation_y(0.8)
    pinhole = draw(Camera(K, turn.T @ R, turn.T @ t, 130, 130)).astype(np.float32)
    xs, ys = np.meshgrid(np.arange(10, 120, dtype=np.float32), np.arange(10, 120, dtype=np.float32))
    rays = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)
    u, v = equirect_pixels(rays @ turn.T, 512)

    def error(shift):
        sampled = cv2.remap(pano, (u + shift).astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR)
        return float(np.abs(sampled - pinhole[10:120, 10:120]).mean())

    assert error(0) < 6 and error(0) < error(3) / 2  # same content, and misplacing it by 3 px shows


def test_video_streams_every_frame_and_marks_the_blurred(tmp_path, shared):
    path = render_video(tmp_path, SMALL, frames=10, blur_fraction=0.3, progress=False)
    scene = read_scene(tmp_path)
    blurred = scene["video"]["blurred"]
    assert len(blurred) == 3 and sorted(scene["cameras"]) == [f"walk/{i:06d}.jpg" for i in range(10)]
    with VideoReader(tmp_path / "walk.avi") as reader:
        frames = [frame for _, _, frame in reader]
        assert reader.fps == 30 and reader.size == (160, 120)
    assert len(frames) == 10 and not (tmp_path / "walk.partial.avi").exists()
    sharp = [sharpness(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)) for f in frames]
    assert max(sharp[i] for i in blurred) < min(s for i, s in enumerate(sharp) if i not in blurred)
    centers = np.array([scene["cameras"][f"walk/{i:06d}.jpg"].center for i in range(10)])
    assert np.allclose(np.linalg.norm(np.diff(centers, axis=0), axis=1), VIDEO_STEP_M, rtol=0.5)
    assert render_video(tmp_path, SMALL, frames=10, blur_fraction=0.3) == path  # finished: reused
    with pytest.raises(SekdError, match="other settings"):
        render_video(tmp_path, SMALL, frames=11, blur_fraction=0.3)


def _rig_model(R_rig, t_rig, free_turns=None):
    """3 instants of a 2-camera rig (camera 1 from rig ``R_rig``, ``t_rig``), or with ``free_turns`` free photos
    whose camera 1 is turned by those extra angles (rad) about y per instant."""
    rec = pycolmap.Reconstruction()
    for cid in (1, 2):
        rec.add_camera(pycolmap.Camera(camera_id=cid, model="PINHOLE", width=160, height=120, params=[100, 100, 80, 60]))
    sensors = [pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=cid) for cid in (1, 2)]
    rigs = [1] if free_turns is None else [1, 2]
    for rig_id in rigs:
        rig = pycolmap.Rig(rig_id=rig_id)
        rig.add_ref_sensor(sensors[rig_id - 1])
        if free_turns is None:
            rig.add_sensor(sensors[1], pycolmap.Rigid3d(pycolmap.Rotation3d(R_rig), t_rig))
        rec.add_rig(rig)
    image_id = 1
    for k in range(3):
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.1, 0.2 * k, 0])), [k, 0.5, 0])
        frames = [(k + 1, 1, [0, 1])] if free_turns is None else [(2 * k + 1, 1, [0]), (2 * k + 2, 2, [1])]
        for frame_id, rig_id, cams in frames:
            frame = pycolmap.Frame(frame_id=frame_id, rig_id=rig_id)
            for j in cams:
                frame.add_data_id(pycolmap.data_t(sensor_id=sensors[j], id=image_id + j))
            frame.rig_from_world = pose if cams[0] == 0 else pycolmap.Rigid3d(
                pycolmap.Rotation3d(rotation_y(free_turns[k]) @ R_rig), t_rig) * pose
            rec.add_frame(frame)
        for j in (0, 1):
            image = pycolmap.Image(name=f"cam{j}/{k:05d}.jpg", camera_id=j + 1, image_id=image_id + j)
            image.frame_id = frames[0][0] if len(frames) == 1 else frames[j][0]
            rec.add_image(image)
        for frame_id, _, _ in frames:
            rec.register_frame(frame_id)
        image_id += 2
    return rec


def test_rig_scores_against_a_known_rotation():
    R_true, t_true = cam1_from_rig(40, 0.3)
    scene = {"rig": {"cam_from_rig_rotation": _xyzw_to_wxyz(R_true), "cam_from_rig_translation": t_true.tolist()}}
    exact = rig_scores(_rig_model(R_true, 2 * t_true), scene)  # the model's scale is its own
    assert exact["rig_rotation_error_deg"] < 1e-6 and exact["rig_translation_error_deg"] < 1e-4
    assert exact["instants_registered"] == 3 and exact["instant_rotation_max_deg"] < 1e-4
    off = rig_scores(_rig_model(rotation_y(math.radians(2)) @ R_true, t_true), scene)
    assert off["rig_rotation_error_deg"] == pytest.approx(2, abs=1e-3)
    assert off["instant_rotation_median_deg"] == pytest.approx(2, abs=1e-3)
    free = rig_scores(_rig_model(R_true, t_true, free_turns=np.radians([0, 1, 4])), scene)
    assert free["rig_rotation_error_deg"] is None and free["instants_registered"] == 3
    assert free["instant_rotation_median_deg"] == pytest.approx(1, abs=1e-3)
    assert free["instant_rotation_max_deg"] == pytest.approx(4, abs=1e-3)
    assert rig_scores(None, scene)["instants_registered"] == 0


def test_panoramas_txt_and_auc_on_perfect_and_perturbed_poses(tmp_path):
    rng = np.random.default_rng(0)
    truth = {}
    for i in range(6):
        R = cv2.Rodrigues(rng.normal(0, 0.5, 3))[0]
        truth[f"{i:05d}.jpg"] = Camera(None, R, -R @ np.array([5.0 * i, rng.normal(), 1.6]), 2048, 1024)
    names = sorted(truth)
    # The model's own frame: turned, scaled by 3, shifted; one panorama also turned by 10 deg when perturbed.
    G, s, shift = cv2.Rodrigues(np.array([0.3, -1.0, 0.2]))[0], 3.0, np.array([1.0, 2.0, 3.0])
    for perturb in (False, True):
        lines = ["# NAME qw qx qy qz tx ty tz", ""]
        for name, cam in truth.items():
            R = cam.R @ G.T
            t = s * cam.t - R @ shift
            if perturb and name == "00002.jpg":
                R, t = rotation_y(math.radians(10)) @ R, rotation_y(math.radians(10)) @ t
            lines.append(" ".join([name, *map(str, _xyzw_to_wxyz(R)), *map(str, t)]))
        (tmp_path / "panoramas.txt").write_text("\n".join(lines) + "\n")
        poses = read_panoramas(tmp_path / "panoramas.txt")
        scores = pose_scores(poses, truth, names)
        assert scores["registered"] == 6
        if not perturb:
            assert np.allclose(poses["00003.jpg"][0], truth["00003.jpg"].R @ G.T)
            assert scores["auc5"] > 0.999 and scores["median_rotation_error_deg"] < 1e-4
        else:  # 5 of 15 pairs hold the turned one: their error is >= 10 deg
            assert scores["auc5"] == pytest.approx(10 / 15, abs=1e-3) and scores["auc20"] < 0.9
    del poses["00001.jpg"]
    assert pose_scores(poses, truth, names)["auc20"] < 10 / 15  # an unposed panorama fails its pairs
    (tmp_path / "panoramas.txt").write_text("00000.jpg 1 0 0\n")
    with pytest.raises(SekdError, match="panoramas.txt:1"):
        read_panoramas(tmp_path / "panoramas.txt")


def test_frame_scores_count_blur_and_gaps():
    truth = {f"walk/{i:06d}.jpg": Camera(None, np.eye(3), np.array([-0.25 * i, 0, 0]), 160, 120) for i in range(50)}
    scene = {"video": {"fps": 10, "frames": 50, "blurred": [3]}, "cameras": truth}
    names = ["walk/000000.jpg", "walk/000003.jpg", "walk/000020.jpg", "walk/000040.jpg"]
    estimated = {n: (truth[n].R, truth[n].t) for n in ("walk/000000.jpg", "walk/000020.jpg")}
    scores = frame_scores(names, estimated, scene)
    assert scores["keyframes"] == 4 and scores["blurred_keyframes"] == 1 and scores["blurred_keyframes_pct"] == 25
    assert scores["registered"] == 2 and scores["gaps"] == 2 and scores["gap_s"] == 5.0  # 0 -> 2 s, 2 s -> 5 s
    assert scores["auc5"] == pytest.approx(1 / 6, abs=1e-4)


def test_cli_help_and_bad_kind():
    runner = CliRunner()
    out = runner.invoke(sekd, ["bench", "captures", "--help"])
    assert out.exit_code == 0 and "panoramas.txt" in out.output and "results.json" in out.output
    out = runner.invoke(sekd, ["bench", "captures", "drone"])
    assert out.exit_code == 2 and "drone" in out.output


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_bench_captures_rig_end_to_end(tmp_path, shared):
    out = CliRunner().invoke(sekd, ["bench", "captures", "rig", "--count", "8", "--image-size", "320", "-o",
                                    str(tmp_path)])
    assert out.exit_code == 0, out.output
    result = json.loads((tmp_path / "rig" / "results.json").read_text())
    assert result["record"]["commit"] is not None or "sekd_sfm" in result["record"]
    assert result["ours"]["registered"] > 0 and "instant_rotation_max_deg" in result["baseline"]
