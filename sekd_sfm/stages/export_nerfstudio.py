"""``sekd export --format nerfstudio`` (alias ``3dgs``): one folder that Gaussian Splatting and NeRF trainers load.

::

    DIR/images/NAME             the registered photos, undistorted (pycolmap's undistorter)
    DIR/masks/NAME.png          their masks undistorted the same way (only when the reconstruction had masks)
    DIR/sparse/0/               the undistorted COLMAP model: PINHOLE cameras, poses, 3D points
    DIR/transforms.json         nerfstudio's camera file, as its COLMAP converter writes it for sparse/0
    DIR/sparse_pc.ply           the 3D points in transforms.json's world (nerfstudio's splat initialisation)

``images/`` + ``sparse/0`` is the layout of the 3DGS reference code and gsplat; ``transforms.json``
+ ``sparse_pc.ply`` is what nerfstudio's dataparser reads. The two describe the same cameras:
``transforms.json`` is computed from ``sparse/0`` with the conventions of nerfstudio's
``colmap_to_json`` (1.1.5), re-implemented here (nerfstudio pins its own torch and OpenCV).
"""
from __future__ import annotations

import json
import logging
import os
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from ..errors import SekdError
from ..files.images import image_size, mask_path, read_mask
from .colmap import colmap_log, require_pycolmap
from .export import model_folder, read_model, world_from_cam

logger = logging.getLogger("sekd")

PLY_NAME = "sparse_pc.ply"
#: What an export writes in DIR; ``--overwrite`` replaces these and leaves anything else alone.
EXPORT_ENTRIES = ("images", "masks", "sparse", "transforms.json", PLY_NAME)
#: The export is built here inside DIR, then moved into place: a failed run leaves no half folder.
STAGING = ".sekd-export.partial"
#: nerfstudio's world from COLMAP's (3 x 4): (x, y, z) -> (x, z, -y). COLMAP's y axis points down
#: in the first photos, so nerfstudio's viewer, which takes z as up, shows the scene upright.
APPLIED_TRANSFORM = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]])
#: COLMAP/OpenCV camera axes (x right, y down, z forward) -> nerfstudio/OpenGL (x right, y up, z backward).
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class SplatExport:
    """What ``export_nerfstudio`` wrote: the folder, counts, and the exported image sizes (width, height)."""

    folder: Path
    images: int
    points: int
    sizes: list[tuple[int, int]]
    masks: int  # photos with a mask file (0: the export has no masks/)


# ----------------------------------------------------------------------------- the model and its photos

def read_exportable(model: str | Path):
    """``(the model's folder, its Reconstruction)`` for ``model`` (a model folder or an export folder holding one);
    SekdError when it is no model or registers no image."""
    model = model_folder(model)
    reconstruction = read_model(model)
    if reconstruction.num_reg_images() == 0:
        raise SekdError(f"{model}: the model has no registered image to export")
    return model, reconstruction


def check_photos(reconstruction, images: Path) -> None:
    """SekdError naming the first registered photo (by name) missing below ``images``, or one whose
    size differs from its camera's (a folder of other photos, or of resized copies)."""
    names = sorted(reconstruction.image(i).name for i in reconstruction.reg_image_ids())
    missing = next((n for n in names if not (images / n).is_file()), None)
    if missing is not None:
        raise SekdError(f"{images / missing}: photo '{missing}' of the model is missing; "
                        "give the folder the model was made from with --images")
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.image(image_id)
        camera = reconstruction.camera(image.camera_id)
        size = image_size(images / image.name)
        if size is not None and tuple(size) != (camera.width, camera.height):
            raise SekdError(f"{images / image.name}: is {size[0]}x{size[1]} px but the model's camera of "
                            f"'{image.name}' is {camera.width}x{camera.height}; give the folder the model was "
                            "made from with --images")


# ----------------------------------------------------------------------------- undistortion

def undistort_options(max_size: int | None):
    """pycolmap's undistortion settings: its defaults (no blank border), images and intrinsics reduced
    to at most ``max_size`` px on the long side when given."""
    return require_pycolmap().UndistortCameraOptions(max_image_size=max_size or -1)


def undistort(model: Path, images: Path, staging: Path, options) -> None:
    """Undistort the registered photos into ``staging/images`` and the model into ``staging/sparse/0``
    (pycolmap's ``undistort_images``, COLMAP output; its MVS files are dropped)."""
    pycolmap = require_pycolmap()
    work = staging / "undistorted"
    try:
        with colmap_log(staging / "colmap.log"):  # COLMAP's progress lines would flood the console
            pycolmap.undistort_images(str(work), str(model), str(images), undistort_options=options)
    except (RuntimeError, ValueError) as exc:
        raise SekdError(f"{model}: pycolmap's undistortion failed ({exc})") from None
    (staging / "sparse").mkdir()
    os.replace(work / "images", staging / "images")
    os.replace(work / "sparse", staging / "sparse" / "0")
    shutil.rmtree(work)


def undistort_mask(keep: np.ndarray, camera, undistorted_camera, options) -> np.ndarray:
    """``keep`` (H x W bool at the photo's size) warped like its photo: H' x W' uint8 of ``undistorted_camera``,
    255 = keep, 0 = ignore.

    The warp interpolates; as in extraction (``files.images.scale_mask``), a pixel is kept only
    when everything it was interpolated from was kept: training never sees a masked pixel's colour.
    """
    pycolmap = require_pycolmap()
    mask = np.where(keep, 255, 0).astype(np.uint8)
    bitmap, warped_camera = pycolmap.undistort_image(options, pycolmap.Bitmap.from_array(mask), camera)
    if (warped_camera.width, warped_camera.height) != (undistorted_camera.width, undistorted_camera.height) or \
            not np.allclose(warped_camera.params, undistorted_camera.params, rtol=0, atol=1e-9):
        raise SekdError(f"pycolmap undistorted a mask to {warped_camera} but its photo to {undistorted_camera}")
    warped = bitmap.to_array().reshape(warped_camera.height, warped_camera.width)
    return np.where(warped == 255, 255, 0).astype(np.uint8)


def write_png(image: np.ndarray, path: Path) -> None:
    """``image`` as PNG at ``path`` (folders made; encoded in memory so any file name works)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise SekdError(f"{path}: PNG encoding failed")
    path.write_bytes(data.tobytes())


def undistort_masks(reconstruction, undistorted, masks: Path, output: Path, options) -> int:
    """Write ``output/NAME.png`` for every registered photo: its mask from ``masks`` undistorted, or all
    kept when it is used whole (no mask file, or one extraction refuses: a warning says why), since
    nerfstudio wants a mask for every frame or for none. Masks are read as extraction reads them
    (``files.images.read_mask``). Returns the number of photos with a mask file; 0 (nothing written,
    one warning) when none has one."""
    names = {i: reconstruction.image(i).name for i in reconstruction.reg_image_ids()}
    if not any(mask_path(masks, n).is_file() for n in names.values()):
        logger.warning("warning: %s: no mask for any photo of the model (expected e.g. %s); exporting without masks",
                       masks, mask_path(masks, min(names.values())).name)
        return 0
    with_file = 0
    for image_id, name in names.items():
        camera = reconstruction.camera(reconstruction.image(image_id).camera_id)
        target = undistorted.camera(undistorted.image(image_id).camera_id)
        mask = read_mask(mask_path(masks, name), (camera.height, camera.width))
        with_file += bool(mask.sha256)
        if mask.refused:
            logger.warning("warning: %s", mask.refused)
        if mask.keep is None:
            warped = np.full((target.height, target.width), 255, np.uint8)
        else:
            warped = undistort_mask(mask.keep, camera, target, options)
        write_png(warped, mask_path(output, name))
    return with_file


# ----------------------------------------------------------------------------- nerfstudio's files

def nerfstudio_intrinsics(camera) -> dict:
    """A pinhole camera as nerfstudio's keys: size (px), focal lengths and principal point (px, COLMAP
    convention: pixel (0, 0) spans [0, 1]), zero OpenCV distortion."""
    params = [float(p) for p in camera.params]
    model = getattr(camera.model, "name", str(camera.model))
    if model == "SIMPLE_PINHOLE":
        fx, cx, cy = params
        fy = fx
    elif model == "PINHOLE":
        fx, fy, cx, cy = params
    else:  # export_nerfstudio undistorts first: only pinhole cameras reach here
        raise SekdError(f"camera {camera.camera_id}: {model} is not a pinhole camera; undistort the model first")
    return {"w": int(camera.width), "h": int(camera.height), "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "camera_model": "OPENCV"}


def nerfstudio_camera_to_world(image) -> np.ndarray:
    """4 x 4 camera-to-world of a pycolmap Image in nerfstudio's convention: OpenGL camera axes,
    world turned by APPLIED_TRANSFORM."""
    rotation, centre = world_from_cam(image)
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rotation, centre
    world = np.vstack([APPLIED_TRANSFORM, [0.0, 0.0, 0.0, 1.0]])
    return world @ c2w @ OPENCV_TO_OPENGL


def nerfstudio_transforms(reconstruction, masks: bool = False) -> dict:
    """The content of nerfstudio's ``transforms.json`` for a pinhole ``reconstruction``.

    As nerfstudio's converter: intrinsics at the top when the model's only camera has id 1,
    else in every frame; frames in image-id order with ``file_path`` ``images/NAME``, the
    4 x 4 ``transform_matrix`` and ``colmap_im_id``; ``mask_path`` ``masks/NAME.png`` when
    ``masks``; then ``applied_transform`` (3 x 4) and ``ply_file_path``.
    """
    single = set(reconstruction.cameras) == {1}  # nerfstudio's test: another id means one camera per frame
    out = nerfstudio_intrinsics(reconstruction.camera(1)) if single else {}
    frames = []
    for image_id in sorted(reconstruction.reg_image_ids()):
        image = reconstruction.image(image_id)
        frame = {"file_path": f"images/{image.name}",
                 "transform_matrix": nerfstudio_camera_to_world(image).tolist(),
                 "colmap_im_id": int(image_id)}
        if masks:
            frame["mask_path"] = f"masks/{image.name}.png"
        if not single:
            frame.update(nerfstudio_intrinsics(reconstruction.camera(image.camera_id)))
        frames.append(frame)
    return {**out, "frames": frames, "applied_transform": APPLIED_TRANSFORM.tolist(), "ply_file_path": PLY_NAME}


def write_points_ply(reconstruction, path: Path, transform: np.ndarray = APPLIED_TRANSFORM) -> int:
    """The 3D points (by id) mapped by ``transform`` (3 x 4) with their colours, as a binary PLY at ``path``;
    returns their count."""
    points = reconstruction.points3D
    ids = sorted(points)
    xyz = np.array([points[i].xyz for i in ids], float).reshape(-1, 3) @ transform[:, :3].T + transform[:, 3]
    vertices = np.empty(len(ids), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                   ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    vertices["x"], vertices["y"], vertices["z"] = xyz.T
    rgb = np.array([points[i].color for i in ids], np.uint8).reshape(-1, 3)
    vertices["red"], vertices["green"], vertices["blue"] = rgb.T
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(ids)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    path.write_bytes(header.encode("ascii") + vertices.tobytes())
    return len(ids)


# ----------------------------------------------------------------------------- the folder

def prepare_output(output: Path, overwrite: bool) -> bool:
    """Check that ``output`` may be written (new, empty, or ``overwrite``); True when it is created here."""
    if output.exists() and not output.is_dir():
        raise SekdError(f"{output}: is a file; give a folder for the export")
    if output.is_dir() and any(output.iterdir()) and not overwrite:
        raise SekdError(f"{output}: the folder is not empty; give a new or empty folder, or --overwrite to "
                        f"replace the export in it ({', '.join(EXPORT_ENTRIES)})")
    created = not output.exists()
    output.mkdir(parents=True, exist_ok=True)
    return created


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def publish(staging: Path, output: Path) -> None:
    """Move the finished export from ``staging`` into ``output``, replacing an earlier export there."""
    for entry in EXPORT_ENTRIES:
        _remove(output / entry)
        if (staging / entry).exists():
            os.replace(staging / entry, output / entry)
    shutil.rmtree(staging)


def export_nerfstudio(model: str | Path, output: str | Path, images: str | Path, masks: str | Path | None = None,
                      max_size: int | None = None, overwrite: bool = False) -> SplatExport:
    """Write the folder for Gaussian Splatting and NeRF training (module docstring) from ``model``.

    ``images``: the photos' folder (photo NAME is ``IMAGES/NAME``); ``masks``: their masks, ``MASKS/NAME.png``
    (None: no masks). ``sekd export`` finds both, when not given, in the record of the reconstruction that wrote
    the model (``pipelines.record.Record.of_model``). ``max_size``: reduce the exported images (and intrinsics) to
    at most this many px on the long side.
    Refuses a non-empty ``output`` unless ``overwrite``; SekdError naming the first missing photo.
    """
    model, reconstruction = read_exportable(model)
    image_dir, mask_dir = Path(images), Path(masks) if masks else None
    if mask_dir is not None and not mask_dir.is_dir():
        raise SekdError(f"{mask_dir}: the mask folder does not exist; give the right one with --masks")
    check_photos(reconstruction, image_dir)
    output = Path(output)
    created = prepare_output(output, overwrite)
    staging = output / STAGING
    _remove(staging)  # left by a killed run
    staging.mkdir()
    try:
        result = _build(reconstruction, model, image_dir, mask_dir, staging, undistort_options(max_size))
        publish(staging, output)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if created and output.is_dir() and not any(output.iterdir()):
            output.rmdir()
        raise
    return replace(result, folder=output)


def _build(reconstruction, model: Path, images: Path, masks: Path | None, staging: Path, options) -> SplatExport:
    """Every file of the export, in ``staging``."""
    logger.info("undistorting %d photos of %s", reconstruction.num_reg_images(), images)
    undistort(model, images, staging, options)
    undistorted = read_model(staging / "sparse" / "0")
    with_masks = undistort_masks(reconstruction, undistorted, masks, staging / "masks", options) if masks else 0
    transforms = nerfstudio_transforms(undistorted, masks=with_masks > 0)
    (staging / "transforms.json").write_text(json.dumps(transforms, indent=4))
    points = write_points_ply(undistorted, staging / PLY_NAME)
    (staging / "colmap.log").unlink(missing_ok=True)
    cameras = [undistorted.camera(undistorted.image(i).camera_id) for i in sorted(undistorted.reg_image_ids())]
    sizes = [(camera.width, camera.height) for camera in cameras]
    return SplatExport(staging, len(sizes), points, sizes, with_masks)
