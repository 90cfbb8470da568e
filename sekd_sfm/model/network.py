"""The SEKD network (Song et al. 2020), layer for layer as the authors released it.

Module and parameter names match the released checkpoint so that
``weights/sekd/sekd.pth`` loads with ``strict=True`` (see ``docs/method.md``, Network).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

DESCRIPTOR_DIM = 128
#: Input height and width must be multiples of this (two stride-2 stages).
STRIDE = 4


class ResBlock(nn.Module):
    """Pre-activation residual block: ``BN -> ReLU -> conv3x3`` plus a shortcut.

    The shortcut is a bias-free 1x1 convolution when the block changes the
    resolution or the channel count, the identity otherwise.
    """

    def __init__(self, c_in: int, c_out: int, stride: int = 1):
        super().__init__()
        self.convb = nn.Sequential(
            nn.BatchNorm2d(c_in),
            nn.ReLU(inplace=False),
            nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=True),
        )
        self.conv_residual = None
        if stride != 1 or c_in != c_out:
            self.conv_residual = nn.Conv2d(c_in, c_out, 1, stride=stride, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shortcut = x if self.conv_residual is None else self.conv_residual(x)
        return self.convb(x) + shortcut


def _stage(c_in: int, c_out: int, stride: int, blocks: int = 3) -> nn.Module:
    """``blocks`` residual blocks, the first one changing resolution/channels; 0 blocks = identity (stride 1 only)."""
    if blocks == 0:
        return nn.Identity()
    return nn.Sequential(ResBlock(c_in, c_out, stride), *(ResBlock(c_out, c_out) for _ in range(blocks - 1)))


def _upsample(c_in: int, c_out: int) -> nn.Sequential:
    # Grouped (8 groups) transposed convolution doubling the resolution.
    return nn.Sequential(
        nn.BatchNorm2d(c_in),
        nn.ReLU(inplace=False),
        nn.ConvTranspose2d(c_in, c_out, 3, stride=2, padding=1, output_padding=1, groups=8, bias=True),
    )


class SEKDForward(nn.Module):
    """The forward pass shared by SEKD's networks: an encoder at 1, 1/2, 1/4 resolution
    (``conv0``, ``resblock0..2``), a decoder back to full resolution with skip connections
    (``deconv0``, ``deconv1``), a 2-class ``detector`` and a ``descriptor`` head at 1/4 resolution.
    Subclasses build those modules."""

    def forward_train(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Return ``(logits B x 2 x H x W, raw descriptors B x 128 x H/4 x W/4, feature0 B x C0 x H x W)``."""
        f0 = self.resblock0(self.conv0(image))
        f1 = self.resblock1(f0)
        f2 = self.resblock2(f1)
        g1 = f1 + self.deconv0(f2)
        feature0 = f0 + self.deconv1(g1)
        return self.detector(feature0), self.descriptor(f2), feature0

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Return ``(keypoint probability B x 1 x H x W, raw descriptors B x 128 x H/4 x W/4)``."""
        logits, descriptors, _ = self.forward_train(image)
        return F.softmax(logits, dim=1)[:, 1:2], descriptors


class SEKDNet(SEKDForward):
    """SEKD detector + descriptor network (661,762 parameters).

    Input: ``B x 1 x H x W`` grayscale in [0, 1] with H, W multiples of 4.
    """

    def __init__(self):
        super().__init__()
        self.conv0 = nn.Conv2d(1, 32, 5, padding=2, bias=True)
        self.resblock0 = _stage(32, 32, 1)
        self.resblock1 = _stage(32, 64, 2)
        self.resblock2 = _stage(64, 128, 2)
        self.deconv0 = _upsample(128, 64)
        self.deconv1 = _upsample(64, 32)
        self.detector = nn.Conv2d(32, 2, 3, padding=1, bias=True)
        self.descriptor = ResBlock(128, 128)


def count_parameters(model: nn.Module) -> int:
    """Number of learnable parameters (BatchNorm running statistics excluded)."""
    return sum(p.numel() for p in model.parameters())


class BlockDiagonalConvTranspose2d(nn.ConvTranspose2d):
    """A grouped transposed convolution computed as a dense one with a block-diagonal weight.

    Same parameters (names and shapes) and the same outputs and gradients as the grouped
    layer; it only runs faster because oneDNN has no fast path for grouped transposed
    convolutions on the CPU (3x at the decoder's last layer).
    """

    # output_size is accepted for nn.ConvTranspose2d's signature only: the output size is fixed.
    def forward(self, x: torch.Tensor, output_size=None) -> torch.Tensor:
        dense = block_diagonal_weight(self.weight, self.groups)
        return F.conv_transpose2d(x, dense, self.bias, self.stride, self.padding, self.output_padding, 1, self.dilation)


def block_diagonal_weight(weight: torch.Tensor, groups: int) -> torch.Tensor:
    """A grouped transposed convolution's weight ``C_in x C_out/groups x k x k`` as the equivalent dense
    ``C_in x C_out x k x k`` one, zero outside each group's block (exact; differentiable)."""
    c_in, per_group = weight.shape[:2]
    # Column block j holds weight[:, j mod per_group]; the mask keeps only each row's own group.
    rows = torch.arange(c_in, device=weight.device) // (c_in // groups)
    cols = torch.arange(per_group * groups, device=weight.device) // per_group
    mask = (rows[:, None] == cols[None, :]).to(weight.dtype)[:, :, None, None]
    return weight.repeat(1, groups, 1, 1) * mask


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
