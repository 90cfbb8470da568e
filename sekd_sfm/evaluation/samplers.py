"""Random geometric and photometric changes of images: the samplers of training, distillation and the benchmarks.

Who draws what:

- training pairs (``train/data.py``): :func:`random_affine` / :func:`random_warp` in normalised
  coordinates (x = column, y = row, in [-1, 1]) and :func:`color_jitter` (torchvision's
  ColorJitter on 8-bit values);
- distillation crops (``train/distill.py``): :func:`random_window_homography` and
  :func:`random_view_change` in pixels, and :func:`jitter_gray`;
- the localisation benchmark (``bench/localization.py``): :func:`random_centred_homography`, pixels;
- the scale benchmark's rendered photos (``bench/scale/``): :func:`expose_u8`.

Every sampler draws from the numpy ``Generator`` it is given, in the order its docstring states.
The order is part of the behaviour: training runs resume from their seeds and the benchmarks
regenerate their data from them, so a draw moved, added or dropped changes every image they
make. Where two users' samplers differ in their numbers (a homography composed of matrices or
fitted to moved corners; an exposure with or without a bias, on float or on 8-bit images;
projective terms drawn only when asked or always), both forms are kept, as separate samplers or
as parameters.

torch is not imported at the top: ``bench/scale`` imports this module in the child processes of
its pycolmap baseline, whose measured memory must not hold torch; only :func:`color_jitter`
(which is given a tensor, so torch is loaded already) needs kornia.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    import torch

#: A closed range ``(low, high)`` a value is drawn from uniformly.
Range = Sequence[float]


# --- geometry: matrices ------------------------------------------------------------------

def random_angle(rng: np.random.Generator, low_deg: float, high_deg: float) -> float:
    """One draw: an angle uniform in ``[low_deg, high_deg]`` degrees, returned in radians."""
    return np.deg2rad(rng.uniform(low_deg, high_deg))


def affine_matrix(angle: float, scale_x: float, scale_y: float, shear: float = 0.0,
                  shift: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """The 2 x 3 map ``[[sx cos a, -sy sin(a+s), tx], [sx sin a, sy cos(a+s), ty]]``.

    x scaled by ``scale_x``, y by ``scale_y``, the y axis sheared by ``shear`` (radians), both
    rotated by ``angle`` (radians), then shifted by ``shift`` (the coordinates' units).
    """
    a, s, (tx, ty) = angle, shear, shift
    return np.array([[scale_x * np.cos(a), -scale_y * np.sin(a + s), tx],
                     [scale_x * np.sin(a), scale_y * np.cos(a + s), ty]])


def homography_of(affine: np.ndarray, projective: Sequence[float] = (0.0, 0.0)) -> np.ndarray:
    """The 3 x 3 homography ``[[affine], [g, h, 1]]`` of a 2 x 3 affine map and projective terms ``(g, h)``."""
    return np.vstack([affine, [projective[0], projective[1], 1.0]])


def random_projective_terms(rng: np.random.Generator, perspective: float) -> np.ndarray:
    """Two draws: projective terms ``(g, h)`` of a homography's last row, uniform in
    ``[-perspective, perspective]`` (1 / the coordinates' unit: pixels or normalised units)."""
    return rng.uniform(-perspective, perspective, 2)


def corners_homography(crop_hw: tuple[int, int], corners: np.ndarray) -> np.ndarray:
    """3 x 3 map from the corner pixels of a ``crop_hw`` crop (top-left, top-right, bottom-right,
    bottom-left) to the 4 x 2 ``corners`` (x, y) in the same order."""
    ch, cw = crop_hw
    source = np.array([[0, 0], [cw - 1, 0], [cw - 1, ch - 1], [0, ch - 1]], dtype=np.float32)
    return cv2.getPerspectiveTransform(source, corners.astype(np.float32))


# --- geometry: samplers ------------------------------------------------------------------

def random_affine(rng: np.random.Generator, rotation_deg: Range, shear_deg: Range, scale: Range,
                  translation: Range, isotropic_scale: bool) -> np.ndarray:
    """A training warp ``theta`` (2 x 3, normalised coordinates; :func:`affine_matrix`).

    Draws, in order: rotation (deg), shear (deg), ``sx``, ``sy`` (not when ``isotropic_scale``:
    ``sy = sx``), ``tx``, ``ty`` (normalised units), each uniform in its range.
    """
    angle, shear = random_angle(rng, *rotation_deg), random_angle(rng, *shear_deg)
    sx = rng.uniform(*scale)
    sy = sx if isotropic_scale else rng.uniform(*scale)
    tx, ty = rng.uniform(*translation), rng.uniform(*translation)
    return affine_matrix(angle, sx, sy, shear, (tx, ty))


def random_warp(rng: np.random.Generator, rotation_deg: Range, shear_deg: Range, scale: Range,
                translation: Range, isotropic_scale: bool, perspective: float) -> np.ndarray:
    """:func:`random_affine`, then with ``perspective`` > 0 the 3 x 3 homography ``[[theta], [g, h, 1]]``
    (:func:`random_projective_terms`). ``perspective`` <= 0 draws nothing more and returns the
    2 x 3 map, so runs without it keep their random streams."""
    theta = random_affine(rng, rotation_deg, shear_deg, scale, translation, isotropic_scale)
    if perspective <= 0:
        return theta
    return homography_of(theta, random_projective_terms(rng, perspective))


def random_centred_homography(rng: np.random.Generator, width: int, height: int, max_rotation_deg: float,
                              scale_range: Range, perspective: float) -> np.ndarray:
    """A 3 x 3 pixel homography about the image centre: rotation, isotropic scale and projective
    terms, plus a sub-pixel shift; normalised so ``H[2, 2] = 1``.

    Draws, in order: angle in ``[-max_rotation_deg, max_rotation_deg]``, scale, projective terms
    ``(g, h)`` in ``[-perspective, perspective]`` (1/px; drawn even when 0), shift ``(x, y)`` in
    [-0.5, 0.5] px.
    """
    angle = random_angle(rng, -max_rotation_deg, max_rotation_deg)
    scale = rng.uniform(*scale_range)
    rotation = homography_of(affine_matrix(angle, scale, scale))
    projective = homography_of(np.eye(3)[:2], random_projective_terms(rng, perspective))
    centre = np.array([[1, 0, -width / 2], [0, 1, -height / 2], [0, 0, 1]])
    H = np.linalg.inv(centre) @ rotation @ projective @ centre
    H[:2, 2] += rng.uniform(-0.5, 0.5, 2)
    return H / H[2, 2]


def random_window_corners(rng: np.random.Generator, centre: tuple[float, float], size_hw: tuple[float, float],
                          perspective: float, rotation_deg: float) -> np.ndarray:
    """4 x 2 corners (x, y; top-left first, clockwise) of a ``size_hw`` window around ``centre``
    (pixels), each corner moved up to ``perspective`` x the window's size, then rotated about the
    centre by up to ``rotation_deg``.

    Draws, in order: the 4 x 2 corner moves (fractions of width, height), the angle.
    """
    (wh, ww), (cx, cy) = size_hw, centre
    corners = np.array([[-ww / 2, -wh / 2], [ww / 2, -wh / 2], [ww / 2, wh / 2], [-ww / 2, wh / 2]])
    corners += rng.uniform(-perspective, perspective, (4, 2)) * [ww, wh]
    rotation = affine_matrix(random_angle(rng, -rotation_deg, rotation_deg), 1.0, 1.0)[:, :2]
    return corners @ rotation.T + [cx, cy]


def random_window_homography(rng: np.random.Generator, image_hw: tuple[int, int], crop_hw: tuple[int, int],
                             scale_range: Range, perspective: float, rotation_deg: float) -> np.ndarray:
    """3 x 3 map from crop pixels to image pixels: a random window of the image at a random scale,
    rotated and perspective-distorted (:func:`random_window_corners`).

    Draws, in order: scale (crop pixels per image pixel), window centre y, x (anywhere the
    unmoved window fits), then the corners' draws.
    """
    (h, w), (ch, cw) = image_hw, crop_hw
    scale = rng.uniform(*scale_range)
    # Window size in image pixels (a crop pixel covers 1/scale image pixels), never larger than the image.
    wh, ww = min(h, ch / scale), min(w, cw / scale)
    cy, cx = rng.uniform(wh / 2, h - wh / 2), rng.uniform(ww / 2, w - ww / 2)
    return corners_homography(crop_hw, random_window_corners(rng, (cx, cy), (wh, ww), perspective, rotation_deg))


def random_view_change(rng: np.random.Generator, crop_hw: tuple[int, int], scale_range: Range,
                       perspective: float, rotation_deg: float) -> np.ndarray:
    """3 x 3 map from a second view's crop pixels to the first view's: scale, perspective warp and
    rotation about the crop centre, so the views overlap mostly.

    Draws, in order: scale, then the corners' draws (:func:`random_window_corners`).
    """
    ch, cw = crop_hw
    scale = rng.uniform(*scale_range)
    window = random_window_corners(rng, ((cw - 1) / 2, (ch - 1) / 2), (ch / scale, cw / scale), perspective,
                                   rotation_deg)
    return corners_homography(crop_hw, window)


# --- photometry --------------------------------------------------------------------------

@dataclass(frozen=True)
class Exposure:
    """A global brightness change: ``(gain * x + bias) ** gamma`` on values ``x`` in [0, 1]."""

    gain: float
    gamma: float
    bias: float = 0.0


def random_exposure(rng: np.random.Generator, gain: Range, gamma: Range, bias: Range | None = None) -> Exposure:
    """Draws, in order: gain, bias (only when ``bias`` is given, else 0), gamma; each uniform in its range."""
    drawn_gain = rng.uniform(*gain)
    drawn_bias = rng.uniform(*bias) if bias is not None else 0.0
    return Exposure(drawn_gain, rng.uniform(*gamma), drawn_bias)


def jitter_gray(image: np.ndarray, rng: np.random.Generator, gain: Range = (0.6, 1.4), bias: Range = (-0.15, 0.15),
                gamma: Range = (0.7, 1.4), blur_chance: float = 0.25, blur_sigma: Range = (0.3, 1.2),
                noise_chance: float = 0.5, noise_sigma: Range = (0.0, 0.03)) -> np.ndarray:
    """Exposure, occasional Gaussian blur and noise on a float ``H x W`` image in [0, 1]; rounded to 8-bit levels.

    Draws, in order: the exposure (:func:`random_exposure` with bias), whether to blur, the blur
    sigma (px), whether to add noise, the noise sigma (in [0, 1] units), the noise image.
    Returns float64 ``H x W`` in [0, 1], multiples of 1/255.
    """
    exposure = random_exposure(rng, gain, gamma, bias)
    image = np.clip(image * exposure.gain + exposure.bias, 0, 1) ** exposure.gamma
    if rng.random() < blur_chance:
        image = cv2.GaussianBlur(image, (0, 0), rng.uniform(*blur_sigma))
    if rng.random() < noise_chance:
        image = image + rng.normal(0, rng.uniform(*noise_sigma), image.shape)
    # Photos are 8-bit: round like a decoded image, so what is jittered looks like a real input.
    return np.round(np.clip(image, 0, 1) * 255) / 255


def expose_u8(image: np.ndarray, rng: np.random.Generator, gain: Range = (0.75, 1.25), gamma: Range = (0.8, 1.25),
              noise_sigma: float = 2.0) -> np.ndarray:
    """One camera exposure and sensor noise on an 8-bit image (any shape, uint8).

    Draws, in order: the exposure (:func:`random_exposure`, no bias), the Gaussian noise image
    (``noise_sigma`` grey levels, truncated to integers). Returns uint8 of the same shape.
    """
    exposure = random_exposure(rng, gain, gamma)
    # A lookup table of the 256 levels: the exposure as a camera's tone curve, truncated to 8 bits.
    levels = np.clip(exposure.gain * np.arange(256) / 255.0, 0, 1) ** exposure.gamma
    lut = np.clip(255.0 * levels, 0, 255).astype(np.uint8)
    image = cv2.LUT(image, lut)
    noise = rng.normal(0.0, noise_sigma, size=image.shape).astype(np.int16)
    return np.clip(image.astype(np.int16) + noise, 0, 255).astype(np.uint8)


# --- photometry: colour jitter of training (torchvision ColorJitter on 8-bit values) -----------

def _gray_u8(rgb: torch.Tensor) -> torch.Tensor:
    """torchvision's uint8 grayscale (truncated), ``3 x H x W`` -> ``1 x H x W``."""
    return (0.2989 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]).floor()[None]


def _blend(a: torch.Tensor, b: torch.Tensor | float, ratio: float) -> torch.Tensor:
    # Truncation after every op mirrors torchvision on uint8 tensors.
    return (ratio * a + (1.0 - ratio) * b).clamp(0, 255).floor()


def _shift_hue(rgb: torch.Tensor, shift: float) -> torch.Tensor:
    """Hue turned by ``shift`` turns (fractions of the colour circle); ``3 x H x W`` 0..255 in and out."""
    import kornia  # here, not at the top: see the module docstring (torch stays out of bench/scale)

    hsv = kornia.color.rgb_to_hsv(rgb[None] / 255.0)[0]
    hsv[0] = (hsv[0] / (2 * math.pi) + shift).remainder(1.0) * (2 * math.pi)
    return (kornia.color.hsv_to_rgb(hsv[None])[0] * 255.0).clamp(0, 255).floor()


def color_jitter(rgb: torch.Tensor, rng: np.random.Generator, brightness: Range, contrast: Range,
                 saturation: Range, hue: Range) -> torch.Tensor:
    """Brightness, contrast, saturation and hue in a random order; ``3 x H x W`` float holding 0..255 integers.

    Draws, in order: the order (a permutation of 4), brightness, contrast, saturation factors,
    the hue shift (turns). All are drawn even for an op whose range is the identity (``[1, 1]``,
    hue ``[0, 0]``), which is skipped as torchvision skips it (hue 0 would still round).
    """
    order = rng.permutation(4)
    b, c, s = (rng.uniform(*r) for r in (brightness, contrast, saturation))
    h = rng.uniform(*hue)
    identity = [list(brightness) == [1, 1], list(contrast) == [1, 1], list(saturation) == [1, 1],
                list(hue) == [0, 0]]
    for op in order:
        if identity[op]:
            continue
        if op == 0:
            rgb = _blend(rgb, rgb.new_zeros(rgb.shape), b)
        elif op == 1:
            rgb = _blend(rgb, _gray_u8(rgb).mean(), c)
        elif op == 2:
            rgb = _blend(rgb, _gray_u8(rgb), s)
        else:
            rgb = _shift_hue(rgb, h)
    return rgb
