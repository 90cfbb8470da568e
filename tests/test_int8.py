"""int8 inference (sekd_sfm/int8.py): agreement with fp32, the per-weights cache, missing extra."""
import os
import sys

import numpy as np
import pytest
import torch
from conftest import SHARED

from sekd_sfm.errors import SekdError
from sekd_sfm.model import int8
from sekd_sfm.model.inference import FastSEKD, SEKDConfig, SEKDExtractor
from sekd_sfm.model.weights import load_model, save_checkpoint
from sekd_sfm.runtime import PRECISIONS

needs_int8 = pytest.mark.skipif(not int8.available(), reason='OpenVINO/NNCF not installed: pip install "sekd-sfm[int8]"')
GOLDEN = SHARED / "reference" / "sekd_forward_golden_crop.npz"


@pytest.fixture(scope="module")
def tiny_calibration(tmp_path_factory):
    """A private cache and a tiny calibration (4 COCO photos at 64x80) so a build takes seconds."""
    saved = {k: os.environ.get(k) for k in ("SEKD_CACHE", "SEKD_INT8_CALIBRATION")}
    os.environ["SEKD_CACHE"] = str(tmp_path_factory.mktemp("cache"))
    os.environ["SEKD_INT8_CALIBRATION"] = "4x64x80"
    yield
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


@pytest.fixture
def count_quantize(monkeypatch):
    calls = []
    real = int8.quantize

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(int8, "quantize", counting)
    return calls


def test_int8_is_a_precision_choice():
    assert "int8" in PRECISIONS


@needs_int8
def test_int8_agrees_with_fp32_on_golden_crop(tiny_calibration):
    golden = np.load(GOLDEN)
    net, _ = load_model()
    image = torch.from_numpy(golden["input"])[None, None]
    prob32, desc32 = FastSEKD(net, "cpu", "fp32")(image)
    prob8, desc8 = int8.Int8SEKD(net, "cpu")(image)
    assert prob8.shape == prob32.shape == (1, 128, 160) and desc8.shape == desc32.shape == (1, 128, 32, 40)
    # Tolerances measured at this calibration: max |dp| 0.02-0.05, cosine median >= 0.99.
    assert (prob8 - prob32).abs().max().item() < 0.1
    cosine = torch.nn.functional.cosine_similarity(desc8, desc32, dim=1)
    assert cosine.median().item() > 0.97
    assert not torch.equal(prob8, prob32)  # it really is another computation


@needs_int8
def test_int8_extractor_keypoints_match_fp32(tiny_calibration):
    net, _ = load_model()
    image = (np.load(GOLDEN)["input"] * 255).round().astype(np.uint8)
    out32 = SEKDExtractor(net, SEKDConfig(precision="fp32", device="cpu")).extract(image)
    out8 = SEKDExtractor(net, SEKDConfig(precision="int8", device="cpu")).extract(image)
    assert out8["descriptors"].shape[1] == 128 and len(out8["keypoints"]) > 20
    np.testing.assert_allclose(np.linalg.norm(out8["descriptors"], axis=1), 1, atol=1e-5)
    same = {tuple(p) for p in out32["keypoints"].astype(int)} & {tuple(p) for p in out8["keypoints"].astype(int)}
    assert len(same) > 0.5 * len(out32["keypoints"])


@needs_int8
def test_cache_is_reused_and_invalidated_when_weights_change(tiny_calibration, count_quantize, tmp_path):
    net, _ = load_model()
    _, first = int8.load_or_build(net)
    _, again = int8.load_or_build(net)
    assert again == first and first.is_file() and first.with_suffix(".bin").is_file()
    assert not list(first.parent.glob("*.tmp*"))  # atomic write left no temporary files
    built = len(count_quantize)
    assert built <= 1  # 0 when an earlier test in this module built it already
    # A perturbed copy of the checkpoint is different weights: a new calibration, another folder.
    with torch.no_grad():
        net.conv0.bias += 1e-3
    other, _ = load_model(save_checkpoint(net, tmp_path / "perturbed.pth"))
    _, changed = int8.load_or_build(other)
    assert len(count_quantize) == built + 1 and changed != first and changed.is_file()


@pytest.mark.slow  # a third calibration: ~10 s more under load
@needs_int8
def test_damaged_cache_entry_is_rebuilt(tiny_calibration, count_quantize):
    net, _ = load_model()
    _, xml = int8.load_or_build(net)
    xml.write_text("not an OpenVINO model")
    before = len(count_quantize)
    _, again = int8.load_or_build(net)
    assert again == xml and len(count_quantize) == before + 1


def test_bad_calibration_knob_is_one_error(monkeypatch):
    monkeypatch.setenv("SEKD_INT8_CALIBRATION", "four")
    with pytest.raises(SekdError, match="COUNTxHEIGHTxWIDTH"):
        int8.calibration_from_env()
    monkeypatch.setenv("SEKD_INT8_CALIBRATION", "0x64x64")
    with pytest.raises(SekdError, match="at least 1 photo"):
        int8.calibration_from_env()


def test_missing_extra_names_the_install_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "openvino", None)  # import openvino now raises ImportError
    net, _ = load_model()
    with pytest.raises(SekdError, match=r'pip install "sekd-sfm\[int8\]"'):
        SEKDExtractor(net, SEKDConfig(precision="int8", device="cpu"))


def test_missing_calibration_photos_is_one_error(monkeypatch, tmp_path):
    monkeypatch.setenv("SEKD_SHARED", str(tmp_path))
    with pytest.raises(SekdError, match="no calibration photos"):
        int8.calibration_images(int8.CalibrationConfig(count=2, height=64, width=64))
