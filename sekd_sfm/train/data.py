"""Training data (docs/method.md "Training"): image subsets, colour jitter, random affine warps, training pairs.

Coordinates: an affine ``theta`` (2 x 3) acts on normalised coordinates (x = column,
y = row, in [-1, 1], ``align_corners=False``). A warped view is ``I^(q) = I(theta q)``;
its correspondence grid ``G(p) = theta^-1 p`` gives, for every target pixel p, its
location in the warped view. Every random draw comes from :func:`rng_for`, seeded by
(seed, round, step, epoch, image), so a resumed run sees exactly the same data.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset

from ..errors import SekdError
from ..evaluation import samplers
from ..files.images import ImageReadError, list_images, read_image, resize_max_side
from .config import TrainConfig

#: Stable integer codes for the random streams of each step kind.
STREAMS = {"a0": 1, "a": 2, "b": 3, "c": 4, "d": 5, "val": 6}


def rng_for(seed: int, round_index: int, kind: str, epoch: int, image_index: int) -> np.random.Generator:
    """The random generator of one image in one epoch of one step: independent of run history."""
    return np.random.default_rng([seed, round_index + 1, STREAMS[kind], epoch, image_index])


def subset_indices(count: int, factor: int, round_index: int) -> list[int]:
    """Indices i of the sorted image list with ``i mod S == k mod S`` (docs/method.md "Training")."""
    return [i for i in range(count) if i % factor == round_index % factor]


class TrainImages:
    """The training images of a folder: sorted keys, RGB uint8 resized to ``long_side``, cropped to ``multiple``."""

    def __init__(self, root: str | Path, long_side: int, multiple: int, cache: bool = True):
        self.root = Path(root)
        self.keys = list_images(self.root)
        self.long_side, self.multiple = long_side, multiple
        self._cache: dict[int, np.ndarray] | None = {} if cache else None  # a dict pickles to DataLoader workers

    def __len__(self) -> int:
        return len(self.keys)

    def rgb(self, index: int) -> np.ndarray:
        """``H x W x 3`` uint8 RGB; H and W multiples of ``multiple``."""
        if self._cache is None:
            return self._read(index)
        if index not in self._cache:
            self._cache[index] = self._read(index)
        return self._cache[index]

    def _read(self, index: int) -> np.ndarray:
        try:
            image = read_image(self.root / self.keys[index], grayscale=False)
        except ImageReadError as exc:
            raise SekdError(str(exc)) from exc
        image, _, _ = resize_max_side(image, self.long_side or None)
        h, w = image.shape[:2]
        h, w = h - h % self.multiple, w - w % self.multiple
        if h == 0 or w == 0:
            raise SekdError(f"{self.root / self.keys[index]}: image smaller than {self.multiple} px after resizing")
        return np.ascontiguousarray(image[:h, :w])


# --- colour jitter (torchvision ColorJitter semantics on 8-bit images; evaluation/samplers.py) -------

def color_jitter(rgb: torch.Tensor, rng: np.random.Generator, cfg: TrainConfig) -> torch.Tensor:
    """Brightness, contrast, saturation, hue in a random order (``samplers.color_jitter`` with the run's
    ranges). ``3 x H x W`` float holding 0..255 integers."""
    return samplers.color_jitter(rgb, rng, cfg.brightness, cfg.contrast, cfg.saturation, cfg.hue)


def to_gray(rgb: torch.Tensor) -> torch.Tensor:
    """``3 x H x W`` 0..255 -> ``1 x H x W`` in [0, 1] (0.299 R + 0.587 G + 0.114 B, not truncated)."""
    return ((0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]) / 255.0)[None]


# --- affine warps (drawn by evaluation/samplers.py with this run's ranges) ----------------------

def random_affine(rng: np.random.Generator, cfg: TrainConfig) -> np.ndarray:
    """theta = [[sx cos a, -sy sin(a+s), tx], [sx sin a, sy cos(a+s), ty]] (normalised coordinates;
    ``samplers.random_affine`` with the run's ranges)."""
    return samplers.random_affine(rng, cfg.rotation_deg, cfg.shear_deg, cfg.scale, cfg.translation, cfg.isotropic_scale)


def random_warp(rng: np.random.Generator, cfg: TrainConfig) -> np.ndarray:
    """The warp of a training pair: ``random_affine``, with projective terms when ``cfg.perspective`` > 0.

    With perspective ``p`` the 2 x 3 affine map ``A`` becomes the 3 x 3 homography
    ``[[A], [g, h, 1]]`` with ``g, h`` uniform in ``[-p, p]`` (normalised coordinates): across
    the view the local scale then changes by up to ``(1 + 2p) / (1 - 2p)``, a viewpoint change the
    affine warps of the specification do not make. ``p = 0`` draws nothing more, so runs without
    it are unchanged (``samplers.random_warp``).
    """
    return samplers.random_warp(rng, cfg.rotation_deg, cfg.shear_deg, cfg.scale, cfg.translation,
                                cfg.isotropic_scale, cfg.perspective)


def invert_affine(theta: np.ndarray) -> np.ndarray:
    """The inverse of a 2 x 3 affine map."""
    inverse = np.linalg.inv(np.vstack([theta, [0.0, 0.0, 1.0]]))
    return inverse[:2]


def invert_warp(theta: np.ndarray) -> np.ndarray:
    """The inverse of a 2 x 3 affine map or of a 3 x 3 homography (normalised so its last entry is 1)."""
    if theta.shape == (2, 3):
        return invert_affine(theta)
    inverse = np.linalg.inv(theta)
    return inverse / inverse[2, 2]


def affine_grid(theta: np.ndarray, height: int, width: int) -> torch.Tensor:
    """``H x W x 2`` normalised locations ``theta p`` for every pixel centre p (``align_corners=False``)."""
    t = torch.as_tensor(theta, dtype=torch.float32)[None]
    return F.affine_grid(t, [1, 1, height, width], align_corners=False)[0]


def warp_grid(theta: np.ndarray, height: int, width: int) -> torch.Tensor:
    """``affine_grid`` for a 2 x 3 affine map or a 3 x 3 homography (normalised coordinates).

    Where a homography's denominator is not positive (beyond its vanishing line) the location
    is put outside the image, so nothing is sampled or matched there.
    """
    if theta.shape == (2, 3):
        return affine_grid(theta, height, width)
    base = affine_grid(np.eye(3)[:2], height, width).double()
    points = base @ torch.as_tensor(theta[:, :2].T) + torch.as_tensor(theta[:, 2])
    depth = points[..., 2:]
    outside = torch.full_like(points[..., :2], 2.0)
    return torch.where(depth > 1e-6, points[..., :2] / depth.clamp(min=1e-6), outside).float()


def sample(image: torch.Tensor, grid: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """``C x H x W`` sampled at an ``h x w x 2`` grid (zeros outside) -> ``C x h x w``."""
    return F.grid_sample(image[None], grid[None], mode=mode, padding_mode="zeros", align_corners=False)[0]


def pixel_of(grid: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Integer pixel ``(row, col)`` of normalised locations ``... x 2``; ``-1`` where outside (-1, 1)."""
    x, y = grid[..., 0], grid[..., 1]
    valid = (x > -1) & (x < 1) & (y > -1) & (y < 1)
    rows = torch.floor((y + 1) / 2 * height).long().clamp(0, height - 1)
    cols = torch.floor((x + 1) / 2 * width).long().clamp(0, width - 1)
    rc = torch.stack([rows, cols], dim=-1)
    return torch.where(valid[..., None], rc, torch.full_like(rc, -1))


def correspondences(theta: np.ndarray, height: int, width: int) -> torch.Tensor:
    """``H x W x 2`` long: pixel (row, col) in the warped view of every target pixel, -1 if it falls outside."""
    return pixel_of(warp_grid(invert_warp(theta), height, width), height, width)


def labels_forward(keypoints: np.ndarray, corr: torch.Tensor) -> torch.Tensor:
    """Label map of the warped view: each target keypoint (x, y) moved to its corresponding pixel (docs/method.md "Training")."""
    height, width = corr.shape[:2]
    out = torch.zeros(height, width)
    if len(keypoints):
        xy = torch.as_tensor(keypoints, dtype=torch.long)
        rc = corr[xy[:, 1], xy[:, 0]]
        rc = rc[rc[:, 0] >= 0]
        out[rc[:, 0], rc[:, 1]] = 1.0
    return out


def labels_inverse(label0: torch.Tensor, theta: np.ndarray) -> torch.Tensor:
    """The authors' code: nearest-sample Y at G, which applies the inverse warp (kept for comparison)."""
    grid = warp_grid(invert_warp(theta), *label0.shape)
    return sample(label0[None], grid, mode="nearest")[0]


def keypoint_map(keypoints: np.ndarray, height: int, width: int) -> torch.Tensor:
    """Binary ``H x W`` map with ones at integer keypoints (x, y)."""
    out = torch.zeros(height, width)
    if len(keypoints):
        xy = torch.as_tensor(keypoints, dtype=torch.long)
        out[xy[:, 1], xy[:, 0]] = 1.0
    return out


def make_view(rgb_u8: np.ndarray, rng: np.random.Generator, cfg: TrainConfig, theta: np.ndarray | None,
              jitter: bool = True) -> torch.Tensor:
    """Colour jitter -> warp (affine or projective; bilinear, zero fill, truncated to 8 bits) -> grayscale: ``1 x H x W``."""
    rgb = torch.from_numpy(rgb_u8).permute(2, 0, 1).float()
    if jitter:
        rgb = color_jitter(rgb, rng, cfg)
    if theta is not None:
        rgb = sample(rgb, warp_grid(theta, *rgb.shape[1:])).floor()
    return to_gray(rgb)


# --- training pairs ---------------------------------------------------------------------------

def _pad_to(t: torch.Tensor, height: int, width: int, value: float = 0.0) -> torch.Tensor:
    """Zero-pad the last two dims bottom/right up to ``height x width``."""
    return F.pad(t, (0, width - t.shape[-1], 0, height - t.shape[-2]), value=value)


def _crop_corr(corr: torch.Tensor, top: int, left: int, height: int, width: int) -> torch.Tensor:
    """Correspondences of the crop window, re-expressed in crop pixels; -1 when outside the view-1 crop."""
    window = corr[top:top + height, left:left + width] - torch.tensor([top, left])
    inside = (window[..., 0] >= 0) & (window[..., 0] < height) & (window[..., 1] >= 0) & (window[..., 1] < width)
    inside &= corr[top:top + height, left:left + width, 0] >= 0
    return torch.where(inside[..., None], window, torch.full_like(window, -1))


def make_pair(rgb_u8: np.ndarray, keypoints: np.ndarray, rng: np.random.Generator, cfg: TrainConfig) -> dict:
    """One training pair (docs/method.md "Training"), cropped to ``crop_height x crop_width``.

    Returns ``image0, image1`` (1 x h x w, [0, 1]), ``label0, label1`` (h x w, {0, 1}) and
    ``corr`` (h x w x 2 long): view-1 crop pixel (row, col) of each view-0 crop pixel, -1 if none.
    """
    height, width = rgb_u8.shape[:2]
    image0 = make_view(rgb_u8, rng, cfg, None, jitter=cfg.jitter_target)
    theta = random_warp(rng, cfg)
    image1 = make_view(rgb_u8, rng, cfg, theta)
    corr = correspondences(theta, height, width)
    label0 = keypoint_map(keypoints, height, width)
    label1 = labels_forward(keypoints, corr) if cfg.label_warp == "forward" else labels_inverse(label0, theta)
    ch, cw = cfg.crop_height, cfg.crop_width
    ph, pw = max(height, ch), max(width, cw)
    top, left = int(rng.integers(0, ph - ch + 1)), int(rng.integers(0, pw - cw + 1))
    crop = (slice(top, top + ch), slice(left, left + cw))
    return {
        "image0": _pad_to(image0, ph, pw)[:, crop[0], crop[1]],
        "image1": _pad_to(image1, ph, pw)[:, crop[0], crop[1]],
        "label0": _pad_to(label0, ph, pw)[crop],
        "label1": _pad_to(label1, ph, pw)[crop],
        "corr": _crop_corr(_pad_to(corr.permute(2, 0, 1), ph, pw, -1).permute(1, 2, 0), top, left, ch, cw),
    }


class PairDataset(Dataset):
    """Training pairs of one epoch of one step: item j = pair of image ``indices[j]`` with its labels."""

    def __init__(self, images: TrainImages, indices: list[int], keypoints: dict[int, np.ndarray],
                 cfg: TrainConfig, round_index: int, kind: str, epoch: int):
        self.images, self.indices, self.keypoints = images, indices, keypoints
        self.cfg, self.round_index, self.kind, self.epoch = cfg, round_index, kind, epoch

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, j: int) -> dict:
        i = self.indices[j]
        rng = rng_for(self.cfg.seed, self.round_index, self.kind, self.epoch, i)
        return make_pair(self.images.rgb(i), self.keypoints[i], rng, self.cfg)
