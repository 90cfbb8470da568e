"""Stage 4: features.h5 + matches.h5 -> COLMAP database, then geometric verification.

Coordinates: our keypoints follow OpenCV (the centre of the top-left pixel is (0, 0));
COLMAP puts it at (0.5, 0.5), so keypoints are written with +0.5. Camera parameters
given by the user (``CameraConfig.params``) are in COLMAP's convention, as COLMAP's own
``--ImageReader.camera_params``.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from ..errors import SekdError
from ..files import features as ff
from ..files import matches as mf
from .colmap import open_database, require_pycolmap, set_options
from .pairs import Pair

logger = logging.getLogger("sekd")
#: Camera sharing: auto (same size and EXIF make, model, focal length = same camera; see camera_groups),
#: one for all, one per folder, one per image.
CAMERA_MODES = {"auto": "AUTO", "single": "SINGLE", "per-folder": "PER_FOLDER", "per-image": "PER_IMAGE"}
#: OpenCV -> COLMAP pixel convention.
COLMAP_PIXEL_OFFSET = 0.5
#: The principal point in bundle adjustment (``principal_point.py``): ``auto`` (mapped fixed, then refined
#: in a final adjustment and kept only where the photos determine it; no test without PRINCIPAL_POINT_MIN_IMAGES
#: photos per camera or with known intrinsics), ``refine`` (the mapper refines it throughout), ``fixed``.
PRINCIPAL_POINT_MODES = ("auto", "refine", "fixed")
#: Photos per camera from which ``auto`` tests a refined principal point. COLMAP keeps it at the
#: image centre: with few views of a camera it trades off against their poses. A camera seen
#: by many photos can pin it down, and a real lens's centre is off the image centre: fountain-P11's
#: 11 photos of one camera (ground-truth principal point 15-17 px from the centre at 3072 px)
#: map with median rotation / translation-direction errors of 0.234 / 0.333 deg with it fixed,
#: 0.096 / 0.084 deg refined (SIFT through `sekd bench sfm`; docs/reconstruction.md). Whether the
#: photos of a camera determine it is then decided on the model (``principal_point.try_refinement``).
PRINCIPAL_POINT_MIN_IMAGES = 8


@dataclass
class CameraConfig:
    """Camera ``model`` (a COLMAP model name), sharing ``mode`` (CAMERA_MODES), known ``params`` ("f,cx,cy,..."),
    and whether bundle adjustment refines the ``principal_point`` (PRINCIPAL_POINT_MODES)."""

    model: str = "SIMPLE_RADIAL"
    mode: str = "auto"
    params: str | None = None
    principal_point: str = "auto"


def check_principal_point_mode(mode: str) -> None:
    """SekdError for a principal-point setting other than PRINCIPAL_POINT_MODES."""
    if mode not in PRINCIPAL_POINT_MODES:
        raise SekdError(f"unknown principal-point setting {mode!r}; choose from {', '.join(PRINCIPAL_POINT_MODES)}")


def images_per_camera(database: str | Path) -> list[int]:
    """How many images of ``database`` each of its cameras has (one number per camera with images)."""
    with open_database(database) as db:
        counts: dict[int, int] = {}
        for image in db.read_all_images():
            counts[image.camera_id] = counts.get(image.camera_id, 0) + 1
    return sorted(counts.values())


def refines_principal_point(camera: CameraConfig, per_camera: list[int]) -> bool:
    """Whether the mapper's bundle adjustments refine the principal point while mapping: only for ``refine``.

    ``auto`` maps with it fixed and may refine it in a final adjustment (``tries_principal_point``).
    """
    check_principal_point_mode(camera.principal_point)
    return camera.principal_point == "refine"


def tries_principal_point(camera: CameraConfig, per_camera: list[int]) -> bool:
    """Whether ``auto`` refines the principal point of the mapped models in a final, tested adjustment
    (``principal_point.py``), for ``per_camera`` images per camera.

    When every camera has at least PRINCIPAL_POINT_MIN_IMAGES images (COLMAP's option holds for all
    cameras at once, and a camera of a few photos cannot fix its principal point) and no known
    intrinsics were given.
    """
    check_principal_point_mode(camera.principal_point)
    return (camera.principal_point == "auto" and not camera.params and bool(per_camera)
            and min(per_camera) >= PRINCIPAL_POINT_MIN_IMAGES)


def camera_model_names() -> list[str]:
    """COLMAP camera model names of the installed pycolmap."""
    return [n for n in require_pycolmap().CameraModelId.__members__ if n != "INVALID"]


def parse_camera_params(model: str, params: str | None, width: int = 1000, height: int = 1000) -> list[float] | None:
    """``params`` ("f,cx,cy,k") as floats, checked against the model's parameter list; None if not given."""
    if model not in camera_model_names():
        raise SekdError(f"unknown camera model {model!r}; choose from {', '.join(camera_model_names())}")
    if params is None:
        return None
    names = require_pycolmap().Camera.create_from_model_name(0, model, 1.0, width, height).params_info
    try:
        values = [float(v) for v in params.replace(" ", "").split(",") if v]
    except ValueError:
        values = []
    if len(values) != len(names.split(",")):
        raise SekdError(f"--camera-params {params!r}: the {model} model takes {len(names.split(','))} "
                        f"comma-separated numbers ({names}), in COLMAP pixel coordinates")
    return values


#: EXIF tags of the camera key: Make and Model (IFD0), FocalLength (Exif sub-IFD).
_EXIF_MAKE, _EXIF_MODEL, _EXIF_IFD, _EXIF_FOCAL = 0x010F, 0x0110, 0x8769, 0x920A


def camera_key(path: Path) -> tuple:
    """``(width, height, make, model, focal length in mm)`` of an image, read without decoding pixels.

    EXIF fields that are absent are None, so photos of one size without EXIF share a key (a
    folder of one camera's frames with the EXIF stripped is the common case). An image PIL
    cannot parse gets a key of its own (its path), hence its own camera.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:  # reads the header only
            width, height = image.size
            exif = image.getexif()
            focal = exif.get_ifd(_EXIF_IFD).get(_EXIF_FOCAL, exif.get(_EXIF_FOCAL))
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
        return (str(path),)

    def text(tag: int) -> str | None:
        value = exif.get(tag)
        return str(value).strip("\x00 ").lower() or None if value is not None else None

    try:
        focal = round(float(focal), 3) if focal is not None else None
    except (TypeError, ValueError, ZeroDivisionError):
        focal = None
    return (width, height, text(_EXIF_MAKE), text(_EXIF_MODEL), focal)


def camera_groups(image_dir: Path, names: list[str]) -> list[list[str]]:
    """``names`` grouped by ``camera_key``: one list per camera, in the order of first appearance."""
    groups: dict[tuple, list[str]] = {}
    for name in names:
        groups.setdefault(camera_key(Path(image_dir) / name), []).append(name)
    return list(groups.values())


def _import_images(database: Path, image_dir: Path, names: list[str], camera: CameraConfig,
                   rig_prefixes: tuple[str, ...] = ()) -> None:
    """Cameras and images into ``database``. ``auto`` imports each camera group as one shared camera.

    COLMAP's own AUTO mode gives every image without an EXIF focal length its own camera
    (11 cameras for fountain-P11's 11 photos of one camera), so the groups are made here.
    The photos under each of ``rig_prefixes`` (a rig's cameras, ``stages.rig``) share one camera whatever the mode.
    """
    pycolmap = require_pycolmap()
    missing = [n for n in names if not (image_dir / n).is_file()]
    if missing:
        raise SekdError(f"{image_dir}: lacks {len(missing)} image(s) that have features: {', '.join(missing[:10])}; "
                        "give the image folder the features were extracted from")
    if camera.mode not in CAMERA_MODES:
        raise SekdError(f"unknown camera mode {camera.mode!r}; choose from {', '.join(CAMERA_MODES)}")
    parse_camera_params(camera.model, camera.params)
    options = pycolmap.ImageReaderOptions()
    options.camera_model = camera.model
    options.camera_params = camera.params or ""
    open_database(database).close()  # import_images needs an existing database file
    rigged = [[n for n in names if n.startswith(prefix)] for prefix in rig_prefixes]
    free = [n for n in names if not n.startswith(tuple(rig_prefixes))]
    single = [group for group in rigged if group] + (camera_groups(image_dir, free) if camera.mode == "auto" else [])
    for group in single:
        pycolmap.import_images(str(database), str(image_dir), pycolmap.CameraMode.SINGLE, group, options)
    if camera.mode != "auto" and free:
        mode = getattr(pycolmap.CameraMode, CAMERA_MODES[camera.mode])
        pycolmap.import_images(str(database), str(image_dir), mode, free, options)
    with open_database(database) as db:
        imported = {image.name for image in db.read_all_images()}
    if set(names) - imported:
        skipped = sorted(set(names) - imported)
        hint = ("--camera-mode single needs images of one size; use auto or per-image" if camera.mode == "single"
                else "see colmap.log for COLMAP's reason")
        raise SekdError(f"{image_dir}: COLMAP did not import {len(skipped)} image(s): {', '.join(skipped[:5])}; {hint}")


def _write_keypoints(db, ids: dict[str, int], features: Path) -> None:
    """Keypoints in COLMAP's pixel convention, after checking each image's size against COLMAP's.

    A size mismatch means the features come from other images (or an EXIF rotation
    was applied on one side only), which would silently break the geometry.
    """
    wrong = []
    with h5py.File(features, "r") as f:
        for name, image_id in ids.items():
            camera = db.read_camera(db.read_image(image_id).camera_id)
            size = f[name]["image_size"][()].tolist()
            if [camera.width, camera.height] != size:
                wrong.append(f"{name} ({camera.width}x{camera.height} on disk, {size[0]}x{size[1]} in the features)")
            keypoints = f[name]["keypoints"][()].astype(np.float32) + COLMAP_PIXEL_OFFSET
            db.write_keypoints(image_id, keypoints.reshape(-1, 2))
    if wrong:
        raise SekdError(f"{features}: image sizes differ from the images on disk for {', '.join(wrong[:5])}; "
                        "re-extract features from these images")


def create_database(image_dir: str | Path, features: str | Path, matches: str | Path, pairs: list[Pair],
                    database: str | Path, camera: CameraConfig | None = None, rig_prefixes: tuple[str, ...] = ()) -> Path:
    """A fresh COLMAP database with cameras, images, keypoints and the raw matches of ``pairs``.

    Images are the keys of ``features``, read from ``image_dir`` by COLMAP (sizes, EXIF focal
    length); those under each of ``rig_prefixes`` share a camera. An existing ``database`` is replaced.
    Returns ``database``.
    """
    image_dir, features, matches, database = Path(image_dir), Path(features), Path(matches), Path(database)
    camera = camera or CameraConfig()
    for suffix in ("", "-wal", "-shm"):
        database.with_name(database.name + suffix).unlink(missing_ok=True)
    names = ff.list_keys(features)
    _import_images(database, image_dir, names, camera, rig_prefixes)
    with open_database(database) as db:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        _write_keypoints(db, ids, features)
        for name0, name1, idx, _ in mf.iter_matches(matches, [p for p in pairs if p[0] in ids and p[1] in ids]):
            db.write_matches(ids[name0], ids[name1], idx.astype(np.uint32))
    logger.info("%s: %d images, %d pairs imported", database, len(ids), len(pairs))
    return database


#: RANSAC trials per model (F and H; E too when the focal length is known) in verification.
#: Pairs that verify stop early (RANSAC ends once its best model makes more trials pointless;
#: 22 ms of CPU per pair on a generated 50-photo scene). Pairs it cannot verify run every
#: trial: photos that share no surface keep ~40 SEKD matches (SIFT's ratio test leaves them
#: under the 15 below which COLMAP skips a pair), so COLMAP's 10000 trials cost 0.31 s per
#: such pair, 94% of the stage. 2000 trials: 4.4x less CPU there, the same verified pairs;
#: weak pairs (~20 inliers, <30% of the matches) can be lost (docs/reconstruction.md).
VERIFY_MAX_TRIALS = 2000


def two_view_options(assignments: list[str] | None = None, seed: int | None = 0):
    """pycolmap TwoViewGeometryOptions: ``VERIFY_MAX_TRIALS``, a fixed RANSAC seed, then ``key=value`` overrides.

    ``ransac.max_num_trials=10000`` among ``assignments`` restores COLMAP's own budget.
    """
    options = require_pycolmap().TwoViewGeometryOptions()
    options.ransac.max_num_trials = VERIFY_MAX_TRIALS
    if seed is not None:
        options.ransac.random_seed = seed
    return set_options(options, assignments or [], "--verification")


def verify_matches(database: str | Path, options=None, num_threads: int = -1) -> Path:
    """Geometric verification of all matched pairs in ``database`` (pycolmap, RANSAC on E, F or H).

    Stores each pair's inlier matches and two-view geometry in the database. Returns ``database``.
    """
    pycolmap = require_pycolmap()
    verifier = pycolmap.GeometricVerifierOptions()
    verifier.num_threads = num_threads
    pycolmap.geometric_verification(str(database), verifier, pycolmap.ExistingMatchedPairingOptions(),
                                    options or two_view_options())
    return Path(database)


def _sharing_key(mode: str, image_dir: Path, name: str) -> tuple:
    """What photos of one camera share under the camera ``mode``: the camera_key (auto), nothing (single),
    the folder (per-folder) or the photo itself (per-image, never shared)."""
    if mode == "auto":
        return camera_key(image_dir / name)
    return {"single": ("all",), "per-folder": (str(Path(name).parent),)}.get(mode, ("image", name))


def add_to_database(database: str | Path, image_dir: str | Path, features: str | Path, matches: str | Path,
                    pairs: list[Pair], names: list[str], camera: CameraConfig | None = None) -> dict[str, int]:
    """Add the photos ``names`` to an existing ``database``: cameras, images, keypoints, raw matches of ``pairs``.

    What is there stays as it is (image and camera ids, keypoints, matches, verified geometries). A new
    photo that shares a camera with photos already in the database (the sharing rule of ``camera.mode``:
    ``camera_key`` for auto) joins that camera; the others get cameras as ``create_database`` would give
    them. ``pairs`` are the pairs to add (each with at least one of ``names``). Returns the new ids by name.
    """
    pycolmap = require_pycolmap()
    image_dir, database, camera = Path(image_dir), Path(database), camera or CameraConfig()
    with open_database(database) as db:
        old = {image.name: image for image in db.read_all_images()}
    if set(names) & set(old):
        raise SekdError(f"{database}: already holds {min(set(names) & set(old))}; only new photos are added")
    existing: dict[tuple, int] = {}
    for name, image in sorted(old.items()):
        if (image_dir / name).is_file():
            existing.setdefault(_sharing_key(camera.mode, image_dir, name), image.camera_id)
    groups: dict[tuple, list[str]] = {}
    for name in names:
        groups.setdefault(_sharing_key(camera.mode, image_dir, name), []).append(name)
    for key, group in groups.items():
        if key in existing:  # joins the camera its photos already have (its intrinsics, as the model has them)
            options = pycolmap.ImageReaderOptions()
            options.camera_model, options.existing_camera_id = camera.model, existing[key]
            pycolmap.import_images(str(database), str(image_dir), pycolmap.CameraMode.SINGLE, group, options)
        else:
            _import_images(database, image_dir, group, CameraConfig(camera.model, "per-image" if camera.mode ==
                                                                    "per-image" else "single", camera.params,
                                                                    camera.principal_point))
    with open_database(database) as db:
        ids = {image.name: image.image_id for image in db.read_all_images() if image.name in set(names)}
        if len(ids) != len(names):
            missing = sorted(set(names) - set(ids))
            raise SekdError(f"{image_dir}: COLMAP did not import {', '.join(missing[:5])}; see colmap.log for why")
        _write_keypoints(db, ids, Path(features))
        every = {**{n: i.image_id for n, i in old.items()}, **ids}
        wanted = [p for p in pairs if p[0] in every and p[1] in every and (p[0] in ids or p[1] in ids)]
        for name0, name1, idx, _ in mf.iter_matches(matches, wanted):
            db.write_matches(every[name0], every[name1], idx.astype(np.uint32))
    logger.info("%s: %d images and %d pairs added", database, len(ids), len(wanted))
    return ids
