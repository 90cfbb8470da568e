"""Keypoint labels: random (a0), from the detector with affine adaptation (a), from descriptor reliability (c).

As in docs/method.md "Training". Labelling runs the network in eval mode without gradients on
full (resized) images; processes label disjoint shares of the images and exchange them.
With a ``parts`` folder, the labelled images are saved every minute in small chunk files, so an
interrupted step resumes from the images it had labelled (a labelling step at the paper's scale
takes hours on a CPU).
"""
from __future__ import annotations

import hashlib
import logging
import os
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from tqdm import tqdm

from ..model.fused import fp32_eval_forward
from ..model.inference import nms_keypoints
from .config import TrainConfig
from .data import (
    TrainImages,
    affine_grid,
    invert_affine,
    make_view,
    random_affine,
    rng_for,
    sample,
)
from .distributed import Context, gather_objects, shard

logger = logging.getLogger("sekd.train")


@dataclass
class Labels:
    """Keypoints of the images of one labelling step: integer (x, y) and the score-map value there."""

    kind: str
    round_index: int
    keypoints: dict[int, np.ndarray] = field(default_factory=dict)   # image index -> N x 2 int32 (x, y)
    scores: dict[int, np.ndarray] = field(default_factory=dict)      # image index -> N float32
    sizes: dict[int, tuple[int, int]] = field(default_factory=dict)  # image index -> (H, W)
    maps: dict[int, np.ndarray] = field(default_factory=dict)        # optional float16 score maps
    threshold: float | None = None                                   # score threshold the keypoints passed
    network: str = ""                                                # sha256 of the labelling network's weights

    @property
    def mean_keypoints(self) -> float:
        return float(np.mean([len(k) for k in self.keypoints.values()])) if self.keypoints else 0.0

    @property
    def bg_weight(self) -> float:
        """Focal-loss background weight ``n_kp / (n_pix - n_kp)`` from the means over images (§5.8)."""
        n_kp = self.mean_keypoints
        n_pix = float(np.mean([h * w for h, w in self.sizes.values()]))
        return n_kp / max(n_pix - n_kp, 1.0)

    def save(self, path: Path) -> None:
        """One ``.npz`` (written atomically) with concatenated keypoints and per-image offsets."""
        order = sorted(self.keypoints)
        arrays = {
            "kind": np.array(self.kind), "round": np.array(self.round_index), "indices": np.array(order, np.int64),
            "sizes": np.array([self.sizes[i] for i in order], np.int64).reshape(-1, 2),
            "counts": np.array([len(self.keypoints[i]) for i in order], np.int64),
            "keypoints": np.concatenate([self.keypoints[i] for i in order] or [np.zeros((0, 2), np.int32)]),
            "scores": np.concatenate([self.scores[i] for i in order] or [np.zeros(0, np.float32)]),
        }
        arrays.update({f"map_{i}": m for i, m in self.maps.items()})
        if self.network:
            arrays["network"] = np.array(self.network)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")  # PID: never shared with another process
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: Path) -> Labels:
        with np.load(path) as z:
            labels = cls(str(z["kind"]), int(z["round"]), network=str(z["network"]) if "network" in z else "")
            bounds = np.concatenate([[0], np.cumsum(z["counts"])])
            for j, i in enumerate(z["indices"].tolist()):
                labels.keypoints[i] = z["keypoints"][bounds[j]:bounds[j + 1]]
                labels.scores[i] = z["scores"][bounds[j]:bounds[j + 1]]
                labels.sizes[i] = tuple(int(v) for v in z["sizes"][j])
                if f"map_{i}" in z:
                    labels.maps[i] = z[f"map_{i}"]
        return labels


# --- network outputs -----------------------------------------------------------------------------

@torch.no_grad()
def forward_views(net: nn.Module | Callable, views: torch.Tensor, chunk: int, device: torch.device):
    """Eval-mode outputs for ``V x 1 x H x W`` views, ``chunk`` at a time, on ``device``:
    probability ``V x H x W``, raw descriptors ``V x 128 x H/4 x W/4``, feature0 ``V x 32 x H x W``.

    ``net``: the network, or its ``forward_train`` (e.g. ``fused.fp32_eval_forward``'s)."""
    forward = net.forward_train if isinstance(net, nn.Module) else net
    outs = []
    for part in views.split(max(chunk, 1)):
        logits, desc, feat = forward(part.to(device))
        outs.append((F.softmax(logits, dim=1)[:, 1], desc, feat))
    return tuple(torch.cat(o) for o in zip(*outs))


def adaptation_views(rgb: np.ndarray, rng: np.random.Generator, cfg: TrainConfig, m: int):
    """Target view and ``m`` warped views (``(m+1) x 1 x H x W``) and their grids G_k (``m x H x W x 2``)."""
    h, w = rgb.shape[:2]
    views, grids = [make_view(rgb, rng, cfg, None, jitter=cfg.jitter_target)], []
    for _ in range(m):
        theta = random_affine(rng, cfg)
        views.append(make_view(rgb, rng, cfg, theta))
        grids.append(affine_grid(invert_affine(theta), h, w))
    return torch.stack(views), torch.stack(grids) if grids else torch.zeros(0, h, w, 2)


def border_mask(height: int, width: int, band: int, device: torch.device | None = None) -> torch.Tensor:
    """``H x W``: 1 inside, 0 within ``band`` pixels of any border."""
    mask = torch.zeros(height, width, device=device)
    mask[band:height - band, band:width - band] = 1.0
    return mask


def average_detections(prob: torch.Tensor, grids: torch.Tensor, band: int) -> torch.Tensor:
    """Pbar = (P0 + sum_k P_k') / (1 + sum_k M_k'): warped-view probabilities (border band zeroed)
    pulled back to the target through G_k (§3.3-3.4). ``prob``: ``(m+1) x H x W``."""
    total, count = prob[0].clone(), torch.ones_like(prob[0])
    mask = border_mask(*prob.shape[1:], band, prob.device)
    for k in range(grids.shape[0]):
        total += sample((prob[k + 1] * mask)[None], grids[k])[0]
        count += sample(mask[None], grids[k])[0]
    return total / count


# --- descriptor reliability ----------------------------------------------------------------------

def reliability_scale(target: torch.Tensor, views: torch.Tensor, grids: torch.Tensor, cfg: TrainConfig,
                      method: str = "auto") -> torch.Tensor:
    """Reliability R_s of one scale (§5.4-5.5), ``h x w``.

    ``target``: unit features ``C x h x w``; ``views``: raw features of the m warped views
    ``m x C x h x w``; ``grids``: G_k at this scale, ``m x h x w x 2`` (normalised).
    For each target pixel p and view k: dist(u) = sqrt(2 - 2 f(p).normalise(g_k(u)) + eps) at the
    (2 radius + 1)^2 lattice u = G_k(p) + stride * (dx, dy) map pixels; the centre gives Drep,
    the minimum over the others Ddis; r_k = v_k Ddis / (Drep + eps'); R = sum r_k / (sum v_k + eps'').
    ``method``: ``tiled`` (fast on CPUs), ``sampled`` (grid_sample, fast on GPUs), ``auto`` by device.
    """
    h, w = target.shape[1:]
    reach = cfg.rel_radius * cfg.rel_stride
    unit = torch.tensor([2.0 / w, 2.0 / h], device=target.device)  # one map pixel, normalised
    valid = ((grids.abs() + reach * unit) < 1).all(-1)             # v_k(p), m x h x w
    total, count = target.new_zeros(h * w), target.new_zeros(h * w)
    flat_target = target.reshape(target.shape[0], -1).t()
    tiled = method == "tiled" or (method == "auto" and target.device.type == "cpu")
    distances = _lattice_distances_tiled if tiled else _lattice_distances_sampled
    for k in range(views.shape[0]):
        pixels = torch.nonzero(valid[k].reshape(-1))[:, 0]
        if len(pixels) == 0:
            continue
        dist = distances(flat_target, views[k], grids[k].reshape(-1, 2)[pixels], pixels, (h, w), cfg)
        centre = cfg.rel_radius
        d_rep = dist[:, centre, centre].clone()
        dist[:, centre, centre] = float("inf")
        d_dis = torch.ones_like(d_rep) if cfg.no_desc_dis else dist.flatten(1).amin(1)
        if cfg.no_desc_rep:
            d_rep = torch.ones_like(d_rep)
        total[pixels] += d_dis / (d_rep + cfg.rel_rep_eps)
        count[pixels] += 1
    return (total / (count + cfg.rel_count_eps)).view(h, w)


#: Target pixels per side of the tiles whose lattice samples share one matrix product.
RELIABILITY_TILE = 16
#: Pixels per vectorised chunk when combining dot products (bounds memory to tens of MB).
RELIABILITY_CHUNK = 8192


def _lattice_distances_sampled(flat_target: torch.Tensor, view: torch.Tensor, grid: torch.Tensor,
                               pixels: torch.Tensor, size: tuple[int, int], cfg: TrainConfig) -> torch.Tensor:
    """The spec's recipe, literally: ``grid_sample`` the raw view map at every lattice point, normalise,
    dist = sqrt(2 - 2 f.g + eps). Target ``pixels`` (N), sampling ``grid`` N x 2 -> ``N x L x L``."""
    h, w = size
    lattice = torch.arange(-cfg.rel_radius, cfg.rel_radius + 1, device=view.device) * cfg.rel_stride
    yy, xx = torch.meshgrid(lattice, lattice, indexing="ij")
    offsets = torch.stack([xx, yy], dim=-1).reshape(-1, 2) * torch.tensor([2.0 / w, 2.0 / h], device=view.device)
    out = []
    for s in range(0, len(pixels), RELIABILITY_CHUNK):
        points = grid[s:s + RELIABILITY_CHUNK, None, :] + offsets[None]            # n x L^2 x 2
        g = F.grid_sample(view[None], points[None], mode="bilinear", padding_mode="zeros", align_corners=False)[0]
        f = flat_target[pixels[s:s + RELIABILITY_CHUNK]].t()[:, :, None]            # C x n x 1
        cosine = (F.normalize(g, dim=0) * f).sum(0)
        out.append(torch.sqrt((2 - 2 * cosine).clamp_min(0) + cfg.rel_dist_eps))
    return torch.cat(out).view(len(pixels), len(lattice), len(lattice))


def _lattice_distances_tiled(flat_target: torch.Tensor, view: torch.Tensor, grid: torch.Tensor, pixels: torch.Tensor,
                             size: tuple[int, int], cfg: TrainConfig) -> torch.Tensor:
    """dist(G(p) + stride (dx, dy)) for target ``pixels`` (N) against one raw view map ``C x h x w``: ``N x L x L``.

    Lattice offsets are whole map pixels, so all L^2 samples of a pixel share its bilinear
    weights: f.g(u) is the weighted sum of f's dot products with the 4 corner vectors, and
    |g(u)|^2 a weighted sum of neighbour dot products (Gram maps). The f.g dot products of a
    tile of target pixels come from one matrix product with the map region its lattices cover.
    Equal to normalising ``grid_sample`` outputs (zero padding, float round-off) but ~10x faster on a CPU.
    """
    h, w = size
    pad = cfg.rel_radius * cfg.rel_stride + 2
    vpad = F.pad(view, (pad, pad, pad, pad))                         # zeros, like grid_sample's padding
    u = ((grid[:, 0] + 1) * w - 1) / 2 + pad                         # grid_sample's pixel coordinates
    v = ((grid[:, 1] + 1) * h - 1) / 2 + pad
    cx, cy = u.floor(), v.floor()
    weights = _corner_weights(u - cx, v - cy)                        # N x 4
    lattice = torch.arange(-cfg.rel_radius, cfg.rel_radius + 1, device=view.device) * cfg.rel_stride
    ys, xs = cy.long()[:, None] + lattice, cx.long()[:, None] + lattice  # N x L: corner-(0, 0) rows / cols
    dots = _tile_dots(flat_target, vpad, pixels, ys, xs, w)
    gram = _gram_maps(vpad)
    out = []
    for s in range(0, len(pixels), RELIABILITY_CHUNK):
        part = slice(s, s + RELIABILITY_CHUNK)
        cosine = _cosines(dots[part], gram, ys[part], xs[part], weights[part], vpad.shape[2])
        out.append(torch.sqrt((2 - 2 * cosine).clamp_min(0) + cfg.rel_dist_eps))
    return torch.cat(out).view(len(pixels), len(lattice), len(lattice))


#: Corners of a bilinear cell as (row, col) offsets, in the order of the weights.
CORNERS = ((0, 0), (0, 1), (1, 0), (1, 1))


def _corner_weights(fx: torch.Tensor, fy: torch.Tensor) -> torch.Tensor:
    """Bilinear weights ``N x 4`` of the corners (0,0), (0,1), (1,0), (1,1) for fractional offsets."""
    return torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], dim=1)


def _tile_dots(flat_target, vpad, pixels, ys, xs, width: int) -> torch.Tensor:
    """f(p) . g(q) for every target pixel p, lattice point and cell corner q: ``N x 4 x L^2``."""
    tile = RELIABILITY_TILE
    tiles = (pixels // width) // tile * (width // tile + 1) + (pixels % width) // tile
    order = torch.argsort(tiles, stable=True)
    bounds = torch.cumsum(torch.bincount(tiles[order]), 0).tolist()
    n, size = ys.shape
    dots = flat_target.new_empty(n, 4, size * size)
    start = 0
    for end in bounds:
        if end == start:
            continue
        idx = order[start:end]
        y0, y1 = int(ys[idx, 0].min()), int(ys[idx, -1].max()) + 2
        x0, x1 = int(xs[idx, 0].min()), int(xs[idx, -1].max()) + 2
        region = vpad[:, y0:y1, x0:x1].reshape(vpad.shape[0], -1)
        base = ((ys[idx] - y0)[:, :, None] * (x1 - x0) + (xs[idx] - x0)[:, None, :]).reshape(len(idx), 1, -1)
        local = torch.cat([base + dy * (x1 - x0) + dx for dy, dx in CORNERS], dim=1)
        dots[idx] = (flat_target[pixels[idx]] @ region).gather(1, local.reshape(len(idx), -1)).view(len(idx), 4, -1)
        start = end
    return dots


def _gram_maps(vpad: torch.Tensor) -> torch.Tensor:
    """``5 x (H W)`` neighbour dot products: g_q.g_q, g_q.g_q+x, g_q.g_q+y, g_q.g_q+x+y, g_q+x.g_q+y."""
    _, height, width = vpad.shape
    gram = vpad.new_zeros(5, height, width)
    gram[0] = (vpad * vpad).sum(0)
    gram[1, :, :-1] = (vpad[:, :, :-1] * vpad[:, :, 1:]).sum(0)
    gram[2, :-1] = (vpad[:, :-1] * vpad[:, 1:]).sum(0)
    gram[3, :-1, :-1] = (vpad[:, :-1, :-1] * vpad[:, 1:, 1:]).sum(0)
    gram[4, :-1, :-1] = (vpad[:, :-1, 1:] * vpad[:, 1:, :-1]).sum(0)
    return gram.reshape(5, -1)


def _cosines(dots, gram, ys, xs, weights, padded_width: int) -> torch.Tensor:
    """Cosine between f(p) and the bilinear sample at each lattice point: ``N x L^2``.

    ``dot = sum_a w_a f.g_a`` and ``|g|^2 = sum_a w_a^2 |g_a|^2 + 2 sum_{a<b} w_a w_b g_a.g_b``.
    """
    n = len(ys)
    base = ((ys[:, :, None]) * padded_width + xs[:, None, :]).reshape(-1)
    step = {(0, 0): 0, (0, 1): 1, (1, 0): padded_width, (1, 1): padded_width + 1}
    # (Gram map, cell corner where it is read, corner pair it weighs): 4 self terms, 6 cross terms.
    terms = [(0, c, (i, i)) for i, c in enumerate(CORNERS)] + [
        (1, (0, 0), (0, 1)), (1, (1, 0), (2, 3)), (2, (0, 0), (0, 2)), (2, (0, 1), (1, 3)),
        (3, (0, 0), (0, 3)), (4, (0, 0), (1, 2))]
    entries = torch.stack([gram[m].index_select(0, base + step[c]).view(n, -1) for m, c, _ in terms], dim=1)
    pair_w = torch.stack([weights[:, a] * weights[:, b] * (1.0 if a == b else 2.0) for _, _, (a, b) in terms], dim=1)
    dot = torch.bmm(weights[:, None, :], dots)[:, 0]
    norm2 = torch.bmm(pair_w[:, None, :], entries)[:, 0]
    return dot / norm2.clamp_min(0).sqrt().clamp_min(1e-12)        # F.normalize's eps


def fused_reliability(desc: torch.Tensor, feat: torch.Tensor, grids: torch.Tensor, cfg: TrainConfig) -> torch.Tensor:
    """R = 0.5 (R_fine + upsample(R_coarse)) (§5.2-5.6). ``desc``/``feat`` hold view 0 (target) then the m views."""
    height, width = feat.shape[-2:]
    coarse_grids = F.interpolate(grids.permute(0, 3, 1, 2), size=desc.shape[-2:], mode="bilinear",
                                 align_corners=False).permute(0, 2, 3, 1)
    coarse = reliability_scale(F.normalize(desc[0], dim=0), desc[1:], coarse_grids, cfg)
    fine = reliability_scale(F.normalize(feat[0], dim=0), feat[1:], grids, cfg)
    up = F.interpolate(coarse[None, None], size=(height, width), mode="bilinear", align_corners=False)[0, 0]
    return 0.5 * (fine + up)


# --- keypoints -------------------------------------------------------------------------------------

def select_keypoints(score: torch.Tensor, threshold: float, radius: int, max_keypoints: int,
                     border: float) -> tuple[np.ndarray, np.ndarray]:
    """NMS (§3.5) on an ``H x W`` map, then drop keypoints closer than ``border`` px to an edge.

    Returns (x, y) ``N x 2`` int32 and scores ``N`` float32, by decreasing score.
    """
    xy, scores = nms_keypoints(score.float().cpu(), radius, threshold, max_keypoints)
    h, w = score.shape
    keep = (xy[:, 0] >= border) & (xy[:, 0] <= w - 1 - border) & (xy[:, 1] >= border) & (xy[:, 1] <= h - 1 - border)
    return xy[keep].numpy().astype(np.int32), scores[keep].numpy().astype(np.float32)


def random_keypoints(height: int, width: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """(a0) ``count`` uniform random pixels drawn with replacement, duplicates merged: ``N x 2`` (x, y)."""
    xy = np.stack([rng.integers(0, width, count), rng.integers(0, height, count)], axis=1)
    return np.unique(xy, axis=0).astype(np.int32)


def label_one(net: nn.Module | Callable, rgb: np.ndarray, rng: np.random.Generator, kind: str, cfg: TrainConfig,
              device: torch.device) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
    """Keypoints, their scores and the score map of one image for labelling step ``kind`` (a0, a or c).

    ``net``: the eval-mode network or its ``forward_train`` (``forward_views``)."""
    h, w = rgb.shape[:2]
    if kind == "a0":
        xy = random_keypoints(h, w, cfg.random_keypoints, rng)
        return xy, np.full(len(xy), cfg.random_score, np.float32), torch.full((h, w), cfg.random_score)
    m = (0 if kind == "a" else 1) if cfg.no_affine else cfg.num_warps
    views, grids = adaptation_views(rgb, rng, cfg, m)
    prob, desc, feat = forward_views(net, views, cfg.label_chunk, device)
    grids = grids.to(device)
    if kind == "a":
        score = average_detections(prob, grids, cfg.border_band)
        threshold, border = cfg.det_threshold, cfg.det_border_factor * cfg.nms_radius
    else:
        score = fused_reliability(desc, feat, grids, cfg)
        # With a keypoint floor, keep every NMS candidate; label_images picks the threshold over all images.
        threshold = 0.0 if cfg.rel_min_keypoints > 0 else cfg.rel_threshold
        border = cfg.rel_border_factor * cfg.nms_radius
    score = score.cpu()
    xy, scores = select_keypoints(score, threshold, cfg.nms_radius, cfg.max_keypoints, border)
    return xy, scores, score


#: Seconds between two chunk files of an interrupted-labelling-safe step (``label_images(parts=...)``).
PARTS_EVERY_SECONDS = 60.0


def label_images(net: nn.Module, images: TrainImages, indices: list[int], kind: str, round_index: int,
                 cfg: TrainConfig, ctx: Context, progress: bool = True, parts: Path | None = None,
                 parts_every: float | None = None) -> Labels:
    """Run labelling step ``kind`` on ``indices``, split over processes; every process gets all labels.

    ``parts``: folder of this step's chunk files. Images found there (labelled by the same network
    weights, by any process) are not labelled again; the newly labelled ones are saved there every
    ``parts_every`` seconds (default ``PARTS_EVERY_SECONDS``). Each image's draws are seeded by
    (seed, round, step, image), so a resumed step gives the labels of an uninterrupted one. The
    caller deletes the folder once the labels are saved.
    """
    was_training = net.training
    net.eval()
    network = weights_sha256(net)
    mine = shard(ctx, indices)
    # This process's labels: the images saved before an interruption, then the ones labelled now.
    part = load_parts(parts, kind, round_index, network, set(mine)) if parts is not None else Labels(kind, round_index)
    done = len(part.keypoints)
    todo = [i for i in mine if i not in part.keypoints]
    if done:
        logger.info("round %d labels (%s): %d of %d images labelled before the interruption, %d to go",
                    round_index, kind, done, len(mine), len(todo))
    forward = fp32_eval_forward(net, ctx.device)  # built once per pass: the weights do not change while labelling
    every = PARTS_EVERY_SECONDS if parts_every is None else parts_every
    chunk, last_save = Labels(kind, round_index, network=network), time.monotonic()
    bar = tqdm(todo, desc=f"round {round_index} ({kind}) labels", disable=not (progress and ctx.main),
               leave=False, dynamic_ncols=True, initial=done, total=len(mine))
    for i in bar:
        rng = rng_for(cfg.seed, round_index, kind, 0, i)
        xy, scores, score = label_one(forward, images.rgb(i), rng, kind, cfg, ctx.device)
        chunk.keypoints[i], chunk.scores[i], chunk.sizes[i] = xy, scores, tuple(score.shape)
        if cfg.save_maps:
            chunk.maps[i] = score.numpy().astype(np.float16)
        bar.set_postfix(kp=len(xy))
        if parts is not None and time.monotonic() - last_save >= every:
            save_part(chunk, parts, ctx.rank)
            _update(part, chunk)
            chunk, last_save = Labels(kind, round_index, network=network), time.monotonic()
    _update(part, chunk)
    net.train(was_training)
    labels = _merge(gather_objects(ctx, part), kind, round_index)
    labels.network = network
    if kind == "a":
        labels.threshold = cfg.det_threshold
    elif kind == "c":
        keep_with_floor(labels, cfg.rel_threshold, cfg.rel_min_keypoints)
    return labels


def weights_sha256(net: nn.Module) -> str:
    """SHA-256 of the parameters and buffers (names, shapes, bytes): which network labelled."""
    digest = hashlib.sha256()
    for name, tensor in sorted(net.state_dict().items()):
        digest.update(f"{name}{tuple(tensor.shape)}{tensor.dtype}".encode())
        digest.update(tensor.detach().cpu().contiguous().view(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def save_part(chunk: Labels, parts: Path, rank: int) -> None:
    """One chunk file ``parts/p{rank}_{first image}.npz`` (atomic): the images labelled since the last one."""
    if not chunk.keypoints:
        return
    parts.mkdir(parents=True, exist_ok=True)
    chunk.save(parts / f"p{rank}_{min(chunk.keypoints):07d}.npz")


def load_parts(parts: Path, kind: str, round_index: int, network: str, wanted: set[int]) -> Labels:
    """The labels of ``wanted`` images found in the chunk files of ``parts``.

    Chunks of another step or network (a folder left from a changed run) and unreadable ones are
    ignored, with a warning: their images are labelled again."""
    found = Labels(kind, round_index)
    for path in sorted(parts.glob("p*.npz")) if parts.is_dir() else []:
        try:
            chunk = Labels.load(path)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            logger.warning("%s: unreadable (%s); labelling its images again", path, exc)
            continue
        if (chunk.kind, chunk.round_index, chunk.network) != (kind, round_index, network):
            logger.warning("%s: labelled by other weights or another step; labelling its images again", path)
            continue
        _update(found, chunk, wanted)
    return found


def _update(labels: Labels, more: Labels, only: set[int] | None = None) -> None:
    """Add ``more``'s per-image entries to ``labels`` (those of the images in ``only``, if given)."""
    for name in ("keypoints", "scores", "sizes", "maps"):
        entries = getattr(more, name)
        getattr(labels, name).update(entries if only is None else {i: v for i, v in entries.items() if i in only})


def keep_with_floor(labels: Labels, threshold: float, min_mean: float) -> None:
    """Keep keypoints scoring above ``threshold``, lowered if needed so the images keep ``min_mean``
    keypoints on average (docs/method.md "Training": lower t_rel when the mean falls below ~100).

    The labels hold every NMS candidate (found with threshold 0, by decreasing score), so a lower
    threshold selects exactly what NMS with that threshold would have. ``min_mean`` 0: fixed threshold.
    """
    need = int(np.ceil(min_mean * len(labels.scores)))
    every = np.sort(np.concatenate(list(labels.scores.values()) or [np.zeros(0, np.float32)]))[::-1]
    lowered = 0 < need and int((every > threshold).sum()) < need and len(every) > 0
    labels.threshold = float(every[min(need, len(every)) - 1]) if lowered else threshold
    for i, scores in labels.scores.items():
        keep = scores >= labels.threshold if lowered else scores > threshold
        labels.keypoints[i], labels.scores[i] = labels.keypoints[i][keep], scores[keep]


def _merge(parts: list[Labels], kind: str, round_index: int) -> Labels:
    labels = Labels(kind, round_index)
    for part in parts:
        _update(labels, part)
    return labels
