"""Training losses on small tensors with hand-computed answers (docs/method.md "Training")."""
import math

import pytest
import torch

from sekd_sfm.train.losses import (
    focal_loss,
    hardest_negatives,
    pairwise_distances,
    preservation_mse,
    repeatability_paper,
    repeatability_weighted,
    spatial_neighbours,
    spread_out,
    triplet_loss,
)
from sekd_sfm.train.steps import matched_keypoints, sample_upsampled

# Anchors a_i and their matches p_i (unit vectors in 2-D):
#   d = [[0,        sqrt(.8), sqrt(.8) ],
#        [sqrt(2),  sqrt(.4), sqrt(3.6)],
#        [2,        sqrt(3.2), sqrt(3.2)]]
A = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
P = torch.tensor([[1.0, 0.0], [0.6, 0.8], [0.6, -0.8]])
R8, R4, R32 = math.sqrt(0.8), math.sqrt(0.4), math.sqrt(3.2)


def test_pairwise_distances_by_hand():
    d = pairwise_distances(A, P)
    expected = torch.tensor([[0.0, R8, R8], [math.sqrt(2), R4, math.sqrt(3.6)], [2.0, R32, R32]])
    assert torch.allclose(d, expected, atol=2e-6)


def test_hardest_negative_uses_rows_and_columns():
    # Anchor 1's hardest negative is d_01 = sqrt(.8), found only in its *column* (anchor swap);
    # its row alone would give sqrt(2). Anchor 2's comes from column 2 (d_02).
    neg = hardest_negatives(pairwise_distances(A, P))
    assert torch.allclose(neg, torch.tensor([R8, R8, R8]), atol=2e-6)


def test_hardest_negative_skips_diagonal_and_near_duplicates():
    d = torch.tensor([[0.5, 0.005, 0.9], [0.7, 0.2, 0.3], [0.4, 0.6, 0.1]])
    # 0.005 < 0.008 counts as the same point; rows give (0.9, 0.3, 0.4), columns (0.4, 0.6, 0.3).
    assert torch.allclose(hardest_negatives(d), torch.tensor([0.4, 0.3, 0.3]))


def test_hardest_negative_skips_excluded_pairs():
    d = torch.tensor([[0.5, 0.05, 0.9], [0.7, 0.2, 0.3], [0.4, 0.6, 0.1]])
    exclude = torch.tensor([[False, True, False], [True, False, False], [False, False, False]])
    # Without 0-1 and 1-0: rows (0.9, 0.3, 0.4), columns (0.4, 0.6, 0.3).
    assert torch.allclose(hardest_negatives(d, exclude=exclude), torch.tensor([0.4, 0.3, 0.3]))
    assert torch.allclose(hardest_negatives(d), torch.tensor([0.05, 0.05, 0.3]))


def test_spatial_neighbours_by_hand():
    points = torch.tensor([[0, 0], [3, 4], [10, 0]])  # distances 5, 10, sqrt(85)
    assert spatial_neighbours(points, 5.5).tolist() == [[False, True, False], [True, False, False],
                                                        [False, False, False]]
    assert not spatial_neighbours(points, 5.0).any()  # strictly closer than the radius
    assert not spatial_neighbours(points, 0.0).any() and spatial_neighbours(points[:0], 3.0).shape == (0, 0)


def test_ratio_form_averages_only_ambiguous_pairs():
    # pos / neg = (0, 0.707, 2.0): only pair 2 exceeds 0.85 -> loss = sqrt(3.2) - sqrt(.8) = sqrt(.8).
    loss = triplet_loss(A, P, "ratio")
    assert loss.item() == pytest.approx(R8, abs=1e-6)


def test_margin_form_mean_and_nonzero_variants():
    terms = [0.0, R4 - R8 + 0.8, R32 - R8 + 0.8]  # first term is negative before the hinge
    assert triplet_loss(A, P, "margin", normalise="count").item() == pytest.approx(sum(terms) / 3, abs=1e-6)
    assert triplet_loss(A, P, "margin", normalise="nonzero").item() == pytest.approx(sum(terms) / 2, abs=1e-6)


def test_triplet_gradient_finite_for_identical_descriptors():
    a = torch.tensor([[1.0, 0.0], [0.0, 1.0]], requires_grad=True)
    loss = triplet_loss(a, a.detach().clone(), "margin")
    loss.backward()
    assert torch.isfinite(a.grad).all()


def test_spread_out_by_hand():
    a = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    # Off-diagonal dots a0.p1 = 1, a1.p0 = 0: mean 0.5, mean square 0.5 = 1 / C -> 0.25 + 0.
    assert spread_out(a, torch.tensor([[1.0, 0.0], [1.0, 0.0]])).item() == pytest.approx(0.25)
    assert spread_out(a, a).item() == 0.0  # orthogonal: perfectly spread
    same = torch.tensor([[0.6, 0.8]] * 3)
    assert spread_out(same, same).item() == pytest.approx(1.0 + (1.0 - 0.5))  # collapsed: mean 1, square 1
    assert spread_out(a[:1], a[:1]).item() == 0.0  # fewer than 2 rows: no pairs


def test_spread_out_pushes_a_common_component_away():
    torch.manual_seed(0)
    base = torch.nn.functional.normalize(torch.randn(50, 16), dim=1)
    common = torch.nn.Parameter(torch.zeros(16))
    d = torch.nn.functional.normalize(base + 3.0 * torch.ones(16) / 4.0 + common, dim=1)
    spread_out(d, d).backward()
    # Gradient descent moves the shared offset against the all-ones direction it came from.
    assert (-common.grad @ torch.ones(16)).item() < 0


def test_focal_loss_by_hand():
    # Pixel 0: keypoint, p1 = 0.8; pixel 1: background, p0 = 0.5; background weight 0.25.
    logits = torch.tensor([[0.0, 0.0], [math.log(4.0), 0.0]])[None, :, None, :]  # 1 x 2 x 1 x 2
    labels = torch.tensor([[[1.0, 0.0]]])
    for gamma in (1.0, 2.0):
        expected = (0.2 ** gamma * -math.log(0.8) + 0.25 * 0.5 ** gamma * -math.log(0.5)) / (2 * 2)
        assert focal_loss(logits, labels, 0.25, gamma).item() == pytest.approx(expected, rel=1e-6)


def test_focal_loss_clamps_certain_predictions():
    # A confidently wrong pixel: softmax gives exactly 0 for the label, clamped to 1e-7.
    logits = torch.tensor([[200.0], [-200.0]])[None, :, None, :]
    value = focal_loss(logits, torch.ones(1, 1, 1), 1.0, 1.0)
    assert value.item() == pytest.approx((1 - 1e-7) * -math.log(1e-7) / 2, rel=1e-5)


def test_repeatability_weighted_and_paper_forms_by_hand():
    u = torch.tensor([[0.5, 0.5], [0.9, 0.1]])
    v = torch.tensor([[0.5, 0.5], [0.6, 0.4]])
    kl_vu = 0.6 * math.log(0.6 / 0.9) + 0.4 * math.log(0.4 / 0.1)
    kl_uv = 0.9 * math.log(0.9 / 0.6) + 0.1 * math.log(0.1 / 0.4)
    # Pixel 0 agrees (no divergence); pixel 1 has weight 0.5 (0.1 + 0.4); mean over 2 x 2 elements.
    assert repeatability_weighted(u, v).item() == pytest.approx(0.5 * 0.25 * (kl_vu + kl_uv) / 4, rel=1e-5)
    assert repeatability_paper(u, v).item() == pytest.approx(0.5 * (kl_vu + kl_uv), rel=1e-5)


def test_repeatability_weight_is_detached():
    u = torch.tensor([[0.7, 0.3]], requires_grad=True)
    v = torch.tensor([[0.7, 0.3]])
    repeatability_weighted(u, v).backward()
    assert torch.allclose(u.grad, torch.zeros_like(u), atol=1e-6)  # zero divergence, weight gets no gradient


def test_preservation_mse_is_mean_over_views():
    new = (torch.ones(2, 3), torch.zeros(2, 3))
    old = (torch.zeros(2, 3), torch.zeros(2, 3))
    assert preservation_mse(new, old).item() == pytest.approx(0.5)


def test_upsampled_descriptor_lookup_equals_interpolation():
    torch.manual_seed(0)
    desc = torch.randn(8, 5, 6)
    full = torch.nn.functional.interpolate(desc[None], size=(20, 24), mode="bilinear", align_corners=False)[0]
    full = torch.nn.functional.normalize(full, dim=0)
    rows, cols = torch.tensor([0, 3, 19, 10, 7]), torch.tensor([0, 23, 5, 11, 0])
    got = sample_upsampled(desc, rows, cols, 20, 24)
    assert torch.allclose(got, full[:, rows, cols].t(), atol=1e-6)


def test_matched_keypoints_keeps_labels_with_correspondence():
    label = torch.zeros(3, 3)
    label[0, 0] = label[1, 2] = label[2, 2] = 1
    corr = torch.full((3, 3, 2), -1, dtype=torch.long)
    corr[0, 0] = torch.tensor([2, 1])
    corr[1, 2] = torch.tensor([0, 0])
    corr[1, 1] = torch.tensor([1, 1])  # not a keypoint: only in the dense set
    p, q = matched_keypoints(label, corr)
    assert p.tolist() == [[0, 0], [1, 2]] and q.tolist() == [[2, 1], [0, 0]]
    p, _ = matched_keypoints(label, corr, dense=True)
    assert p.tolist() == [[0, 0], [1, 1], [1, 2]]


def _tiny_batch():
    """One 4 x 4 pair: identity correspondences, keypoints at (1, 1) and (2, 2)."""
    torch.manual_seed(0)
    label = torch.zeros(1, 4, 4)
    label[0, 1, 1] = label[0, 2, 2] = 1
    rows, cols = torch.meshgrid(torch.arange(4), torch.arange(4), indexing="ij")
    corr = torch.stack([rows, cols], dim=-1)[None]
    outputs = tuple((torch.randn(1, 2, 4, 4), torch.randn(1, 8, 1, 1), None) for _ in range(2))
    reference = tuple((torch.randn(1, 2, 4, 4), torch.randn(1, 8, 1, 1), None) for _ in range(2))
    return outputs, reference, {"label0": label, "label1": label.clone(), "corr": corr}


def test_detector_loss_assembly_and_no_det_rep_switch():
    from sekd_sfm.train.config import TrainConfig
    from sekd_sfm.train.steps import detector_loss

    outputs, reference, batch = _tiny_batch()
    cfg = TrainConfig(beta=1.0, lambda_keep=0.1)
    total, parts = detector_loss(outputs, reference, batch, cfg, bg_weight=0.5)
    assert parts["rep"] > 0 and total.item() == pytest.approx(parts["det"] + parts["rep"] + 0.1 * parts["keep"], rel=1e-6)
    total, parts = detector_loss(outputs, reference, batch, TrainConfig(no_det_rep=True, lambda_keep=0.1), 0.5)
    assert total.item() == pytest.approx(parts["det"] + 0.1 * parts["keep"], rel=1e-6)  # beta = 0


def test_descriptor_loss_assembly_and_round0_alpha():
    from sekd_sfm.train.config import TrainConfig
    from sekd_sfm.train.steps import descriptor_loss

    outputs, reference, batch = _tiny_batch()
    total, parts = descriptor_loss(outputs, reference, batch, TrainConfig(), alpha=1.0)
    assert parts["used"] == 1.0 and total.item() == pytest.approx(parts["desc"] + parts["pres"], rel=1e-6)
    l0, r0 = outputs[0][0], reference[0][0]
    assert parts["pres"] == pytest.approx(0.5 * ((l0 - r0) ** 2).mean().item()
                                          + 0.5 * ((outputs[1][0] - reference[1][0]) ** 2).mean().item(), rel=1e-6)
    total, parts = descriptor_loss(outputs, reference, batch, TrainConfig(), alpha=0.0)
    assert total.item() == pytest.approx(parts["desc"], rel=1e-6) and "spread" not in parts


def test_descriptor_loss_adds_the_weighted_spread_term():
    from sekd_sfm.train.config import TrainConfig
    from sekd_sfm.train.steps import descriptor_loss, sample_upsampled

    outputs, reference, batch = _tiny_batch()
    total, parts = descriptor_loss(outputs, reference, batch, TrainConfig(spread_weight=2.0), alpha=0.0)
    # 1 x 1 descriptor maps: both keypoints get the same unit vector in each view.
    d0 = sample_upsampled(outputs[0][1][0], torch.tensor([1, 2]), torch.tensor([1, 2]), 4, 4)
    d1 = sample_upsampled(outputs[1][1][0], torch.tensor([1, 2]), torch.tensor([1, 2]), 4, 4)
    assert parts["spread"] == pytest.approx(spread_out(d0, d1).item(), rel=1e-6) and parts["spread"] > 0
    assert total.item() == pytest.approx(parts["desc"] + 2.0 * parts["spread"], rel=1e-6)
