"""The oneDNN-fused CPU forward (sekd_sfm.model.fused) computes what the eager network computes."""
import numpy as np
import pytest
import torch
from torch import nn

from sekd_sfm.model import fused as fused_module
from sekd_sfm.model.fused import FusedForward, _BnRelu, fused_forward_available
from sekd_sfm.model.inference import FastSEKD
from sekd_sfm.model.lite import SEKDLiteNet
from sekd_sfm.model.network import SEKDNet, use_fast_deconv
from sekd_sfm.model.weights import EMBEDDED_MODELS, load_model
from sekd_sfm.runtime import cpu_has_fast_bf16

pytestmark = pytest.mark.skipif(not fused_forward_available(), reason="this PyTorch has no oneDNN fused convolutions")


def _channels_last(x: torch.Tensor, dtype=torch.float32) -> torch.Tensor:
    return x.to(dtype).contiguous(memory_format=torch.channels_last)


def _eager(net: nn.Module, image: torch.Tensor):
    with torch.inference_mode():
        logits, desc, _ = use_fast_deconv(net).forward_train(image)
    return logits, desc


def _randomised(net: nn.Module) -> nn.Module:
    """Running statistics and affine parameters away from their defaults (negative scales included),
    so that a wrong BatchNorm fold cannot pass unnoticed."""
    gen = torch.Generator().manual_seed(0)
    for module in net.modules():
        if isinstance(module, nn.BatchNorm2d):
            c = module.num_features
            module.running_mean.copy_(torch.randn(c, generator=gen) * 0.5)
            module.running_var.copy_(torch.rand(c, generator=gen) + 0.2)
            module.weight.data.copy_(torch.randn(c, generator=gen))
            module.bias.data.copy_(torch.randn(c, generator=gen) * 0.3)
    return net.eval()


def test_bn_relu_is_one_depthwise_convolution_with_the_same_values():
    # Hand-computed: scale = w / sqrt(var + eps), shift = b - mean * scale, then ReLU.
    bn = nn.BatchNorm2d(2, eps=0.0).eval()
    bn.running_mean.copy_(torch.tensor([1.0, -2.0]))
    bn.running_var.copy_(torch.tensor([4.0, 0.25]))
    bn.weight.data.copy_(torch.tensor([2.0, -1.0]))
    bn.bias.data.copy_(torch.tensor([0.5, 0.0]))
    x = torch.tensor([[[[3.0, -1.0]], [[-2.0, 0.0]]]])  # 1 x 2 x 1 x 2
    # channel 0: (x - 1) / 2 * 2 + 0.5 = x - 0.5 -> [2.5, -1.5]; channel 1: -(x + 2) / 0.5 -> [0, -4]
    expected = torch.tensor([[[[2.5, 0.0]], [[0.0, 0.0]]]])
    with torch.inference_mode():
        out = _BnRelu(bn, torch.float32)(_channels_last(x))
    assert torch.equal(out, expected)


@pytest.mark.parametrize("make", [SEKDNet, SEKDLiteNet, lambda: SEKDLiteNet(blocks=(0, 1, 1), context_dilations=(2,))])
def test_fused_forward_equals_the_eager_network_in_fp32(make):
    torch.manual_seed(0)
    net = _randomised(make())
    image = _channels_last(torch.rand(2, 1, 36, 52))
    logits, desc = _eager(net, image)
    with torch.inference_mode():
        fused_logits, fused_desc = FusedForward(net, torch.float32)(image)
    assert fused_logits.shape == logits.shape == (2, 2, 36, 52) and fused_desc.shape == desc.shape == (2, 128, 9, 13)
    # Float round-off only: the folded BatchNorm rounds once where the eager one rounds twice.
    torch.testing.assert_close(fused_logits, logits, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(fused_desc, desc, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("name", ["authors", "lite"])
def test_fast_path_keypoints_with_the_fused_forward_match_the_eager_ones(name, monkeypatch):
    net = load_model(EMBEDDED_MODELS[name])[0]
    rng = np.random.default_rng(1)
    image = torch.from_numpy(rng.random((1, 1, 96, 128), dtype=np.float32))
    fused = FastSEKD(net, "cpu", "fp32")
    assert fused.fused is not None
    monkeypatch.setenv(fused_module.ENV_SWITCH, "0")
    eager = FastSEKD(net, "cpu", "fp32")
    assert eager.fused is None
    (prob_f, desc_f), (prob_e, desc_e) = fused(image), eager(image)
    assert (prob_f - prob_e).abs().max() < 1e-5
    assert torch.nn.functional.cosine_similarity(desc_f, desc_e, dim=1).min() > 0.99999


@pytest.mark.skipif(not cpu_has_fast_bf16(), reason="no native bf16 on this CPU")
def test_fused_bf16_stays_within_bf16_rounding_of_fp32(authors_net):
    image = torch.rand(1, 1, 64, 96, generator=torch.Generator().manual_seed(2))
    prob32, desc32 = FastSEKD(authors_net, "cpu", "fp32")(image)
    model = FastSEKD(authors_net, "cpu", "bf16")
    assert model.fused is not None
    prob16, desc16 = model(image)
    assert prob16.dtype == desc16.dtype == torch.float32
    assert (prob16 - prob32).abs().max() < 0.02
    assert torch.nn.functional.cosine_similarity(desc16, desc32, dim=1).median() > 0.999


def test_other_layouts_and_training_mode_are_refused():
    class Other(SEKDNet):
        def __init__(self):
            super().__init__()
            self.descriptor = nn.Sequential(nn.BatchNorm2d(128), nn.Tanh(), nn.Conv2d(128, 128, 1))

    with pytest.raises(TypeError):
        FusedForward(Other().eval(), torch.float32)
    with pytest.raises(TypeError, match="layout"):  # no SEKD module names at all (e.g. a wrapper module)
        FusedForward(nn.Sequential(SEKDNet()).eval(), torch.float32)
    assert FastSEKD(Other(), "cpu", "fp32").fused is None  # served by the eager forward instead
    with pytest.raises(ValueError, match="eval mode"):
        FusedForward(SEKDNet().train(), torch.float32)


def test_switch_turns_the_fused_forward_off(monkeypatch):
    monkeypatch.setenv(fused_module.ENV_SWITCH, "0")
    assert not fused_forward_available()
    assert FastSEKD(SEKDNet(), "cpu", "fp32").fused is None


def test_every_weight_is_laid_out_channels_last_even_with_one_input_channel():
    # conv0 has one input channel: there a plain tensor already counts as channels-last, and its
    # strides sent oneDNN to a kernel 18x slower; the fused forward must restride it.
    fused = FusedForward(SEKDNet().eval(), torch.float32)
    blocks = [b for stage in fused.stages for b in stage] + [fused.descriptor]
    convs = [fused.conv0, fused.detector] + [b.conv for b in blocks] + [b.shortcut for b in blocks if b.shortcut]
    weights = [c.weight for c in convs] + [b.bn_relu.weight for b in blocks]
    assert fused.conv0.weight.shape == (32, 1, 5, 5)
    assert all(w.stride(1) == 1 for w in weights)


def test_doctor_says_whether_the_fused_forward_is_on():
    from click.testing import CliRunner

    from sekd_sfm.cli.main import sekd

    assert "SEKD_FUSED= (on: oneDNN fused" in CliRunner().invoke(sekd, ["doctor"], env={"SEKD_FUSED": ""}).output
    off = CliRunner().invoke(sekd, ["doctor"], env={"SEKD_FUSED": "0"})
    assert off.exit_code == 0 and "SEKD_FUSED=0 (off: the eager PyTorch forward)" in off.output


def test_labels_from_the_fused_forward_match_the_eager_network(authors_net):
    import copy
    import dataclasses

    from sekd_sfm.model.fused import fp32_eval_forward
    from sekd_sfm.train.config import TrainConfig
    from sekd_sfm.train.labels import label_one

    net = use_fast_deconv(copy.deepcopy(authors_net)).eval()
    forward = fp32_eval_forward(net, torch.device("cpu"))
    assert forward != net.forward_train  # the fused one was built
    rng = np.random.default_rng(0)
    rgb = (np.kron(rng.random((12, 16, 3)), np.ones((8, 8, 1))) * 255).astype(np.uint8)  # 96 x 128 blocks
    cfg = dataclasses.replace(TrainConfig(), num_warps=2, border_band=4, det_threshold=0.0, rel_threshold=0.0)
    for kind in ("a", "c"):
        xy_f, _, score_f = label_one(forward, rgb, np.random.default_rng(1), kind, cfg, torch.device("cpu"))
        xy_e, _, score_e = label_one(net, rgb, np.random.default_rng(1), kind, cfg, torch.device("cpu"))
        assert (score_f - score_e).abs().max() < 1e-4
        same = {tuple(p) for p in xy_f} & {tuple(p) for p in xy_e}
        assert len(xy_e) > 20 and len(same) >= 0.98 * len(xy_e)


def test_eval_forward_keeps_the_eager_network_where_the_fused_one_does_not_apply(monkeypatch):
    from sekd_sfm.model.fused import fp32_eval_forward

    net = SEKDNet()
    assert fp32_eval_forward(net.train(), torch.device("cpu")) == net.forward_train  # BatchNorm in training mode
    monkeypatch.setenv(fused_module.ENV_SWITCH, "0")
    assert fp32_eval_forward(net.eval(), torch.device("cpu")) == net.forward_train


def test_a_pytorch_that_cannot_run_the_fused_operators_falls_back_to_the_eager_network(monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("could not create a primitive")

    monkeypatch.setattr(fused_module, "_BnRelu", lambda bn, dtype: broken)
    with pytest.raises(RuntimeError):
        FusedForward(SEKDNet().eval(), torch.float32)
    model = FastSEKD(SEKDNet(), "cpu", "fp32")
    assert model.fused is None
    prob, desc = model(torch.rand(1, 1, 32, 32))
    assert prob.shape == (1, 32, 32) and desc.shape == (1, 128, 8, 8)


@pytest.mark.parametrize(("switch", "expected"), [("1", "fused"), ("0", "eager")])
def test_feature_file_records_how_the_network_ran(tmp_path, monkeypatch, switch, expected):
    import cv2
    import h5py

    from sekd_sfm.features import FeatureConfig
    from sekd_sfm.stages.extract import extract_features

    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    cv2.imwrite(str(photos / "a.png"), (np.kron(rng.random((8, 10)), np.ones((8, 8))) * 255).astype(np.uint8))
    monkeypatch.setenv(fused_module.ENV_SWITCH, switch)
    output = extract_features(photos, tmp_path / "features.h5", FeatureConfig(), progress=False, num_threads=1)
    with h5py.File(output, "r") as f:
        assert f.attrs["network_forward"] == expected and "a.png" in f


def test_bench_speed_reports_the_forward_and_the_fast_paths_agreement(shared, tmp_path, monkeypatch):
    import json

    from click.testing import CliRunner

    from sekd_sfm.cli.main import sekd
    from sekd_sfm.model import int8

    monkeypatch.setattr(int8, "available", lambda: False)  # no calibration here: tests/test_int8.py covers int8
    out = tmp_path / "speed.json"
    result = CliRunner().invoke(sekd, ["bench", "speed", "--count", "2", "--repeats", "1", "--height", "96",
                                       "--width", "128", "--num-threads", "1", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert "fused forward" in result.output
    report = json.loads(out.read_text())
    assert report["fast_forward"] == "fused"
    assert report["agreement_fast_fp32"]["same_pixel"] == 1.0  # the fused fp32 path keeps plain fp32's keypoints
    assert set(report["images_per_s"]) >= {"sekd plain fp32", "sekd fast fp32", "sekd fast auto", "opencv sift"}


def test_bench_speed_reports_an_int8_runtime_failure_and_times_the_other_paths(shared, tmp_path, monkeypatch):
    import json

    from click.testing import CliRunner

    from sekd_sfm.cli.main import sekd
    from sekd_sfm.model import int8

    def refuse(*args, **kwargs):  # what OpenVINO raises on a CPU it cannot compile the network for
        raise RuntimeError("Exception from src/inference/src/cpp/core.cpp:117:\nno primitive for Deconvolution")

    monkeypatch.setattr(int8, "available", lambda: True)
    monkeypatch.setattr(int8, "_import_openvino", lambda: None)  # with or without the extra installed
    monkeypatch.setattr(int8, "load_or_build", refuse)
    out = tmp_path / "speed.json"
    result = CliRunner().invoke(sekd, ["bench", "speed", "--count", "1", "--repeats", "1", "--height", "64",
                                       "--width", "96", "--num-threads", "1", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert ("sekd int8          failed, not timed: SekdError: --precision int8: OpenVINO could not build the "
            "quantized network on this CPU (Exception from src/inference/src/cpp/core.cpp:117:)") in result.output
    report = json.loads(out.read_text())
    assert set(report["failed"]) == {"sekd int8", "sekd lite int8"} and "int8_vs_sift" not in report
    assert {"sekd fast fp32", "sekd lite fp32", "opencv sift"} <= set(report["images_per_s"])
