"""SEKD-Lite: a slim network with the same inputs and outputs as :class:`~sekd_sfm.model.network.SEKDNet`.

The full network spends most of its ~26 GMAC (at 480x640) in three 32-channel residual
blocks at full resolution and three blocks each at 1/2 and 1/4 resolution. SEKD-Lite keeps
the layout (encoder at 1, 1/2, 1/4 resolution, the same grouped transposed-convolution
decoder, a 2-class detector at full resolution, 128-D descriptors at 1/4 resolution) with
at most one block per stage, two dilated "context" blocks at 1/4 resolution (dilation 2 and
4: a descriptor sees ~60 px around its keypoint, as the full network's does, for little time
since that resolution has 1/16 of the pixels) and a 1x1 descriptor head. The default (SEKD-Lite
version 3, ``sekd_sfm/model/checkpoints/sekd_lite.pth``) has no residual block at full resolution and
8/24/48 channels: 1.39 GMAC, 63,618 parameters; versions 1 and 2 were 16/32/64 channels with
a full-resolution block (3.3 GMAC, 114,274 parameters), about half as fast on CPUs without
native bf16. It is trained by distillation from the full model (``sekd distill``,
docs/model_card_lite.md). Module names follow SEKDNet's (``deconv0``/``deconv1`` etc.), so
the inference fast path (:func:`~sekd_sfm.model.network.use_fast_deconv`) applies unchanged.
"""
from __future__ import annotations

from torch import nn

from .network import DESCRIPTOR_DIM, ResBlock, SEKDForward, _stage, _upsample

#: The name recorded in a checkpoint's ``'sekd_sfm': {'architecture': ...}`` entry.
ARCHITECTURE = "sekd-lite"
#: Default constructor settings (also what ``sekd_sfm/model/checkpoints/sekd_lite.pth`` was trained with).
DEFAULT_CONFIG = {"channels": [8, 24, 48], "blocks": [0, 1, 1], "context_dilations": [2, 4], "stem_kernel": 3}
#: The grouped decoder convolutions use 8 groups, as in SEKDNet: channel counts must divide by 8.
_GROUPS = 8


class DilatedResBlock(ResBlock):
    """:class:`ResBlock` (same channels in and out) whose 3x3 convolution is dilated by ``dilation``."""

    def __init__(self, channels: int, dilation: int):
        super().__init__(channels, channels)
        self.convb[2] = nn.Conv2d(channels, channels, 3, padding=dilation, dilation=dilation, bias=True)


class SEKDLiteNet(SEKDForward):
    """Slim SEKD detector + descriptor network.

    Input: ``B x 1 x H x W`` grayscale in [0, 1] with H, W multiples of 4. Outputs as SEKDNet:
    keypoint probability ``B x 1 x H x W`` and raw (not normalised) descriptors ``B x 128 x H/4 x W/4``.
    ``channels`` = (full, 1/2, 1/4 resolution), ``blocks`` = residual blocks per stage (the
    full-resolution stage may have 0, the others at least 1), ``context_dilations`` = one more
    residual block at 1/4 resolution per entry, with that dilation, ``stem_kernel`` = size of
    the first convolution.
    """

    architecture = ARCHITECTURE

    def __init__(self, channels: tuple[int, int, int] | list[int] = (8, 24, 48),
                 blocks: tuple[int, int, int] | list[int] = (0, 1, 1),
                 context_dilations: tuple[int, ...] | list[int] = (2, 4), stem_kernel: int = 3):
        super().__init__()
        c0, c1, c2 = (int(c) for c in channels)
        b0, b1, b2 = (int(b) for b in blocks)
        if min(c0, c1, c2) <= 0 or any(c % _GROUPS for c in (c0, c1, c2)):
            raise ValueError(f"SEKD-Lite channels must be positive multiples of {_GROUPS}, got {list(channels)}")
        if b0 < 0 or b1 < 1 or b2 < 1:
            raise ValueError(f"SEKD-Lite blocks must be >= 0 at full resolution and >= 1 below, got {list(blocks)}")
        if stem_kernel % 2 != 1:
            raise ValueError(f"stem_kernel must be odd, got {stem_kernel}")
        dilations = [int(d) for d in context_dilations]
        if any(d < 1 for d in dilations):
            raise ValueError(f"context_dilations must be >= 1, got {list(context_dilations)}")
        self.config = {"channels": [c0, c1, c2], "blocks": [b0, b1, b2], "context_dilations": dilations,
                       "stem_kernel": int(stem_kernel)}
        self.conv0 = nn.Conv2d(1, c0, stem_kernel, padding=stem_kernel // 2, bias=True)
        self.resblock0 = _stage(c0, c0, 1, b0)
        self.resblock1 = _stage(c0, c1, 2, b1)
        self.resblock2 = _stage(c1, c2, 2, b2)
        for d in dilations:  # appended to the 1/4 stage: names resblock2.<i>.* like SEKDNet's blocks
            self.resblock2.append(DilatedResBlock(c2, d))
        self.deconv0 = _upsample(c2, c1)
        self.deconv1 = _upsample(c1, c0)
        self.detector = nn.Conv2d(c0, 2, 3, padding=1, bias=True)
        # A 1x1 head (pre-activated like the residual blocks) instead of SEKDNet's 128-channel 3x3 block.
        # It also widens c2 to the 128 descriptor dimensions.
        self.descriptor = nn.Sequential(nn.BatchNorm2d(c2), nn.ReLU(inplace=False),
                                        nn.Conv2d(c2, DESCRIPTOR_DIM, 1, bias=True))


def build_lite(config: dict | None = None) -> SEKDLiteNet:
    """A SEKD-Lite network from a checkpoint's recorded ``config`` (None: :data:`DEFAULT_CONFIG`)."""
    config = {**DEFAULT_CONFIG, **(config or {})}
    return SEKDLiteNet(config["channels"], config["blocks"], config["context_dilations"], config["stem_kernel"])
