"""`sekd bench scale`: the generated scene (exact projection, co-visibility), measurement, metrics, end to end."""
import dataclasses
import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sekd_sfm.bench.scale.measure import run_measured
from sekd_sfm.bench.scale.run import growth_exponent, pair_errors, pairs_recall
from sekd_sfm.bench.scale.scene import (
    GRAIN_SCALE,
    MIN_TEXTURED,
    Camera,
    Face,
    SceneConfig,
    SurfaceView,
    Textures,
    add_grain,
    apparent_size,
    assign_textures,
    covisibility_counts,
    generate_scene,
    grain_texture,
    layout_scene,
    pavement_texture,
    pixel_overlap,
    read_covisibility,
    read_scene,
    render,
    render_layers,
    texture_cells,
    textured_fraction,
)
from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.evaluation.strecha import read_cameras

# A camera at the origin looking down +z: x ~ K X, f = 100 px, 160 x 120 px, principal point at the centre.
K = np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]])
CAMERA = Camera(K, np.eye(3), np.zeros(3), 160, 120)


def _two_colour_texture(tmp_path: Path) -> Textures:
    texture = np.zeros((20, 40, 3), np.uint8)
    texture[:, :20] = (0, 0, 255)   # left half red (BGR)
    texture[:, 20:] = (255, 0, 0)   # right half blue
    cv2.imwrite(str(tmp_path / "t.png"), texture)
    return Textures([tmp_path / "t.png"])


def _wall(x0, y0, z, width, height, crop=(0, 0, 40, 20)) -> Face:
    # Facing the camera: u = +x (right), v = +y (down), normal v x u = -z.
    return Face(np.array([x0, y0, z]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), width, height, 0, crop,
                (1.0, 1.0, 1.0))


def test_render_puts_a_facade_corner_where_the_pinhole_projects_it(tmp_path):
    # Wall 2 m x 1 m at 5 m, top-left corner (-1, -0.5, 5): by hand x = 79.5 + 100 * -1/5 = 59.5,
    # y = 59.5 + 100 * -0.5/5 = 49.5; bottom-right (1, 0.5, 5) -> (99.5, 69.5). One texel per pixel.
    face = _wall(-1.0, -0.5, 5.0, 2.0, 1.0)
    assert np.allclose(face.normal, [0, 0, -1])
    image, face_id = render(CAMERA, [face], _two_colour_texture(tmp_path))
    drawn = np.argwhere(face_id == 0)
    assert drawn[:, 1].min() == 60 and drawn[:, 1].max() == 99    # columns 59.5..99.5 -> pixel centres 60..99
    assert drawn[:, 0].min() == 50 and drawn[:, 0].max() == 69
    assert len(drawn) == 40 * 20
    assert tuple(image[60, 70]) == (0, 0, 255) and tuple(image[60, 90]) == (255, 0, 0)  # texture left/right halves
    pix, depth = CAMERA.project(face.corners())
    assert np.allclose(pix, [[59.5, 49.5], [99.5, 49.5], [99.5, 69.5], [59.5, 69.5]]) and np.allclose(depth, 5)


def test_render_depth_test_keeps_the_nearer_face_whatever_the_order(tmp_path):
    near, far = _wall(-1.0, -0.5, 5.0, 2.0, 1.0), _wall(-3.0, -1.5, 8.0, 6.0, 3.0)
    textures = _two_colour_texture(tmp_path)
    _, ids_a = render(CAMERA, [near, far], textures)
    _, ids_b = render(CAMERA, [far, near], textures)
    assert ids_a[60, 80] == 0 and ids_b[60, 80] == 1   # the near wall, indexed 0 then 1
    assert ids_a[45, 50] == 1 and ids_b[45, 50] == 0   # only the far wall there (cols 42..117, rows 41..78)
    assert ids_a[0, 0] == -1                           # sky


def test_render_clips_a_face_crossing_the_camera_plane(tmp_path):
    # A floor 1.5 m below the camera from z = -10 to z = +10 m: only its front half may be drawn, below the horizon.
    floor = Face(np.array([-5.0, 1.5, 10.0]), np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), 10.0, 20.0, 0,
                 (0, 0, 40, 20), (1.0, 1.0, 1.0))
    assert np.allclose(floor.normal, [0, -1, 0])  # up, towards the camera (y is down)
    _, ids = render(CAMERA, [floor], _two_colour_texture(tmp_path))
    rows = np.flatnonzero((ids == 0).any(axis=1))
    # Far edge at 10 m: y = 59.5 + 100 * 1.5 / 10 = 74.5; the near plane cuts the rest off below the image.
    assert rows.min() == 75 and rows.max() == 119


def test_covisibility_counts_are_symmetric_shared_points():
    shared, seen = covisibility_counts([np.array([0, 1, 2]), np.array([1, 2, 3]), np.array([5])], 6)
    dense = shared.toarray()
    assert (dense == dense.T).all()
    assert dense[0, 1] == 2 and dense[0, 2] == 0 and dense[1, 2] == 0 and dense[2, 2] == 1
    assert seen.tolist() == [3, 3, 1]


def test_grain_is_unit_noise_unique_and_repeatable():
    a = grain_texture(300, 200, np.random.default_rng([0, 5, 1]))
    assert a.shape == (200, 300, 1) and a.dtype == np.uint8
    noise = (a.astype(np.float32) - 128) / GRAIN_SCALE
    assert abs(float(noise.mean())) < 0.02 and 0.97 < float(noise.std()) < 1.03
    assert np.array_equal(a, grain_texture(300, 200, np.random.default_rng([0, 5, 1])))
    assert not np.array_equal(a, grain_texture(300, 200, np.random.default_rng([0, 5, 2])))
    # Structure down to 3 texels: neighbouring texels differ, texels 30 apart are nearly independent.
    assert np.corrcoef(noise[:, :-30].ravel(), noise[:, 30:].ravel())[0, 1] < 0.5


def test_add_grain_hand_computed():
    # Unit noise +1 and -1 (128 +- 32): moves of 1 x (0.06 x brightness + 6) grey levels.
    image = np.array([[[0, 0, 0], [100, 100, 100], [250, 250, 250]]], np.uint8)
    grain = np.array([[160, 96, 160]], np.uint8)
    assert add_grain(image, grain)[0, :, 0].tolist() == [6, 88, 255]  # 0 + 6; 100 - 12; 250 + 21 clipped


def test_generated_textures_beyond_the_budget_are_dropped_and_made_again_identically(monkeypatch):
    textures = Textures([])
    monkeypatch.setattr(Textures, "GENERATED_BYTES", 2 * 100 * 100 * 4 // 3 + 1)  # about two grain pyramids
    ids = [textures.add_generated("grain", 100, 100, (0, 5, k)) for k in range(3)]
    first = textures.level(ids[0], 0).copy()
    textures.level(ids[1], 0), textures.level(ids[2], 0)
    assert ids[0] not in textures._cache and ids[2] in textures._cache  # the least recently used went
    assert np.array_equal(textures.level(ids[0], 0), first)


def test_grain_follows_the_surface_between_views(tmp_path):
    # The grain is a texture of the face: a point of the wall shows the same grain in two photos.
    textures = _two_colour_texture(tmp_path)
    wall = _wall(-4.0, -3.0, 10.0, 8.0, 6.0)
    wall.grain = textures.add_generated("grain", 512, 384, (0, 5, 0))
    a, _ = render(CAMERA, [wall], textures)
    b, _ = render(Camera(K, np.eye(3), np.array([-0.8, 0, 0]), 160, 120), [wall], textures)  # 0.8 m right = 8 px at 10 m
    plain, _ = render(CAMERA, [_wall(-4.0, -3.0, 10.0, 8.0, 6.0)], textures)
    # The wall spans columns 40..119, rows 30..89 in a; b sees it 8 px further left.
    part_a, part_b = a[32:88, 50:110].astype(float), b[32:88, 42:102].astype(float)
    assert np.abs(part_a - part_b).mean() < 1.0
    assert (a[32:88, 42:118] != plain[32:88, 42:118]).any(axis=2).mean() > 0.5  # the grain is there


def _view(camera: Camera, faces: list[Face], tmp_path: Path) -> SurfaceView:
    _, face_id, depth = render_layers(camera, faces, _two_colour_texture(tmp_path))
    return SurfaceView.of(camera, face_id, depth)


def test_pixel_overlap_of_a_sideways_step_is_the_shared_field_of_view(tmp_path):
    # A wall filling the view at 10 m. The field of view there is 16 m wide (160 px, f = 100: 1.6 m per 10 px).
    # Camera b steps 4 m right: it sees x in [-4, 12], a sees [-8, 8]: a's columns over x >= -4, i.e. 3/4.
    wall = _wall(-30.0, -20.0, 10.0, 60.0, 40.0)
    b = Camera(K, np.eye(3), np.array([-4.0, 0, 0]), 160, 120)
    view_a, view_b = _view(CAMERA, [wall], tmp_path), _view(b, [wall], tmp_path)
    assert len(view_a.points) == 20 * 15 and np.allclose(view_a.points[:, 2], 10)  # one point per 8 x 8 px cell
    assert pixel_overlap(view_a, CAMERA, view_b, b) == pytest.approx(0.75)
    assert pixel_overlap(view_b, b, view_a, CAMERA) == pytest.approx(0.75)
    # Rays from 4 m apart meet at 10 m at 13-23 degrees: none within 10 degrees.
    assert pixel_overlap(view_a, CAMERA, view_b, b, max_angle=10) == 0.0


def test_pixel_overlap_counts_only_what_the_other_photo_sees_unoccluded(tmp_path):
    # A near wall in front of b's view (but outside a's, which looks from far left) hides the right half.
    wall = _wall(-30.0, -20.0, 10.0, 60.0, 40.0)
    blocker = _wall(0.0, -20.0, 2.0, 10.0, 40.0)  # x >= 0 at 2 m: covers b's right half
    b = CAMERA
    a = Camera(K, np.eye(3), np.array([0.0, 0, 0]), 160, 120)
    view_a = _view(a, [wall], tmp_path)  # a's rendering without the blocker: the wall everywhere
    view_b = _view(b, [wall, blocker], tmp_path)
    assert pixel_overlap(view_a, a, view_b, b) == pytest.approx(0.5)
    assert pixel_overlap(view_b, b, view_b, b) == pytest.approx(1.0)


def test_assign_textures_gives_every_face_its_own_region():
    sizes = [(640, 480), (480, 640)]
    faces = [_wall(0.0, 0.0, 5.0, 2.0 + i % 3, 1.0 + i % 2) for i in range(14)]  # 14 faces > 2 photos x 2 x 2 tiles
    assign_textures(faces, sizes, np.random.default_rng(0))
    keys = [(f.texture, f.crop[0] // (sizes[f.texture][0] // 3), f.crop[1] // (sizes[f.texture][1] // 3)) for f in faces]
    assert len(set(keys)) == len(faces)  # 2 photos x 3 x 3 tiles = 18 slots, each used at most once
    for f in faces:
        x, y, w, h = f.crop
        tw, th = sizes[f.texture][0] // 3, sizes[f.texture][1] // 3
        assert x // tw == (x + w - 1) // tw and y // th == (y + h - 1) // th  # inside one tile
        assert abs(w / h - f.width / f.height) < 0.02 * f.width / f.height  # the face's own aspect
    assert assign_textures([], sizes, np.random.default_rng(0)) == []


def test_assign_textures_cuts_only_as_many_photos_finer_as_needed():
    # 5 faces, 4 photos: one photo is cut into 2 x 2, the other three stay whole.
    sizes = [(640, 480)] * 4
    faces = [_wall(0.0, 0.0, 5.0, 4.0, 3.0) for _ in range(5)]
    priority = np.array([1.0, 5.0, 2.0, 4.0, 3.0])
    assign_textures(faces, sizes, np.random.default_rng(1), priority=priority)
    whole = [i for i, f in enumerate(faces) if f.crop[2] > 320]
    assert sorted(whole) == [1, 3, 4]  # the three largest priorities take the whole photos
    assert len({f.texture for f in faces}) == 4


def test_pavement_textures_are_textured_unique_and_repeatable():
    a = pavement_texture(96, 64, np.random.default_rng([0, 4, 1]))
    assert a.shape == (64, 96, 3) and a.dtype == np.uint8
    assert np.array_equal(a, pavement_texture(96, 64, np.random.default_rng([0, 4, 1])))
    assert not np.array_equal(a, pavement_texture(96, 64, np.random.default_rng([0, 4, 2])))
    assert textured_fraction(texture_cells(a), (0, 0, 96, 64)) == 1.0


def test_texture_cells_and_textured_fraction_hand_computed():
    photo = np.zeros((32, 64), np.uint8)
    photo[:, 32:] = np.tile(np.array([0, 0, 40, 40], np.uint8), (32, 8))  # right half: 2-texel stripes
    cells = texture_cells(photo)
    assert cells.shape == (2, 4)
    assert np.all(cells[:, :2] == 0)  # flat: no gradient
    # Sobel / 8 of a 40-level step = 20 grey levels at every stripe texel but one per cell: the first
    # column (0 on both sides) and the last (mirrored border: 40 on both sides) -> 15/16 x 20 = 18.75.
    assert np.allclose(cells[:, 2:], 18.75)
    assert textured_fraction(cells, (0, 0, 64, 32)) == 0.5
    assert textured_fraction(cells, (32, 0, 32, 32)) == 1.0
    assert textured_fraction(cells, (0, 0, 8, 8)) == 1.0  # under one cell: not judged


def test_assign_textures_skips_blank_regions():
    # Photo 0 is blank on its left half: no face may take a crop mostly inside it.
    sizes = [(64, 32)]
    blank_left = texture_cells(np.hstack([np.zeros((32, 32), np.uint8),
                                          np.tile(np.array([0, 0, 40, 40], np.uint8), (32, 8))]))
    faces = [_wall(0.0, 0.0, 5.0, 1.0, 1.0) for _ in range(2)]  # square faces: a 32 x 32 crop at most
    assign_textures(faces, sizes, np.random.default_rng(0), cells=[blank_left])
    for f in faces:
        assert textured_fraction(blank_left, f.crop) >= MIN_TEXTURED


def test_apparent_size_ranks_near_facades_above_grazing_and_far_faces():
    # Walls face the camera at the origin (normal -z). By hand: 10 m x 6 m seen square-on at 5 m and
    # 5.83 m (centre (0, 3, 5)): 60 * (5 / 5.83) / 34 = 1.51 sr; at 40 m: 60 * 0.997 / 1609 = 0.037.
    centers = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -100.0]])
    near, far = _wall(-5.0, 0.0, 5.0, 10.0, 6.0), _wall(-5.0, 0.0, 40.0, 10.0, 6.0)
    # Ground 1.6 m below the camera (y is down; normal v x u = -y, up), 5-11 m ahead: centre (0, 1.6, 8),
    # cos = 1.6 / 8.16, 60 * 0.196 / 66.56 = 0.177 sr.
    grazing = Face(np.array([-5.0, 1.6, 11.0]), np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), 10.0, 6.0, 0,
                   (0, 0, 40, 20), (1.0, 1.0, 1.0))
    sizes = apparent_size([near, far, grazing], centers)
    assert sizes[0] == pytest.approx(60 * (5 / math.sqrt(34)) / 34, rel=1e-6)
    assert sizes[1] == pytest.approx(60 * (40 / math.sqrt(1609)) / 1609, rel=1e-6)
    assert sizes[2] == pytest.approx(60 * (1.6 / math.sqrt(66.56)) / 66.56, rel=1e-6)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory, shared):
    config = SceneConfig(num_images=12, image_size=160, seed=3)
    out = tmp_path_factory.mktemp("scene")
    generate_scene(out, config, progress=False)
    return out, config


def test_generated_scene_files_and_cameras_agree(tiny_scene):
    out, _ = tiny_scene
    scene = read_scene(out)
    images = sorted(p.name for p in (out / "images").iterdir())
    assert len(images) == 12 and len(scene["distractors"]) == 1 and len(scene["cameras"]) == 11
    assert set(scene["cameras"]) | set(scene["distractors"]) == set(images)
    assert cv2.imread(str(out / "images" / images[0])).shape == (120, 160, 3)
    strecha = read_cameras(out / "gt_dense_cameras")
    assert set(strecha) == set(scene["cameras"])
    for name, camera in scene["cameras"].items():
        R, t = strecha[name].cam_from_world
        assert np.allclose(R, camera.R) and np.allclose(t, camera.t) and np.allclose(strecha[name].K, camera.K)
        assert np.allclose(camera.R @ camera.R.T, np.eye(3)) and abs(np.linalg.det(camera.R) - 1) < 1e-9
    # f from the 60 deg field of view: 80 / tan(30 deg).
    assert math.isclose(scene["cameras"][images[0] if images[0] in scene["cameras"] else images[1]].K[0, 0],
                        80 / math.tan(math.radians(30)))


def test_generated_photo_shows_the_facade_corner_where_its_camera_projects_it(tiny_scene):
    out, config = tiny_scene
    layout = layout_scene(config)
    scene = read_scene(out)
    name = next(n for n in scene["cameras"])
    camera = scene["cameras"][name]
    assert np.allclose(camera.R, layout.cameras[0].R)
    _, face_id = render(camera, layout.faces, layout.textures)
    checked = 0
    for index in np.unique(face_id[face_id >= 0]):
        face = layout.faces[index]
        pix, depth = camera.project(face.corners())
        centre, _ = camera.project(face.corners().mean(0, keepdims=True))
        for corner, z in zip(pix, depth):
            inward = corner + 2.5 * (centre[0] - corner) / np.linalg.norm(centre[0] - corner)
            col, row = np.round(inward).astype(int)
            if z > 0 and 0 <= col < camera.width and 0 <= row < camera.height and face_id[row, col] == index:
                checked += 1
    assert checked >= 2  # at least two facade corners appear, unoccluded, exactly where projected
    # The photo on disk is that rendering (after exposure change, noise and JPEG): same structure.
    photo = cv2.imread(str(out / "images" / name), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    rendered = cv2.cvtColor(render(camera, layout.faces, layout.textures)[0], cv2.COLOR_BGR2GRAY).astype(np.float32)
    assert np.corrcoef(photo.ravel(), rendered.ravel())[0, 1] > 0.8


def test_ground_truth_covisibility_is_non_empty_and_about_scene_photos(tiny_scene):
    out, _ = tiny_scene
    scene = read_scene(out)
    pairs = read_covisibility(out, min_overlap=0.1)
    assert pairs and all(len(p) == 2 and p <= set(scene["cameras"]) for p in pairs)
    names = sorted(scene["cameras"])
    assert frozenset(names[:2]) in pairs  # neighbours along the walk overlap
    lines = (out / "covisibility.txt").read_text().splitlines()
    assert all(a < b for a, b, *_ in (line.split() for line in lines))  # each unordered pair once
    assert len(read_covisibility(out, min_overlap=0.0)) == len(lines) >= len(pairs)
    matchable = read_covisibility(out, min_overlap=0.1, matchable=True)
    assert matchable and frozenset(names[:2]) in matchable and all(0.1 <= v <= 1 for v in matchable.values())
    assert set(matchable) <= set(read_covisibility(out, min_overlap=0.0))


def test_covisibility_file_of_another_format_is_one_clear_error(tmp_path):
    (tmp_path / "covisibility.txt").write_text("a.jpg b.jpg 10 0.5\n")  # the 4-column format of older scenes
    with pytest.raises(SekdError, match="generate the scene again"):
        read_covisibility(tmp_path)


def test_scene_generation_is_deterministic_and_resumable(tiny_scene, tmp_path):
    out, config = tiny_scene
    again = tmp_path / "again"
    generate_scene(again, config, progress=False)
    for name in ("covisibility.txt", "images/00005.jpg"):
        assert (out / name).read_bytes() == (again / name).read_bytes()
    stamp = (again / "scene.json").stat().st_mtime_ns
    generate_scene(again, config, progress=False)  # finished: reused
    assert (again / "scene.json").stat().st_mtime_ns == stamp
    with pytest.raises(SekdError, match="another configuration"):
        generate_scene(again, SceneConfig(num_images=13, image_size=160, seed=3), progress=False)


def test_scene_errors(tmp_path):
    with pytest.raises(SekdError, match="at least 2 images"):
        SceneConfig(num_images=1)
    (tmp_path / "few").mkdir()
    cv2.imwrite(str(tmp_path / "few" / "a.jpg"), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(SekdError, match="1 photos"):
        generate_scene(tmp_path / "s", SceneConfig(num_images=10, textures=str(tmp_path / "few")))
    with pytest.raises(SekdError, match="not found"):
        generate_scene(tmp_path / "s", SceneConfig(num_images=10, textures=str(tmp_path / "none")))
    with pytest.raises(SekdError, match="not a generated scene"):
        read_scene(tmp_path)


def test_ring_scene_photographs_the_object_from_a_circle(tmp_path, shared):
    from sekd_sfm.bench.scale.layout import RING_ELEVATION_DEG, RING_TARGET

    config = SceneConfig(num_images=8, image_size=160, hfov_deg=24, layout="ring", seed=2)
    generate_scene(tmp_path, config, progress=False)
    scene = read_scene(tmp_path)
    assert scene["config"]["layout"] == "ring" and scene["distractors"] == [] and len(scene["cameras"]) == 8
    layout = layout_scene(config)
    centers = np.array([camera.center for camera in layout.cameras])
    distances = np.linalg.norm(centers - RING_TARGET, axis=1)
    assert np.allclose(distances, layout.block.distance, rtol=0.05)  # a circle around the target
    elevations = np.degrees(np.arcsin((centers[:, 2] - RING_TARGET[2]) / distances))
    assert np.allclose(elevations, RING_ELEVATION_DEG, atol=4)
    azimuths = np.degrees(np.arctan2(centers[:, 1], centers[:, 0])) % 360
    assert np.allclose(np.diff(azimuths), 45, atol=3)  # evenly around
    for camera in scene["cameras"].values():
        assert camera.K[0, 0] == pytest.approx(80 / math.tan(math.radians(12)))  # 24 deg over 160 px
        pix, depth = camera.project(RING_TARGET[None])
        assert depth[0] > 0 and np.hypot(*(pix[0] - [79.5, 59.5])) < 15  # looking at the object's middle
        _, face_id = render(camera, layout.faces, layout.textures)
        assert (face_id >= 0).mean() > 0.6  # the object and its plate fill the photo
    pairs = read_covisibility(tmp_path, min_overlap=0.1)
    names = sorted(scene["cameras"])
    assert frozenset(names[:2]) in pairs and frozenset((names[0], names[-1])) in pairs  # the ring closes


def test_scene_layouts_and_the_block_record_of_older_scenes():
    from sekd_sfm.bench.scale.scene import _config_record

    assert "layout" not in _config_record(SceneConfig())  # block scenes generated before the ring stay reusable
    assert _config_record(SceneConfig(layout="ring"))["layout"] == "ring"
    with pytest.raises(SekdError, match="unknown scene layout 'spiral'; choose from block, ring"):
        SceneConfig(layout="spiral")


def test_cli_generates_a_ring(tmp_path, shared):
    result = CliRunner().invoke(sekd, ["bench", "scale", "--layout", "ring", "--hfov", "24", "--sizes", "8",
                                       "--image-size", "96", "--generate-only", "-o", str(tmp_path)])
    assert result.exit_code == 0, result.output
    scene = read_scene(tmp_path / "n8/scene")
    assert scene["config"]["layout"] == "ring" and scene["config"]["hfov_deg"] == 24 and len(scene["cameras"]) == 8


def test_rotation_and_translation_errors_apart():
    from sekd_sfm.bench.scale.run import pair_rotation_translation_errors

    truth = {"a.jpg": Camera(K, np.eye(3), np.zeros(3), 160, 120),
             "b.jpg": Camera(K, np.eye(3), np.array([-1.0, 0, 0]), 160, 120)}
    turn, _ = cv2.Rodrigues(np.array([0.0, 0.0, math.radians(2)]))  # b turned 2 deg, its translation unchanged
    estimated = {"a.jpg": (np.eye(3), np.zeros(3)), "b.jpg": (turn, np.array([-1.0, 0, 0]))}
    rotation, translation = pair_rotation_translation_errors(estimated, truth, ["a.jpg", "b.jpg"], np.array([[0, 1]]))
    assert rotation[0] == pytest.approx(2, abs=1e-6) and translation[0] == pytest.approx(0, abs=1e-4)


def test_pair_errors_ignore_the_world_frame_and_fail_unregistered_pairs():
    rng = np.random.default_rng(0)
    truth = {}
    for k in range(4):
        R, _ = cv2.Rodrigues(rng.normal(0, 0.3, 3))
        truth[f"{k}.jpg"] = Camera(K, R, rng.normal(0, 2, 3), 160, 120)
    # The same cameras in another world frame and scale: X' = s Q X + c, so R' = R Q^T, t' = s t - R' c.
    Q, _ = cv2.Rodrigues(np.array([0.2, -0.5, 1.0]))
    s, c = 3.0, np.array([1.0, 2.0, 3.0])
    estimated = {n: (cam.R @ Q.T, s * cam.t - cam.R @ Q.T @ c) for n, cam in truth.items() if n != "3.jpg"}
    names = sorted(truth)
    pairs = np.array([(0, 1), (0, 2), (1, 2), (0, 3)])
    errors = pair_errors(estimated, truth, names, pairs)
    assert np.allclose(errors[:3], 0, atol=1e-4) and np.isinf(errors[3])
    # A 10 deg error in one camera's rotation shows as (at least) 10 deg in its pairs.
    turn, _ = cv2.Rodrigues(np.array([0.0, math.radians(10), 0.0]))
    estimated["1.jpg"] = (turn @ estimated["1.jpg"][0], turn @ estimated["1.jpg"][1])
    errors = pair_errors(estimated, truth, names, pairs)
    assert errors[0] == pytest.approx(10, abs=1e-6) and errors[1] == pytest.approx(0, abs=1e-4)


def test_pairs_recall_and_growth_exponent():
    covisible = {frozenset(("a", "b")): 0.5, frozenset(("b", "c")): 0.3}
    result = pairs_recall([("b", "a"), ("a", "c"), ("c", "d")], covisible)
    assert result == {"pairs": 3, "covisible_pairs": 2, "recall": 0.5, "precision": 1 / 3}
    assert pairs_recall([], {}) == {"pairs": 0, "covisible_pairs": 0, "recall": None, "precision": None}
    assert growth_exponent([10, 20, 40], [1.0, 4.0, 16.0]) == pytest.approx(2.0)
    assert growth_exponent([10, 20, 40], [3.0, 6.0, 12.0]) == pytest.approx(1.0)
    assert growth_exponent([10], [1.0]) is None and growth_exponent([10, 20], [0, 5]) is None


def test_run_measured_reports_bytes_memory_and_errors(tmp_path):
    data = b"x" * (24 * 1024 * 1024)
    m = run_measured(Path.write_bytes, (tmp_path / "out.bin", data), tmp_path / "m.json")
    assert m.error is None and m.result == len(data)
    assert m.bytes_written >= len(data) and m.peak_rss >= len(data)
    assert 0 <= m.cpu_s < 60 and m.wall_s > 0
    saved = json.loads((tmp_path / "m.json").read_text())["samples"]  # kept to trace a peak afterwards
    assert saved and max(rss for _, rss, _, _ in saved) == max(s[1] for s in m.samples)
    failed = run_measured(Path.read_text, (tmp_path / "missing.txt",), tmp_path / "m2.json")
    assert failed.result is None and "FileNotFoundError" in failed.error


def test_cli_rejects_bad_sizes(tmp_path):
    result = CliRunner().invoke(sekd, ["bench", "scale", "--sizes", "ten", "-o", str(tmp_path)])
    assert result.exit_code == 2 and "comma" in result.output
    result = CliRunner().invoke(sekd, ["bench", "scale", "--sizes", "4", "-o", str(tmp_path)])
    assert result.exit_code == 2 and "at least 8" in result.output


def test_cli_generate_only(tmp_path, shared):
    result = CliRunner().invoke(sekd, ["bench", "scale", "--sizes", "10", "--image-size", "96", "--generate-only",
                                       "-o", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert "n=10:" in result.output and "images/s" in result.output
    assert len(list((tmp_path / "n10/scene/images").iterdir())) == 10


@pytest.mark.slow
def test_bench_scale_end_to_end_and_resume(tmp_path, shared):
    args = ["bench", "scale", "--sizes", "12", "--image-size", "160", "-o", str(tmp_path), "--num-threads", "2"]
    result = CliRunner().invoke(sekd, args)
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "results.json").read_text())
    (row,) = report["results"]
    assert row["size"] == 12 and row["scene_images"] == 11
    for name in ("ours", "pycolmap"):
        p = row[name]
        assert p["failure"] is None and p["registered"] >= 8 and p["registered_distractors"] == []
        assert 0 < p["auc5"] <= 1 and p["peak_rss_mb"] > 10
        assert {"extract", "match", "verify", "map"} <= set(p["stages"])
    assert row["pairs"]["recall"] == 1.0  # 12 photos: every pair is matched
    assert "| 12 | ours |" in result.output and (tmp_path / "scale.png").is_file()
    run = row["run"]  # each size records where and with what it ran, and the table says so
    assert run["cpu"]["model"] and run["sekd_sfm"] and run["command"] and run["date"]
    assert f"N = 12 on {run['cpu']['model']}, " in (tmp_path / "results.md").read_text()
    stamp = (tmp_path / "n12/result.json").stat().st_mtime_ns
    again = CliRunner().invoke(sekd, args)
    assert again.exit_code == 0 and (tmp_path / "n12/result.json").stat().st_mtime_ns == stamp


def test_a_table_of_sizes_from_two_machines_names_both():
    from sekd_sfm.bench.scale.run import run_lines

    epyc = {"model": "AMD EPYC", "torch_kernels": "AVX2", "cores": 2}
    runs = [{"size": 250, "run": {"cpu": epyc, "commit": "abc", "sekd_sfm": "0.2.0"}},
            {"size": 500, "run": {"cpu": epyc, "commit": "abc", "sekd_sfm": "0.2.0"}},
            {"size": 1000, "run": {"cpu": "Intel Xeon", "commit": "def", "sekd_sfm": "0.2.0"}},
            {"size": 2000}]  # measured before sizes recorded their run
    assert run_lines(runs) == ["N = 250, 500 on AMD EPYC, AVX2, 2 cores, sekd 0.2.0 at commit abc",
                               "N = 1000 on Intel Xeon, sekd 0.2.0 at commit def"]


def test_retrieval_finds_the_true_neighbours_of_a_generated_street(tmp_path, shared):
    # 40 photos (39 along the street + 1 distractor) at 320 px, SEKD features, the default retrieval.
    from sekd_sfm.bench.scale.run import retrieval_recall
    from sekd_sfm.features import FeatureConfig
    from sekd_sfm.stages.extract import extract_features
    from sekd_sfm.stages.retrieval import compute_global_descriptors

    scene = tmp_path / "scene"
    generate_scene(scene, SceneConfig(num_images=40, image_size=320, seed=1), progress=False)
    features = extract_features(scene / "images", tmp_path / "features.h5", FeatureConfig(max_keypoints=1000),
                                num_threads=1, progress=False)
    names = sorted(read_scene(scene)["cameras"])
    truth = read_covisibility(scene, 0.1, matchable=True)
    assert len(truth) >= len(names)  # every photo overlaps its walk neighbours
    recall = retrieval_recall(compute_global_descriptors(features, progress=False), names, truth, 10)
    assert recall >= 0.9, recall
    assert retrieval_recall(tmp_path / "missing.global.h5", names, truth, 10) is None


def test_bench_scale_leaves_a_size_another_process_runs(tmp_path):
    from sekd_sfm.bench.scale.run import ScaleConfig, run_scale_benchmark
    from sekd_sfm.files.locking import exclusive_lock

    (tmp_path / "n12").mkdir()
    with exclusive_lock(tmp_path / "n12", "benchmark size folder"):  # as a second `sekd bench scale` would hold it
        run_scale_benchmark(tmp_path, ScaleConfig(sizes=(12,), image_size=160))
    assert not (tmp_path / "n12/result.json").exists() and not (tmp_path / "n12/scene").exists()
    assert json.loads((tmp_path / "results.json").read_text())["results"] == []


def _finished_baseline(folder, pairs, pycolmap_version):
    """A size folder as an earlier run leaves it: pycolmap/pairs-colmap.txt, pycolmap/model, result.json."""
    from sekd_sfm.bench.scale.run import ScaleConfig

    (folder / "pycolmap/model").mkdir(parents=True)
    (folder / "pycolmap/pairs-colmap.txt").write_text("".join(f"{a} {b}\n" for a, b in pairs))
    settings = {**dataclasses.asdict(ScaleConfig()), "versions": {"pycolmap": pycolmap_version}}
    result = {"pycolmap": {"failure": None, "registered": 7, "model": "elsewhere"}, "settings": settings}
    (folder / "result.json").write_text(json.dumps(result))
    return result


def test_pycolmap_run_is_reused_only_for_the_same_scene_pairs_and_version(tmp_path):
    from sekd_sfm.bench.scale.run import ScaleConfig, reusable_baseline
    from sekd_sfm.runtime import package_versions

    pairs = [("00000.jpg", "00001.jpg"), ("00001.jpg", "00002.jpg")]
    previous = _finished_baseline(tmp_path, pairs, package_versions()["pycolmap"])
    work = tmp_path / "pycolmap"
    reused = reusable_baseline(previous, work, pairs, ScaleConfig())
    assert reused["registered"] == 7 and reused["model"] == str(work / "model") and reused["reused_from"] == str(work)
    assert reusable_baseline(previous, work, pairs[:1], ScaleConfig()) is None            # other pairs
    assert reusable_baseline(previous, work, pairs, ScaleConfig(spacing=2.0)) is None     # another scene
    assert reusable_baseline(previous, work, pairs, ScaleConfig(repeats=2)) is None       # repeated structure
    assert reusable_baseline(None, work, pairs, ScaleConfig()) is None
    other_version = {**previous, "settings": {**previous["settings"], "versions": {"pycolmap": "0.0"}}}
    assert reusable_baseline(other_version, work, pairs, ScaleConfig()) is None
    failed = {**previous, "pycolmap": {"failure": "map: no model"}}
    assert reusable_baseline(failed, work, pairs, ScaleConfig()) is None


def test_link_scene_takes_only_a_scene_of_the_same_configuration(tmp_path):
    from sekd_sfm.bench.scale.run import link_scene

    config = SceneConfig(num_images=10, image_size=96, seed=3)
    generate_scene(tmp_path / "a", config, progress=False)
    assert link_scene(tmp_path / "a", tmp_path / "b", config)
    assert read_scene(tmp_path / "b")["config"] == read_scene(tmp_path / "a")["config"]
    image = min((tmp_path / "a/images").iterdir())
    assert os.stat(image).st_ino == os.stat(tmp_path / "b/images" / image.name).st_ino  # linked, not copied
    assert not link_scene(tmp_path / "a", tmp_path / "c", dataclasses.replace(config, seed=4))
    assert not (tmp_path / "c").exists() and not link_scene(tmp_path / "missing", tmp_path / "d", config)


def test_bench_scale_refuses_an_unknown_mapper_option_before_any_work(tmp_path):
    result = CliRunner().invoke(sekd, ["bench", "scale", "--sizes", "10", "-o", str(tmp_path / "out"),
                                       "--mapper-type", "hierarchical", "--mapper", "no_such_option=1"])
    assert result.exit_code != 0 and "no_such_option" in result.output
    assert not (tmp_path / "out").exists()


def test_baseline_above_its_mapping_limit_stops_after_verification_and_reports_dashes(tiny_scene, tmp_path):
    from sekd_sfm.bench.scale.run import exponents, run_pycolmap, scale_markdown

    scene_dir, _ = tiny_scene
    names = sorted(p.name for p in (scene_dir / "images").iterdir())
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:i + 3]]  # a walk: each photo and the next two
    record = run_pycolmap(scene_dir, tmp_path / "pycolmap", pairs, len(names), 0, 1, 160, map_stage=False)
    assert record["failure"] is None and record["skipped"] == ["map"]
    assert set(record["stages"]) == {"extract", "match", "verify"} and not (tmp_path / "pycolmap/model").exists()
    assert (tmp_path / "pycolmap/pairs-colmap.txt").read_text().count("\n") == len(pairs)

    def row(size, skipped):  # stage times grow as N^1 (extract) and N^2 (map)
        stages = {"extract": {"time_s": size, "cpu_s": size}}
        if not skipped:
            stages["map"] = {"time_s": size ** 2, "cpu_s": size ** 2}
        run = {"stages": stages, "wall_s": size + (0 if skipped else size ** 2),
               "registered": None if skipped else size, "scene_images": size, "registered_distractors": [],
               "auc5": None, "auc5_covisible": None, "median_pose_error_deg": None, "peak_rss_mb": 1,
               "written_mb": 1, "failure": None,
               "skipped": ["map"] if skipped else []}
        run["cpu_s"] = run["wall_s"]
        return {"size": size, "distractors": [], "pairs": {"pairs": 1, "recall": 1.0}, "pycolmap": run}

    results = [row(10, False), row(20, False), row(40, True)]
    fitted = exponents(results, "pycolmap")
    assert fitted["extract"] == pytest.approx(1.0) and fitted["map"] == pytest.approx(2.0)
    # The total fits the whole runs only: (10 + 100) -> (20 + 400), not the 40-photo run without its map.
    assert fitted["total"] == pytest.approx(math.log(420 / 110) / math.log(2))
    table = scale_markdown({"results": results, "exponents": {"pycolmap": fitted}})
    last = next(line for line in table.splitlines() if line.startswith("| 40 | pycolmap SIFT |"))
    assert "| 1 | same pairs | same pairs | - | - | - |" in last and last.endswith("(stopped before: map)")


# ----------------------------------------------------------------------------- repeated and symmetric structure

def _texture_key(face: Face) -> tuple:
    """What a face shows: photo region, colour gain and grain (equal keys: a local feature cannot tell them apart)."""
    return face.texture, tuple(face.crop), face.gain, face.grain


def _upright(layout) -> list[Face]:
    return [face for face in layout.faces if abs(face.normal[2]) < 0.5]


def _copies(faces: list[Face]) -> dict[tuple, list[Face]]:
    groups: dict[tuple, list[Face]] = {}
    for face in faces:
        groups.setdefault(_texture_key(face), []).append(face)
    return groups


def _centre(face: Face) -> np.ndarray:
    return face.corners().mean(0)


def _front(face: Face, block) -> bool:
    """A building's front (within 2 m of the street line), not a side wall reaching into the block."""
    x, y, _ = _centre(face)
    return min(block.hx - abs(x), block.hy - abs(y)) < 2


def test_assign_shared_textures_gives_each_group_one_region():
    from sekd_sfm.bench.scale.texturing import assign_shared_textures

    sizes = [(640, 480), (480, 640)]
    faces = [_wall(0.0, 0.0, 5.0, 2.0, 1.0) for _ in range(6)]
    for i, face in enumerate(faces):
        face.gain = (1.0 + i, 1.0, 1.0)
    representative = assign_shared_textures(faces, [0, 1, 0, 2, 1, 0], sizes, np.random.default_rng(0))
    assert representative == [0, 1, 0, 3, 1, 0]
    assert len({_texture_key(faces[i]) for i in (0, 2, 5)}) == 1 and faces[5].gain == (1.0, 1.0, 1.0)  # the first's
    assert len({(f.texture, f.crop) for f in faces}) == 3  # three groups, three regions
    # Every group one face: assign_textures, draw for draw.
    a = [_wall(0.0, 0.0, 5.0, 2.0 + i % 3, 1.0 + i % 2) for i in range(14)]
    b = [_wall(0.0, 0.0, 5.0, 2.0 + i % 3, 1.0 + i % 2) for i in range(14)]
    assign_textures(a, sizes, np.random.default_rng(4))
    assert assign_shared_textures(b, list(range(14)), sizes, np.random.default_rng(4)) == list(range(14))
    assert [(f.texture, f.crop) for f in a] == [(f.texture, f.crop) for f in b]


def test_one_repeat_without_mirror_is_the_scene_as_before(shared):
    import hashlib

    from sekd_sfm.bench.scale.scene import _config_record

    # Digests of the layouts (faces, textures, cameras) as generated before repeats and mirrors existed: the
    # default scenes stay the same, draw for draw (on the shared photos; re-pin only if these change).
    def digest(layout) -> str:
        faces = [[f.texture, list(f.crop), f.grain, [round(g, 9) for g in f.gain],
                  [round(float(v), 9) for v in (*f.origin, *f.u, *f.v, f.width, f.height)]] for f in layout.faces]
        cameras = [[round(float(v), 9) for v in (*c.R.ravel(), *c.t)] for c in layout.cameras]
        data = json.dumps([faces, cameras, sorted(layout.distractor_slots), [p.name for p in layout.pool]])
        return hashlib.sha256(data.encode()).hexdigest()[:16]

    block = layout_scene(SceneConfig(num_images=12, image_size=160, seed=3))
    ring = layout_scene(SceneConfig(num_images=8, image_size=160, hfov_deg=24, layout="ring", seed=2))
    assert (digest(block), digest(ring)) == ("9f2f191737447f5a", "3dd1970deaea3f49")
    assert all(len(faces) == 1 for faces in _copies(_upright(block)).values())  # no texture twice
    record = _config_record(SceneConfig())
    assert "repeats" not in record and "symmetric" not in record  # earlier scenes stay reusable
    assert _config_record(SceneConfig(repeats=3, symmetric=True))["repeats"] == 3
    with pytest.raises(SekdError, match="repeats 9 is outside 1..8"):
        SceneConfig(repeats=9)


def test_repeats_show_each_facade_on_the_other_side_of_the_block(shared):
    # Two repeats: the street's second half repeats its first, so every building's copy stands on the
    # opposite side (side 0 <-> 2, 1 <-> 3), facing the other way, the same size.
    layout = layout_scene(SceneConfig(num_images=36, image_size=96, spacing=6, repeats=2))
    groups = _copies(_upright(layout))
    assert max(len(faces) for faces in groups.values()) == 2
    pairs = [faces for faces in groups.values() if len(faces) == 2]
    assert len(pairs) >= 0.8 * len(groups)  # side walls at the block's corners have no copy
    for a, b in pairs:
        assert np.allclose(a.normal, -b.normal) and (a.width, a.height) == pytest.approx((b.width, b.height))
        if _front(a, layout.block):
            assert np.linalg.norm(_centre(a) - _centre(b)) > 20
    assert len({(f.texture, f.crop) for f in _upright(layout)}) == len(groups)  # a region per group, once
    ground = [f for f in layout.faces if abs(f.normal[2]) > 0.5]
    assert len({f.texture for f in ground}) == len(ground)  # the pavement never repeats


def test_three_repeats_spread_each_texture_over_three_places(shared):
    layout = layout_scene(SceneConfig(num_images=40, image_size=96, repeats=3))
    groups = _copies(_upright(layout))
    assert max(len(faces) for faces in groups.values()) == 3
    fronts = [faces for faces in groups.values() if len(faces) == 3 and _front(faces[0], layout.block)]
    assert len(fronts) >= len(groups) / 3
    for faces in fronts:
        assert len({tuple(np.round(f.normal, 6)) for f in faces}) >= 2  # on at least two sides of the block
        centres = np.array([_centre(f) for f in faces])
        assert min(np.linalg.norm(centres[i] - centres[j]) for i in range(3) for j in range(i)) > 20


def test_symmetric_block_carries_the_long_sides_facades_in_mirror_order(shared):
    layout = layout_scene(SceneConfig(num_images=40, image_size=96, symmetric=True))
    keys = {_texture_key(f) for f in _upright(layout)}
    assert max(len(faces) for faces in _copies(_upright(layout)).values()) == 2
    # The mirror y -> -y takes every facade onto one with the same texture: side 0's facade at x in [a, b]
    # faces side 2's at the same x (walked the other way round: mirror order).
    mirrored = {(tuple(np.round(_centre(f) * [1, -1, 1], 6)), tuple(np.round(f.normal * [1, -1, 1], 6))): f
                for f in _upright(layout)}
    for face in _upright(layout):
        twin = mirrored[(tuple(np.round(_centre(face), 6)), tuple(np.round(face.normal, 6)))]
        assert _texture_key(twin) == _texture_key(face)
    side0 = sorted((f for f in _upright(layout) if np.allclose(f.normal, [0, -1, 0]) and _centre(f)[1] > -20),
                   key=lambda f: _centre(f)[0])
    side2 = sorted((f for f in _upright(layout) if np.allclose(f.normal, [0, 1, 0]) and _centre(f)[1] < 20),
                   key=lambda f: -_centre(f)[0])  # in walking order
    assert [_texture_key(f) for f in side0] == [_texture_key(f) for f in side2][::-1] and len(side0) >= 3
    assert len(keys) < len(_upright(layout))


def _turned(face: Face, T: np.ndarray) -> tuple:
    M = np.eye(3)
    M[:2, :2] = T
    return tuple(np.round(M @ _centre(face), 6)), tuple(np.round(M @ face.normal, 6))


@pytest.mark.parametrize("symmetric", [False, True])
def test_ring_repeats_are_a_temple_of_like_columns(shared, symmetric):
    layout = layout_scene(SceneConfig(num_images=8, image_size=96, hfov_deg=24, layout="ring", repeats=4,
                                      symmetric=symmetric))
    objects = [f for f in layout.faces if f.grain >= 0]
    at = {_turned(f, np.eye(2)): f for f in objects}
    quarter = np.array([[0.0, -1.0], [1.0, 0.0]])
    for face in objects:  # a quarter turn takes every face onto one with the same texture
        assert _texture_key(at[_turned(face, quarter)]) == _texture_key(face)
    columns = _copies(objects)
    assert max(len(faces) for faces in columns.values()) == (8 if symmetric else 4)  # mirrored: both side walls
    plate = [f for f in layout.faces if f.grain < 0]
    assert len(plate) == 16 and len({f.texture for f in plate}) == 16  # the plate tells the views apart
    if symmetric:
        mirror = np.diag([1.0, -1.0])
        assert all(_texture_key(at[_turned(face, mirror)]) == _texture_key(face) for face in objects)


def test_symmetric_ring_mirrors_its_boxes(shared):
    layout = layout_scene(SceneConfig(num_images=8, image_size=96, hfov_deg=24, layout="ring", symmetric=True))
    objects = [f for f in layout.faces if f.grain >= 0]
    at = {_turned(f, np.eye(2)): f for f in objects}
    mirror = np.diag([-1.0, 1.0])
    assert all(_texture_key(at[_turned(face, mirror)]) == _texture_key(face) for face in objects)
    assert len(_copies(objects)) < len(objects) < 2 * len(_copies(objects)) + 6  # pairs; the boxes on the plane


def test_covisibility_of_repeated_facades_stays_geometric(tmp_path, shared):
    # Photos of the two copies of a facade (opposite sides of the block) show the same texture on different
    # faces: not co-visible, whatever the matcher may think.
    config = SceneConfig(num_images=36, image_size=96, spacing=6, repeats=2)
    generate_scene(tmp_path, config, progress=False)
    layout = layout_scene(config)
    names = sorted(read_scene(tmp_path)["cameras"])
    from sekd_sfm.bench.scale.rendering import candidate_faces

    faces = layout.faces
    culling = (np.array([f.corners().mean(0) for f in faces]), np.array([0.5 * math.hypot(f.width, f.height) for f in faces]),
               np.array([f.origin for f in faces]), np.array([f.normal for f in faces]))
    seen, drawn = [], []  # per photo: the facades filling 2 % of it; every face it shows
    for camera in layout.cameras:  # as the scene's photos are rendered: faces turned away are not drawn
        _, face_id = render(camera, faces, layout.textures, candidate_faces(camera, *culling))
        ids, counts = np.unique(face_id[face_id >= 0], return_counts=True)
        seen.append({int(i) for i, n in zip(ids, counts) if n > 0.02 * face_id.size and layout.faces[i].grain >= 0})
        drawn.append(set(ids.tolist()))
    covisible = read_covisibility(tmp_path, min_overlap=0.0)
    alike = 0
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            same_texture = {_texture_key(layout.faces[i]) for i in seen[a]} & {_texture_key(layout.faces[i]) for i in seen[b]}
            if same_texture and not drawn[a] & drawn[b]:
                alike += 1
                assert frozenset((names[a], names[b])) not in covisible
    assert alike >= 10
    assert all(drawn[names.index(a)] & drawn[names.index(b)] for a, b in map(sorted, covisible))  # a face in common


def test_cli_generates_repeated_and_symmetric_scenes(tmp_path, shared):
    result = CliRunner().invoke(sekd, ["bench", "scale", "--layout", "ring", "--hfov", "24", "--sizes", "8", "--repeats",
                                       "3", "--symmetric", "--image-size", "64", "--generate-only", "-o", str(tmp_path)])
    assert result.exit_code == 0, result.output
    config = read_scene(tmp_path / "n8/scene")["config"]
    assert config["repeats"] == 3 and config["symmetric"] is True
    result = CliRunner().invoke(sekd, ["bench", "scale", "--sizes", "8", "--repeats", "9", "--generate-only", "-o",
                                       str(tmp_path)])
    assert result.exit_code == 2 and "--repeats" in result.output
