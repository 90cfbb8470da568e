"""SEKD in tiles: the same maps on every tile's core, the same keypoints (to float round-off), a budget from memory."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from conftest import SHARED

from sekd_sfm import load_model
from sekd_sfm.model import tiling
from sekd_sfm.model.inference import SEKDConfig, SEKDExtractor, crop_to_stride

PHOTO = SHARED / "data/sfm/fountain-P11/images/0005.jpg"


@pytest.fixture(scope="module")
def photo(shared) -> np.ndarray:
    """A 1024 x 680 grayscale photo, sides multiples of 4 (0.7 MP: large enough for 12 tiles of a small budget)."""
    image = cv2.imread(str(PHOTO), cv2.IMREAD_GRAYSCALE)
    return crop_to_stride(cv2.resize(image, (1024, 683), interpolation=cv2.INTER_AREA))


@pytest.fixture(scope="module")
def extractor() -> SEKDExtractor:
    return SEKDExtractor(load_model(None)[0], SEKDConfig(precision="fp32"))


def test_budget_follows_memory_within_bounds(monkeypatch):
    monkeypatch.delenv("SEKD_PIXEL_BUDGET", raising=False)
    gib = 1 << 30
    assert tiling.pixel_budget(24 * gib) == int(24 * gib / 12 / tiling.BYTES_PER_PIXEL)  # ~2.3 MP: ~2 GB a pass
    assert tiling.pixel_budget(4 * gib) == tiling.MIN_BUDGET
    assert tiling.pixel_budget(512 * gib) == tiling.MAX_BUDGET
    assert tiling.pixel_budget() <= tiling.MAX_BUDGET
    monkeypatch.setenv("SEKD_PIXEL_BUDGET", "250000")
    assert tiling.pixel_budget(24 * gib) == 250_000


def test_doctor_prints_the_budget(monkeypatch):
    from click.testing import CliRunner

    from sekd_sfm.cli.main import sekd

    monkeypatch.setenv("SEKD_PIXEL_BUDGET", "1500000")
    result = CliRunner().invoke(sekd, ["doctor"])
    assert result.exit_code == 0
    assert "pixel budget      1.5 MP per SEKD forward pass" in result.output


@pytest.mark.parametrize(("height", "width", "side"), [(680, 1024, 256), (4, 4, 64), (1000, 52, 256), (512, 512, 512)])
def test_tile_cores_cover_the_image_once(height, width, side):
    covered = np.zeros((height, width), np.int32)
    for tile in tiling.tiles(height, width, side):
        covered[tile.y0:tile.y1, tile.x0:tile.x1] += 1
        assert 0 <= tile.wy0 <= tile.y0 < tile.y1 <= tile.wy1 <= height
        assert 0 <= tile.wx0 <= tile.x0 < tile.x1 <= tile.wx1 <= width
        assert all(v % 4 == 0 for v in (tile.wy0, tile.wx0, tile.y0, tile.x0))  # on the network's stride grid
    assert (covered == 1).all()


def test_tiles_give_the_whole_image_maps_on_their_cores(photo, extractor):
    """With the margin, a tile's core holds the untiled probabilities (float round-off) and raw descriptors."""
    image = torch.from_numpy(photo.astype(np.float32) / 255)[None, None]
    prob_full, raw_full = (m[0] for m in extractor.model(image))
    grid = tiling.tiles(*photo.shape, tiling.core_side(200_000))
    assert len(grid) == 12
    for tile, prob, raw in tiling.windows(image, grid, extractor.model):
        core = prob[tile.y0 - tile.wy0:tile.y1 - tile.wy0, tile.x0 - tile.wx0:tile.x1 - tile.wx0]
        assert torch.allclose(core, prob_full[tile.y0:tile.y1, tile.x0:tile.x1], atol=1e-6, rtol=0)
        rows = slice((tile.y0 - tile.wy0) // 4, (tile.y1 - tile.wy0) // 4)
        raw_core = raw[:, rows, (tile.x0 - tile.wx0) // 4:(tile.x1 - tile.wx0) // 4]
        assert torch.allclose(raw_core, raw_full[:, tile.y0 // 4:tile.y1 // 4, tile.x0 // 4:tile.x1 // 4], atol=1e-5)


def test_tiled_keypoints_equal_untiled_ones(photo, extractor, monkeypatch):
    """The extractor switches to tiles above its budget; keypoints and descriptors are the untiled ones, apart from
    candidates whose scores tie to float round-off (at the NMS or the top-k boundary), as with another thread count."""
    whole = extractor.extract(photo)
    monkeypatch.setattr(extractor, "pixel_budget", 200_000)
    tiled = extractor.extract(photo)
    assert len(tiled["keypoints"]) == len(whole["keypoints"]) == 2000
    index = {tuple(np.round(xy, 3)): i for i, xy in enumerate(whole["keypoints"])}
    keys = [tuple(np.round(xy, 3)) for xy in tiled["keypoints"]]
    common = [(index[key], j) for j, key in enumerate(keys) if key in index]
    assert len(common) >= 0.98 * 2000
    i, j = np.array(common).T
    np.testing.assert_allclose(tiled["descriptors"][j], whole["descriptors"][i], atol=1e-5)
    np.testing.assert_allclose(tiled["scores"][j], whole["scores"][i], atol=1e-6)
    assert (np.abs(i - j) <= 20).mean() > 0.95  # by decreasing score, as untiled


def test_a_photo_out_of_memory_is_skipped_and_the_others_written(tmp_path, monkeypatch):
    """One photo whose pass runs out of memory is listed in ``failed_images``; the run goes on and a resume retries it."""
    import h5py

    from sekd_sfm import FeatureConfig, extract_features, list_keys

    images = tmp_path / "images"
    images.mkdir()
    for name in ("0000.jpg", "0001.jpg", "0002.jpg"):
        (images / name).symlink_to(SHARED / "data/sfm/fountain-P11/images" / name)
    real = SEKDExtractor.extract
    calls = []

    def extract(self, image, *args, **kwargs):
        calls.append(image.shape)
        if len(calls) == 2:  # the second photo: as torch's CPU allocator reports it
            raise RuntimeError("[enforce fail at alloc_cpu.cpp:118] DefaultCPUAllocator: can't allocate memory")
        return real(self, image, *args, **kwargs)

    monkeypatch.setattr(SEKDExtractor, "extract", extract)
    out = extract_features(images, tmp_path / "f.h5", FeatureConfig(resize_max=320, max_keypoints=200), progress=False)
    assert list_keys(out) == ["0000.jpg", "0002.jpg"]
    with h5py.File(out) as f:
        assert f.attrs["failed_images"] == '["0001.jpg"]'
    monkeypatch.setattr(SEKDExtractor, "extract", real)
    extract_features(images, out, FeatureConfig(resize_max=320, max_keypoints=200), progress=False)
    assert list_keys(out) == ["0000.jpg", "0001.jpg", "0002.jpg"]  # the resume computes only the failed one
