"""Pictures: `sekd show matches/keypoints` PNGs (size, inlier colouring, errors) and the HTML 3D export."""
from __future__ import annotations

import base64
import json
import re

import cv2
import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from sekd_sfm.cli.main import sekd
from sekd_sfm.files import features as ff
from sekd_sfm.files import matches as mf
from sekd_sfm.viz import INLIER, OUTLIER, draw_pair, inlier_mask

SIZES = {"a/x.jpg": (300, 200), "y.png": (240, 260)}  # width, height


def _two_views(n_true=40, n_false=10, seed=0):
    """Keypoints of ``n_true`` 3D points seen by two cameras (exact), then ``n_false`` random wrong matches."""
    rng = np.random.default_rng(seed)
    points = rng.uniform([-1, -1, 4], [1, 1, 6], (n_true, 3))
    K = np.array([[200.0, 0, 120], [0, 200, 110], [0, 0, 1]])
    angle = np.radians(8)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    cam1 = points @ R.T + [-0.6, 0.05, 0]
    kp0 = (points @ K.T)[:, :2] / points[:, 2:]
    kp1 = (cam1 @ K.T)[:, :2] / cam1[:, 2:]
    wrong0 = rng.uniform([0, 0], [220, 190], (n_false, 2))
    wrong1 = rng.uniform([0, 0], [220, 250], (n_false, 2))
    return np.r_[kp0, wrong0].astype(np.float32), np.r_[kp1, wrong1].astype(np.float32)


@pytest.fixture
def files(tmp_path):
    """Images of two sizes (one in a subfolder), their features and the matches i <-> i (scores 0..1)."""
    kp0, kp1 = _two_views()
    images = tmp_path / "images"
    features, matches = tmp_path / "features.h5", tmp_path / "matches.h5"
    with h5py.File(features, "w") as f:
        f.attrs.update({"format": ff.FORMAT, "feature_type": "sift", "descriptor_dim": 4,
                        "descriptor_dtype": "float32", "config": "{}"})
        for (name, (w, h)), kp in zip(SIZES.items(), (kp0, kp1)):
            (images / name).parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(images / name), np.full((h, w, 3), 255, np.uint8))
            f[f"{name}/keypoints"] = kp
            f[f"{name}/descriptors"] = np.zeros((4, len(kp)), np.float32)
            f[f"{name}/scores"] = np.linspace(1, 0, len(kp), dtype=np.float32)
            f[f"{name}/image_size"] = np.array([w, h], np.int32)
    with h5py.File(matches, "w") as f:
        n = len(kp0)
        mf.write_pair_group(f, mf.pair_key("a/x.jpg", "y.png"),
                            {"matches0": np.arange(n), "matching_scores0": np.linspace(0, 1, n)})
    return images, features, matches


@pytest.mark.parametrize("max_side,expected", [(0, (260, 540)), (150, (150, 150 + 138))])
def test_show_matches_png_size(files, tmp_path, max_side, expected):
    images, features, matches = files
    out = tmp_path / "pair.png"
    # The pair is found in either order.
    result = CliRunner().invoke(sekd, ["show", "matches", str(features), str(matches), "y.png", "a/x.jpg",
                                       "--images", str(images), "-o", str(out), "--max-side", str(max_side)])
    assert result.exit_code == 0, result.output
    assert result.output.strip() == f"{out}: 50 matches"
    assert cv2.imread(str(out)).shape == (*expected, 3)


def test_inliers_are_the_geometrically_consistent_matches(files):
    images, features, matches = files
    picture = draw_pair(features, matches, "a/x.jpg", "y.png", images, inliers=True, max_side=None)
    assert 40 <= picture.inliers <= 42 and picture.matches == 50  # 40 true matches, 10 random ones (~all rejected)
    kp0, kp1 = _two_views()
    mask = inlier_mask(kp0, kp1)
    assert mask[:40].all() and mask.sum() == picture.inliers
    # Each end point is a dot of its match's colour (where no other dot is within 5 px).
    apart = [i for i in range(50) if (np.linalg.norm(kp0 - kp0[i], axis=1) < 5).sum() == 1]
    centre = np.round(kp0[apart]).astype(int)
    drawn = picture.image[centre[:, 1], centre[:, 0]]
    assert (drawn == np.where(mask[apart, None], INLIER, OUTLIER)).all() and (~mask[apart]).sum() >= 5


def test_show_matches_inliers_cli_and_grey_canvas(files, tmp_path):
    _, features, matches = files
    out = tmp_path / "sub" / "pair.png"
    result = CliRunner().invoke(sekd, ["show", "matches", str(features), str(matches), "a/x.jpg", "y.png",
                                       "-o", str(out), "--inliers"])
    assert result.exit_code == 0, result.output
    assert re.fullmatch(rf"{re.escape(str(out))}: 50 matches, 4[0-2] inliers \(fundamental matrix, 4 px\)",
                        result.output.strip())
    assert cv2.imread(str(out)).shape == (260, 540, 3)  # recorded sizes, no image folder needed


def test_show_keypoints(files, tmp_path):
    images, features, _ = files
    out = tmp_path / "kp.png"
    result = CliRunner().invoke(sekd, ["show", "keypoints", str(features), "a/x.jpg", "--images", str(images),
                                       "-o", str(out)])
    assert result.exit_code == 0, result.output
    picture = cv2.imread(str(out))
    assert picture.shape == (200, 300, 3) and (picture != 255).any()  # circles drawn on the white image


@pytest.mark.parametrize("args,message", [
    (["matches", "{f}", "{m}", "a/x.jpg", "nope.jpg", "-o", "{t}/p.png"], "no matches for the pair 'a/x.jpg' - 'n"),
    (["matches", "{m}", "{m}", "a/x.jpg", "y.png", "-o", "{t}/p.png"], "not a feature file"),
    (["matches", "{f}", "{t}/none.h5", "a/x.jpg", "y.png", "-o", "{t}/p.png"], "not a readable match file"),
    (["matches", "{f}", "{m}", "a/x.jpg", "y.png", "-o", "{t}/p.jpg"], "ending in .png"),
    (["keypoints", "{f}", "zz.jpg", "-o", "{t}/k.png"], "has no features for image 'zz.jpg'"),
    (["keypoints", "{f}", "a/x.jpg", "-o", "{t}/k.png", "--images", "{t}"], "not a decodable image"),
    (["keypoints", "{f}", "y.png", "-o", "{t}/k.png", "--images", "{t}/small"], "is 10x10 px but the features"),
])
def test_show_errors_are_one_line(files, tmp_path, args, message):
    _images, features, matches = files
    (tmp_path / "a").mkdir()
    (tmp_path / "a/x.jpg").write_text("not an image")
    (tmp_path / "small").mkdir()
    cv2.imwrite(str(tmp_path / "small/y.png"), np.zeros((10, 10), np.uint8))
    args = [a.format(f=features, m=matches, t=tmp_path) for a in args]
    result = CliRunner().invoke(sekd, ["show", *args])
    lines = result.output.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1 and lines[0].startswith("Error: "), result.output
    assert message in lines[0], lines[0]


# ----------------------------------------------------------------------------- HTML 3D export

TINY_MODEL = {  # COLMAP text model: three registered images (one name nested), two 3D points
    "cameras.txt": "1 SIMPLE_PINHOLE 640 480 500 320 240\n",
    "images.txt": "1 1 0 0 0 0 0 0 1 a/x.jpg\n100 100 0 200 200 1\n"
                  "2 0.9961947 0 0.0871557 0 -0.5 0 0.1 1 b/y.jpg\n210 200 1 110 100 0\n"
                  "3 1 0 0 0 1 0 0 1 c.jpg\n\n",
    "points3D.txt": "0 -0.4 -0.3 2 255 0 0 0.5 1 0 2 1\n1 0.3 0.2 3 0 255 0 0.5 1 1 2 0\n",
}


def _values(trace: dict, key: str) -> np.ndarray:
    """A numeric trace attribute: plain JSON list, or plotly's base64 typed array (``bdata``, plotly >= 6)."""
    value = trace[key]
    if isinstance(value, dict):
        return np.frombuffer(base64.b64decode(value["bdata"]), dtype=value["dtype"])
    return np.array(value, float)


def _plotly_data(page: str) -> list[dict]:
    """The traces passed to Plotly.newPlot in a page written by plotly."""
    start = page.index("Plotly.newPlot(")
    rest = page[start + len("Plotly.newPlot("):]
    rest = rest[rest.index(",") + 1:].lstrip()  # skip the element id
    return json.JSONDecoder().raw_decode(rest)[0]


def test_html_export_contains_every_registered_image_and_point(tmp_path):
    pytest.importorskip("plotly")
    model = tmp_path / "model"
    model.mkdir()
    for name, text in TINY_MODEL.items():
        (model / name).write_text(text)
    out = tmp_path / "model.html"
    result = CliRunner().invoke(sekd, ["export", str(model), "-o", str(out), "--format", "html"])
    assert result.exit_code == 0, result.output
    page = out.read_text()
    assert "plotly.js v" in page and "cdn.plot.ly" not in page.split("<script", 2)[1][:200]  # embedded, offline
    points, cameras = _plotly_data(page)
    assert sorted({n for n in cameras["text"] if n}) == ["a/x.jpg", "b/y.jpg", "c.jpg"]
    x, y, z = (_values(cameras, k) for k in "xyz")
    assert len(x) == len(cameras["text"]) == 3 * 13  # 12 polyline vertices + one gap (NaN) per camera
    assert np.isnan(x[12::13]).all() and not np.isnan(np.delete(x, np.s_[12::13])).any()
    assert (x[0], y[0], z[0]) == (0, 0, 0)  # camera 1 sits at the origin: its frustum starts there
    xyz = np.stack([_values(points, k) for k in "xyz"], 1)
    assert sorted(map(tuple, xyz.tolist())) == [(-0.4, -0.3, 2.0), (0.3, 0.2, 3.0)]
    assert sorted(points["marker"]["color"]) == ["rgb(0,255,0)", "rgb(255,0,0)"]


def test_html_export_needs_html_name(tmp_path):
    model = tmp_path / "model"
    model.mkdir()
    for name, text in TINY_MODEL.items():
        (model / name).write_text(text)
    result = CliRunner().invoke(sekd, ["export", str(model), "-o", str(tmp_path / "m.ply"), "--format", "html"])
    assert result.exit_code == 1 and "ending in .html" in result.output


def test_html_export_of_an_empty_model(tmp_path):
    pytest.importorskip("plotly")
    model = tmp_path / "model"
    model.mkdir()
    (model / "cameras.txt").write_text(TINY_MODEL["cameras.txt"])
    (model / "images.txt").write_text("")
    (model / "points3D.txt").write_text("")
    out = tmp_path / "empty.html"
    assert CliRunner().invoke(sekd, ["export", str(model), "-o", str(out), "--format", "html"]).exit_code == 0
    points, cameras = _plotly_data(out.read_text())
    assert len(_values(points, "x")) == len(_values(cameras, "x")) == 0
    assert "0 registered images, 0 points" in out.read_text()


# ----------------------------------------------------------------------------- sekd show model

def _export_folder(tmp_path):
    """TINY_MODEL laid out as `sekd export --format nerfstudio` writes it: DIR/sparse/0."""
    model = tmp_path / "splat" / "sparse" / "0"
    model.mkdir(parents=True)
    for name, text in TINY_MODEL.items():
        (model / name).write_text(text)
    return tmp_path / "splat"


def test_show_model_html_of_an_export_folder(tmp_path):
    pytest.importorskip("plotly")
    out = tmp_path / "view.html"
    result = CliRunner().invoke(sekd, ["show", "model", str(_export_folder(tmp_path)), "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert result.output.strip() == f"{out}: 3 registered images, 2 points"
    points, cameras = _plotly_data(out.read_text())
    assert sorted({n for n in cameras["text"] if n}) == ["a/x.jpg", "b/y.jpg", "c.jpg"]
    assert len(_values(points, "x")) == 2 and "0: 3 registered images, 2 points" in out.read_text()


def test_show_model_png_looks_over_the_cameras(tmp_path):
    out = tmp_path / "view.png"
    result = CliRunner().invoke(sekd, ["show", "model", str(_export_folder(tmp_path) / "sparse/0"), "-o", str(out)])
    assert result.exit_code == 0, result.output
    picture = cv2.imread(str(out))
    red = (picture[:, :, 2] > 180) & (picture[:, :, 1] < 80) & (picture[:, :, 0] < 80)
    assert picture.shape == (900, 1200, 3) and red.sum() > 50  # frusta drawn in red


def test_view_frame_is_upright_behind_the_cameras(tmp_path):
    """Rows right, depth, up: up is minus the cameras' mean image-y axis, depth their mean viewing direction."""
    import pycolmap

    from sekd_sfm.stages.export import view_frame

    frame = view_frame(pycolmap.Reconstruction(str(_export_folder(tmp_path) / "sparse/0")))
    assert np.allclose(frame @ frame.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(frame), 1)
    assert frame[2] @ [0, -1, 0] > 0.99 and frame[1] @ [0, 0, 1] > 0.99  # near-identity poses: up = -y, depth = z


@pytest.mark.parametrize("args,message", [
    (["{t}/nowhere", "-o", "{t}/v.html"], "not a COLMAP model folder"),
    (["{t}/splat", "-o", "{t}/v.jpg"], "ending in .html (interactive page) or .png"),
])
def test_show_model_errors_are_one_line(tmp_path, args, message):
    _export_folder(tmp_path)
    result = CliRunner().invoke(sekd, ["show", "model", *[a.format(t=tmp_path) for a in args]])
    lines = result.output.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1 and lines[0].startswith("Error: "), result.output
    assert message in lines[0], lines[0]
