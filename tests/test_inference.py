"""Keypoint selection, sub-pixel refinement and descriptor sampling (docs/method.md)."""
import os

import cv2
import numpy as np
import pytest
import torch
from conftest import GRAFFITI

from sekd_sfm.model.inference import (
    FastSEKD,
    SEKDConfig,
    SEKDExtractor,
    max_filter,
    nms_keypoints,
    pyramid,
    refine_subpixel,
    sample_descriptors,
)
from sekd_sfm.runtime import cpu_has_fast_bf16, cpu_reports_bf16


def test_nms_keeps_local_maxima_above_threshold_by_score():
    prob = torch.zeros(10, 12)
    prob[2, 3] = 0.9   # a maximum
    prob[2, 5] = 0.8   # within radius 2 of the first: suppressed
    prob[7, 9] = 0.7   # a maximum
    prob[8, 1] = 0.3   # a maximum below the threshold
    xy, scores = nms_keypoints(prob, radius=2, threshold=0.4, max_keypoints=10)
    assert xy.tolist() == [[3, 2], [9, 7]]
    assert torch.allclose(scores, torch.tensor([0.9, 0.7]))


def test_nms_top_k_and_zero_radius():
    prob = torch.tensor([[0.5, 0.6, 0.7, 0.8]])
    xy, _ = nms_keypoints(prob, radius=0, threshold=0.0, max_keypoints=2)
    assert xy.tolist() == [[3, 0], [2, 0]]


def test_nms_on_empty_map():
    xy, scores = nms_keypoints(torch.zeros(8, 8), radius=4, threshold=0.4, max_keypoints=5)
    assert xy.shape == (0, 2) and scores.shape == (0,)


@pytest.mark.parametrize("radius", [0, 1, 4])
def test_max_filter_equals_square_max_pool(radius):
    x = torch.rand(37, 53)
    expected = torch.nn.functional.max_pool2d(x[None, None], 2 * radius + 1, 1, radius)[0, 0]
    assert torch.equal(max_filter(x, radius), expected)


def test_subpixel_recovers_quadratic_peak():
    # p(x, y) = 1 - (x - 5.3)^2 / 50 - (y - 3.8)^2 / 50 is a separable quadratic: exact fit.
    ys, xs = torch.meshgrid(torch.arange(8.0), torch.arange(10.0), indexing="ij")
    prob = 1 - (xs - 5.3) ** 2 / 50 - (ys - 3.8) ** 2 / 50
    refined = refine_subpixel(prob, torch.tensor([[5, 4], [0, 4]]))
    assert torch.allclose(refined[0], torch.tensor([5.3, 3.8]), atol=1e-4)
    assert refined[1].tolist() == [0.0, 4.0]  # on the border: unchanged


def test_descriptor_sampling_convention():
    # Raw map 2 x 2 x 2 (h = w = 2) of a 8 x 8 image: channel 0 = column index, channel 1 = 1.
    raw = torch.stack([torch.tensor([[0.0, 1.0], [0.0, 1.0]]), torch.ones(2, 2)])
    # grid x = 2 * 4 / 8 - 1 = 0 -> map coordinate 0.5 (align_corners=False): halfway between columns.
    desc = sample_descriptors(raw, torch.tensor([[4.0, 4.0]]), 8, 8)
    assert torch.allclose(desc, torch.tensor([[0.5, 1.0]]) / np.hypot(0.5, 1.0))
    assert sample_descriptors(raw, torch.zeros(0, 2), 8, 8).shape == (0, 2)
    # The channels-last map (the fast path's layout) is read as rows: same numbers.
    rows = raw[None].contiguous(memory_format=torch.channels_last)[0]
    assert rows.stride(0) == 1
    assert torch.allclose(sample_descriptors(rows, torch.tensor([[4.0, 4.0]]), 8, 8), desc)
    assert sample_descriptors(rows, torch.zeros(0, 2), 8, 8).shape == (0, 2)


def test_descriptor_sampling_of_both_layouts_agrees_at_borders():
    # Keypoints on every border and corner, where bilinear sampling pads with zeros.
    raw = torch.randn(1, 16, 6, 10, generator=torch.Generator().manual_seed(0))
    xy = torch.tensor([[0.0, 0.0], [39.0, 23.0], [0.0, 23.0], [39.0, 0.0], [1.5, 2.0], [20.3, 11.7], [38.6, 0.4]])
    reference = sample_descriptors(raw[0], xy, 24, 40)  # grid_sample on the plain map
    rows = sample_descriptors(raw.contiguous(memory_format=torch.channels_last)[0], xy, 24, 40)
    assert torch.allclose(rows, reference, atol=1e-6)
    assert torch.allclose(rows.norm(dim=1), torch.ones(len(xy)))


def test_pyramid_levels_stop_at_128_pixels():
    levels = pyramid(np.zeros((600, 1000), np.uint8), multi_scale=True)
    assert [lv[0].shape for lv in levels] == [(600, 1000), (300, 500), (148, 248)]
    assert len(pyramid(np.zeros((600, 1000), np.uint8), multi_scale=False)) == 1


def _same_pixel_and_cosine(reference_kp, reference_desc, out):
    index = {(int(x), int(y)): i for i, (x, y) in enumerate(out["keypoints"])}
    hits = [(j, index[(int(x), int(y))]) for j, (x, y, _) in enumerate(reference_kp) if (int(x), int(y)) in index]
    cosines = [float(reference_desc[j].astype(np.float32) @ out["descriptors"][i]) for j, i in hits]
    return len(hits) / len(reference_kp), min(cosines)


def test_reproduces_authors_keypoints_on_v_graffiti(shared, authors_net):
    reference = np.load(shared / "reference/sekd_official_v_graffiti.npz")
    extractor = SEKDExtractor(authors_net, SEKDConfig(max_keypoints=500, threshold=0.4, nms_radius=4,
                                                      precision="fp32", device="cpu", subpixel=False))
    for i in range(1, 7):
        image = cv2.imread(str(GRAFFITI / f"{i}.ppm"), cv2.IMREAD_GRAYSCALE)
        same, cosine = _same_pixel_and_cosine(reference[f"kp{i}"], reference[f"desc{i}"], extractor.extract(image))
        assert same >= 0.98, f"image {i}: {same:.3f} of the authors' keypoints reproduced"
        assert cosine >= 0.999


@pytest.mark.skipif(not cpu_has_fast_bf16(), reason="no native bf16 on this CPU")
def test_bf16_fast_path_agrees_with_fp32(shared, authors_net):
    image = cv2.imread(str(GRAFFITI / "1.ppm"), cv2.IMREAD_GRAYSCALE)
    config = {"max_keypoints": 500, "threshold": 0.4, "device": "cpu"}
    fp32 = SEKDExtractor(authors_net, SEKDConfig(precision="fp32", **config)).extract(image)
    bf16 = SEKDExtractor(authors_net, SEKDConfig(precision="bf16", **config)).extract(image)
    kp = np.concatenate([fp32["keypoints"], fp32["scores"][:, None]], 1)
    same, cosine = _same_pixel_and_cosine(kp, fp32["descriptors"], bf16)
    # 0.972 measured; 0.87 when the softmax ran in bf16 (ties between neighbouring peaks)
    assert same >= 0.95 and cosine >= 0.98


@pytest.mark.skipif(not cpu_has_fast_bf16(), reason="no native bf16 on this CPU")
def test_bf16_probabilities_are_an_fp32_softmax_of_the_bf16_logits(authors_net):
    rng = np.random.default_rng(0)
    image = torch.from_numpy(rng.random((1, 1, 64, 96), dtype=np.float32))
    model = FastSEKD(authors_net, "cpu", "bf16")
    prob, desc = model(image)
    with torch.inference_mode():
        x = image.to(torch.bfloat16).contiguous(memory_format=torch.channels_last)
        logits = model.fused(x)[0] if model.fused is not None else model.net.forward_train(x)[0]
    expected = torch.softmax(logits.float(), dim=1)[:, 1]
    assert prob.dtype == torch.float32 and desc.dtype == torch.float32
    assert torch.equal(prob, expected)
    # Not on bf16's grid: a bf16 softmax would leave ~0.002 steps near 0.5, i.e. ties for NMS.
    assert not torch.equal(prob.to(torch.bfloat16).float(), prob)


def test_multi_scale_maps_keypoints_into_the_image(authors_net):
    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur((rng.random((300, 400)) * 255).astype(np.uint8), (5, 5), 1.5)
    out = SEKDExtractor(authors_net, SEKDConfig(max_keypoints=300, threshold=0.0, multi_scale=True,
                                                precision="fp32", device="cpu")).extract(image)
    assert len(out["keypoints"]) == 300
    assert np.all(out["keypoints"] >= -0.5) and np.all(out["keypoints"] <= [399.5, 299.5])
    assert np.all(np.diff(out["scores"]) <= 0)
    assert np.allclose(np.linalg.norm(out["descriptors"], axis=1), 1, atol=1e-5)


def test_auto_precision_needs_bf16_in_the_cpu_flags(monkeypatch):
    from sekd_sfm import runtime

    monkeypatch.setattr(runtime, "cpu_flags", lambda: frozenset({"avx2", "fma", "avx512f"}))
    assert not runtime.cpu_has_fast_bf16() and runtime.resolve_precision("auto", torch.device("cpu")) == "fp32"


@pytest.mark.skipif(not cpu_reports_bf16(),
                    reason="the CPU has no native bf16")
def test_auto_precision_is_fp32_where_onednn_is_held_below_the_cpus_bf16():
    """ONEDNN_MAX_CPU_ISA=AVX2 makes bf16 convolutions ~70x slower than fp32: auto must not pick bf16 then."""
    import subprocess
    import sys

    code = "import torch; from sekd_sfm.runtime import resolve_precision; print(resolve_precision('auto', torch.device('cpu')))"
    for isa, expected in (("AVX2", "fp32"), ("ALL", "bf16")):
        out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "ONEDNN_MAX_CPU_ISA": isa},
                             capture_output=True, text=True, check=True).stdout.strip()
        assert out == expected, (isa, out)
