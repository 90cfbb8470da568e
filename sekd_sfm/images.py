"""Finding and reading images: keys, decoding, resizing.

An image's key is its path relative to the image root in POSIX form
(``sub dir/Ünïcode 1.jpg``), used as its name in every output file. EXIF orientation
is *not* applied: COLMAP works in the stored pixel frame, and so do we.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .errors import SekdError

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".tif", ".tiff", ".bmp")


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
    try:
        data = np.fromfile(str(path), dtype=np.uint8)  # handles any file name, unlike imread on Windows
    except OSError as exc:
        raise ImageReadError(f"{path}: cannot read file ({exc.strerror})") from exc
    flags = cv2.IMREAD_IGNORE_ORIENTATION | (cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR)
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None:
        raise ImageReadError(f"{path}: not a decodable image (corrupt or unsupported format)")
    if image.dtype != np.uint8:
        image = _to_uint8(image)
    return image if grayscale else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


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


def to_original_pixels(keypoints: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Map ``N x 2`` keypoints of a resized image back to original pixels (pixel-centre convention)."""
    if sx == 1.0 and sy == 1.0:
        return keypoints
    return ((keypoints + 0.5) * np.array([sx, sy], dtype=np.float64) - 0.5).astype(np.float32)
