"""Training data and configuration: affine warps, correspondences, label warps, pairs, jitter, YAML."""
import dataclasses

import numpy as np
import pytest
import torch

from sekd_sfm.errors import SekdError
from sekd_sfm.train.config import (
    SCHEDULES,
    TrainConfig,
    coerce,
    parse_set,
    resolve_config,
    schedule_config,
)
from sekd_sfm.train.data import (
    PairDataset,
    affine_grid,
    color_jitter,
    correspondences,
    invert_affine,
    labels_forward,
    labels_inverse,
    make_pair,
    random_affine,
    random_warp,
    rng_for,
    sample,
    subset_indices,
    to_gray,
    warp_grid,
)

IDENTITY = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
#: 30 degrees rotation, scales 1.2 / 0.9, a small translation (normalised units).
THETA = np.array([[1.2 * np.cos(0.5), -0.9 * np.sin(0.5), 0.03], [1.2 * np.sin(0.5), 0.9 * np.cos(0.5), -0.02]])


def no_jitter(**kw) -> TrainConfig:
    return dataclasses.replace(TrainConfig(), brightness=[1.0, 1.0], contrast=[1.0, 1.0], saturation=[1.0, 1.0],
                               hue=[0.0, 0.0], **kw)


def blob(height: int, width: int, x: float, y: float, sigma: float = 1.5) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                            indexing="ij")
    return torch.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma ** 2))


def test_identity_correspondences_are_the_pixels_themselves():
    corr = correspondences(IDENTITY, 6, 8)
    rows, cols = torch.meshgrid(torch.arange(6), torch.arange(8), indexing="ij")
    assert torch.equal(corr, torch.stack([rows, cols], dim=-1))


def test_one_pixel_translation():
    # theta shifts sampling one pixel right: I^(q) = I(q + 1 px), so target pixel c sits at c - 1.
    theta = np.array([[1.0, 0.0, 2.0 / 8], [0.0, 1.0, 0.0]])
    corr = correspondences(theta, 4, 8)
    assert corr[2, 5].tolist() == [2, 4]
    assert corr[1, 0].tolist() == [-1, -1]  # falls off the left edge
    image = torch.arange(32, dtype=torch.float32).view(1, 4, 8)
    warped = sample(image, affine_grid(theta, 4, 8))
    assert torch.allclose(warped[0, :, :7], image[0, :, 1:])


def test_affine_warp_of_image_and_keypoint_agree():
    h, w, x, y = 64, 80, 30, 25
    warped = sample(blob(h, w, x, y)[None], affine_grid(THETA, h, w))[0]
    peak = torch.nonzero(warped == warped.max())[0]
    corr = correspondences(THETA, h, w)
    assert (peak - corr[y, x]).abs().max() <= 1  # the keypoint moves where the image content moves
    label = labels_forward(np.array([[x, y]]), corr)
    assert label.sum() == 1 and label[tuple(corr[y, x])] == 1


def test_inverse_label_warp_is_the_codes_defect():
    # The authors' nearest sampling applies theta^-1 instead of theta: for a pure translation
    # it moves keypoints the wrong way.
    theta = np.array([[1.0, 0.0, 4.0 / 16], [0.0, 1.0, 0.0]])  # two pixels
    label0 = torch.zeros(8, 16)
    label0[4, 8] = 1
    forward = labels_forward(np.array([[8, 4]]), correspondences(theta, 8, 16))
    assert torch.nonzero(forward).tolist() == [[4, 6]]
    assert torch.nonzero(labels_inverse(label0, theta)).tolist() == [[4, 10]]


def test_invert_affine_round_trip():
    composed = np.vstack([THETA, [0, 0, 1]]) @ np.vstack([invert_affine(THETA), [0, 0, 1]])
    assert np.allclose(composed, np.eye(3))


def test_random_affine_parameters_follow_the_spec():
    cfg = dataclasses.replace(TrainConfig(), rotation_deg=[30.0, 30.0], shear_deg=[0.0, 0.0], scale=[2.0, 2.0],
                              translation=[0.01, 0.01])
    theta = random_affine(np.random.default_rng(0), cfg)
    a = np.deg2rad(30)
    assert np.allclose(theta, [[2 * np.cos(a), -2 * np.sin(a), 0.01], [2 * np.sin(a), 2 * np.cos(a), 0.01]])


#: THETA with projective terms g = 0.1, h = -0.05.
HOMOGRAPHY = np.vstack([THETA, [0.1, -0.05, 1.0]])


def test_homography_grid_is_hand_computed():
    # 2 x 2 image: pixel centres at normalised (-0.5, -0.5) ... (0.5, 0.5).
    grid = warp_grid(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.0, 1.0]]), 2, 2)
    # x' = x / (0.5 x + 1), y' = y / (0.5 x + 1)
    assert torch.allclose(grid[0, 0], torch.tensor([-0.5 / 0.75, -0.5 / 0.75]))
    assert torch.allclose(grid[1, 1], torch.tensor([0.5 / 1.25, 0.5 / 1.25]))
    assert torch.allclose(warp_grid(THETA, 5, 7), affine_grid(THETA, 5, 7))  # 2 x 3 stays affine


def test_homography_beyond_its_vanishing_line_samples_nothing():
    grid = warp_grid(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [2.0, 0.0, 1.0]]), 2, 4)
    # x = -0.75: denominator 2 x + 1 = -0.5 < 0 -> outside; x = 0.75: inside.
    assert (grid[:, 0] == 2.0).all() and (grid[:, 3].abs() < 1).all()


def test_projective_warp_of_image_and_keypoint_agree():
    h, w, x, y = 64, 80, 30, 25
    warped = sample(blob(h, w, x, y)[None], warp_grid(HOMOGRAPHY, h, w))[0]
    peak = torch.nonzero(warped == warped.max())[0]
    corr = correspondences(HOMOGRAPHY, h, w)
    assert (peak - corr[y, x]).abs().max() <= 1
    label = labels_forward(np.array([[x, y]]), corr)
    assert label.sum() == 1 and label[tuple(corr[y, x])] == 1


def test_random_warp_without_perspective_is_the_affine_draw():
    cfg = TrainConfig()
    a, b = np.random.default_rng(3), np.random.default_rng(3)
    assert np.array_equal(random_warp(a, cfg), random_affine(b, cfg))
    assert a.uniform() == b.uniform()  # nothing more drawn: runs without perspective are unchanged
    theta = random_warp(np.random.default_rng(3), dataclasses.replace(cfg, perspective=0.2))
    assert theta.shape == (3, 3) and np.abs(theta[2, :2]).max() <= 0.2 and theta[2, 2] == 1
    assert np.array_equal(theta[:2], random_affine(np.random.default_rng(3), cfg))


def test_pair_labels_and_correspondences_agree():
    cfg = no_jitter(crop_height=48, crop_width=64)
    rgb = np.random.default_rng(0).integers(0, 255, (64, 80, 3), dtype=np.uint8)
    keypoints = np.array([[x, y] for x in range(8, 72, 6) for y in range(8, 56, 6)], np.int32)
    pair = make_pair(rgb, keypoints, np.random.default_rng(3), cfg)
    assert pair["image0"].shape == (1, 48, 64) and pair["corr"].shape == (48, 64, 2)
    label0, label1, corr = pair["label0"], pair["label1"], pair["corr"]
    kp = torch.nonzero(label0 > 0)
    target = corr[kp[:, 0], kp[:, 1]]
    target = target[target[:, 0] >= 0]
    assert len(target) > 5
    assert (label1[target[:, 0], target[:, 1]] == 1).all()  # every mapped keypoint is labelled in view 1
    assert corr.max() < 64 and ((corr >= 0).all(-1) | (corr == -1).all(-1)).all()


def test_pair_pads_small_images():
    cfg = no_jitter(crop_height=64, crop_width=64)
    rgb = np.full((32, 48, 3), 200, np.uint8)
    pair = make_pair(rgb, np.array([[10, 10]], np.int32), np.random.default_rng(0), cfg)
    assert pair["image0"].shape == (1, 64, 64)
    assert (pair["image0"][0, 32:] == 0).all() and (pair["image0"][0, :, 48:] == 0).all()
    assert (pair["corr"][32:] == -1).all() and (pair["corr"][:, 48:] == -1).all()
    assert pair["image0"][0, 5, 5].item() == pytest.approx(200 / 255, abs=1e-6)


def test_pairs_are_deterministic_per_seed_round_step_epoch_image():
    class Images:
        def rgb(self, i):
            return np.random.default_rng(i).integers(0, 255, (40, 48, 3), dtype=np.uint8)

    cfg = dataclasses.replace(TrainConfig(), crop_height=32, crop_width=32)
    kps = {0: np.array([[5, 5]], np.int32), 1: np.array([[9, 9]], np.int32)}
    a = PairDataset(Images(), [0, 1], kps, cfg, 1, "b", 2)[1]
    b = PairDataset(Images(), [1, 0], kps, cfg, 1, "b", 2)[0]  # another order: same pair for image 1
    c = PairDataset(Images(), [0, 1], kps, cfg, 1, "b", 3)[1]  # next epoch: fresh draw
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a["image1"], c["image1"])


def test_color_jitter_brightness_truncates_like_torchvision():
    cfg = dataclasses.replace(no_jitter(), brightness=[1.5, 1.5])
    rgb = torch.tensor([[[10.0, 100.0, 200.0]]]).expand(3, 1, 3).clone()
    out = color_jitter(rgb, np.random.default_rng(0), cfg)
    assert out[0, 0].tolist() == [15.0, 150.0, 255.0]


def test_color_jitter_identity_and_grayscale():
    rgb = torch.tensor([[[255.0]], [[0.0]], [[0.0]]])
    assert torch.equal(color_jitter(rgb, np.random.default_rng(0), no_jitter()), rgb)
    assert to_gray(rgb).item() == pytest.approx(0.299)


def test_subsets_alternate_and_cover_everything():
    assert subset_indices(7, 2, 0) == [0, 2, 4, 6] and subset_indices(7, 2, 3) == [1, 3, 5]
    assert sorted(subset_indices(10, 5, 1) + subset_indices(10, 5, 2)) == [1, 2, 6, 7]


def test_rng_streams_differ_by_every_key():
    draws = {rng_for(*key).random() for key in [(0, 0, "b", 0, 0), (1, 0, "b", 0, 0), (0, 1, "b", 0, 0),
                                                 (0, 0, "d", 0, 0), (0, 0, "b", 1, 0), (0, 0, "b", 0, 1)]}
    assert len(draws) == 6


# --- configuration -------------------------------------------------------------------------------

def test_schedules_load_and_differ():
    configs = {name: schedule_config(name) for name in SCHEDULES}
    assert configs["paper"].crop_height == 512 and configs["paper"].num_warps == 12
    assert configs["cpu"].crop_height == 192 and configs["cpu"].rounds == 5
    assert configs["tiny"].rounds == 2


def test_overrides_and_yaml_file(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("schedule: tiny\nlr: 1e-4\nno_affine: yes\nval_sets: [a, b]\n")
    cfg = resolve_config(None, path, parse_set(["rounds=3", "scale=[0.5, 2]", "desc_loss=margin"]))
    assert cfg.schedule == "tiny" and cfg.lr == 1e-4 and cfg.no_affine is True  # "1e-4" is a string in YAML 1.1
    assert cfg.rounds == 3 and cfg.scale == [0.5, 2.0] and cfg.val_sets == ["a", "b"]


@pytest.mark.parametrize("items,message", [
    (["bogus=1"], "unknown config key"),
    (["rounds=two"], "cannot use"),
    (["desc_loss=hinge"], "not one of"),
    (["crop_height=30"], "multiple of 4"),
    (["scale=[2, 1]"], "range"),
    (["lr"], "KEY=VALUE"),
])
def test_bad_settings_are_one_line_errors(items, message):
    with pytest.raises(SekdError, match=message) as info:
        resolve_config("tiny", None, parse_set(items))
    assert "\n" not in str(info.value)


def test_coerce_rejects_fractional_int_and_accepts_bool_words():
    assert coerce("round0_random", "on") is True and coerce("rounds", 3.0) == 3
    with pytest.raises(SekdError):
        coerce("rounds", 2.5)
