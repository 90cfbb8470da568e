"""Model export (``sekd export``): a COLMAP model -> COLMAP text files, a coloured PLY point cloud,
or an interactive 3D page (HTML: points and camera frusta, works offline).

The folder for Gaussian Splatting and NeRF trainers (``--format nerfstudio``) is written by
``export_nerfstudio.py``.
"""
from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ..errors import SekdError
from .colmap import require_pycolmap

EXPORT_FORMATS = ("text", "ply", "html")
#: The files of a COLMAP model (binary or text); a folder holding any of them is read as a model.
MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin", "cameras.txt", "images.txt", "points3D.txt")
#: Points drawn in the HTML page at most (a random, seeded subset beyond): keeps the page light in a browser.
HTML_MAX_POINTS = 200_000


def _is_model(folder: Path) -> bool:
    return folder.is_dir() and any((folder / name).is_file() for name in MODEL_FILES)


def model_folder(path: str | Path) -> Path:
    """The COLMAP model in ``path``: ``path`` itself, or the model of an export folder for
    Gaussian Splatting / NeRF (``path/sparse/0``, or ``path/sparse`` as COLMAP's undistorter
    writes it). ``path`` unchanged when none holds a model (``read_model`` then says so)."""
    path = Path(path)
    for folder in (path, path / "sparse" / "0", path / "sparse"):
        if _is_model(folder):
            return folder
    return path


def read_model(model: str | Path):
    """A COLMAP model folder (binary or text), or an export folder holding one (``model_folder``),
    as a pycolmap Reconstruction; SekdError if it is neither."""
    given, model = Path(model), model_folder(model)
    if not _is_model(model):
        raise SekdError(f"{given}: not a COLMAP model folder (no cameras/images/points3D .bin or .txt files, "
                        "nor an export folder with sparse/0)")
    try:
        return require_pycolmap().Reconstruction(str(model))
    except (ValueError, RuntimeError) as exc:
        raise SekdError(f"{model}: cannot read the COLMAP model ({exc})") from None


def export_model(model: str | Path, output: str | Path, fmt: str = "text") -> Path:
    """Write ``model`` as COLMAP text files in the folder ``output``, or as a PLY or HTML file ``output``.

    The PLY holds the 3D points with their RGB colours (binary little-endian); the HTML page
    is described in ``export_html``. Returns ``output``.
    """
    if fmt not in EXPORT_FORMATS:
        raise SekdError(f"unknown export format {fmt!r}; choose from {', '.join(EXPORT_FORMATS)}")
    reconstruction, output = read_model(model), Path(output)
    if fmt == "text":
        output.mkdir(parents=True, exist_ok=True)
        reconstruction.write_text(str(output))
    elif fmt == "html":
        export_html(reconstruction, output, title=str(model))
    else:
        output.parent.mkdir(parents=True, exist_ok=True)
        reconstruction.export_PLY(str(output))
    return output


def world_from_cam(image) -> tuple[np.ndarray, np.ndarray]:
    """The pose of a pycolmap Image as camera-to-world (R 3x3, camera centre 3, world units).

    ``cam_from_world`` became a method (from a property) with the rigs of pycolmap 3.12.
    """
    cam_from_world = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    pose = cam_from_world.inverse()
    return pose.rotation.matrix(), np.asarray(pose.translation)


def frustum_lines(reconstruction, size: float) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Camera frusta of the registered images as polylines (world coordinates).

    Each camera gives 16 points (centre to the four image corners at depth ``size``, then the
    rectangle), followed by a NaN row so the lines of different cameras stay apart. Returns
    ``K x 3`` points, their hover names, and the ``C x 3`` camera centres.
    """
    points, names, centres = [], [], []
    for image_id in sorted(reconstruction.reg_image_ids()):
        image = reconstruction.image(image_id)
        camera = reconstruction.camera(image.camera_id)
        rotation, centre = world_from_cam(image)
        corners = np.array([[0, 0], [camera.width, 0], [camera.width, camera.height], [0, camera.height]], float)
        rays = np.c_[camera.cam_from_img(corners), np.ones(4)]  # COLMAP pixel corners -> normalised, z = 1
        # Depth scaled so the frustum's longer side is about ``size`` whatever the focal length.
        rays *= size / max(np.ptp(rays[:, 0]), np.ptp(rays[:, 1]), 1e-9)
        world = rays @ rotation.T + centre
        c0, c1, c2, c3 = world
        polyline = [centre, c0, c1, centre, c2, c3, centre, c0, c1, c2, c3, c0]
        points += polyline + [np.full(3, np.nan)]
        names += [image.name] * len(polyline) + [""]
        centres.append(centre)
    return np.array(points).reshape(-1, 3), names, np.array(centres).reshape(-1, 3)


def view_frame(reconstruction) -> np.ndarray:
    """3 x 3 rotation whose rows are the picture's right, depth and up axes, in world coordinates.

    Up is the cameras' mean "up" (COLMAP's camera y axis points down in the image), depth their
    mean viewing direction made orthogonal to it: the picture looks over the cameras' shoulders.
    """
    rotations = [world_from_cam(reconstruction.image(i))[0] for i in reconstruction.reg_image_ids()]
    if not rotations:
        return np.eye(3)
    up = -np.mean([r[:, 1] for r in rotations], axis=0)
    forward = np.mean([r[:, 2] for r in rotations], axis=0)
    up /= np.linalg.norm(up) or 1.0
    forward -= forward @ up * up
    if np.linalg.norm(forward) < 1e-9:  # cameras looking straight up or down: any horizontal depth axis
        forward = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    forward /= np.linalg.norm(forward)
    return np.stack([np.cross(forward, up), forward, up])


#: Points farther from the median point than this many times the 90th-percentile distance are
#: left out of the page: a few stray far points would otherwise shrink the scene to a dot.
FAR_POINT_FACTOR = 4.0


def model_points(reconstruction, max_points: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, int]:
    """3D points (N x 3) and RGB colours (N x 3 uint8) to draw: far strays left out, then at most
    ``max_points`` (a seeded random subset). Also returns the model's total point count."""
    xyz = np.array([p.xyz for p in reconstruction.points3D.values()], float).reshape(-1, 3)
    rgb = np.array([p.color for p in reconstruction.points3D.values()], np.uint8).reshape(-1, 3)
    total = len(xyz)
    if total >= 10:
        distance = np.linalg.norm(xyz - np.median(xyz, axis=0), axis=1)
        near = distance <= FAR_POINT_FACTOR * np.percentile(distance, 90)
        xyz, rgb = xyz[near], rgb[near]
    if len(xyz) > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(len(xyz), max_points, replace=False))
        xyz, rgb = xyz[keep], rgb[keep]
    return xyz, rgb, total


def scene_size(xyz: np.ndarray, centres: np.ndarray) -> float:
    """A robust scene extent: the 5-95 % range of points and cameras (far outliers ignored)."""
    everything = np.concatenate([xyz, centres]) if len(xyz) else centres
    if len(everything) < 2:
        return 1.0
    low, high = np.percentile(everything, [5, 95], axis=0)
    return float(np.linalg.norm(high - low)) or 1.0


def _plotly_camera(frame: np.ndarray, drawn: np.ndarray) -> dict:
    """plotly's scene camera looking over the cameras' shoulders (``view_frame``), far enough back to see
    everything ``drawn`` (N x 3).

    plotly places the eye in units of its scene box, whose sides (``aspectmode`` data) are the data
    ranges divided by their geometric mean; one world direction is the same direction there.
    """
    ranges = np.ptp(drawn, axis=0) if len(drawn) > 1 else np.ones(3)
    ranges = np.maximum(ranges, 1e-9 * max(ranges.max(), 1e-9))
    box = ranges / np.exp(np.log(ranges).mean())
    _right, depth, up = frame
    # About 25 degrees above the cameras, 1.1 box lengths back: plotly's default eye (1.25, 1.25, 1.25)
    # left the cameras of a real scene outside the view (seen in headless Chromium on fountain-P11).
    direction = up * 0.45 - depth
    eye = direction / np.linalg.norm(direction) * 1.1 * box.max()
    return {"up": _xyz(up), "eye": _xyz(eye)}


def _xyz(vector: np.ndarray) -> dict:
    return {"x": float(vector[0]), "y": float(vector[1]), "z": float(vector[2])}


def export_html(reconstruction, output: str | Path, title: str = "model", max_points: int = HTML_MAX_POINTS) -> Path:
    """Write an interactive 3D page of ``reconstruction``: coloured points and one frustum per registered image.

    Hovering a frustum shows the image name. plotly.js is embedded (about 4.5 MB), so the
    page works offline; opened in any browser, it can be rotated, zoomed and panned.
    Needs the optional ``plotly`` package (``pip install "sekd-sfm[viz]"``). Returns ``output``.
    """
    try:
        import plotly.graph_objects as go
    except ImportError:
        raise SekdError('the HTML export needs plotly: pip install "sekd-sfm[viz]" (or pip install plotly)') from None
    output = Path(output)
    if output.suffix.lower() not in (".html", ".htm"):
        raise SekdError(f"{output}: an HTML export needs a file name ending in .html")
    xyz, rgb, total = model_points(reconstruction, max_points)
    centres = np.array([world_from_cam(reconstruction.image(i))[1]
                        for i in reconstruction.reg_image_ids()]).reshape(-1, 3)
    lines, names, centres = frustum_lines(reconstruction, 0.04 * scene_size(xyz, centres))
    frame = view_frame(reconstruction)
    shown = f"{len(xyz):,} of {total:,}" if total > len(xyz) else f"{total:,}"
    figure = go.Figure([
        go.Scatter3d(x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], mode="markers", name=f"3D points ({shown})",
                     marker={"size": 1.5, "color": [f"rgb({r},{g},{b})" for r, g, b in rgb]}, hoverinfo="skip"),
        go.Scatter3d(x=lines[:, 0], y=lines[:, 1], z=lines[:, 2], mode="lines", name=f"cameras ({len(centres)})",
                     line={"color": "rgb(220,30,30)", "width": 2}, text=names, hoverinfo="text"),
    ])
    figure.update_layout(
        title=f"{html.escape(title)}: {len(centres)} registered images, {shown} points",
        scene={"aspectmode": "data", "xaxis": {"visible": False}, "yaxis": {"visible": False},
               "zaxis": {"visible": False}},
        scene_camera=_plotly_camera(frame, np.concatenate([xyz, lines[~np.isnan(lines[:, 0])]])),
        margin={"l": 0, "r": 0, "t": 40, "b": 0}, legend={"x": 0, "y": 1})
    output.parent.mkdir(parents=True, exist_ok=True)
    try:
        figure.write_html(str(output), include_plotlyjs=True, full_html=True)
    except OSError as exc:
        raise SekdError(f"{output}: cannot write the page ({exc.strerror or exc})") from None
    return output
