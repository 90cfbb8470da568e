"""Labelling steps: detector averaging (a), descriptor reliability (c), random keypoints (a0), NMS, storage."""
import dataclasses
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from sekd_sfm.train.config import TrainConfig
from sekd_sfm.train.distributed import Context
from sekd_sfm.train.labels import (
    Labels,
    average_detections,
    fused_reliability,
    keep_with_floor,
    label_images,
    label_one,
    random_keypoints,
    reliability_scale,
    select_keypoints,
    weights_sha256,
)
from sekd_sfm.train.model import (
    BlockDiagonalConvTranspose2d,
    new_network,
    use_fast_deconv,
)

CFG = TrainConfig()


def identity_grids(m: int, h: int, w: int) -> torch.Tensor:
    theta = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]]).expand(m, 2, 3)
    return F.affine_grid(theta, [m, 1, h, w], align_corners=False)


def one_unique_location(h=32, w=32, at=(16, 16)):
    """Every pixel holds e1 except one holding e2, in the target and in one identical view."""
    target = torch.zeros(4, h, w)
    target[0] = 1
    target[:, at[0], at[1]] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    return target, target[None].clone()


def reliability_direct(target, views, grids, cfg):
    """docs/method.md "Training" transcribed with grid_sample: the oracle for the fast implementation."""
    h, w = target.shape[1:]
    unit = torch.tensor([2.0 / w, 2.0 / h])
    reach = cfg.rel_radius * cfg.rel_stride
    valid = ((grids.abs() + reach * unit) < 1).all(-1).float()

    def dist(dx, dy):
        grid = grids + torch.tensor([dx, dy]) * cfg.rel_stride * unit
        g = F.normalize(F.grid_sample(views, grid, mode="bilinear", padding_mode="zeros", align_corners=False), dim=1)
        return torch.sqrt(2 - 2 * (g * target[None]).sum(1) + cfg.rel_dist_eps)

    offsets = [(dx, dy) for dy in range(-3, 4) for dx in range(-3, 4) if (dx, dy) != (0, 0)]
    d_dis = torch.stack([dist(dx, dy) for dx, dy in offsets]).amin(0)
    r = valid * d_dis / (dist(0, 0) + cfg.rel_rep_eps)
    return r.sum(0) / (valid.sum(0) + cfg.rel_count_eps)


def test_unique_location_has_the_highest_reliability():
    target, views = one_unique_location()
    r = reliability_scale(target, views, identity_grids(1, 32, 32), CFG)
    peak = math.sqrt(2 + 1e-4) / (math.sqrt(1e-4) + 0.03) / 1.01   # distinct from all 48 neighbours
    flat = math.sqrt(1e-4) / (math.sqrt(1e-4) + 0.03) / 1.01         # neighbours identical to it
    assert r[16, 16].item() == pytest.approx(peak, rel=1e-4)
    assert r[10, 20].item() == pytest.approx(flat, rel=1e-4)
    assert torch.nonzero(r == r.max()).tolist() == [[16, 16]]
    # Valid only where the +-6 px lattice stays inside: columns/rows 6..25 of 32.
    assert r[5, 16] == 0 and r[16, 26] == 0 and r[6, 6] > 0 and r[25, 25] > 0


def test_reliability_ablations_by_hand():
    target, views = one_unique_location()
    grids = identity_grids(1, 32, 32)
    no_rep = reliability_scale(target, views, grids, dataclasses.replace(CFG, no_desc_rep=True))
    assert no_rep[16, 16].item() == pytest.approx(math.sqrt(2 + 1e-4) / 1.03 / 1.01, rel=1e-4)
    no_dis = reliability_scale(target, views, grids, dataclasses.replace(CFG, no_desc_dis=True))
    # Without distinctness every repeatable pixel scores 1 / (0.01 + 0.03): no peak at the unique one.
    assert torch.allclose(no_dis[6:26, 6:26], torch.full((20, 20), 1 / 0.04 / 1.01), rtol=1e-4)


def test_repeatability_lowers_reliability():
    # The unique pixel becomes unrepeatable when the view holds e3 there instead of e2.
    target, views = one_unique_location()
    views[0, :, 16, 16] = torch.tensor([0.0, 0.0, 1.0, 0.0])
    r = reliability_scale(target, views, identity_grids(1, 32, 32), CFG)
    assert r[16, 16].item() == pytest.approx(math.sqrt(2 + 1e-4) / (math.sqrt(2 + 1e-4) + 0.03) / 1.01, rel=1e-4)


@pytest.mark.parametrize("method", ["tiled", "sampled"])
def test_reliability_implementations_equal_the_transcription(method):
    # tiled: the CPU algorithm (matrix products + Gram maps); sampled: grid_sample per pixel (GPU).
    torch.manual_seed(0)
    thetas = torch.tensor([[[0.9, 0.3, 0.01], [-0.1, 1.1, 0.0]], [[1.2, 0.0, 0.02], [0.3, 0.8, -0.03]]])
    for c, h, w in ((16, 40, 56), (8, 23, 37)):
        views = torch.randn(2, c, h, w)
        target = F.normalize(torch.randn(c, h, w), dim=0)
        grids = F.affine_grid(thetas, [2, 1, h, w], align_corners=False)
        got = reliability_scale(target, views, grids, CFG, method=method)
        assert torch.allclose(got, reliability_direct(target, views, grids, CFG), atol=1e-4)


def test_fused_map_averages_fine_and_upsampled_coarse():
    torch.manual_seed(1)
    desc, feat = torch.randn(3, 8, 12, 16), torch.randn(3, 4, 48, 64)
    thetas = torch.tensor([[[1.0, 0.1, 0.0], [0.0, 0.9, 0.02]], [[0.8, 0.0, 0.0], [0.2, 1.1, 0.0]]])
    grids = F.affine_grid(thetas, [2, 1, 48, 64], align_corners=False)
    fused = fused_reliability(desc, feat, grids, CFG)
    coarse_grids = F.interpolate(grids.permute(0, 3, 1, 2), size=(12, 16), mode="bilinear",
                                 align_corners=False).permute(0, 2, 3, 1)
    coarse = reliability_direct(F.normalize(desc[0], dim=0), desc[1:], coarse_grids, CFG)
    fine = reliability_direct(F.normalize(feat[0], dim=0), feat[1:], grids, CFG)
    up = F.interpolate(coarse[None, None], size=(48, 64), mode="bilinear", align_corners=False)[0, 0]
    assert torch.allclose(fused, 0.5 * (fine + up), atol=1e-4)


def test_detector_average_by_hand():
    prob = torch.stack([torch.full((8, 8), v) for v in (0.2, 0.5, 0.8)])
    pbar = average_detections(prob, identity_grids(2, 8, 8), band=2)
    assert torch.allclose(pbar[2:6, 2:6], torch.full((4, 4), 0.5))   # (0.2 + 0.5 + 0.8) / 3
    assert torch.allclose(pbar[0], torch.full((8,), 0.2))           # band: the target view only


def test_select_keypoints_nms_threshold_cap_and_border():
    score = torch.zeros(20, 20)
    score[10, 10], score[10, 12], score[5, 15], score[1, 10], score[15, 4] = 0.9, 0.8, 0.7, 0.95, 0.3
    xy, scores = select_keypoints(score, threshold=0.5, radius=3, max_keypoints=10, border=3)
    # (12,10) is suppressed by (10,10); (10,1) lies in the border; (4,15) is below the threshold.
    assert xy.tolist() == [[10, 10], [15, 5]] and scores.tolist() == pytest.approx([0.9, 0.7])
    xy, _ = select_keypoints(score, threshold=0.5, radius=3, max_keypoints=2, border=3)
    assert xy.tolist() == [[10, 10]]  # the cap keeps the 2 best (one in the border), then the border goes


def test_random_keypoints_in_range_and_unique():
    xy = random_keypoints(10, 20, 500, np.random.default_rng(0))
    assert len(np.unique(xy, axis=0)) == len(xy) and len(xy) < 200  # 200 pixels: duplicates merged
    assert xy[:, 0].max() < 20 and xy[:, 1].max() < 10 and xy.min() >= 0


def test_label_one_runs_each_kind_on_a_network():
    torch.set_num_threads(1)
    net = use_fast_deconv(new_network(0)).eval()
    rgb = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    cfg = dataclasses.replace(CFG, num_warps=2, border_band=4, det_threshold=0.0, rel_threshold=0.0)
    for kind in ("a0", "a", "c"):
        xy, scores, score = label_one(net, rgb, np.random.default_rng(1), kind, cfg, torch.device("cpu"))
        assert score.shape == (48, 64) and len(xy) == len(scores) > 0
        assert torch.allclose(score[xy[:, 1], xy[:, 0]], torch.from_numpy(scores))


def test_labels_round_trip(tmp_path):
    labels = Labels("c", 2)
    labels.keypoints = {3: np.array([[1, 2], [3, 4]], np.int32), 0: np.zeros((0, 2), np.int32)}
    labels.scores = {3: np.array([0.5, 0.25], np.float32), 0: np.zeros(0, np.float32)}
    labels.sizes = {3: (10, 20), 0: (10, 30)}
    labels.save(tmp_path / "l.npz")
    back = Labels.load(tmp_path / "l.npz")
    assert back.kind == "c" and back.round_index == 2 and back.sizes == labels.sizes
    assert np.array_equal(back.keypoints[3], labels.keypoints[3]) and back.keypoints[0].shape == (0, 2)
    assert back.bg_weight == pytest.approx(1.0 / (250 - 1.0))  # mean 1 keypoint over mean 250 pixels


def test_block_diagonal_deconv_matches_grouped():
    torch.manual_seed(0)
    grouped = torch.nn.ConvTranspose2d(16, 8, 3, stride=2, padding=1, output_padding=1, groups=8)
    fast = BlockDiagonalConvTranspose2d(16, 8, 3, stride=2, padding=1, output_padding=1, groups=8)
    fast.load_state_dict(grouped.state_dict())
    x = torch.randn(2, 16, 5, 6, requires_grad=True)
    y1, y2 = grouped(x), fast(x)
    assert torch.allclose(y1, y2, atol=1e-6)
    y1.square().sum().backward()
    g1 = grouped.weight.grad.clone()
    y2.square().sum().backward()
    assert torch.allclose(g1, fast.weight.grad, atol=1e-5)


def test_no_affine_uses_the_target_view_in_a_and_one_warp_in_c(monkeypatch):
    from sekd_sfm.train import labels as labels_module

    seen = []
    original = labels_module.forward_views

    def counting(net, views, chunk, device):
        seen.append(views.shape[0])
        return original(net, views, chunk, device)

    monkeypatch.setattr(labels_module, "forward_views", counting)
    net = new_network(0).eval()
    rgb = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    for no_affine in (False, True):
        cfg = dataclasses.replace(CFG, num_warps=3, no_affine=no_affine)
        for kind in ("a", "c"):
            label_one(net, rgb, np.random.default_rng(1), kind, cfg, torch.device("cpu"))
    assert seen == [4, 4, 1, 2]  # target + m warps; no_affine: target only (a), target + 1 warp (c)


def _candidates() -> Labels:
    labels = Labels("c", 1)
    labels.scores = {0: np.array([0.9, 0.5, 0.2], np.float32), 1: np.array([0.95, 0.3], np.float32)}
    labels.keypoints = {i: np.arange(2 * len(s), dtype=np.int32).reshape(-1, 2) for i, s in labels.scores.items()}
    return labels


@pytest.mark.parametrize("min_mean, threshold, kept", [
    (0, 0.85, {0: [0.9], 1: [0.95]}),              # no floor: the fixed threshold (strictly above)
    (1, 0.85, {0: [0.9], 1: [0.95]}),              # 2 above 0.85 already reach 1 per image
    (2, 0.3, {0: [0.9, 0.5], 1: [0.95, 0.3]}),     # 4 needed: lowered to the 4th best score
    (10, 0.2, {0: [0.9, 0.5, 0.2], 1: [0.95, 0.3]}),  # more than there are: every candidate
])
def test_reliability_threshold_is_lowered_to_keep_the_floor(min_mean, threshold, kept):
    labels = _candidates()
    keep_with_floor(labels, 0.85, min_mean)
    assert labels.threshold == pytest.approx(threshold)
    assert {i: s.tolist() for i, s in labels.scores.items()} == {i: pytest.approx(v) for i, v in kept.items()}
    assert [len(k) for k in labels.keypoints.values()] == [len(v) for v in kept.values()]


def test_threshold_floor_on_no_candidates():
    labels = Labels("c", 0)
    keep_with_floor(labels, 0.85, 100)
    assert labels.threshold == 0.85 and labels.mean_keypoints == 0.0


class CountedImages:
    """``TrainImages`` stand-in: ``count`` random 48 x 64 photos; records the reads; ``KeyboardInterrupt``
    on read number ``stop`` (0-based), as a Ctrl-C in the middle of a labelling step."""

    def __init__(self, count: int, stop: int | None = None):
        self.count, self.stop, self.reads = count, stop, []

    def __len__(self) -> int:
        return self.count

    def rgb(self, index: int) -> np.ndarray:
        if len(self.reads) == self.stop:
            raise KeyboardInterrupt
        self.reads.append(index)
        return np.random.default_rng(index).integers(0, 255, (48, 64, 3), dtype=np.uint8)


LABEL_CFG = dataclasses.replace(CFG, num_warps=2, border_band=4, rel_threshold=0.0, rel_min_keypoints=0)


def _label(net, images, parts=None, kind="c"):
    return label_images(net, images, list(range(images.count)), kind, 1, LABEL_CFG, Context(), progress=False,
                        parts=parts, parts_every=0.0)


def test_interrupted_labelling_resumes_from_the_saved_images(tmp_path):
    torch.set_num_threads(1)
    net = use_fast_deconv(new_network(0)).eval()
    whole = _label(net, CountedImages(5))
    parts = tmp_path / "r1_c.parts"
    with pytest.raises(KeyboardInterrupt):
        _label(net, CountedImages(5, stop=3), parts)
    assert sorted(p.name for p in parts.iterdir()) == ["p0_0000000.npz", "p0_0000001.npz", "p0_0000002.npz"]
    images = CountedImages(5)
    resumed = _label(net, images, parts)
    assert images.reads == [3, 4]  # the three saved images are not labelled again
    assert resumed.network == whole.network == weights_sha256(net)
    assert resumed.sizes == whole.sizes and sorted(resumed.keypoints) == [0, 1, 2, 3, 4]
    for i in range(5):  # same process, same threads: bitwise the uninterrupted labels
        assert np.array_equal(resumed.keypoints[i], whole.keypoints[i])
        assert np.array_equal(resumed.scores[i], whole.scores[i])


def test_saved_images_of_other_weights_or_steps_are_labelled_again(tmp_path, caplog):
    torch.set_num_threads(1)
    net = use_fast_deconv(new_network(0)).eval()
    other = use_fast_deconv(new_network(1)).eval()
    for network, kind in ((other, "c"), (net, "a")):
        parts = tmp_path / f"{kind}.parts"
        with pytest.raises(KeyboardInterrupt):
            _label(net, CountedImages(3, stop=2), parts)  # images 0, 1 saved by step (c) of `net`
        images = CountedImages(3)
        _label(network, images, parts, kind)
        assert images.reads == [0, 1, 2]
    assert caplog.text.count("labelled by other weights or another step") == 4
    (tmp_path / "a.parts" / "p0_0000000.npz").write_bytes(b"not a zip file")  # e.g. a disk error
    images = CountedImages(3)
    _label(net, images, tmp_path / "a.parts", "a")
    assert images.reads == [0] and "unreadable" in caplog.text


def test_weights_sha256_sees_a_changed_parameter():
    net = new_network(0)
    before = weights_sha256(net)
    assert weights_sha256(new_network(0)) == before and len(before) == 64
    with torch.no_grad():
        next(net.parameters()).view(-1)[0] += 1e-6
    assert weights_sha256(net) != before
