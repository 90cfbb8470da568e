"""SEKD-Lite (sekd_sfm/network_lite.py): architecture, checkpoints, the embedded model, `sekd distill`."""
import json
import re
from dataclasses import asdict
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import ROOT, SHARED

from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.model.inference import FastSEKD, SEKDConfig, SEKDExtractor
from sekd_sfm.model.lite import SEKDLiteNet, build_lite
from sekd_sfm.model.network import SEKDNet
from sekd_sfm.model.weights import (
    EMBEDDED_MODELS,
    file_sha256,
    load_model,
    save_checkpoint,
)
from sekd_sfm.train import distill as distill_module
from sekd_sfm.train.distill import DistillConfig, distill
from sekd_sfm.train.model import initial_network

LITE = EMBEDDED_MODELS["lite"]
AUTHORS = EMBEDDED_MODELS["authors"]
GOLDEN = SHARED / "reference" / "sekd_forward_golden_crop.npz"
#: The embedded Lite model's own fp32 outputs on the golden crop (tests/data/lite_golden_*.npy,
#: written when the model was shipped; descriptors of every 4th cell, to keep the files small):
#: a regression reference for the network and its loading.
LITE_GOLDEN = {name: ROOT / "tests" / "data" / f"lite_golden_{name}.npy" for name in ("location", "descriptor_every4")}
COCO = SHARED / "data" / "train" / "coco"


def _one_error_line(result) -> str:
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.output
    return lines[0]


# --- architecture and checkpoints ------------------------------------------------------------

def test_lite_has_the_expected_parameter_count_and_outputs():
    net = SEKDLiteNet().eval()
    assert sum(p.numel() for p in net.parameters()) == 63_618  # vs 661,762 for SEKDNet
    assert net.config == {"channels": [8, 24, 48], "blocks": [0, 1, 1], "context_dilations": [2, 4], "stem_kernel": 3}
    assert isinstance(net.resblock0, torch.nn.Identity)  # no residual block at full resolution
    assert net.resblock2[2].convb[2].dilation == (4, 4)
    with torch.no_grad():
        prob, desc = net(torch.rand(2, 1, 32, 48))
    assert prob.shape == (2, 1, 32, 48) and desc.shape == (2, 128, 8, 12)
    assert prob.min() >= 0 and prob.max() <= 1


@pytest.mark.parametrize("channels, blocks, dilations", [([16, 30, 64], [1, 1, 1], [2]), ([16, 32, 64], [1, 0, 1], [2]),
                                                       ([16, 32, 64], [1, 1, 1], [0])])
def test_bad_lite_configuration_is_refused(channels, blocks, dilations):
    with pytest.raises(ValueError):
        SEKDLiteNet(channels, blocks, dilations)


def test_lite_checkpoint_records_its_architecture_and_loads(tmp_path):
    torch.manual_seed(0)
    net = build_lite({"channels": [8, 16, 32], "blocks": [0, 1, 2], "context_dilations": [3]}).eval()
    path = save_checkpoint(net, tmp_path / "lite.pth", {"note": "x"})
    meta = torch.load(path, weights_only=True)["sekd_sfm"]
    assert meta["architecture"] == "sekd-lite" and meta["config"]["channels"] == [8, 16, 32] and meta["note"] == "x"
    loaded, _ = load_model(path)
    assert isinstance(loaded, SEKDLiteNet) and loaded.config == net.config
    x = torch.rand(1, 1, 16, 24)
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(net(x), loaded(x)))


def test_lite_checkpoint_is_refused_where_the_full_network_is_required(tmp_path):
    path = save_checkpoint(SEKDLiteNet(), tmp_path / "lite.pth")
    with pytest.raises(SekdError, match=r"lite\.pth: this is a SEKD-Lite \(sekd-lite\) checkpoint, but a full SEKD"):
        load_model(path, architecture="sekd")
    with pytest.raises(SekdError, match="SEKD-Lite"):
        initial_network(str(path), seed=0)  # `sekd evolve --init-weights`, `sekd adapt --from`
    # The command line: the distillation teacher must be a full network.
    line = _one_error_line(CliRunner().invoke(sekd, ["distill", "-o", str(tmp_path / "run"), "--teacher", str(path)]))
    assert "SEKD-Lite" in line and "full SEKD network (sekd) checkpoint is required" in line


def test_full_checkpoint_is_refused_where_lite_is_required_and_mislabelled_files_fail_cleanly(tmp_path):
    with pytest.raises(SekdError, match=r"full SEKD network \(sekd\) checkpoint, but a SEKD-Lite"):
        load_model(AUTHORS, architecture="sekd-lite")
    # A full network's tensors under a Lite label, and an unknown architecture.
    torch.save({"state_dict": SEKDNet().state_dict(), "sekd_sfm": {"architecture": "sekd-lite"}}, tmp_path / "a.pth")
    with pytest.raises(SekdError, match=r"a\.pth: checkpoint does not fit the SEKD-Lite"):
        load_model(tmp_path / "a.pth")
    torch.save({"state_dict": SEKDNet().state_dict(), "sekd_sfm": {"architecture": "sekd-huge"}}, tmp_path / "b.pth")
    with pytest.raises(SekdError, match="unknown network architecture 'sekd-huge'"):
        load_model(tmp_path / "b.pth")


# --- the embedded model ----------------------------------------------------------------------

def test_embedded_lite_loads_with_its_card_checksum():
    net, info = load_model(LITE)
    assert isinstance(net, SEKDLiteNet) and sum(p.numel() for p in net.parameters()) == 63_618
    assert LITE.stat().st_size < 500_000
    assert info.meta["architecture"] == "sekd-lite" and info.meta["teacher"] == "sekd_authors.pth"
    card = (ROOT / "docs/model_card_lite.md").read_text()
    assert re.search(r"SHA-256 \| `([0-9a-f]{64})`", card).group(1) == file_sha256(LITE, 64)


def test_embedded_lite_agrees_with_its_reference_and_its_teacher_on_the_golden_crop():
    net, _ = load_model(LITE)
    golden, ref = np.load(GOLDEN), {name: np.load(path) for name, path in LITE_GOLDEN.items()}
    image = torch.from_numpy(golden["input"])[None, None]
    with torch.no_grad():
        prob, desc = net(image)
    # fp32 against its own reference: float round-off only.
    np.testing.assert_allclose(prob.numpy(), ref["location"], atol=1e-5)
    np.testing.assert_allclose(desc[:, :, ::4, ::4].numpy(), ref["descriptor_every4"], rtol=1e-4, atol=1e-4)
    # The fast paths: fp32 exact to round-off; bf16 within bf16 precision.
    fp32 = FastSEKD(net, "cpu", "fp32")(image)
    assert (fp32[0] - prob[:, 0]).abs().max() < 1e-5
    prob16, desc16 = FastSEKD(net, "cpu", "bf16")(image)
    assert (prob16 - prob[:, 0]).abs().max() < 0.1
    assert torch.nn.functional.cosine_similarity(desc16, desc, dim=1).median() > 0.99
    # Against the teacher's outputs (the authors' model): a distilled copy, not an identical one.
    # Measured when shipping version 3: descriptor cosine median 0.409 over the 32 x 40 cells, mean
    # |dp| 0.0116 (the teacher's probabilities span 0.2-0.67); an untrained Lite gives cosine ~0 here.
    # (Version 2, twice the channels: 0.547. The matching term of the second distillation trades
    # closeness to the teacher for matching across viewpoints.)
    teacher_prob = torch.from_numpy(golden["location"])
    cosine = torch.nn.functional.cosine_similarity(desc, torch.from_numpy(golden["descriptor"]), dim=1)
    assert cosine.median() > 0.35
    assert (prob - teacher_prob).abs().mean() < 0.02


@pytest.fixture
def two_photos(tmp_path, shared) -> Path:
    folder = tmp_path / "photos"
    folder.mkdir()
    for name in sorted(p.name for p in COCO.iterdir())[:2]:
        (folder / name).write_bytes((COCO / name).read_bytes())
    return folder


def test_extract_model_lite_on_two_photos(tmp_path, two_photos):
    out = tmp_path / "f.h5"
    result = CliRunner().invoke(sekd, ["extract", str(two_photos), "-o", str(out), "--model", "lite",
                                       "--resize-max", "320", "--no-progress"])
    assert result.exit_code == 0, result.output
    with h5py.File(out) as f:
        assert f.attrs["model_sha256"] == file_sha256(LITE)
        assert len(f.keys()) == 2
        for key in f:
            kp, desc = f[key]["keypoints"][()], f[key]["descriptors"][()]
            assert len(kp) > 50 and desc.shape == (128, len(kp))  # hloc layout: D x N
            np.testing.assert_allclose(np.linalg.norm(desc.astype(np.float32), axis=0), 1, atol=1e-3)


# --- distillation ----------------------------------------------------------------------------

@pytest.fixture
def tiny_photos(tmp_path, shared) -> Path:
    """Two COCO photos shrunk to 80 x 64 px (the run's data)."""
    folder = tmp_path / "tiny"
    folder.mkdir()
    for name in sorted(p.name for p in COCO.iterdir())[:2]:
        image = cv2.imread(str(COCO / name))
        cv2.imwrite(str(folder / (Path(name).stem + ".png")), cv2.resize(image, (80, 64), interpolation=cv2.INTER_AREA))
    return folder


def _tiny_config(photos: Path, steps: int) -> DistillConfig:
    return DistillConfig(photos=str(photos), steps=steps, batch_size=2, crop=[32, 48], long_side=80,
                         val_every=2, warmup_steps=1, save_every_s=0.0)


def test_distill_three_steps_writes_a_checkpoint_that_extract_accepts(tmp_path, tiny_photos):
    result = CliRunner().invoke(sekd, ["distill", "-o", str(tmp_path / "run"), "--photos", str(tiny_photos),
                                       "--steps", "3", "--batch-size", "2", "--crop", "32", "48", "--no-progress"])
    assert result.exit_code == 0, result.output
    student = tmp_path / "run" / "student.pth"
    assert result.output.strip().splitlines()[-1] == str(student)
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["config"]["steps"] == 3 and config["teacher_sha256"] == file_sha256(AUTHORS)
    records = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if "loss" in r] == [1, 2, 3]
    assert [r["step"] for r in records if "val" in r] == [3] and "repeatability" in records[-1]["val"]
    net, info = load_model(student)
    assert isinstance(net, SEKDLiteNet) and info.meta["step"] == 3
    out = tmp_path / "f.h5"
    result = CliRunner().invoke(sekd, ["extract", str(tiny_photos), "-o", str(out), "--weights", str(student),
                                       "--no-progress"])
    assert result.exit_code == 0, result.output
    assert h5py.File(out).attrs["model_sha256"] == file_sha256(student)


def test_distill_resume_continues_exactly_where_it_stopped(tmp_path, tiny_photos, monkeypatch):
    straight = distill(tmp_path / "a", _tiny_config(tiny_photos, 4), progress=False)
    real, calls = distill_module.distill_losses, []

    def interrupted(*args, **kwargs):  # Ctrl-C during the third step (calls: steps 1, 2, validation, step 3)
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(distill_module, "distill_losses", interrupted)
    with pytest.raises(SekdError, match=r"interrupted at step 2; continue with: sekd distill -o .* --resume"):
        distill(tmp_path / "b", _tiny_config(tiny_photos, 4), progress=False)
    monkeypatch.setattr(distill_module, "distill_losses", real)
    assert torch.load(tmp_path / "b" / "state.pt", weights_only=True)["step"] == 2
    with open(tmp_path / "b" / "metrics.jsonl", "a") as f:  # as if killed after logging a step it never saved
        f.write(json.dumps({"step": 3, "loss": 9.0}) + "\n")
    result = CliRunner().invoke(sekd, ["distill", "-o", str(tmp_path / "b"), "--resume", "--no-progress"])
    assert result.exit_code == 0, result.output
    a, b = (torch.load(p, weights_only=True)["state_dict"] for p in (straight, tmp_path / "b" / "student.pth"))
    assert all(torch.equal(a[k], b[k]) for k in a)  # same data and optimiser state: the same model
    records = [json.loads(line) for line in (tmp_path / "b" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if "loss" in r] == [1, 2, 3, 4]


def test_distill_init_starts_from_the_given_lite_and_keeps_its_channels(tmp_path, tiny_photos):
    source = distill(tmp_path / "a", DistillConfig(**{**asdict(_tiny_config(tiny_photos, 1)),
                                                      "student": {"channels": [16, 16, 32]}}), progress=False)
    config = DistillConfig(**{**asdict(_tiny_config(tiny_photos, 1)), "init": str(source), "lr": 1e-12,
                              "warmup_steps": 1, "lr_min": 1e-12})
    student = distill(tmp_path / "b", config, progress=False)
    start, after = (torch.load(p, weights_only=True)["state_dict"] for p in (source, student))
    assert start["conv0.weight"].shape[0] == 16   # the checkpoint's channels, not the default 8
    # One step at a learning rate of 1e-12 leaves the weights where --init put them.
    assert all(torch.allclose(start[k].float(), after[k].float(), atol=1e-6) for k in start if "weight" in k)
    recorded = json.loads((tmp_path / "b" / "config.json").read_text())
    assert recorded["init_sha256"] == file_sha256(source) and recorded["config"]["student"]["channels"] == [16, 16, 32]
    assert load_model(student)[1].meta["init_sha256"] == file_sha256(source)  # the lineage travels with the model
    # A resumed run continues from its own state: the --init file is no longer needed.
    source.unlink()
    assert distill(tmp_path / "b", resume=True, progress=False) == student


def test_distill_in_bf16_trains_an_fp32_student(tmp_path, tiny_photos):
    config = DistillConfig(**{**asdict(_tiny_config(tiny_photos, 2)), "train_precision": "bf16"})
    student = distill(tmp_path / "run", config, progress=False)
    state = torch.load(student, weights_only=True)["state_dict"]
    assert all(v.dtype == torch.float32 for k, v in state.items() if v.is_floating_point())
    records = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["loss"]) for r in records if "loss" in r)
    assert load_model(student)[0](torch.rand(1, 1, 32, 48))[0].dtype == torch.float32


def test_map_points_applies_a_homography_by_hand():
    # x' = (2x + 1) / (0.5x + 1), y' = (y - 3) / (0.5x + 1)
    h = torch.tensor([[2.0, 0.0, 1.0], [0.0, 1.0, -3.0], [0.5, 0.0, 1.0]])
    xy = torch.tensor([[0.0, 0.0], [2.0, 5.0]])
    assert torch.allclose(distill_module.map_points(h, xy), torch.tensor([[1.0, -3.0], [2.5, 1.0]]))


def test_make_pair_views_show_the_same_scene_point_where_the_map_says(monkeypatch):
    monkeypatch.setattr(distill_module, "jitter_gray", lambda image, rng: image)  # geometry only
    yy, xx = np.mgrid[0:300, 0:400]
    gray = (127 + 60 * np.sin(xx / 23.0) + 60 * np.cos(yy / 31.0)).astype(np.uint8)  # smooth: bilinear is exact to ~1 level
    config = DistillConfig(crop=[96, 128])
    view0, view1, zero_to_one = distill_module.make_pair(gray, np.random.default_rng(3), config)
    assert view0.shape == view1.shape == (96, 128) and zero_to_one.shape == (3, 3)
    ys, xs = np.mgrid[8:88:8, 8:120:8]
    xy0 = torch.tensor(np.stack([xs.ravel(), ys.ravel()], 1), dtype=torch.float32)
    xy1 = distill_module.map_points(torch.from_numpy(zero_to_one).float(), xy0).numpy()
    inside = (xy1[:, 0] > 1) & (xy1[:, 0] < 126) & (xy1[:, 1] > 1) & (xy1[:, 1] < 94)
    assert inside.sum() > 40  # the views overlap mostly
    seen0 = view0[ys.ravel()[inside], xs.ravel()[inside]]
    seen1 = cv2.remap(view1, xy1[inside, 0:1], xy1[inside, 1:2], cv2.INTER_LINEAR)[:, 0]
    assert np.abs(seen0 - seen1).max() < 6 / 255
    assert not np.allclose(view0, view1, atol=0.05)  # a different view, not a copy


def _two_views_with_peaks(desc1_roll: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Teacher logits with 3 peaks (view 0) and one-hot descriptors per 1/4 cell; view 1 = view 0
    with its descriptor channels rolled by ``desc1_roll`` (0: identical views)."""
    logit = torch.full((2, 1, 32, 32), -5.0)
    for x, y in [(5, 6), (17, 10), (26, 25)]:
        logit[0, 0, y, x] = 3.0
    desc = torch.zeros(2, 128, 8, 8)
    for c in range(64):
        desc[:, c, c // 8, c % 8] = 1.0
    desc[1] = desc[1].roll(desc1_roll, dims=0)
    return logit, desc


def test_pair_accuracy_and_loss_on_hand_made_descriptors():
    identity = torch.eye(3)[None]
    logit, same = _two_views_with_peaks(0)
    found = distill_module.pair_correspondences(logit, identity, 500)
    assert [len(xy0) for xy0, _ in found] == [3] and torch.equal(found[0][0], found[0][1])  # the 3 peaks, unmoved
    assert distill_module.pair_accuracy(same, found, 32, 32) == 1.0
    # Orthogonal unit descriptors: positives at distance 0, negatives at sqrt(2); no triplet is active.
    assert float(distill_module.pair_loss(same, found, 32, 32)) == 0.0
    _, other = _two_views_with_peaks(64)  # view 1's descriptors are orthogonal to all of view 0's
    assert distill_module.pair_accuracy(other, found, 32, 32) < 1.0
    assert float(distill_module.pair_loss(other, found, 32, 32)) == pytest.approx(0.0, abs=1e-6)  # pos = neg
    shift = torch.tensor([[1.0, 0, 40], [0, 1, 0], [0, 0, 1]])[None]  # every peak leaves view 1
    gone = distill_module.pair_correspondences(logit, shift, 500)
    assert [len(xy0) for xy0, _ in gone] == [0]
    assert distill_module.pair_accuracy(same, gone, 32, 32) == 0.0
    assert float(distill_module.pair_loss(same, gone, 32, 32)) == 0.0


def test_distill_with_the_matching_term_trains_on_view_pairs(tmp_path, tiny_photos):
    config = DistillConfig(**{**asdict(_tiny_config(tiny_photos, 2)), "pair_weight": 1.0, "crop": [64, 64]})
    images, maps = distill_module.batch_for(distill_module.GrayPhotos(tiny_photos, 80), [0, 1], 0, config)
    assert images.shape == (2, 1, 64, 64) and maps.shape == (1, 3, 3)
    student = distill(tmp_path / "run", config, progress=False)
    records = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert all("pair" in r and np.isfinite(r["pair"]) for r in records if "loss" in r)
    val = records[-1]["val"]
    assert 0 <= val["pair_accuracy"] <= 1 and 0 <= val["teacher_pair_accuracy"] <= 1
    assert isinstance(load_model(student)[0], SEKDLiteNet)
    plain = _tiny_config(tiny_photos, 1)
    assert distill_module.batch_for(distill_module.GrayPhotos(tiny_photos, 80), [0, 1], 0, plain)[1] is None


@pytest.mark.parametrize("args, message", [
    (["--resume"], "no distillation to resume"),
    (["--init", "authors"], "is a full SEKD network .* checkpoint, but a SEKD-Lite"),
    (["--init", "lite", "--channels", "8", "16", "32"], "--init keeps the checkpoint's architecture; drop --channels"),
    (["--init", "lite", "--blocks", "0", "1", "1"], "--init keeps the checkpoint's architecture"),
    (["--context-dilations", "2,x"], "--context-dilations takes comma-separated integers such as 2,4; got '2,x'"),
    (["--blocks", "1", "0", "1"], "invalid student configuration .* blocks must be >= 0 at full resolution and >= 1 below"),
    (["--resume", "--steps", "5"], "--resume continues .* with its recorded settings; drop --steps"),
    (["--photos", "{tmp}/nowhere"], "nowhere: photo folder not found"),
    (["--crop", "30", "48"], "--crop must be HEIGHT WIDTH, multiples of 4"),
    (["--teacher", "{tmp}/missing.pth"], "--teacher .*missing.pth: neither an embedded model nor"),
    (["--pair-weight", "1", "--batch-size", "3"], "--pair-weight must be >= 0, and > 0 needs an even --batch-size"),
])
def test_distill_bad_input_is_one_error_line(tmp_path, args, message):
    args = [a.format(tmp=tmp_path) for a in args]
    line = _one_error_line(CliRunner().invoke(sekd, ["distill", "-o", str(tmp_path / "run"), *args]))
    assert re.match(f"Error: .*{message}", line), line


def test_distill_refuses_to_overwrite_a_run(tmp_path, tiny_photos):
    distill(tmp_path / "run", _tiny_config(tiny_photos, 1), progress=False)
    line = _one_error_line(CliRunner().invoke(sekd, ["distill", "-o", str(tmp_path / "run"), "--photos", str(tiny_photos)]))
    assert "a distillation run already lives here; continue it with --resume" in line


def test_lite_extractor_runs_on_empty_and_tiny_images():
    net = SEKDLiteNet().eval()
    out = SEKDExtractor(net, SEKDConfig(device="cpu", precision="fp32")).extract(np.zeros((2, 2), np.uint8))
    assert out["keypoints"].shape == (0, 2) and out["descriptors"].shape == (0, 128)
