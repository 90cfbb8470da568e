"""The network as training uses it: creation, fast grouped deconvolutions, frozen copies, export.

State-dict names never change, so every model saved here loads with
``sekd_sfm.weights.load_model`` and runs in ``sekd extract``.
"""
from __future__ import annotations

import copy
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from ..network import SEKDNet
from ..weights import load_model, save_checkpoint


class BlockDiagonalConvTranspose2d(nn.ConvTranspose2d):
    """A grouped transposed convolution computed as a dense one with a block-diagonal weight.

    Same parameters (names and shapes) and the same outputs and gradients as the grouped
    layer; it only runs faster because oneDNN has no fast path for grouped transposed
    convolutions on the CPU (3x at the decoder's last layer).
    """

    def forward(self, x: torch.Tensor, output_size=None) -> torch.Tensor:  # noqa: ARG002 - fixed output size
        g = self.groups
        c_in, per_group = self.weight.shape[:2]
        # Column block j holds weight[:, j mod per_group]; the mask keeps only each row's own group.
        rows = torch.arange(c_in, device=x.device) // (c_in // g)
        cols = torch.arange(per_group * g, device=x.device) // per_group
        mask = (rows[:, None] == cols[None, :]).to(self.weight.dtype)[:, :, None, None]
        dense = self.weight.repeat(1, g, 1, 1) * mask
        return F.conv_transpose2d(x, dense, self.bias, self.stride, self.padding, self.output_padding, 1, self.dilation)


def _fast_copy_of(layer: nn.ConvTranspose2d) -> BlockDiagonalConvTranspose2d:
    new = BlockDiagonalConvTranspose2d(
        layer.in_channels, layer.out_channels, layer.kernel_size, stride=layer.stride, padding=layer.padding,
        output_padding=layer.output_padding, groups=layer.groups, bias=layer.bias is not None,
    )
    new.weight, new.bias = layer.weight, layer.bias  # share the Parameters: nothing is copied
    return new


def use_fast_deconv(net: SEKDNet) -> SEKDNet:
    """Swap the decoder's grouped transposed convolutions for the block-diagonal form, in place."""
    for name in ("deconv0", "deconv1"):
        block = getattr(net, name)
        if type(block[2]) is nn.ConvTranspose2d and block[2].groups > 1:
            block[2] = _fast_copy_of(block[2])
    return net


def new_network(seed: int) -> SEKDNet:
    """A randomly initialised network (PyTorch default init) that depends only on ``seed``."""
    state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        return SEKDNet()
    finally:
        torch.random.set_rng_state(state)


def initial_network(weights: str, seed: int) -> SEKDNet:
    """The starting model: a checkpoint when ``weights`` is set, else a seeded random network."""
    if weights:
        return load_model(Path(weights).expanduser())[0]
    return new_network(seed)


def frozen_copy(net: nn.Module) -> nn.Module:
    """A deep copy in eval mode without gradients: the reference of the preservation losses."""
    frozen = copy.deepcopy(net).eval()
    for p in frozen.parameters():
        p.requires_grad_(False)
    return frozen


def plain_copy(net: nn.Module) -> SEKDNet:
    """An ordinary ``SEKDNet`` on the CPU with the same weights (for inference code and export)."""
    plain = SEKDNet()
    plain.load_state_dict({k: v.detach().cpu() for k, v in net.state_dict().items()})
    return plain.eval()


def export(net: nn.Module, path: Path, meta: dict) -> Path:
    """Write ``{'state_dict', 'sekd_sfm': meta}`` atomically (the format ``sekd extract --weights`` reads)."""
    return save_checkpoint(net, path, meta)
