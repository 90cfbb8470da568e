"""Model export (``sekd export``): a COLMAP model -> COLMAP text files, a coloured PLY point cloud,
or an interactive 3D page (HTML: points and camera frusta, works offline)."""
from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ..errors import SekdError
from .colmap import require_pycolmap

EXPORT_FORMATS = ("text", "ply", "html")
#: Points drawn in the HTML page at most (a random, seeded subset beyond): keeps the page light in a browser.
HTML_MAX_POINTS = 200_000


def read_model(model: str | Path):
    """A COLMAP model folder (binary or text) as a pycolmap Reconstruction; SekdError if it is not one."""
    model = Path(model)
    names = ("cameras.bin", "images.bin", "points3D.bin", "cameras.txt", "images.txt", "points3D.txt")
    if not model.is_dir() or not any((model / n).is_file() for n in names):
        raise SekdError(f"{model}: not a COLMAP model folder (no cameras/images/points3D .bin or .txt files)")
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


def _pose(image):
    """``world_from_cam`` of a pycolmap Image as (R 3x3, centre 3).

    ``cam_from_world`` became a method (from a property) with the rigs of pycolmap 3.12.
    """
    cam_from_world = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    world_from_cam = cam_from_world.inverse()
    return world_from_cam.rotation.matrix(), np.asarray(world_from_cam.translation)


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
        rotation, centre = _pose(image)
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


#: Points farther from the median point than this many times the 90th-percentile distance are
#: left out of the page: a few stray far points would otherwise shrink the scene to a dot.
FAR_POINT_FACTOR = 4.0


def _points(reconstruction, max_points: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, int]:
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


def _scene_size(xyz: np.ndarray, centres: np.ndarray) -> float:
    """A robust scene extent: the 5-95 % range of points and cameras (far outliers ignored)."""
    everything = np.concatenate([xyz, centres]) if len(xyz) else centres
    if len(everything) < 2:
        return 1.0
    low, high = np.percentile(everything, [5, 95], axis=0)
    return float(np.linalg.norm(high - low)) or 1.0


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
    xyz, rgb, total = _points(reconstruction, max_points)
    centres = np.array([_pose(reconstruction.image(i))[1] for i in reconstruction.reg_image_ids()]).reshape(-1, 3)
    lines, names, centres = frustum_lines(reconstruction, 0.04 * _scene_size(xyz, centres))
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
        # COLMAP's y axis points down in the image: look from behind the cameras, y up on screen.
        scene_camera={"up": {"x": 0, "y": -1, "z": 0}, "eye": {"x": 0.4, "y": -1.0, "z": -1.4}},
        margin={"l": 0, "r": 0, "t": 40, "b": 0}, legend={"x": 0, "y": 1})
    output.parent.mkdir(parents=True, exist_ok=True)
    try:
        figure.write_html(str(output), include_plotlyjs=True, full_html=True)
    except OSError as exc:
        raise SekdError(f"{output}: cannot write the page ({exc.strerror or exc})") from None
    return output
