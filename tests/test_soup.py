"""Weight averages of checkpoints (sekd_sfm/train/soup.py)."""
import pytest
import torch

from sekd_sfm.errors import SekdError
from sekd_sfm.model.lite import SEKDLiteNet, build_lite
from sekd_sfm.model.network import SEKDNet
from sekd_sfm.model.weights import file_sha256, load_model, save_checkpoint
from sekd_sfm.train.soup import average_checkpoints, main

SMALL = {"channels": [8, 16, 32]}


def _filled(net: torch.nn.Module, value: float, batches: int) -> torch.nn.Module:
    """Every float tensor (parameters and BatchNorm statistics) set to ``value``; counters to ``batches``."""
    with torch.no_grad():
        for tensor in net.state_dict().values():
            tensor.fill_(value if tensor.is_floating_point() else batches)
    return net


def test_weighted_average_by_hand(tmp_path):
    a = save_checkpoint(_filled(build_lite(SMALL), 1.0, 5), tmp_path / "a.pth")
    b = save_checkpoint(_filled(build_lite(SMALL), 3.0, 9), tmp_path / "b.pth")
    out = average_checkpoints([a, b], tmp_path / "soup.pth", [3, 1])  # normalised to 0.75, 0.25
    net, info = load_model(out)
    assert isinstance(net, SEKDLiteNet) and net.config["channels"] == [8, 16, 32]
    for key, value in net.state_dict().items():
        expected = 1.5 if value.is_floating_point() else 5  # 0.75 x 1 + 0.25 x 3; counters from the first
        assert torch.all(value == expected), key
    assert info.meta["soup"] == [{"file": str(a), "sha256": file_sha256(a), "weight": 0.75},
                                 {"file": str(b), "sha256": file_sha256(b), "weight": 0.25}]


def test_equal_weights_by_default_and_full_networks(tmp_path):
    a = save_checkpoint(_filled(SEKDNet(), 2.0, 1), tmp_path / "a.pth")
    b = save_checkpoint(_filled(SEKDNet(), 4.0, 1), tmp_path / "b.pth")
    net, info = load_model(average_checkpoints([a, b], tmp_path / "soup.pth"))
    assert isinstance(net, SEKDNet) and float(net.conv0.weight.detach().flatten()[0]) == 3.0
    assert [i["weight"] for i in info.meta["soup"]] == [0.5, 0.5]


@pytest.mark.parametrize("weights, message", [
    ([1.0], "gives 1 weights for 2 checkpoints"),
    ([1.0, -1.0], "must be positive"),
    ([1.0, float("nan")], "must be positive"),
])
def test_bad_weights_are_refused(tmp_path, weights, message):
    a = save_checkpoint(build_lite(SMALL), tmp_path / "a.pth")
    with pytest.raises(SekdError, match=message):
        average_checkpoints([a, a], tmp_path / "soup.pth", weights)
    assert not (tmp_path / "soup.pth").exists()


def test_different_networks_are_refused(tmp_path):
    lite = save_checkpoint(build_lite(SMALL), tmp_path / "lite.pth")
    other = save_checkpoint(build_lite({"channels": [16, 32, 64]}), tmp_path / "other.pth")
    full = save_checkpoint(SEKDNet(), tmp_path / "full.pth")
    with pytest.raises(SekdError, match="other channels"):
        average_checkpoints([lite, other], tmp_path / "soup.pth")
    with pytest.raises(SekdError, match="full SEKD network .* but a SEKD-Lite"):
        average_checkpoints([lite, full], tmp_path / "soup.pth")
    with pytest.raises(SekdError, match="at least 2 checkpoints"):
        average_checkpoints([lite], tmp_path / "soup.pth")


def test_command_line_error_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path / "missing.pth"), str(tmp_path / "missing.pth"), "-o", str(tmp_path / "soup.pth")])
    assert str(exit_info.value).startswith("Error: ") and "missing.pth" in str(exit_info.value)
    assert "\n" not in str(exit_info.value)
