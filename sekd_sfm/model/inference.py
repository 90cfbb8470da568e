"""SEKD inference (docs/method.md, Inference): fast network preparation, NMS, top-k, sub-pixel, descriptors.

Pixel convention throughout: keypoint (x, y) = (column, row) with integer values at
pixel centres (OpenCV); COLMAP's +0.5 shift happens only when writing a database.
"""
from __future__ import annotations

import copy
from dataclasses import asdict, dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..files.images import scale_mask
from ..runtime import resolve_device, resolve_precision, tune_allocator
from .fused import fused_or_none
from .network import STRIDE, SEKDNet, use_fast_deconv
from .tiling import detect_tiled, pixel_budget, strongest

_DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}
#: Multi-scale pyramid levels stop when a side would be this small or smaller (authors' rule).
MIN_PYRAMID_SIDE = 128


@dataclass
class SEKDConfig:
    """Detection settings. Defaults suit SfM; the authors' HPatches export used max_keypoints=500."""

    max_keypoints: int = 2000
    threshold: float = 0.4
    nms_radius: int = 4
    #: Sub-pixel keypoints (a parabola through the probability map around each peak). Integer
    #: positions cost mapping accuracy that accumulates along long walks: on the generated
    #: 250-photo street, pose AUC@5 0.807 with integer keypoints, 0.957 with this refinement
    #: (pycolmap's SIFT: 0.966; docs/benchmarks.md, Large scenes).
    subpixel: bool = True
    multi_scale: bool = False
    precision: str = "auto"
    device: str = "auto"

    def as_dict(self) -> dict:
        return asdict(self)


class FastSEKD(nn.Module):
    """An eval-mode SEKD network prepared for speed on ``device`` at ``precision``.

    ``fp32`` is exact to float round-off (the grouped transposed convolutions run as
    block-diagonal dense ones, which oneDNN computes several times faster; channels-last layout;
    on the CPU each residual block runs as two fused oneDNN primitives, ``sekd_sfm.model.fused``); ``bf16`` keeps bf16 weights and
    activations (native on AVX512-BF16/AMX CPUs) up to the detector's logits, then takes the
    softmax in fp32; both maps are returned as float32.
    """

    def __init__(self, net: SEKDNet, device: str = "auto", precision: str = "auto"):
        super().__init__()
        self.device = resolve_device(device)
        self.precision = resolve_precision(precision, self.device)
        if self.precision not in _DTYPES:  # int8 is another runtime: SEKDExtractor builds sekd_sfm.model.int8.Int8SEKD
            raise ValueError(f"FastSEKD runs {', '.join(_DTYPES)}; for int8 use SEKDExtractor or sekd_sfm.model.int8.Int8SEKD")
        net = use_fast_deconv(copy.deepcopy(net).eval())
        self.dtype = _DTYPES[self.precision]
        # Folded from the fp32 parameters, before they are rounded to the network's dtype.
        self.fused = fused_or_none(net.float(), self.dtype) if self.device.type == "cpu" else None
        self.net = net.to(self.device, self.dtype).to(memory_format=torch.channels_last)
        if self.device.type == "cpu":
            tune_allocator()

    @torch.inference_mode()
    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``B x 1 x H x W`` float in [0, 1] -> (probability ``B x H x W``, raw descriptors ``B x 128 x H/4 x W/4``), float32.

        The descriptors stay in the network's channels-last memory layout: ``sample_descriptors``
        reads them as rows, and a transposed copy would cost more than the sampling itself.
        """
        x = images.to(self.device, self.dtype).contiguous(memory_format=torch.channels_last)
        logits, desc = self.fused(x) if self.fused is not None else self.net.forward_train(x)[:2]
        # The softmax runs in fp32 whatever the network's precision: the probabilities lie within
        # a few hundredths of 0.5, where bf16 has a step of 0.002-0.004, so a bf16 softmax turns
        # neighbouring peaks into ties and NMS picks other pixels (84.7 % of the keypoints at the
        # fp32 pixel at 2000 keypoints, against 95.5 % with this fp32 softmax, at no measurable cost).
        prob = F.softmax(logits.float(), dim=1)[:, 1]
        return prob.contiguous(), desc.float()


def max_filter(image: torch.Tensor, radius: int) -> torch.Tensor:
    """Maximum over the (2r+1) x (2r+1) window around each pixel of an ``H x W`` map (borders ignored).

    Same values as a square ``max_pool2d`` (stride 1, padding r). On the CPU OpenCV's
    dilation takes 1 ms at 480x640 where a 9x9 max-pool takes 40 ms; on a GPU two 1-D pools.
    """
    k = 2 * radius + 1
    if image.device.type == "cpu":
        return torch.from_numpy(cv2.dilate(image.float().numpy(), np.ones((k, k), np.uint8)))
    rows = F.max_pool2d(image[None, None], (1, k), stride=1, padding=(0, radius))
    return F.max_pool2d(rows, (k, 1), stride=1, padding=(radius, 0))[0, 0]


def nms_keypoints(prob: torch.Tensor, radius: int, threshold: float, max_keypoints: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Local maxima of an ``H x W`` map over a (2r+1)^2 window, above ``threshold``, best ``max_keypoints``.

    Returns integer pixel positions ``N x 2`` (x, y) and their scores ``N``, by decreasing score.
    """
    pooled = max_filter(prob, radius)
    ys, xs = torch.nonzero((prob == pooled) & (prob > threshold), as_tuple=True)
    scores, order = strongest(prob[ys, xs], max_keypoints)
    return torch.stack([xs[order], ys[order]], dim=1), scores


def refine_subpixel(prob: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Per-axis 1-D quadratic peak fit through the 3 values around each keypoint (offset in [-1, 1]).

    Keypoints within 1 px of the border keep their integer position. ``xy``: ``N x 2`` long.
    """
    h, w = prob.shape
    out = xy.float().clone()
    inner = (xy[:, 0] > 0) & (xy[:, 0] < w - 1) & (xy[:, 1] > 0) & (xy[:, 1] < h - 1)
    x, y = xy[inner, 0], xy[inner, 1]
    centre = prob[y, x]
    for axis, (before, after) in enumerate(((prob[y, x - 1], prob[y, x + 1]), (prob[y - 1, x], prob[y + 1, x]))):
        curvature = before - 2 * centre + after
        offset = -(after - before) / (2 * curvature)
        offset = torch.where(curvature.abs() > 1e-12, offset, torch.zeros_like(offset))
        out[inner, axis] += offset.clamp(-1, 1)
    return out


def sample_descriptors(raw: torch.Tensor, xy: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Bilinear descriptors at keypoints, L2-normalised: ``C x h x w`` map, ``N x 2`` -> ``N x C``.

    Uses the authors' convention (``grid_sample`` with grid = 2 x / W - 1, ``align_corners=False``,
    zero padding), which the released weights were trained and evaluated with. A channels-last
    map (the fast path's) is read as rows of its ``h*w x C`` view, four corners per keypoint:
    ``grid_sample`` would first need the whole map transposed, which costs more than
    the sampling (7 ms of SEKD-Lite's ~60 ms per 480x640 image).
    """
    channels, h, w = raw.shape
    if xy.shape[0] == 0:
        return raw.new_zeros(0, channels)
    if raw.stride(0) != 1:  # a contiguous (channels-first) map: grid_sample reads it in place
        grid = torch.stack([2 * xy[:, 0] / width - 1, 2 * xy[:, 1] / height - 1], dim=1).to(raw)
        desc = F.grid_sample(raw[None], grid[None, None], mode="bilinear", align_corners=False)[0, :, 0]
        return F.normalize(desc, p=2, dim=0).t().contiguous()
    rows = raw.permute(1, 2, 0).reshape(h * w, channels)  # a view: no copy for channels-last memory
    # grid_sample's map coordinate for align_corners=False: ((2 x / W - 1) + 1) w / 2 - 1/2.
    u = xy[:, 0].to(raw.dtype) * (w / width) - 0.5
    v = xy[:, 1].to(raw.dtype) * (h / height) - 0.5
    x0, y0 = u.floor(), v.floor()
    fx, fy = u - x0, v - y0
    xs = torch.stack([x0, x0 + 1, x0, x0 + 1]).long()  # 4 x N corners: top-left, top-right, bottom-left, bottom-right
    ys = torch.stack([y0, y0, y0 + 1, y0 + 1]).long()
    weights = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    weights = weights * ((xs >= 0) & (xs < w) & (ys >= 0) & (ys < h))  # zero padding outside the map
    index = ys.clamp(0, h - 1) * w + xs.clamp(0, w - 1)
    corners = rows.index_select(0, index.reshape(-1)).view(4, -1, channels)
    desc = (weights[..., None] * corners).sum(0)
    return F.normalize(desc, p=2, dim=1)


def crop_to_stride(image: np.ndarray) -> np.ndarray:
    """Crop the bottom/right remainder so both sides are multiples of 4 (as the authors do)."""
    h, w = image.shape[:2]
    return image[: h - h % STRIDE, : w - w % STRIDE]


def pyramid(image: np.ndarray, multi_scale: bool) -> list[tuple[np.ndarray, float, float]]:
    """Levels ``(image, scale_x, scale_y)``: full size, then /2, /4, ... while both sides exceed 128 px."""
    levels = [(crop_to_stride(image), 1.0, 1.0)]
    factor = 2
    h, w = image.shape[:2]
    while multi_scale and min(h // factor, w // factor) > MIN_PYRAMID_SIDE:
        small = crop_to_stride(cv2.resize(image, (w // factor, h // factor), interpolation=cv2.INTER_AREA))
        levels.append((small, w / (w // factor), h / (h // factor)))
        factor *= 2
    return levels


def level_mask(mask: np.ndarray, shape: tuple[int, int], sx: float, sy: float) -> np.ndarray:
    """The image's ``mask`` (``H x W`` bool) for a pyramid level of ``shape`` and scales (sx, sy) (``pyramid``):
    resized as the level was (to (W / sx, H / sy), every covered pixel kept), then cropped to the stride."""
    h, w = mask.shape
    return scale_mask(mask, (round(h / sy), round(w / sx)))[: shape[0], : shape[1]]


def _window(mask: np.ndarray | None, offset: tuple[int, int], shape: tuple[int, int]) -> np.ndarray | None:
    """The part of ``mask`` under a tile's window at ``offset`` (x, y) of ``shape`` (H, W); None without a mask."""
    return None if mask is None else mask[offset[1]:offset[1] + shape[0], offset[0]:offset[0] + shape[1]]


class SEKDExtractor:
    """SEKD keypoints and descriptors for one grayscale image at a time.

    ``extract(image, mask=None)`` takes ``H x W`` uint8 (or float in [0, 1]) and returns keypoints
    ``N x 2`` float32 (x, y in the image's pixels), scores ``N`` and unit descriptors ``N x 128``.
    ``mask`` (``H x W`` bool, True = detect there) zeroes the probability map where it is False at
    every pyramid level, before NMS and the top-k: a masked photo keeps its ``max_keypoints``.
    """

    descriptor_dim = 128
    binary = False

    def __init__(self, net: SEKDNet, config: SEKDConfig):
        self.config = config
        if config.precision == "int8":
            from .int8 import Int8SEKD  # optional extra: imported only when asked for
            self.model = Int8SEKD(net, config.device)
        else:
            self.model = FastSEKD(net, config.device, config.precision)
        #: Pixels of one forward pass; larger images run in tiles (``tiling``), same keypoints to float round-off.
        self.pixel_budget = pixel_budget()

    def _level(self, image: np.ndarray,
               mask: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        scale = 255.0 if image.dtype == np.uint8 else 1.0
        tensor = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32) / scale)[None, None]
        if image.shape[0] * image.shape[1] > self.pixel_budget:  # one pass would not fit in memory: in tiles
            return detect_tiled(tensor, self.model,
                                lambda prob, raw, offset: self._keypoints(prob, raw, 0, _window(mask, offset, prob.shape)),
                                self.config.max_keypoints, self.pixel_budget)
        prob, raw = self.model(tensor)
        return self._keypoints(prob[0].cpu(), raw[0].cpu(), self.config.max_keypoints, mask)

    def _keypoints(self, prob: torch.Tensor, raw: torch.Tensor, max_keypoints: int,
                   mask: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Keypoints ``N x 2`` (pixels of ``prob``), scores ``N``, descriptors ``N x 128`` from the network's maps
        (``prob`` H x W, ``raw`` 128 x H/4 x W/4); ``max_keypoints`` 0 keeps all; ``mask`` (H x W bool, or None)."""
        if mask is not None:  # probability 0 is below any threshold: no peak there, and the sub-pixel fit leans away
            prob = prob.masked_fill(~torch.from_numpy(np.ascontiguousarray(mask)), 0.0)
        cfg = self.config
        xy, scores = nms_keypoints(prob, cfg.nms_radius, cfg.threshold, max_keypoints)
        xy = refine_subpixel(prob, xy) if cfg.subpixel else xy.float()
        return xy, scores, sample_descriptors(raw, xy, *prob.shape)

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> dict[str, np.ndarray]:
        if image.ndim != 2:
            raise ValueError(f"SEKD expects a single-channel image, got shape {image.shape}")
        parts = []
        for level, sx, sy in pyramid(image, self.config.multi_scale):
            if min(level.shape) < STRIDE:
                continue
            xy, scores, desc = self._level(level, None if mask is None else level_mask(mask, level.shape, sx, sy))
            # Level pixel centres map back as x_full = (x + 0.5) * s - 0.5.
            xy = (xy + 0.5) * torch.tensor([sx, sy]) - 0.5
            parts.append((xy, scores, desc))
        if not parts:
            return _empty(self.descriptor_dim)
        xy, scores, desc = (torch.cat(p) for p in zip(*parts))
        if len(parts) > 1 and self.config.max_keypoints and scores.numel() > self.config.max_keypoints:
            scores, order = torch.topk(scores, self.config.max_keypoints, sorted=True)
            xy, desc = xy[order], desc[order]
        return {"keypoints": xy.numpy().astype(np.float32), "scores": scores.numpy().astype(np.float32),
                "descriptors": desc.numpy().astype(np.float32)}


def _empty(dim: int) -> dict[str, np.ndarray]:
    return {"keypoints": np.zeros((0, 2), np.float32), "scores": np.zeros(0, np.float32),
            "descriptors": np.zeros((0, dim), np.float32)}
