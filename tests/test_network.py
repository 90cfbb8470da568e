"""The network is the authors' to float round-off (docs/method.md)."""
import numpy as np
import pytest
import torch
from conftest import SEKD_WEIGHTS

from sekd_sfm.model.inference import FastSEKD
from sekd_sfm.model.network import SEKDNet, count_parameters, use_fast_deconv
from sekd_sfm.model.weights import load_model


def test_parameter_count():
    assert count_parameters(SEKDNet()) == 661_762


def test_authors_weights_load_strictly(authors_net):
    state = torch.load(SEKD_WEIGHTS, map_location="cpu", weights_only=True)["state_dict"]
    assert set(state) == set(SEKDNet().state_dict())


def test_golden_crop_matches_authors_output(shared, authors_net):
    golden = np.load(shared / "reference/sekd_forward_golden_crop.npz")
    with torch.no_grad():
        prob, desc = authors_net(torch.from_numpy(golden["input"])[None, None])
    assert np.abs(prob.numpy() - golden["location"]).max() <= 1e-5
    assert np.abs(desc.numpy() - golden["descriptor"]).max() <= 1e-4


@pytest.mark.parametrize("shape", [(4, 4), (32, 48), (60, 44)])
def test_output_shapes(shape):
    prob, desc = SEKDNet().eval()(torch.rand(2, 1, *shape))
    assert prob.shape == (2, 1, *shape)
    assert desc.shape == (2, 128, shape[0] // 4, shape[1] // 4)
    assert torch.all((prob >= 0) & (prob <= 1))


def test_block_diagonal_transposed_conv_is_equivalent():
    torch.manual_seed(0)
    net = SEKDNet().eval()
    x = torch.randn(1, 128, 5, 7)
    with torch.no_grad():
        expected = net.deconv0(x)
        assert torch.allclose(use_fast_deconv(net).deconv0(x), expected, atol=1e-6)


def test_fast_fp32_equals_plain_forward(authors_net):
    x = torch.rand(1, 1, 64, 96)
    with torch.no_grad():
        prob, desc = authors_net(x)
    fast_prob, fast_desc = FastSEKD(authors_net, "cpu", "fp32")(x)
    assert torch.allclose(fast_prob, prob[:, 0], atol=1e-5)
    assert torch.allclose(fast_desc, desc, atol=1e-4)


def test_missing_embedded_model_says_to_pass_weights(monkeypatch, tmp_path):
    from sekd_sfm.errors import SekdError
    from sekd_sfm.model import weights

    monkeypatch.setitem(weights.EMBEDDED_MODELS, weights.DEFAULT_MODEL, tmp_path / "absent.pth")
    with pytest.raises(SekdError, match="--weights"):
        load_model(None)


def test_bad_checkpoint_is_one_clear_error(tmp_path):
    from sekd_sfm.errors import SekdError

    bad = tmp_path / "bad.pth"
    torch.save({"state_dict": {"conv0.weight": torch.zeros(1)}}, bad)
    with pytest.raises(SekdError, match="does not fit"):
        load_model(bad)
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(SekdError, match="cannot read"):
        load_model(tmp_path / "junk.pth")


def test_our_checkpoint_round_trips(tmp_path, authors_net):
    from sekd_sfm.model.weights import save_checkpoint

    path = save_checkpoint(authors_net, tmp_path / "ours.pth", {"round": 3})
    net, info = load_model(path)
    assert info.meta == {"round": 3}
    for a, b in zip(net.state_dict().values(), authors_net.state_dict().values()):
        assert torch.equal(a, b)
