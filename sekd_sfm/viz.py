"""Pictures of the files (``sekd show``): keypoints and matches drawn on the images, a model in 3D
(PNG here; the interactive HTML page is ``sfm.export.export_html``).

Keypoints are in original-image pixels (OpenCV convention: integer = pixel centre), so they
are drawn on the images as stored; when no image folder is given, a grey canvas of the
recorded image size stands in. Large images are reduced to ``max_side`` pixels for drawing.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import h5py
import numpy as np

from .errors import SekdError
from .files import features as ff
from .files import matches as mf
from .files.images import ImageReadError, read_image

logger = logging.getLogger("sekd")
#: Long side of each image in a picture (pixels); larger images are reduced for drawing.
DRAW_MAX_SIDE = 1600
#: Match colours (BGR): RANSAC inliers and outliers.
INLIER, OUTLIER = (60, 200, 60), (40, 40, 230)


@dataclass
class MatchPicture:
    """What ``draw_pair`` drew: ``image`` H x W x 3 uint8 (BGR), match and inlier counts (None: not checked)."""

    image: np.ndarray
    matches: int
    inliers: int | None


def check_inputs(features: Path, matches: Path | None = None) -> None:
    """SekdError naming the file if ``features`` is not a feature file (sekd's or hloc's) or ``matches`` not HDF5."""
    ff.read_attrs(features)
    if matches is not None and not (matches.is_file() and h5py.is_hdf5(matches)):
        raise SekdError(f"{matches}: not a readable match file (missing or not HDF5); "
                        "pass the file written by `sekd match`")


def load_canvas(name: str, features: Path, images: Path | None) -> np.ndarray:
    """The image ``name`` as H x W x 3 uint8 BGR: from ``images`` if given, else grey at the recorded size.

    SekdError if the image's size is not the one the features were extracted from (a wrong folder).
    """
    width, height = (int(v) for v in ff.read_features(features, name).get("image_size", (0, 0)))
    if images is None:
        if not width or not height:
            raise SekdError(f"{features}: image '{name}' has no recorded image_size; "
                            "give the image folder with --images")
        return np.full((height, width, 3), 200, np.uint8)
    try:
        rgb = read_image(images / name, grayscale=False)
    except ImageReadError as exc:
        raise SekdError(f"{exc}; give the folder the features were extracted from with --images") from None
    if width and (rgb.shape[1], rgb.shape[0]) != (width, height):
        raise SekdError(f"{images / name}: is {rgb.shape[1]}x{rgb.shape[0]} px but the features of '{name}' were "
                        f"extracted from a {width}x{height} image; give the right folder with --images")
    return np.ascontiguousarray(rgb[:, :, ::-1])


def _fit(image: np.ndarray, max_side: int | None) -> tuple[np.ndarray, float]:
    """``image`` reduced so its long side is at most ``max_side``, and the scale applied (<= 1)."""
    side = max(image.shape[:2])
    if not max_side or side <= max_side:
        return image, 1.0
    scale = max_side / side
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), scale


def _to_canvas(points: np.ndarray, scale: float, offset: float = 0.0) -> np.ndarray:
    """Original-pixel points (N x 2, pixel centre = integer) -> drawing coordinates (cv2 fixed point, 4 bits)."""
    xy = (points + 0.5) * scale - 0.5
    xy[:, 0] += offset
    return np.round(xy * 16).astype(np.int32)


def score_colors(scores: np.ndarray) -> np.ndarray:
    """BGR colour per score in [0, 1] (N x 3 uint8): OpenCV's turbo colour map, blue = low, red = high."""
    levels = np.clip(np.nan_to_num(scores) * 255, 0, 255).astype(np.uint8).reshape(-1, 1)
    return cv2.applyColorMap(levels, cv2.COLORMAP_TURBO).reshape(-1, 3)


def draw_keypoints(image: np.ndarray, keypoints: np.ndarray, scores: np.ndarray | None = None,
                   max_side: int | None = DRAW_MAX_SIDE) -> np.ndarray:
    """``image`` (H x W x 3 BGR) reduced to ``max_side`` with ``keypoints`` (N x 2, original pixels) as circles.

    Colour by ``scores`` rank (turbo map, red = strongest) when given, else green.
    """
    canvas, scale = _fit(image, max_side)
    canvas = canvas.copy()
    if scores is not None and len(scores):
        colors = score_colors(np.argsort(np.argsort(scores)) / max(1, len(scores) - 1))
    else:
        colors = np.tile(np.array(INLIER, np.uint8), (len(keypoints), 1))
    radius = max(2, round(max(canvas.shape[:2]) / 400))
    for (x, y), color in zip(_to_canvas(np.asarray(keypoints, np.float64), scale), colors):
        cv2.circle(canvas, (int(x), int(y)), radius * 16, tuple(int(c) for c in color), 1, cv2.LINE_AA, 4)
    return canvas


def inlier_mask(points0: np.ndarray, points1: np.ndarray, max_error: float = 4.0, seed: int = 0) -> np.ndarray | None:
    """Matches consistent with one fundamental matrix (OpenCV USAC MAGSAC++, ``max_error`` px); None below 8 matches."""
    if len(points0) < 8:
        return None
    cv2.setRNGSeed(seed)
    _, mask = cv2.findFundamentalMat(points0.astype(np.float64), points1.astype(np.float64), cv2.USAC_MAGSAC,
                                     max_error, 0.999, 10000)
    return np.zeros(len(points0), bool) if mask is None else mask.ravel().astype(bool)


def draw_matches(image0: np.ndarray, image1: np.ndarray, points0: np.ndarray, points1: np.ndarray,
                 colors: np.ndarray, max_side: int | None = DRAW_MAX_SIDE) -> np.ndarray:
    """The two images side by side (each reduced to ``max_side``, tops aligned, black below the shorter)
    with a line per match from ``points0`` (M x 2) to ``points1`` (M x 2), original pixels, ``colors`` M x 3 BGR."""
    left, s0 = _fit(image0, max_side)
    right, s1 = _fit(image1, max_side)
    canvas = np.zeros((max(left.shape[0], right.shape[0]), left.shape[1] + right.shape[1], 3), np.uint8)
    canvas[:left.shape[0], :left.shape[1]] = left
    canvas[:right.shape[0], left.shape[1]:] = right
    p0 = _to_canvas(np.asarray(points0, np.float64), s0)
    p1 = _to_canvas(np.asarray(points1, np.float64), s1, offset=left.shape[1])
    # Lines half transparent (hundreds of them would hide the images), end points opaque.
    lines = canvas.copy()
    for a, b, color in zip(p0, p1, colors):
        cv2.line(lines, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), tuple(int(c) for c in color), 1, cv2.LINE_AA, 4)
    canvas = cv2.addWeighted(lines, 0.5, canvas, 0.5, 0)
    radius = 16 * max(2, round(canvas.shape[0] / 300))
    for a, b, color in zip(p0, p1, colors):
        for x, y in (a, b):
            cv2.circle(canvas, (int(x), int(y)), radius, tuple(int(c) for c in color), -1, cv2.LINE_AA, 4)
    return canvas


def draw_pair(features: str | Path, matches: str | Path, name0: str, name1: str, images: str | Path | None = None,
              inliers: bool = False, max_error: float = 4.0, max_side: int | None = DRAW_MAX_SIDE) -> MatchPicture:
    """The matches of ``name0`` - ``name1`` drawn side by side, coloured by score (turbo map, red = distinctive)
    or, with ``inliers``, green for RANSAC inliers of a fundamental matrix and red for the others."""
    features, matches = Path(features), Path(matches)
    images = Path(images) if images is not None else None
    check_inputs(features, matches)
    idx, scores = mf.read_matches(matches, name0, name1)
    kp0 = ff.read_features(features, name0)["keypoints"]
    kp1 = ff.read_features(features, name1)["keypoints"]
    if len(idx) and (idx[:, 0].max() >= len(kp0) or idx[:, 1].max() >= len(kp1)):
        raise SekdError(f"{matches}: the matches of '{name0}' - '{name1}' index keypoints that {features} does not "
                        "have; give the feature file the matches were computed from")
    points0, points1 = kp0[idx[:, 0]], kp1[idx[:, 1]]
    mask = inlier_mask(points0, points1, max_error) if inliers else None
    if mask is not None:
        colors = np.where(mask[:, None], np.array(INLIER, np.uint8), np.array(OUTLIER, np.uint8))
    else:
        colors = score_colors(scores)
    canvas = draw_matches(load_canvas(name0, features, images), load_canvas(name1, features, images),
                          points0, points1, colors, max_side)
    return MatchPicture(canvas, len(idx), int(mask.sum()) if mask is not None else None)


def write_png(image: np.ndarray, output: str | Path) -> Path:
    """Write ``image`` (BGR) as PNG; SekdError naming the file when that fails."""
    output = Path(output)
    if output.suffix.lower() != ".png":
        raise SekdError(f"{output}: the picture is written as PNG; give a file name ending in .png")
    output.parent.mkdir(parents=True, exist_ok=True)
    ok, data = cv2.imencode(".png", image)
    try:
        if not ok:
            raise OSError("PNG encoding failed")
        output.write_bytes(data.tobytes())
    except OSError as exc:
        raise SekdError(f"{output}: cannot write the picture ({exc})") from None
    return output


# ----------------------------------------------------------------------------- a model in 3D, as a PNG

#: Points drawn in a model picture at most (a seeded subset beyond): more only darken the picture.
MODEL_PNG_MAX_POINTS = 30_000


def draw_model(reconstruction, title: str, max_points: int = MODEL_PNG_MAX_POINTS,
               size: tuple[int, int] = (1200, 900)) -> np.ndarray:
    """A picture (H x W x 3 uint8 BGR, ``size`` = width, height px) of the model's coloured 3D points and
    one red frustum per registered image, seen from behind and above the cameras (``view_frame``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from .stages.export import (
        frustum_lines,
        model_points,
        scene_size,
        view_frame,
        world_from_cam,
    )

    xyz, rgb, total = model_points(reconstruction, max_points)
    centres = np.array([world_from_cam(reconstruction.image(i))[1]
                        for i in reconstruction.reg_image_ids()]).reshape(-1, 3)
    extent = scene_size(xyz, centres)
    lines, _, centres = frustum_lines(reconstruction, 0.04 * extent)
    frame = view_frame(reconstruction)
    xyz, lines, centres = xyz @ frame.T, lines @ frame.T, centres @ frame.T
    figure = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    axes = figure.add_axes((0.0, 0.0, 1.0, 0.95), projection="3d")
    dot = float(np.clip(6000 / max(len(xyz), 1), 0.5, 4.0))  # few points: larger dots, still visible
    axes.scatter(*xyz.T, c=rgb / 255.0, s=dot, depthshade=False, linewidths=0)
    axes.plot(*lines.T, color=(0.86, 0.12, 0.12), linewidth=0.8)
    shown = f"{len(xyz):,} of {total:,}" if total > len(xyz) else f"{total:,}"
    axes.set_title(f"{title}: {len(centres)} registered images, {shown} points", fontsize=10)
    _equal_box(axes, np.concatenate([xyz, centres]) if len(xyz) else centres)
    axes.view_init(elev=20, azim=-90)  # the eye on the -depth side: behind the cameras, a little above
    axes.set_axis_off()
    canvas = FigureCanvasAgg(figure)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[:, :, 2::-1])


def _equal_box(axes, points: np.ndarray) -> None:
    """Equal scale on the three axes around the 2-98 % range of ``points`` (N x 3): strays do not shrink the scene."""
    if len(points) < 2:
        return
    low, high = np.percentile(points, [2, 98], axis=0)
    half = max(float((high - low).max()) / 2 * 1.1, 1e-9)
    middle = (low + high) / 2
    for setter, centre in zip((axes.set_xlim, axes.set_ylim, axes.set_zlim), middle):
        setter(centre - half, centre + half)
    axes.set_box_aspect((1, 1, 1), zoom=1.5)  # matplotlib leaves a wide margin around the box
