"""Finding and reading images: keys, decoding, resizing.

An image's key is its path relative to the image root in POSIX form
(``sub dir/Ünïcode 1.jpg``), used as its name in every output file. EXIF orientation
is *not* applied: COLMAP works in the stored pixel frame, and so do we.

Masks follow COLMAP's convention (docs/masks.md): the mask of photo ``NAME`` is
``MASKS/NAME.png``, zero = ignore that pixel.
"""
from __future__ import annotations

import hashlib
import struct
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import SekdError

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".tif", ".tiff", ".bmp")
#: Default pixel cap (``--max-pixels``): larger images are decoded at 1/2, 1/4 or 1/8 size.
DEFAULT_MAX_PIXELS = 100_000_000
#: Decode-time reductions OpenCV offers (IMREAD_REDUCED_*): factor -> (grayscale flag, colour flag).
_REDUCED = {
    2: (cv2.IMREAD_REDUCED_GRAYSCALE_2, cv2.IMREAD_REDUCED_COLOR_2),
    4: (cv2.IMREAD_REDUCED_GRAYSCALE_4, cv2.IMREAD_REDUCED_COLOR_4),
    8: (cv2.IMREAD_REDUCED_GRAYSCALE_8, cv2.IMREAD_REDUCED_COLOR_8),
}
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_PIL_LOCK = threading.Lock()


class ImageReadError(Exception):
    """An image file that cannot be decoded (the message says which and why)."""


def list_images(root: str | Path) -> list[str]:
    """Keys of all images below ``root`` (recursive, any extension case), sorted.

    Raises SekdError for a missing folder or one with no images.
    """
    root = Path(root)
    if not root.is_dir():
        raise SekdError(f"{root}: image folder not found; give a folder that contains images")
    keys = sorted(
        p.relative_to(root).as_posix()
        for p in root.rglob("*")
        if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file()
    )
    if not keys:
        raise SekdError(f"{root}: no images found (looked for {', '.join(IMAGE_EXTENSIONS)}, any case, recursively)")
    return keys


def read_image(path: str | Path, grayscale: bool = True) -> np.ndarray:
    """Decode an image to uint8, ``H x W`` (grayscale) or ``H x W x 3`` (RGB), ignoring EXIF orientation.

    Grayscale uses OpenCV's IMREAD_GRAYSCALE decode path, which the SEKD reference outputs
    were produced with (converting a colour image afterwards differs by one grey level on
    ~0.05% of pixels). 16-bit images are scaled to 8 bits; alpha is dropped.
    """
    flags = cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR
    return _decode(path, flags, grayscale)


def _decode(path: str | Path, flags: int, grayscale: bool) -> np.ndarray:
    try:
        data = np.fromfile(str(path), dtype=np.uint8)  # handles any file name, unlike imread on Windows
    except OSError as exc:
        raise ImageReadError(f"{path}: cannot read file ({exc.strerror})") from exc
    except MemoryError as exc:
        raise ImageReadError(f"{path}: file too large to read into memory") from exc
    try:  # a corrupt file can make OpenCV raise instead of returning None
        image = cv2.imdecode(data, flags | cv2.IMREAD_IGNORE_ORIENTATION) if data.size else None
    except (cv2.error, MemoryError) as exc:
        raise ImageReadError(f"{path}: not a decodable image ({str(exc).strip().splitlines()[-1][:200]})") from exc
    if image is None:
        raise ImageReadError(f"{path}: not a decodable image (corrupt or unsupported format)")
    if image.dtype != np.uint8:
        image = _to_uint8(image)
    if image.ndim == 3 and grayscale:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image if grayscale or image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def image_size(path: str | Path) -> tuple[int, int] | None:
    """``(width, height)`` from the file header, without decoding the pixels; None when unknown.

    PNG and JPEG are parsed here (the formats OpenCV can decode at reduced size); other
    formats go through Pillow's lazy ``open``, which also reads only the header.
    """
    try:
        with open(path, "rb") as f:
            head = f.read(32)
            if head.startswith(b"\x89PNG\r\n\x1a\n") and head[12:16] == b"IHDR":
                return struct.unpack(">II", head[16:24])
            if head.startswith(b"\xff\xd8"):
                return _jpeg_size(f)
    except (OSError, struct.error):
        return None
    return _pil_size(path)


def _jpeg_size(f, max_garbage: int = 65536) -> tuple[int, int] | None:
    """Walk the JPEG markers up to the first start-of-frame (SOFn) and read its size.

    Segments are skipped by their length, so this reads a few bytes per segment; a corrupt
    file ends the walk (None) after ``max_garbage`` bytes that are not markers.
    """
    f.seek(2)
    garbage = 0
    while True:
        byte = f.read(1)
        while byte and byte != b"\xff" and garbage < max_garbage:  # tolerate garbage, as libjpeg does
            byte, garbage = f.read(1), garbage + 1
        while byte == b"\xff":  # fill bytes
            byte = f.read(1)
        if not byte or garbage >= max_garbage:
            return None
        marker = byte[0]
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:
            continue  # markers without a length
        if marker in (0xD9, 0xDA):
            return None  # end of image or scan data before any frame header
        length = struct.unpack(">H", f.read(2))[0]
        if length < 2:
            return None  # a corrupt length would walk backwards forever
        if marker in _JPEG_SOF:
            height, width = struct.unpack(">xHH", f.read(5))
            return (width, height) if width and height else None
        f.seek(length - 2, 1)


def _pil_size(path: str | Path) -> tuple[int, int] | None:
    try:
        from PIL import Image
    except ImportError:
        return None
    with _PIL_LOCK:  # Pillow's decompression-bomb check would refuse exactly the images we need to size
        limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
        try:
            with Image.open(path) as im:
                return im.size
        except Exception:  # noqa: BLE001 - any header Pillow cannot parse: size unknown, OpenCV decides
            return None
        finally:
            Image.MAX_IMAGE_PIXELS = limit


def reduction_factor(width: int, height: int, max_pixels: int | None) -> int:
    """The decode-time reduction (1, 2, 4 or 8) that brings ``width x height`` within ``max_pixels``.

    Raises ImageReadError when even 1/8 is too large.
    """
    if not max_pixels or width * height <= max_pixels:
        return 1
    for factor in _REDUCED:
        if (width // factor) * (height // factor) <= max_pixels:
            return factor
    raise ImageReadError(
        f"{width} x {height} px ({width * height / 1e6:.0f} MP) is more than 64 times the pixel cap "
        f"({max_pixels / 1e6:g} MP); downscale the file or raise --max-pixels"
    )


def load_scaled(path: str | Path, resize_max: int | None = None, grayscale: bool = True,
                max_pixels: int | None = DEFAULT_MAX_PIXELS) -> tuple[tuple[int, int], np.ndarray, float, float]:
    """Decode an image for feature extraction, within the pixel cap, then apply ``resize_max``.

    An image above ``max_pixels`` is decoded at 1/2, 1/4 or 1/8 size (JPEG: by libjpeg's
    DCT scaling, which never holds the full image; other formats: OpenCV decodes, then
    downsizes), so one huge photo neither exhausts memory nor blocks a folder.
    Returns ``((height, width) of the original, image, sx, sy)`` with (sx, sy) = original
    pixels per pixel of ``image``, for ``to_original_pixels``. ImageReadError when the
    image cannot be decoded or is beyond 64x the cap.
    """
    size = image_size(path) if max_pixels else None
    factor = 1
    if size is not None:
        try:
            factor = reduction_factor(*size, max_pixels)
        except ImageReadError as exc:
            raise ImageReadError(f"{path}: {exc}") from None
    if factor == 1:
        image = read_image(path, grayscale)
        original = image.shape[:2]
        if max_pixels and original[0] * original[1] > max_pixels:  # the header lied or was unknown
            image, sx0, sy0 = _downsize_to_cap(image, max_pixels)
        else:
            sx0 = sy0 = 1.0
    else:
        width, height = size
        image = _decode(path, _REDUCED[factor][0 if grayscale else 1], grayscale)
        original = (height, width)
        if _is_jpeg(path):  # libjpeg's DCT scaling: output pixel i covers original pixels [f i, f i + f)
            sx0 = sy0 = float(factor)
        else:  # OpenCV resizes to floor(W / f): the scale is the size ratio
            sx0, sy0 = width / image.shape[1], height / image.shape[0]
    small, sx, sy = resize_max_side(image, resize_max)
    return original, small, sx0 * sx, sy0 * sy


def _downsize_to_cap(image: np.ndarray, max_pixels: int) -> tuple[np.ndarray, float, float]:
    h, w = image.shape[:2]
    ratio = (max_pixels / (h * w)) ** 0.5
    new_w, new_h = max(1, int(w * ratio)), max(1, int(h * ratio))
    return cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_AREA), w / new_w, h / new_h


def _is_jpeg(path: str | Path) -> bool:
    with open(path, "rb") as f:
        return f.read(2) == b"\xff\xd8"


def _to_uint8(image: np.ndarray) -> np.ndarray:
    if image.dtype == np.uint16:
        return (image >> 8).astype(np.uint8)
    return cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def resize_max_side(image: np.ndarray, max_side: int | None) -> tuple[np.ndarray, float, float]:
    """Downscale so the long side is at most ``max_side`` (area interpolation; never upscales).

    Returns the image and the scales (sx, sy) = original size / new size per axis, so that
    a pixel centre maps back as x_orig = (x + 0.5) * sx - 0.5.
    """
    h, w = image.shape[:2]
    if not max_side or max(h, w) <= max_side:
        return image, 1.0, 1.0
    ratio = max_side / max(h, w)
    new_w, new_h = max(1, round(w * ratio)), max(1, round(h * ratio))
    resized = cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_AREA)
    return resized, w / new_w, h / new_h


def resized_to_original_matrix(sx: float, sy: float) -> np.ndarray:
    """3x3 map from resized to original pixels (pixel-centre convention), as ``to_original_pixels``."""
    return np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1.0]])


def to_resized_pixels(points: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """The inverse of ``to_original_pixels``: ``N x 2`` original pixels -> pixels of the resized image (float64)."""
    return (np.asarray(points, dtype=np.float64) + 0.5) / np.array([sx, sy]) - 0.5


def to_original_pixels(keypoints: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Map ``N x 2`` keypoints of a resized image back to original pixels (pixel-centre convention)."""
    if sx == 1.0 and sy == 1.0:
        return keypoints
    return ((keypoints + 0.5) * np.array([sx, sy], dtype=np.float64) - 0.5).astype(np.float32)


#: A photo's mask is ``MASKS/<key>`` + this (COLMAP's convention: ``a/b.jpg`` -> ``a/b.jpg.png``).
MASK_SUFFIX = ".png"
#: A mask whose aspect ratio differs from its photo's by more than this (relative) is refused: it was made for
#: another photo (a rotated or cropped one), and stretching it would ignore the wrong pixels.
MASK_ASPECT_TOLERANCE = 0.02
#: Fraction of a processed pixel that must be kept for the pixel to be kept: a processed pixel that covers any
#: ignored original pixel is ignored (the margin absorbs float round-off of the area average).
_KEEP_AREA = 1 - 1e-3


@dataclass(frozen=True)
class PhotoMask:
    """A photo's mask as extraction uses it.

    ``sha256``: of the mask file's bytes ("" = the photo has no mask file). ``keep``: ``H x W``
    bool at the photo's original size, True = use the pixel; None = the photo is used whole (no
    file, a file that ignores nothing, or a refused file). ``ignored``: fraction of the photo's
    pixels ignored. ``refused``: why a mask file was not used ("" when it was).
    """

    sha256: str = ""
    keep: np.ndarray | None = None
    ignored: float = 0.0
    refused: str = ""


def mask_path(masks_dir: str | Path, key: str) -> Path:
    """The mask file of the photo ``key``: ``masks_dir/key.png`` (COLMAP's convention)."""
    return Path(masks_dir) / (key + MASK_SUFFIX)


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_mask(path: str | Path, size: tuple[int, int]) -> PhotoMask:
    """The mask at ``path`` for a photo of ``size`` = (height, width) original pixels; never raises.

    No file: an empty PhotoMask (used whole). A file that cannot be decoded, ignores every
    pixel, or has another aspect ratio than the photo is refused (``refused`` says why; the
    photo is used whole). Any non-zero value (in any colour channel; alpha is not read) keeps
    the pixel. A mask of another size is resized to the photo's (nearest neighbour: no grey
    edge to threshold).
    """
    path = Path(path)
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except FileNotFoundError:
        return PhotoMask()
    except OSError as exc:
        return PhotoMask("", None, 0.0, f"{path}: cannot read the mask ({exc.strerror}); the photo is used whole")
    sha = hashlib.sha256(data).hexdigest()
    keep, problem = _decode_mask(data, size)
    if problem:
        return PhotoMask(sha, None, 0.0, f"{path}: {problem}; the photo is used whole")
    ignored = 1.0 - float(np.count_nonzero(keep)) / keep.size
    return PhotoMask(sha, keep if ignored > 0 else None, ignored)


def _decode_mask(data: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray | None, str]:
    """``(keep H x W bool at size, "")`` or ``(None, what is wrong)`` for a mask file's bytes."""
    try:  # UNCHANGED: a 16-bit mask of 0/1 would read as all zero through an 8-bit conversion
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION) if data.size else None
    except cv2.error:
        image = None
    if image is None:
        return None, "not a decodable image (a mask is a PNG, zero = ignore)"
    keep = image[..., :3].any(axis=-1) if image.ndim == 3 else image != 0
    if not keep.any():
        return None, "the mask is zero everywhere (it would ignore the whole photo)"
    (height, width), (mh, mw) = size, keep.shape
    if abs((mw / mh) / (width / height) - 1) > MASK_ASPECT_TOLERANCE:
        return None, f"the mask is {mw} x {mh} px, the photo {width} x {height}: another aspect ratio"
    if (mh, mw) != (height, width):
        keep = cv2.resize(keep.view(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST).astype(bool)
    return keep, ""


def scale_mask(keep: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``keep`` (``H x W`` bool) at ``shape`` = (height, width) <= its own, conservatively: a pixel is kept only
    if every original pixel it covers is kept (area average), so a keypoint there never lies on an ignored one."""
    if keep.shape == tuple(shape):
        return keep
    area = cv2.resize(keep.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    return area >= _KEEP_AREA


def kept_at(keep: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
    """Whether the pixel of each keypoint (``N x 2`` x, y; integer = pixel centre) is kept: ``N`` bool.

    Positions outside the mask are clamped to its border pixel.
    """
    xy = np.rint(np.asarray(keypoints, dtype=np.float64)).astype(np.int64).reshape(-1, 2)
    h, w = keep.shape
    return keep[np.clip(xy[:, 1], 0, h - 1), np.clip(xy[:, 0], 0, w - 1)]
