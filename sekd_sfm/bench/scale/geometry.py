"""The scene's geometry: textured rectangles (faces) and pinhole cameras.

World units are metres, z up. Pixel coordinates follow OpenCV (integer = pixel centre).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

NEAR = 0.1          # near clipping plane (m)


@dataclass
class Face:
    """A textured rectangle: top-left corner ``origin``, unit axes ``u`` (right) and ``v`` (down), size in m."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    width: float
    height: float
    texture: int                    # index into the texture photo list
    crop: tuple[int, int, int, int]  # x, y, w, h in the photo (level-0 pixels)
    gain: tuple[float, float, float]  # BGR colour gain
    grain: int = -1                 # index of its surface grain texture (``GRAIN_TEXELS`` per metre), -1: none
    normal: np.ndarray = field(init=False)

    def __post_init__(self):
        # u (right) x v (down) is the viewing direction, so v x u points back towards the viewer.
        self.normal = np.cross(self.v, self.u)

    def corners(self) -> np.ndarray:
        """4 x 3 corners: top-left, top-right, bottom-right, bottom-left."""
        u, v = self.u * self.width, self.v * self.height
        return np.stack([self.origin, self.origin + u, self.origin + u + v, self.origin + v])

    def samples(self, step: float = 0.5, cap: int = 600) -> np.ndarray:
        """M x 3 points on a regular grid over the face (cell centres), at most about ``cap``."""
        step = max(step, math.sqrt(self.width * self.height / cap))
        nu, nv = max(1, round(self.width / step)), max(1, round(self.height / step))
        a = (np.arange(nu) + 0.5) / nu * self.width
        b = (np.arange(nv) + 0.5) / nv * self.height
        aa, bb = np.meshgrid(a, b)
        return self.origin + aa.reshape(-1, 1) * self.u + bb.reshape(-1, 1) * self.v


@dataclass
class Camera:
    """Pinhole camera: ``K`` 3x3 (OpenCV pixel centres), world-to-camera ``R``, ``t``; size in px."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(pixels M x 2, depth M)`` of world points ``M x 3`` (depth <= 0: behind the camera)."""
        cam = points @ self.R.T + self.t
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            pix = (cam @ self.K.T)[:, :2] / z[:, None]
        return pix, z
