"""`sekd export --format nerfstudio|3dgs`: the undistorted folder for Gaussian Splatting and NeRF trainers.

Checked against nerfstudio's own converter (``colmap_to_json`` of nerfstudio 1.1.5, installed with
``--no-deps`` into a cache folder and run in a child process: nerfstudio pins other torch and OpenCV
versions, so it never goes into our environment), and against the camera models: every 3D point
lands where the distorted camera saw it, every exported pixel is the original pixel the cameras say.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from click.testing import CliRunner
from conftest import SHARED

from sekd_sfm.cli.main import sekd
from sekd_sfm.stages.export_nerfstudio import export_nerfstudio, nerfstudio_transforms

NERFSTUDIO = "nerfstudio==1.1.5"
#: What nerfstudio's colmap_utils imports beyond our environment (read from its source): all light.
NERFSTUDIO_LIGHT_DEPS = ("appdirs", "imageio", "rawpy", "jaxtyping", "wadler-lindig")
FOUNTAIN = SHARED / "data/sfm/fountain-P11/images"
W, H = 320, 240


# ----------------------------------------------------------------------------- a synthetic model

def look_at(centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cam_from_world`` (R, t) of a camera at ``centre`` looking at the origin, image y down."""
    z = -centre / np.linalg.norm(centre)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ centre


def texture(rng, seed_shape=(24, 32)) -> np.ndarray:
    """A smooth random colour image H x W x 3 (bilinear interpolation is exact enough on it)."""
    small = rng.uniform(0, 255, (*seed_shape, 3)).astype(np.float32)
    return np.clip(cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC), 0, 255).astype(np.uint8)


def write_synthetic(root: Path, cameras: list[str], names=("a.png", "sub/b.png", "c.png"), seed=0) -> Path:
    """A COLMAP text model ``root/model`` of three views of 120 points, with ``cameras`` (one line of
    cameras.txt each; view i uses camera min(i, len-1) + 1), and its photos in ``root/photos``."""
    rng = np.random.default_rng(seed)
    points = rng.uniform([-1, -0.8, -0.5], [1, 0.8, 0.5], (120, 3))
    models = [pycolmap.Camera(model=line.split()[0], width=W, height=H, params=[float(v) for v in line.split()[3:]])
              for line in cameras]
    model, photos = root / "model", root / "photos"
    model.mkdir(parents=True)
    image_lines, tracks = [], {i: [] for i in range(len(points))}
    for index, name in enumerate(names):
        camera_id = min(index, len(cameras) - 1) + 1
        angle = np.radians(-20 + 20 * index)
        R, t = look_at(np.array([4 * np.sin(angle), -0.5, -4 * np.cos(angle)]))
        xy = models[camera_id - 1].img_from_cam(points @ R.T + t)
        qx, qy, qz, qw = pycolmap.Rotation3d(R).quat
        image_lines.append(f"{index + 1} {qw} {qx} {qy} {qz} {t[0]} {t[1]} {t[2]} {camera_id} {name}")
        image_lines.append(" ".join(f"{x} {y} {i}" for i, (x, y) in enumerate(xy)))
        for i in range(len(points)):
            tracks[i] += [index + 1, i]
        (photos / name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(photos / name), texture(rng))
    (model / "cameras.txt").write_text("".join(f"{i + 1} {line.split()[0]} {W} {H} {' '.join(line.split()[3:])}\n"
                                               for i, line in enumerate(cameras)))
    (model / "images.txt").write_text("\n".join(image_lines) + "\n")
    (model / "points3D.txt").write_text("".join(
        f"{i} {x} {y} {z} {i % 256} 100 200 0.1 {' '.join(map(str, tracks[i]))}\n"
        for i, (x, y, z) in enumerate(points)))
    return model


RADIAL = "SIMPLE_RADIAL 0 0 250 161 118 -0.12"  # strong barrel distortion, principal point off-centre


def masks_left_third(root: Path, names) -> Path:
    """Masks hiding the left third of each named photo (zero = ignore)."""
    masks = root / "masks"
    for name in names:
        mask = np.full((H, W), 255, np.uint8)
        mask[:, : W // 3] = 0
        (masks / f"{name}.png").parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(masks / f"{name}.png"), mask)
    return masks


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """The distorted synthetic model exported with masks (one photo without a mask) at --max-size 200."""
    root = tmp_path_factory.mktemp("synthetic")
    model = write_synthetic(root, [RADIAL])
    masks = masks_left_third(root, ["a.png", "sub/b.png"])
    result = export_nerfstudio(model, root / "export", images=root / "photos", masks=masks, max_size=200)
    return root, model, result


def _pairs(original, exported):
    """(original Image, its camera, exported Image, its camera) per image id."""
    for image_id in sorted(exported.reg_image_ids()):
        a, b = original.image(image_id), exported.image(image_id)
        yield a, original.camera(a.camera_id), b, exported.camera(b.camera_id)


def round_trip_errors(original, exported) -> np.ndarray:
    """Per 3D point and image (px of the original photo): where the point projects through the exported
    pinhole camera, taken back through the two camera models, minus where the original camera projects it."""
    errors = []
    xyz = np.array([p.xyz for p in original.points3D.values()])
    for a, camera, b, pinhole in _pairs(original, exported):
        seen = a.cam_from_world() * xyz
        distorted = camera.img_from_cam(seen)
        undistorted = pinhole.img_from_cam(b.cam_from_world() * xyz)
        back = camera.img_from_cam(np.c_[pinhole.cam_from_img(undistorted), np.ones(len(undistorted))])
        errors.append(np.linalg.norm(back - distorted, axis=1))
    return np.concatenate(errors)


def test_undistortion_round_trips(synthetic):
    _, model, result = synthetic
    original, exported = pycolmap.Reconstruction(str(model)), pycolmap.Reconstruction(str(result.folder / "sparse/0"))
    errors = round_trip_errors(original, exported)
    print(f"synthetic round trip: max {errors.max():.2e} px over {len(errors)} point projections")
    assert len(errors) == 360 and errors.max() < 0.05
    assert {c.model.name for c in exported.cameras.values()} == {"PINHOLE"}
    assert exported.num_points3D() == 120 and result.points == 120


def test_exported_pixels_are_where_the_cameras_say(synthetic):
    """Each exported image equals the original resampled through the two camera models (cv2.remap)."""
    root, model, result = synthetic
    original, exported = pycolmap.Reconstruction(str(model)), pycolmap.Reconstruction(str(result.folder / "sparse/0"))
    for a, camera, b, pinhole in _pairs(original, exported):
        assert max(pinhole.width, pinhole.height) == 200  # --max-size
        picture = cv2.imread(str(result.folder / "images" / b.name))
        assert picture.shape == (pinhole.height, pinhole.width, 3)
        u, v = np.meshgrid(np.arange(pinhole.width) + 0.5, np.arange(pinhole.height) + 0.5)  # COLMAP: centre at +0.5
        rays = pinhole.cam_from_img(np.c_[u.ravel(), v.ravel()])
        source = camera.img_from_cam(np.c_[rays, np.ones(len(rays))]).astype(np.float32) - 0.5  # to OpenCV pixels
        expected = cv2.remap(cv2.imread(str(root / "photos" / a.name)), source[:, 0].reshape(u.shape),
                             source[:, 1].reshape(u.shape), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        difference = np.abs(picture.astype(float) - expected)[2:-2, 2:-2]
        print(f"{a.name}: exported - remapped original, mean {difference.mean():.3f}, "
              f"99th percentile {np.percentile(difference, 99):.1f} grey levels")
        assert difference.mean() < 1.0 and np.percentile(difference, 99) < 6, (a.name, difference.mean())


def test_masks_are_undistorted_beside_the_images(synthetic):
    _, model, result = synthetic
    original, exported = pycolmap.Reconstruction(str(model)), pycolmap.Reconstruction(str(result.folder / "sparse/0"))
    assert result.masks == 2
    for a, camera, b, pinhole in _pairs(original, exported):
        mask = cv2.imread(str(result.folder / "masks" / f"{b.name}.png"), cv2.IMREAD_UNCHANGED)
        assert mask.shape == (pinhole.height, pinhole.width) and set(np.unique(mask)) <= {0, 255}
        if a.name == "c.png":  # no mask file: used whole
            assert (mask == 255).all()
            continue
        u, v = np.meshgrid(np.arange(pinhole.width) + 0.5, np.arange(pinhole.height) + 0.5)
        rays = pinhole.cam_from_img(np.c_[u.ravel(), v.ravel()])
        x = camera.img_from_cam(np.c_[rays, np.ones(len(rays))])[:, 0].reshape(u.shape)
        hidden, kept = x < W // 3 - 2, x > W // 3 + 2  # original pixels, away from the mask's edge
        assert (mask[hidden] == 0).all() and (mask[kept] == 255).all() and hidden.any() and kept.any()
    frames = json.loads((result.folder / "transforms.json").read_text())["frames"]
    assert [f["mask_path"] for f in frames] == ["masks/a.png.png", "masks/sub/b.png.png", "masks/c.png.png"]
    assert [f["file_path"] for f in frames] == ["images/a.png", "images/sub/b.png", "images/c.png"]


def test_transforms_json_describes_the_exported_model(synthetic):
    """Independent of nerfstudio: the camera-to-world of each frame, turned back by applied_transform and
    to OpenCV axes, is the pose of sparse/0; the PLY holds the points in the same world."""
    _, _, result = synthetic
    exported = pycolmap.Reconstruction(str(result.folder / "sparse/0"))
    transforms = json.loads((result.folder / "transforms.json").read_text())
    applied = np.vstack([transforms["applied_transform"], [0, 0, 0, 1]])
    for frame in transforms["frames"]:
        image = exported.image(frame["colmap_im_id"])
        c2w = np.linalg.inv(applied) @ np.array(frame["transform_matrix"]) @ np.diag([1, -1, -1, 1])
        assert np.allclose(np.linalg.inv(c2w)[:3], image.cam_from_world().matrix(), atol=1e-9)
    camera = exported.camera(1)
    assert [transforms[k] for k in ("w", "h", "fl_x", "fl_y", "cx", "cy")] == [camera.width, camera.height,
                                                                              *camera.params]
    assert transforms["camera_model"] == "OPENCV" and transforms["ply_file_path"] == "sparse_pc.ply"
    xyz, _ = read_ply(result.folder / "sparse_pc.ply")
    world = np.array([exported.points3D[i].xyz for i in sorted(exported.points3D)])
    assert np.allclose(xyz, world @ applied[:3, :3].T, atol=1e-5)


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """x, y, z (N x 3) and red, green, blue (N x 3) of a PLY file, ASCII (nerfstudio's) or binary (ours)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii")
    count = int(header.split("element vertex ")[1].split()[0])
    if "format ascii" in header:
        rows = np.array([line.split() for line in data[end:].decode("ascii").splitlines()], float).reshape(-1, 6)
        return rows[:, :3], rows[:, 3:].astype(np.uint8)
    vertices = np.frombuffer(data[end:], [("xyz", "<f4", 3), ("rgb", "u1", 3)], count)
    return vertices["xyz"].astype(float), vertices["rgb"]


@pytest.fixture(scope="module")
def two_cameras(tmp_path_factory):
    """A model whose third photo has a camera of its own (PINHOLE), exported without --max-size."""
    root = tmp_path_factory.mktemp("two_cameras")
    model = write_synthetic(root, [RADIAL, "PINHOLE 0 0 240 250 160 120"])
    return export_nerfstudio(model, root / "export", images=root / "photos")


def test_two_cameras_put_the_intrinsics_in_every_frame(two_cameras):
    result = two_cameras
    transforms = json.loads((result.folder / "transforms.json").read_text())
    assert "fl_x" not in transforms and [f["fl_y"] for f in transforms["frames"]][1:] == [250, 250]
    assert all(f["camera_model"] == "OPENCV" and "mask_path" not in f for f in transforms["frames"])
    assert result.masks == 0 and not (result.folder / "masks").exists()
    for frame in transforms["frames"]:  # a pinhole photo is copied at full size: still its camera's size
        assert cv2.imread(str(result.folder / frame["file_path"])).shape == (frame["h"], frame["w"], 3)


def test_max_size_resizes_photos_of_pinhole_cameras_too(tmp_path):
    """A pinhole photo needs no undistortion, but --max-size still applies to it (and to its intrinsics)."""
    model = write_synthetic(tmp_path, ["PINHOLE 0 0 240 250 160 120"])
    result = export_nerfstudio(model, tmp_path / "export", images=tmp_path / "photos", max_size=160)
    assert result.sizes == [(160, 120)] * 3
    assert {cv2.imread(str(p)).shape for p in (tmp_path / "export/images").rglob("*.png")} == {(120, 160, 3)}
    camera = pycolmap.Reconstruction(str(tmp_path / "export/sparse/0")).camera(1)
    assert np.allclose(camera.params, [120, 125, 80, 60])


# ----------------------------------------------------------------------------- the command and bad input

def test_cli_finds_photos_and_masks_from_stats_json(tmp_path, monkeypatch):
    """stats.json of `sekd reconstruct` records folders relative to where it ran: found from anywhere."""
    run = tmp_path / "run"
    write_synthetic(run / "out", [RADIAL])
    shutil.move(run / "out" / "photos", run / "photos")
    masks_left_third(run, ["c.png"])
    stats = {"images_dir": "photos", "output": "out/model", "config": {"masks": "masks"}}
    (run / "out" / "stats.json").write_text(json.dumps(stats))
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(sekd, ["-q", "export", "run/out/model", "-o", "splat", "--format", "3dgs",
                                       "--max-size", "160"])
    assert result.exit_code == 0, result.output
    assert re.fullmatch(r"splat: 3 undistorted images \(160x1[01]\d px, pinhole\), masks for 1, 120 points; "
                        r"sparse/0, transforms.json, sparse_pc.ply", result.output.strip()), result.output
    assert sorted(p.name for p in (tmp_path / "splat").iterdir()) == ["images", "masks", "sparse", "sparse_pc.ply",
                                                                     "transforms.json"]
    assert (tmp_path / "splat/masks/sub/b.png.png").is_file()  # without a mask file: all kept


def test_export_refuses_a_non_empty_folder_and_overwrite_replaces(tmp_path):
    model = write_synthetic(tmp_path, [RADIAL])
    out = tmp_path / "export"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "images").mkdir()
    (out / "images" / "stale.jpg").write_text("old")
    args = ["export", str(model), "-o", str(out), "--format", "nerfstudio", "--images", str(tmp_path / "photos")]
    result = CliRunner().invoke(sekd, args)
    lines = result.output.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1
    assert "the folder is not empty" in lines[0] and "--overwrite" in lines[0]
    result = CliRunner().invoke(sekd, [*args, "--overwrite"])
    assert result.exit_code == 0, result.output
    assert (out / "notes.txt").read_text() == "mine" and not (out / "images" / "stale.jpg").exists()
    assert sorted(p.name for p in (out / "images").rglob("*.png")) == ["a.png", "b.png", "c.png"]
    assert not (out / ".sekd-export.partial").exists()


@pytest.mark.parametrize("setup,args,message", [
    ("missing", [], ("photos/c.png: photo 'c.png' of the model is missing; give the folder the model was made "
                     "from with --images")),
    ("resized", [], "photos/a.png: is 160x120 px but the model's camera of 'a.png' is 320x240"),
    ("none", ["--images", None], "no stats.json of `sekd reconstruct` beside the model"),
    ("none", ["--masks", "{t}/nowhere"], "nowhere: the mask folder does not exist"),
    ("none", ["--format", "ply", "--max-size", "100"], "apply to --format nerfstudio/3dgs only"),
])
def test_bad_input_is_one_error_line(tmp_path, setup, args, message):
    model = write_synthetic(tmp_path, [RADIAL])
    if setup == "missing":
        (tmp_path / "photos/c.png").unlink()
        (tmp_path / "photos/sub/b.png").unlink()  # the first missing by name is named: c.png < sub/b.png
    if setup == "resized":
        cv2.imwrite(str(tmp_path / "photos/a.png"), np.zeros((120, 160, 3), np.uint8))
    base = ["export", str(model), "-o", str(tmp_path / "export.ply" if "ply" in args else tmp_path / "export"),
            "--format", "nerfstudio", "--images", str(tmp_path / "photos")]
    if args[:2] == ["--images", None]:
        base, args = base[:-2], []
    result = CliRunner().invoke(sekd, [*base, *[a.format(t=tmp_path) for a in args]])
    lines = result.output.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1 and lines[0].startswith("Error: "), result.output
    assert message in lines[0], lines[0]
    assert not (tmp_path / "export").exists()  # nothing half-written


def test_a_masks_folder_without_any_mask_warns(tmp_path, caplog):
    model = write_synthetic(tmp_path, [RADIAL])
    (tmp_path / "masks").mkdir()
    result = export_nerfstudio(model, tmp_path / "export", images=tmp_path / "photos", masks=tmp_path / "masks")
    assert result.masks == 0 and not (tmp_path / "export/masks").exists()
    assert "no mask for any photo of the model (expected e.g. a.png.png)" in caplog.text


def test_a_mask_extraction_refuses_leaves_the_photo_whole(tmp_path, caplog):
    """As in extraction (files.images.read_mask): an all-zero mask is a warning and the photo is used whole."""
    model = write_synthetic(tmp_path, [RADIAL])
    masks = masks_left_third(tmp_path, ["a.png"])
    cv2.imwrite(str(masks / "c.png.png"), np.zeros((H, W), np.uint8))
    result = export_nerfstudio(model, tmp_path / "export", images=tmp_path / "photos", masks=masks)
    assert result.masks == 2 and "c.png.png: the mask is zero everywhere" in caplog.text
    assert (cv2.imread(str(tmp_path / "export/masks/c.png.png"), cv2.IMREAD_UNCHANGED) == 255).all()
    assert (cv2.imread(str(tmp_path / "export/masks/a.png.png"), cv2.IMREAD_UNCHANGED) == 0).any()


def test_transforms_of_a_model_with_a_distorted_camera_are_refused(tmp_path):
    model = write_synthetic(tmp_path, [RADIAL])
    with pytest.raises(Exception, match="SIMPLE_RADIAL is not a pinhole camera"):
        nerfstudio_transforms(pycolmap.Reconstruction(str(model)))


# ----------------------------------------------------------------------------- a real reconstruction

@pytest.fixture(scope="module")
def fountain(tmp_path_factory):
    """Four fountain-P11 photos (3072 x 2048, symlinked) reconstructed with SIFT at 640 px, exported at 480 px."""
    if not FOUNTAIN.is_dir():
        pytest.skip(f"fountain-P11 not found at {FOUNTAIN} (set SEKD_SHARED)")
    from sekd_sfm import FeatureConfig, ReconstructConfig, reconstruct
    from sekd_sfm.stages.refine import RefineConfig

    root = tmp_path_factory.mktemp("fountain")
    (root / "photos").mkdir()
    for name in ("0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg"):
        (root / "photos" / name).symlink_to(FOUNTAIN / name)
    config = ReconstructConfig(features=FeatureConfig(feature="sift", resize_max=640),
                               refine=RefineConfig(enabled=False))
    model = reconstruct(root / "photos", root / "out", config, progress=False)
    result = CliRunner().invoke(sekd, ["-q", "export", str(model), "-o", str(root / "splat"), "--format", "nerfstudio",
                                       "--max-size", "480"])
    assert result.exit_code == 0, result.output
    return model, root / "splat"


def test_real_export_images_have_their_cameras_size(fountain):
    model, splat = fountain
    exported = pycolmap.Reconstruction(str(splat / "sparse/0"))
    assert exported.num_reg_images() == pycolmap.Reconstruction(str(model)).num_reg_images() == 4
    sizes = []
    for image in exported.images.values():
        camera = exported.camera(image.camera_id)
        shape = cv2.imread(str(splat / "images" / image.name)).shape
        sizes.append((image.name, shape[1], shape[0], camera.width, camera.height))
        assert shape[:2] == (camera.height, camera.width)
    print("image sizes (name, file w h, camera w h):", sizes)
    errors = round_trip_errors(pycolmap.Reconstruction(str(model)), exported)
    print(f"fountain round trip: max {errors.max():.2e} px over {len(errors)} point projections")
    assert errors.max() < 0.05


def nerfstudio_site() -> Path:
    """A folder holding nerfstudio 1.1.5 and the light packages its COLMAP converter imports, installed
    with --no-deps (made once, in $SEKD_CACHE or ~/.cache/sekd); skips the test when pip cannot."""
    if os.environ.get("SEKD_CACHE"):
        cache = Path(os.environ["SEKD_CACHE"])
    else:
        cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "sekd"
    site = cache / "nerfstudio-1.1.5"
    if (site / "nerfstudio" / "process_data" / "colmap_utils.py").is_file():
        return site
    partial = cache / f"nerfstudio-1.1.5.partial-{os.getpid()}"
    command = [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(partial), NERFSTUDIO,
               *NERFSTUDIO_LIGHT_DEPS]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600, check=False)
    if done.returncode != 0:
        shutil.rmtree(partial, ignore_errors=True)
        pytest.skip(f"cannot install {NERFSTUDIO} (--no-deps) to compare with its converter: "
                    f"{(done.stderr.strip().splitlines() or ['pip failed'])[-1]}")
    try:
        os.replace(partial, site)
    except OSError:  # another test process installed it meanwhile
        shutil.rmtree(partial, ignore_errors=True)
    return site


CONVERT = """
import json, sys
from pathlib import Path
from nerfstudio.process_data.colmap_utils import colmap_to_json
for sparse, out in json.loads(sys.argv[1]):
    Path(out).mkdir(parents=True, exist_ok=True)
    colmap_to_json(Path(sparse), Path(out))
"""


@pytest.fixture(scope="module")
def nerfstudio_runs(fountain, synthetic, two_cameras, tmp_path_factory):
    """nerfstudio's converter run on the sparse/0 of the real and the synthetic exports: {name: (ours, theirs)}."""
    site = nerfstudio_site()
    root = tmp_path_factory.mktemp("nerfstudio")
    exports = {"fountain": fountain[1], "synthetic": synthetic[2].folder, "two_cameras": two_cameras.folder}
    jobs = [(str(folder / "sparse/0"), str(root / name)) for name, folder in exports.items()]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, "-c", CONVERT, json.dumps(jobs)], env=env, capture_output=True, text=True,
                          timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    return {name: (folder, root / name) for name, folder in exports.items()}


def _max_difference(ours: dict, theirs: dict) -> float:
    """Largest difference of the numbers of two transforms.json (same keys, same strings, asserted)."""
    assert list(ours) == list(theirs) and len(ours["frames"]) == len(theirs["frames"])
    worst = 0.0
    for key, value in ours.items():
        if key == "frames":
            for a, b in zip(value, theirs["frames"]):
                a = {k: v for k, v in a.items() if k != "mask_path"}  # nerfstudio's converter takes one mask for all
                assert list(a) == list(b) and all(a[k] == b[k] for k in ("file_path", "colmap_im_id"))
                worst = max(worst, *(np.abs(np.array(a[k], float) - np.array(b[k], float)).max()
                                     for k in a if k not in ("file_path", "camera_model")))
                assert a.get("camera_model") == b.get("camera_model")
        elif isinstance(value, str):
            assert value == theirs[key]
        else:
            worst = max(worst, float(np.abs(np.array(value, float) - np.array(theirs[key], float)).max()))
    return worst


@pytest.mark.parametrize("name", ["fountain", "synthetic", "two_cameras"])
def test_transforms_json_equals_nerfstudios(nerfstudio_runs, name):
    ours, theirs = nerfstudio_runs[name]
    difference = _max_difference(json.loads((ours / "transforms.json").read_text()),
                                 json.loads((theirs / "transforms.json").read_text()))
    xyz, rgb = read_ply(ours / "sparse_pc.ply")
    their_xyz, their_rgb = read_ply(theirs / "sparse_pc.ply")
    print(f"{name}: transforms.json max difference {difference:.2e}; "
          f"sparse_pc.ply max difference {np.abs(xyz - their_xyz).max():.2e} ({len(xyz)} points)")
    assert difference <= 1e-6
    assert np.abs(xyz - their_xyz).max() < 1e-5 and (rgb == their_rgb).all()  # nerfstudio prints 6 decimals


def test_show_model_draws_the_export_folder(fountain, tmp_path):
    _, splat = fountain
    result = CliRunner().invoke(sekd, ["show", "model", str(splat), "-o", str(tmp_path / "view.png")])
    assert result.exit_code == 0, result.output
    assert result.output.strip().startswith(f"{tmp_path / 'view.png'}: 4 registered images, ")
    picture = cv2.imread(str(tmp_path / "view.png"))
    red = (picture[:, :, 2] > 180) & (picture[:, :, 1] < 80) & (picture[:, :, 0] < 80)
    assert picture.shape == (900, 1200, 3) and red.sum() > 50  # the frusta are drawn
