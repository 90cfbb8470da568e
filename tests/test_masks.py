"""Masks (``--masks``, COLMAP's convention, docs/masks.md): ignored pixels give no keypoint, the budget is
refilled from the rest, the feature file records each mask's hash, and a changed mask re-extracts its photo."""
from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import SEKD_WEIGHTS

import sekd_sfm.stages.extract as ex
from sekd_sfm.cli.main import sekd
from sekd_sfm.features import FeatureConfig
from sekd_sfm.features.peers import PEER_WEIGHTS
from sekd_sfm.files import features as ff
from sekd_sfm.files import shards
from sekd_sfm.files.images import image_size, read_mask, scale_mask
from sekd_sfm.model.inference import SEKDConfig
from sekd_sfm.stages.extract import ExtractWorker, extract_features
from sekd_sfm.stages.retrieval import global_path

PHOTOS = ("0000.jpg", "0004.jpg", "0008.jpg")  # fountain-P11, 3072 x 2048, extracted at 320 px: fast
RESIZE = 320


@pytest.fixture
def photos(tmp_path, shared) -> Path:
    """Three real photos (symlinks: the shared data stays where it is)."""
    folder = tmp_path / "images"
    folder.mkdir()
    for name in PHOTOS:
        (folder / name).symlink_to(shared / "data/sfm/fountain-P11/images" / name)
    return folder


def left_third(width: int, height: int) -> np.ndarray:
    """A mask ignoring the left third of a ``width x height`` photo (uint8, 0 = ignore)."""
    mask = np.full((height, width), 255, np.uint8)
    mask[:, : width // 3] = 0
    return mask


def write_masks(photos: Path, folder: Path, make=left_third, names=PHOTOS) -> Path:
    """``folder/NAME.png`` for each photo NAME, from ``make(width, height)``."""
    folder.mkdir(exist_ok=True)
    for name in names:
        cv2.imwrite(str(folder / f"{name}.png"), make(*image_size(photos / name)))
    return folder


def sekd_features(max_keypoints: int) -> FeatureConfig:
    return FeatureConfig(feature="sekd", max_keypoints=max_keypoints, resize_max=RESIZE, weights=str(SEKD_WEIGHTS),
                         sekd=SEKDConfig(precision="fp32", device="cpu"))


def sift(max_keypoints: int) -> FeatureConfig:
    return FeatureConfig(feature="sift", max_keypoints=max_keypoints, resize_max=RESIZE)


def arrays(path: Path) -> dict[str, dict[str, np.ndarray]]:
    return {key: ff.read_features(path, key) for key in ff.list_keys(path)}


def in_left_third(path: Path, key: str) -> int:
    """Keypoints of ``key`` whose pixel (original, rounded) lies in the left third."""
    found = ff.read_features(path, key)
    width = int(found["image_size"][0])
    return int((np.rint(found["keypoints"][:, 0]) < width // 3).sum())


def count_extractions(monkeypatch) -> list[str]:
    """Record the photos ``_features_of`` extracts (by their image size: fine for counting)."""
    calls: list[str] = []
    real = ex._features_of
    monkeypatch.setattr(ex, "_features_of", lambda *a: calls.append(a[1][1].shape) or real(*a))
    return calls


@pytest.mark.parametrize("config", [sekd_features(150), sift(150)], ids=["sekd", "sift"])
def test_masked_keypoints_are_dropped_before_the_top_k(photos, tmp_path, config):
    masks = write_masks(photos, tmp_path / "masks")
    whole = extract_features(photos, tmp_path / "whole.h5", config, progress=False)
    masked = extract_features(photos, tmp_path / "masked.h5", config, progress=False, masks=masks)
    for key in PHOTOS:
        assert in_left_third(whole, key) > 0  # the mask has something to remove
        assert in_left_third(masked, key) == 0
        # the budget is refilled from the rest of the photo, not left short by the masked keypoints
        assert len(ff.read_features(masked, key)["keypoints"]) == config.max_keypoints


def test_a_peer_feature_is_masked_too(photos, tmp_path, shared):
    if not (shared / PEER_WEIGHTS["aliked"]).is_file():
        pytest.skip("ALIKED weights absent")
    config = FeatureConfig(feature="aliked", max_keypoints=100, resize_max=RESIZE, sekd=SEKDConfig(device="cpu"))
    masked = extract_features(photos, tmp_path / "f.h5", config, progress=False,
                              masks=write_masks(photos, tmp_path / "masks"))
    for key in PHOTOS:
        assert in_left_third(masked, key) == 0
        assert len(ff.read_features(masked, key)["keypoints"]) == 100


def test_the_file_records_the_masks(photos, tmp_path):
    masks = write_masks(photos, tmp_path / "masks", names=PHOTOS[:2])  # the third photo has no mask: used whole
    out = extract_features(photos, tmp_path / "f.h5", sift(100), progress=False, masks=masks)
    with h5py.File(out) as f:
        assert f.attrs[ff.MASKS] == str(masks.resolve())
        for name in PHOTOS[:2]:
            assert f[name].attrs["mask_sha256"] == hashlib.sha256((masks / f"{name}.png").read_bytes()).hexdigest()
            assert f[name].attrs["mask_ignored"] == pytest.approx(1 / 3, abs=1e-3)
            assert "mask_refused" not in f[name].attrs
        assert not set(f[PHOTOS[2]].attrs) & set(ff.MASK_ATTRS)
    assert in_left_third(out, PHOTOS[2]) > 0


def test_without_masks_nothing_changes(photos, tmp_path):
    """No --masks: no mask attribute anywhere; an all-white mask (ignores nothing) gives the same arrays."""
    whole = extract_features(photos, tmp_path / "whole.h5", sift(100), progress=False)
    white = write_masks(photos, tmp_path / "white", make=lambda w, h: np.full((h, w), 255, np.uint8))
    masked = extract_features(photos, tmp_path / "white.h5", sift(100), progress=False, masks=white)
    with h5py.File(whole) as f:
        assert ff.MASKS not in f.attrs
        assert all(not set(f[key].attrs) & set(ff.MASK_ATTRS) for key in PHOTOS)
    a, b = arrays(whole), arrays(masked)
    assert all(np.array_equal(a[k][name], b[k][name]) for k in PHOTOS for name in a[k])
    with h5py.File(masked) as f:
        assert f[PHOTOS[0]].attrs["mask_ignored"] == 0.0  # recorded, though it ignores nothing


def test_resume_re_extracts_only_the_photo_whose_mask_changed(photos, tmp_path, monkeypatch):
    masks = write_masks(photos, tmp_path / "masks")
    out = tmp_path / "f.h5"
    extract_features(photos, out, sift(100), progress=False, masks=masks)
    before = arrays(out)
    global_path(out).write_bytes(b"global descriptors of the old features")  # the retrieval's cache
    calls = count_extractions(monkeypatch)
    extract_features(photos, out, sift(100), progress=False, masks=masks)
    assert calls == [] and global_path(out).is_file()  # unchanged masks: nothing redone, the cache kept

    right_half = lambda w, h: np.pad(np.zeros((h, w // 2), np.uint8), ((0, 0), (0, w - w // 2)), constant_values=255)
    write_masks(photos, masks, make=right_half, names=PHOTOS[1:2])
    extract_features(photos, out, sift(100), progress=False, masks=masks)
    assert len(calls) == 1
    after = arrays(out)
    assert not np.array_equal(after[PHOTOS[1]]["keypoints"], before[PHOTOS[1]]["keypoints"])
    assert all(np.array_equal(after[k]["keypoints"], before[k]["keypoints"]) for k in (PHOTOS[0], PHOTOS[2]))
    with h5py.File(out) as f:
        assert f[PHOTOS[1]].attrs["mask_ignored"] == pytest.approx(0.5, abs=1e-3)
    assert not global_path(out).exists()  # made from the old features: dropped, pairing makes it again

    (masks / f"{PHOTOS[2]}.png").unlink()  # a removed mask: that photo is extracted again, whole
    extract_features(photos, out, sift(100), progress=False, masks=masks)
    assert len(calls) == 2 and in_left_third(out, PHOTOS[2]) > 0
    extract_features(photos, out, sift(100), progress=False)  # no --masks at all: the masked photos, whole
    assert len(calls) == 4
    with h5py.File(out) as f:
        assert f.attrs[ff.MASKS] == "" and not any(set(f[k].attrs) & set(ff.MASK_ATTRS) for k in PHOTOS)


def test_a_masks_folder_without_any_mask_warns_once(photos, tmp_path, caplog):
    empty = tmp_path / "maks"  # a typo: the masks are elsewhere
    empty.mkdir()
    with caplog.at_level(logging.WARNING, logger="sekd"):
        out = extract_features(photos, tmp_path / "f.h5", sift(100), progress=False, masks=empty)
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1
    assert str(empty) in warnings[0] and str(empty / f"{PHOTOS[0]}.png") in warnings[0]
    assert in_left_third(out, PHOTOS[0]) > 0  # used whole


@pytest.mark.parametrize("content", [b"not a png", "zeros"], ids=["unreadable", "all-zero"])
def test_a_bad_mask_warns_and_the_photo_is_used_whole(photos, tmp_path, caplog, content):
    masks = write_masks(photos, tmp_path / "masks", names=PHOTOS[1:])
    bad = masks / f"{PHOTOS[0]}.png"
    if content == "zeros":
        cv2.imwrite(str(bad), np.zeros((2048, 3072), np.uint8))
    else:
        bad.write_bytes(content)
    whole = extract_features(photos, tmp_path / "whole.h5", sift(100), progress=False)
    with caplog.at_level(logging.WARNING, logger="sekd"):
        out = extract_features(photos, tmp_path / "f.h5", sift(100), progress=False, masks=masks)
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and str(bad) in warnings[0] and "used whole" in warnings[0]
    assert np.array_equal(ff.read_features(out, PHOTOS[0])["keypoints"], ff.read_features(whole, PHOTOS[0])["keypoints"])
    with h5py.File(out) as f:
        assert f[PHOTOS[0]].attrs["mask_sha256"] == hashlib.sha256(bad.read_bytes()).hexdigest()
        assert f[PHOTOS[0]].attrs["mask_ignored"] == 0.0 and "used whole" in f[PHOTOS[0]].attrs["mask_refused"]


def test_sekd_in_tiles_is_masked_alike(photos):
    """A photo too large for one forward pass runs in tiles (``model.tiling``): each tile sees its part of the mask."""
    from sekd_sfm.features import build_extractor
    from sekd_sfm.files.images import load_scaled

    extractor, _ = build_extractor(sekd_features(200))
    _, image, _, _ = load_scaled(photos / PHOTOS[0], RESIZE)
    mask = np.ones(image.shape, bool)
    mask[:, : image.shape[1] // 3] = False
    whole = extractor.extract(image, mask)["keypoints"]
    extractor.pixel_budget = 40_000  # tiles with a 72 px core
    tiled = extractor.extract(image, mask)["keypoints"]
    assert len(tiled) == len(whole) == 200 and (tiled[:, 0] < image.shape[1] // 3 - 0.5).sum() == 0
    assert len({tuple(k) for k in np.round(tiled, 3)} & {tuple(k) for k in np.round(whole, 3)}) >= 198


def test_mask_sizes(tmp_path):
    """A mask of another size is resized to the photo's; another aspect ratio is refused; resizing down keeps a
    pixel only if every pixel it covers is kept."""
    half = tmp_path / "half.png"
    cv2.imwrite(str(half), left_third(1536, 1024))
    mask = read_mask(half, (2048, 3072))
    assert mask.keep.shape == (2048, 3072) and not mask.refused
    assert mask.keep[:, 1023].sum() == 0 and mask.keep[:, 1025].all()
    assert read_mask(half, (3072, 2048)).refused  # a portrait photo: made for another one
    assert read_mask(tmp_path / "absent.png", (10, 10)).sha256 == ""
    keep = np.ones((4, 6), bool)
    keep[0, 2] = False
    assert scale_mask(keep, (2, 3)).tolist() == [[True, False, True], [True, True, True]]


def test_the_worker_takes_the_masks_folder(photos, tmp_path):
    """The worker's constructor arguments (what travels to Ray workers) include the masks folder, a plain str."""
    masks = write_masks(photos, tmp_path / "masks")
    worker = ExtractWorker(str(photos), sift(100), None, str(masks))
    (_, found, error), = worker([PHOTOS[0]])
    assert error == "" and "mask_sha256" in found
    assert (np.rint(found["keypoints"][:, 0]) < 3072 // 3).sum() == 0


def test_records_of_virtual_groups_are_read_from_their_shard(tmp_path):
    """``--ray-merge virtual``: the output's groups are virtual datasets; their mask record lives in the shard."""
    out = tmp_path / "f.h5"
    item = {"keypoints": np.zeros((3, 2), np.float32), "descriptors": np.zeros((3, 4), np.float32),
            "scores": np.zeros(3, np.float32), "image_size": np.array([8, 6], np.int32),
            "mask_sha256": np.array("ab" * 32), "mask_ignored": np.array(0.25)}
    shards.write_shard(out, [("a.jpg", item), ("b.jpg", {k: v for k, v in item.items() if not k.startswith("mask")})],
                       ff.write_image_group)
    with h5py.File(out, "w") as f:
        shards.link_shards(f, out, set(), shards.describe_all(out))
    assert ff.mask_records(out) == {"a.jpg": "ab" * 32, "b.jpg": ""}


def test_cli(photos, tmp_path):
    masks = write_masks(photos, tmp_path / "masks")
    result = CliRunner().invoke(sekd, ["extract", str(photos), "-o", str(tmp_path / "f.h5"), "--feature", "sift",
                                       "--max-keypoints", "100", "--resize-max", str(RESIZE), "--masks", str(masks),
                                       "--no-progress"])
    assert result.exit_code == 0, result.output
    assert in_left_third(tmp_path / "f.h5", PHOTOS[0]) == 0
    missing = CliRunner().invoke(sekd, ["extract", str(photos), "--masks", str(tmp_path / "nowhere")])
    assert missing.exit_code == 2 and "does not exist" in missing.output
    (photos / "masks").mkdir()
    inside = CliRunner().invoke(sekd, ["extract", str(photos), "--masks", str(photos / "masks")])
    assert inside.exit_code == 1 and "inside the image folder" in inside.output
    for command in ("extract", "reconstruct"):
        assert "--masks" in CliRunner().invoke(sekd, [command, "--help"]).output


def test_stats_record_the_masks_folder():
    from sekd_sfm.pipelines.config import ReconstructConfig
    from sekd_sfm.pipelines.config import config_dict as _config_dict

    assert _config_dict(ReconstructConfig())["masks"] is None
    assert _config_dict(ReconstructConfig(masks="/data/masks"))["masks"] == "/data/masks"
