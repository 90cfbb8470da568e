"""SEKD on images larger than memory allows at once: the network in overlapping tiles, one image's keypoints.

The network is fully convolutional, so a tile with a margin of at least its receptive field
around its core gives, on the core, the whole image's probabilities and descriptors (to float
round-off). Each tile's keypoints are found on its core (NMS over the tile's window, which holds
the core's neighbourhood), refined, described, and kept in a running top-k: memory is one tile's
forward pass plus ``max_keypoints`` rows, whatever the image's size; the keypoints and their
order are the untiled ones (ties of equal scores at the k-th place aside).

The pixel budget of one forward pass follows the machine's memory (``pixel_budget``): about
0.8-0.9 GB of activations per megapixel were measured for the fp32 fast path at 0.3-5 MP.
"""
from __future__ import annotations

import os
import resource
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch

from .network import STRIDE

#: Pixels of margin around a tile's core: above the network's receptive-field radius (about 40 px:
#: a 5x5 convolution and 3x3 ones at full, half and quarter resolution) and NMS's radius, and a
#: multiple of the network's stride, so tiles line up with the whole image's downsampled grid.
MARGIN = 64
#: Bytes of activations one forward pass needs per input pixel (measured: 924, 857, 794 MB per
#: megapixel at 0.3, 1.2, 4.9 MP, fp32 fast path on a 2-core AVX2 CPU); the larger value, for safety.
BYTES_PER_PIXEL = 950
#: Share of the machine's memory (or of the address-space limit, ``ulimit -v``) one forward pass may use.
MEMORY_SHARE = 1 / 12
#: Bounds of the pixel budget: below 1 MP tiles would cost more in margins than they save; above
#: 4 MP a pass needs ~4 GB whatever the machine holds.
MIN_BUDGET, MAX_BUDGET = 1_000_000, 4_000_000

#: A forward pass: ``1 x 1 x H x W`` float image -> (probability ``1 x H x W``, raw descriptors ``1 x C x H/4 x W/4``).
Forward = Callable[[torch.Tensor], "tuple[torch.Tensor, torch.Tensor]"]
#: What one window's maps become: ``(prob H x W, raw C x h x w, offset (x, y))`` -> keypoints, scores, descriptors.
Detect = Callable[[torch.Tensor, torch.Tensor, tuple[int, int]], "tuple[torch.Tensor, torch.Tensor, torch.Tensor]"]


def memory_limit() -> int:
    """Bytes this process may use: the machine's memory, or less under an address-space limit (``ulimit -v``)."""
    physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    return min(physical, soft) if soft != resource.RLIM_INFINITY else physical


def pixel_budget(memory: int | None = None) -> int:
    """Pixels one forward pass may take (images above it run in tiles): a share of ``memory`` (default:
    ``memory_limit()``), between MIN_BUDGET and MAX_BUDGET. ``SEKD_PIXEL_BUDGET`` overrides it."""
    override = os.environ.get("SEKD_PIXEL_BUDGET", "")
    if override.isdigit() and int(override) > 0:
        return int(override)
    memory = memory_limit() if memory is None else memory
    return int(min(MAX_BUDGET, max(MIN_BUDGET, memory * MEMORY_SHARE / BYTES_PER_PIXEL)))


@dataclass(frozen=True)
class Tile:
    """One tile: its core ``[y0, y1) x [x0, x1)`` (the pixels it answers for) and its window (core + margin,
    clipped to the image), in image pixels; every bound a multiple of STRIDE (the image's sides are)."""

    y0: int
    y1: int
    x0: int
    x1: int
    wy0: int
    wy1: int
    wx0: int
    wx1: int

    @property
    def offset(self) -> tuple[int, int]:
        """``(x, y)`` of the window's top-left pixel in the image."""
        return self.wx0, self.wy0


def core_side(budget: int, margin: int = MARGIN) -> int:
    """The side of a square core whose window (core + 2 margins) holds at most ``budget`` pixels (a multiple of
    STRIDE)."""
    side = int(budget ** 0.5) - 2 * margin
    return max(STRIDE * 16, side - side % STRIDE)


def tiles(height: int, width: int, side: int, margin: int = MARGIN) -> list[Tile]:
    """Cores of ``side`` pixels (the last row and column smaller) covering ``height x width``, with their windows."""
    out = []
    for y0 in range(0, height, side):
        for x0 in range(0, width, side):
            y1, x1 = min(height, y0 + side), min(width, x0 + side)
            out.append(Tile(y0, y1, x0, x1, max(0, y0 - margin), min(height, y1 + margin),
                            max(0, x0 - margin), min(width, x1 + margin)))
    return out


def windows(image: torch.Tensor, grid: list[Tile],
            forward: Forward) -> Iterator[tuple[Tile, torch.Tensor, torch.Tensor]]:
    """``(tile, prob, raw)`` per tile: the network on the tile's window of ``image`` (``1 x 1 x H x W``)."""
    for tile in grid:
        window = image[:, :, tile.wy0:tile.wy1, tile.wx0:tile.wx1]
        prob, raw = forward(window)
        yield tile, prob[0].cpu(), raw[0].cpu()


def in_core(xy: torch.Tensor, tile: Tile) -> torch.Tensor:
    """Which of the window's keypoints ``xy`` (``N x 2``, window pixels) lie in the tile's core."""
    x, y = xy[:, 0] + tile.wx0, xy[:, 1] + tile.wy0
    return (x >= tile.x0) & (x < tile.x1) & (y >= tile.y0) & (y < tile.y1)


def strongest(scores: torch.Tensor, max_keypoints: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``max_keypoints`` highest of ``scores`` (``N``; all when 0 or fewer), best first, and their indices.

    One rule for a whole image's NMS (``inference.nms_keypoints``) and for the tiles' merge, so both order alike.
    """
    if max_keypoints and scores.numel() > max_keypoints:
        return torch.topk(scores, max_keypoints, sorted=True)
    return torch.sort(scores, descending=True, stable=True)


def keep_best(kept: tuple[torch.Tensor, ...] | None, new: tuple[torch.Tensor, ...],
              max_keypoints: int) -> tuple[torch.Tensor, ...]:
    """The ``max_keypoints`` best of two sets ``(xy, scores, descriptors)`` by score (all when 0), best first."""
    xy, scores, desc = new if kept is None else (torch.cat([a, b]) for a, b in zip(kept, new))
    scores, order = strongest(scores, max_keypoints)
    return xy[order], scores, desc[order]


def detect_tiled(image: torch.Tensor, forward: Forward, detect: Detect, max_keypoints: int, budget: int,
                 margin: int = MARGIN) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Keypoints ``N x 2`` (image pixels), scores ``N`` and descriptors ``N x C`` of ``image`` (``1 x 1 x H x W``)
    computed tile by tile, each forward pass at most ``budget`` pixels.

    ``detect(prob, raw, offset)`` finds one window's keypoints (all of them: the top-k is taken here,
    over the whole image) in window pixels; only those in the tile's core count.
    """
    height, width = image.shape[-2:]
    kept = None
    for tile, prob, raw in windows(image, tiles(height, width, core_side(budget, margin), margin), forward):
        xy, scores, desc = detect(prob, raw, tile.offset)
        core = in_core(xy, tile)
        shifted = xy[core] + torch.tensor(tile.offset, dtype=xy.dtype)
        kept = keep_best(kept, (shifted, scores[core], desc[core]), max_keypoints)
    return kept
