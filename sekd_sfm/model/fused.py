"""A oneDNN-fused CPU forward pass for SEKD's pre-activation networks (SEKDNet and SEKD-Lite).

Why: in a pre-activation residual block (``BN -> ReLU -> conv3x3`` plus a shortcut) three of
the four operations are element-wise passes over the block's maps. With bf16 on a CPU with
AMX the 3x3 convolution itself is so fast that those passes take most of the time: at
480x640 a full-resolution block of SEKDNet costs 2.3 ms of convolution and 4.1 ms of
BatchNorm, ReLU and residual add (2 threads). This forward computes the same function with
two oneDNN primitives per block, through the fused-convolution operators PyTorch ships for
its own CPU compiler (``torch.ops.mkldnn._convolution_pointwise``, a private operator: where
a PyTorch build lacks it or cannot run it, ``FastSEKD`` keeps the eager network):

- eval-mode BatchNorm is a per-channel affine map, so ``ReLU(BN(x))`` is a depthwise 1x1
  convolution (weight = scale, bias = shift) with a ReLU post-op: one read, one write;
- the block's 3x3 convolution adds the shortcut as a sum post-op while it writes its output.

The decoder's grouped transposed convolutions run as their dense block-diagonal equivalent
(``network.BlockDiagonalConvTranspose2d``), with the dense weight built once here instead of
at every call. Results equal the eager network's to float round-off (the folded BatchNorm
rounds once instead of twice). ``scripts/bench_fused.py`` measures the gain.
"""
from __future__ import annotations

import os

import torch
import torch.nn.functional as F
from torch import nn

from .network import ResBlock, block_diagonal_weight

#: Set to 0 to run the eager network instead (e.g. to rule the fused path out when debugging).
ENV_SWITCH = "SEKD_FUSED"


def fused_forward_available() -> bool:
    """Whether this PyTorch has the oneDNN fused-convolution operators and they are not switched off."""
    if os.environ.get(ENV_SWITCH, "1") == "0":
        return False
    if not torch.backends.mkldnn.is_available():
        return False
    try:
        op = torch.ops.mkldnn._convolution_pointwise
        return "binary" in op.overloads()
    except (AttributeError, RuntimeError):
        return False


def _cl(tensor: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``tensor`` detached, in ``dtype``, channels-last when it is 4-D (the layout oneDNN's kernels want)."""
    tensor = tensor.detach().to(dtype)
    # clone, not contiguous(): with one input channel (conv0's 32 x 1 x 5 x 5) a plain tensor already
    # counts as channels-last and contiguous() keeps its strides, which send oneDNN to a kernel 18x
    # slower (15 ms instead of 0.8 ms at 480x640 in bf16).
    return tensor.clone(memory_format=torch.channels_last) if tensor.dim() == 4 else tensor.clone()


class _BnRelu:
    """``ReLU(BatchNorm(x))`` (eval mode) as one depthwise 1x1 convolution with a ReLU post-op."""

    def __init__(self, bn: nn.BatchNorm2d, dtype: torch.dtype):
        scale = bn.weight.detach().double() / torch.sqrt(bn.running_var.double() + bn.eps)
        shift = bn.bias.detach().double() - bn.running_mean.double() * scale
        self.weight = _cl(scale[:, None, None, None], dtype)  # C x 1 x 1 x 1: one group per channel
        # In the input's dtype: oneDNN accepts an fp32 bias with bf16 data but then leaves its fast
        # kernels (the whole bf16 forward 1.05x eager instead of 1.44x).
        self.bias = shift.to(dtype)
        self.channels = scale.numel()

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return torch.ops.mkldnn._convolution_pointwise(
            x, self.weight, self.bias, [0, 0], [1, 1], [1, 1], self.channels, "relu", [], None)


class _Conv:
    """A Conv2d's weights in the fused dtype and layout; ``(t)`` convolves, ``(t, other)`` adds ``other`` as it writes."""

    def __init__(self, conv: nn.Conv2d, dtype: torch.dtype):
        self.weight = _cl(conv.weight, dtype)
        self.bias = None if conv.bias is None else _cl(conv.bias, dtype)
        self.padding, self.stride = list(conv.padding), list(conv.stride)
        self.dilation, self.groups = list(conv.dilation), conv.groups

    def __call__(self, t: torch.Tensor, other: torch.Tensor | None = None) -> torch.Tensor:
        if other is None:
            return F.conv2d(t, self.weight, self.bias, self.stride, self.padding, self.dilation, self.groups)
        return torch.ops.mkldnn._convolution_pointwise.binary(
            t, other, self.weight, self.bias, self.padding, self.stride, self.dilation, self.groups,
            "add", None, None, [], None)


class _Block:
    """A pre-activation ResBlock: ``conv(ReLU(BN(x))) + shortcut(x)`` in two (three with a 1x1 shortcut) primitives."""

    def __init__(self, block: ResBlock, dtype: torch.dtype):
        bn, relu, conv = block.convb
        if not (isinstance(bn, nn.BatchNorm2d) and isinstance(relu, nn.ReLU) and type(conv) is nn.Conv2d):
            raise TypeError("not a pre-activation block")
        self.bn_relu, self.conv = _BnRelu(bn, dtype), _Conv(conv, dtype)
        self.shortcut = None if block.conv_residual is None else _Conv(block.conv_residual, dtype)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        shortcut = x if self.shortcut is None else self.shortcut(x)
        return self.conv(self.bn_relu(x), shortcut)


class _Upsample:
    """``BN -> ReLU -> grouped transposed conv`` (stride 2), the transposed conv as its dense block-diagonal form."""

    def __init__(self, seq: nn.Sequential, dtype: torch.dtype):
        bn, relu, deconv = seq
        if not (isinstance(bn, nn.BatchNorm2d) and isinstance(relu, nn.ReLU) and isinstance(deconv, nn.ConvTranspose2d)):
            raise TypeError("not a decoder block")
        self.bn_relu = _BnRelu(bn, dtype)
        self.weight = _cl(block_diagonal_weight(deconv.weight.detach(), deconv.groups), dtype)
        self.bias = None if deconv.bias is None else _cl(deconv.bias, dtype)
        self.args = (deconv.stride, deconv.padding, deconv.output_padding, 1, deconv.dilation)

    def __call__(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        return F.conv_transpose2d(self.bn_relu(x), self.weight, self.bias, *self.args).add_(skip)


def _stage(stage: nn.Module, dtype: torch.dtype) -> list[_Block]:
    if isinstance(stage, nn.Identity):
        return []
    return [_Block(block, dtype) for block in stage]


class FusedForward:
    """``image -> (detector logits B x 2 x H x W, raw descriptors B x 128 x H/4 x W/4)`` of an eval-mode
    SEKD network (``SEKDForward.forward_train``'s first two outputs), fused for the CPU.

    ``image``: ``B x 1 x H x W`` in ``dtype``, channels-last. Built once per network and dtype from
    the network's fp32 parameters (so that each folded value is rounded to ``dtype`` once), which
    are copied: later changes to the network are not seen.
    Raises TypeError for a network whose modules are not SEKD's pre-activation layout, and
    RuntimeError when this PyTorch cannot run the fused operators (a 16 x 16 probe runs here).
    """

    def __init__(self, net: nn.Module, dtype: torch.dtype):
        if net.training:
            raise ValueError("the fused forward folds BatchNorm's running statistics: put the network in eval mode")
        try:
            self._build(net, dtype)
        except (AttributeError, ValueError) as exc:  # a wrapper module, other module names or block lengths
            raise TypeError(f"not SEKD's layout: {exc}") from None
        with torch.no_grad():  # fail here, where the caller can fall back, rather than in the first real call
            self(torch.zeros(1, 1, 16, 16, dtype=dtype).contiguous(memory_format=torch.channels_last))

    def _build(self, net: nn.Module, dtype: torch.dtype) -> None:
        self.conv0 = _Conv(net.conv0, dtype)
        self.stages = [_stage(net.resblock0, dtype), _stage(net.resblock1, dtype), _stage(net.resblock2, dtype)]
        self.deconv0, self.deconv1 = _Upsample(net.deconv0, dtype), _Upsample(net.deconv1, dtype)
        self.detector = _Conv(net.detector, dtype)
        head = net.descriptor
        if isinstance(head, ResBlock):
            self.descriptor = _Block(head, dtype)
        else:  # SEKD-Lite: BN -> ReLU -> 1x1 conv
            bn, relu, conv = head
            if not isinstance(relu, nn.ReLU):
                raise TypeError("unknown descriptor head")
            bn_relu, conv = _BnRelu(bn, dtype), _Conv(conv, dtype)
            self.descriptor = lambda x: conv(bn_relu(x))

    def __call__(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits, desc, _ = self.forward_train(image)
        return logits, desc

    def forward_train(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """As ``SEKDForward.forward_train``: ``(logits, raw descriptors, feature0 B x C0 x H x W)``, channels-last."""
        features = []
        x = self.conv0(image)
        for stage in self.stages:
            for block in stage:
                x = block(x)
            features.append(x)
        f0, f1, f2 = features
        g1 = self.deconv0(f2, f1)
        feature0 = self.deconv1(g1, f0)
        return self.detector(feature0), self.descriptor(f2), feature0


def fused_or_none(net: nn.Module, dtype: torch.dtype) -> FusedForward | None:
    """The fused forward of the eval-mode ``net`` at ``dtype``, or None where it does not apply (switched
    off, a PyTorch without or unable to run the fused operators, another layout): use the eager network."""
    if not fused_forward_available():
        return None
    try:
        return FusedForward(net, dtype)
    except (TypeError, RuntimeError):
        return None


def fp32_eval_forward(net: nn.Module, device: torch.device):
    """``images B x 1 x H x W -> (logits, raw descriptors, feature0)`` of the eval-mode ``net`` in fp32: the
    fused forward on the CPU where it applies (1.15x the eager one), else ``net.forward_train``.

    For the fp32 forwards outside extraction (training labels, the distillation teacher). Outputs
    are contiguous (the layout the eager network returns). Build it after the network's last change.
    """
    fused = fused_or_none(net, torch.float32) if device.type == "cpu" and not net.training else None
    if fused is None:
        return net.forward_train

    def forward(images: torch.Tensor):
        x = images.float().contiguous(memory_format=torch.channels_last)
        return tuple(out.contiguous() for out in fused.forward_train(x))
    return forward
