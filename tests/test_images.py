"""Finding and decoding images."""
import cv2
import numpy as np
import pytest

from sekd_sfm.errors import SekdError
from sekd_sfm.files.images import (
    ImageReadError,
    list_images,
    read_image,
    resize_max_side,
    to_original_pixels,
)


def test_list_images_recursive_any_case_unicode_and_spaces(tmp_path):
    image = np.zeros((8, 8), np.uint8)
    for name in ["b.JPG", "a dir/ünï cödé.png", "a dir/deep/x.PpM", "notes.txt", "c.tiff"]:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        _, data = cv2.imencode(".png", image)
        (tmp_path / name).write_bytes(data.tobytes())
    assert list_images(tmp_path) == ["a dir/deep/x.PpM", "a dir/ünï cödé.png", "b.JPG", "c.tiff"]


def test_list_images_errors(tmp_path):
    with pytest.raises(SekdError, match="not found"):
        list_images(tmp_path / "missing")
    with pytest.raises(SekdError, match="no images found"):
        list_images(tmp_path)


def test_read_16bit_rgba_and_gray(tmp_path):
    gray16 = (np.arange(64, dtype=np.uint16).reshape(8, 8) * 1000)
    cv2.imwrite(str(tmp_path / "g16.png"), gray16)
    assert read_image(tmp_path / "g16.png").tolist() == (gray16 >> 8).astype(np.uint8).tolist()
    rgba = np.zeros((4, 6, 4), np.uint8)
    rgba[..., 2] = 200  # red in BGRA
    rgba[..., 3] = 7
    cv2.imwrite(str(tmp_path / "rgba.png"), rgba)
    assert read_image(tmp_path / "rgba.png").shape == (4, 6)
    assert read_image(tmp_path / "rgba.png", grayscale=False)[0, 0].tolist() == [200, 0, 0]


def test_corrupt_and_empty_files_raise(tmp_path):
    (tmp_path / "bad.jpg").write_bytes(b"\xff\xd8 this is not a jpeg")
    (tmp_path / "empty.png").write_bytes(b"")
    for name in ("bad.jpg", "empty.png"):
        with pytest.raises(ImageReadError, match=name):
            read_image(tmp_path / name)


def test_exif_orientation_is_not_applied(tmp_path):
    from PIL import Image

    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 CW to display"
    Image.fromarray(np.zeros((10, 30, 3), np.uint8)).save(tmp_path / "rot.jpg", exif=exif)
    assert read_image(tmp_path / "rot.jpg").shape == (10, 30)  # stored pixel frame, as COLMAP


def test_resize_and_map_back():
    image = np.zeros((300, 400), np.uint8)
    small, sx, sy = resize_max_side(image, 100)
    assert small.shape == (75, 100) and (sx, sy) == (4.0, 4.0)
    assert to_original_pixels(np.array([[0.0, 0.0], [99.0, 74.0]], np.float32), sx, sy).tolist() == [[1.5, 1.5], [397.5, 297.5]]
    assert resize_max_side(image, 1000)[0] is image
