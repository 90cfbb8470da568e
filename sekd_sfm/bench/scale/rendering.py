"""Exact rendering of the scene's faces into a camera: image, face index and depth per pixel.

Each visible face is drawn with ``cv2.warpPerspective`` by the homography of its plane,
clipped to the near plane, with a per-pixel depth test; sky and the far ground are flat
colours (they carry no features). Pixel coordinates follow OpenCV (integer = pixel centre).
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from .geometry import NEAR, Camera, Face
from .texturing import Textures, add_grain

MAX_RANGE = 90.0    # faces farther than this are not drawn (m); they would be a few pixels
SKY_BGR = (235, 206, 170)
FAR_GROUND_BGR = (96, 100, 104)


def _clip_near(points: np.ndarray, near: float = NEAR) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (camera coordinates, M x 3) to ``z >= near``."""
    out = []
    for i in range(len(points)):
        a, b = points[i], points[(i + 1) % len(points)]
        if a[2] >= near:
            out.append(a)
        if (a[2] >= near) != (b[2] >= near):
            w = (near - a[2]) / (b[2] - a[2])
            out.append(a + w * (b - a))
    return np.array(out)


def _inside_convex(polygon: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """``len(py) x len(px)`` mask of the pixel centres inside a convex polygon (M x 2, either orientation).

    Exact (pixel centre against the edges' half-planes), unlike a rasteriser that also keeps
    the pixels an edge merely touches.
    """
    x, y = polygon[:, 0], polygon[:, 1]
    orientation = np.sign(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) or 1.0
    inside = np.ones((len(py), len(px)), bool)
    for k in range(len(polygon)):
        a, b = polygon[k], polygon[(k + 1) % len(polygon)]
        ex, ey = np.float32(orientation * (b[0] - a[0])), np.float32(orientation * (b[1] - a[1]))
        inside &= ex * (py[:, None] - np.float32(a[1])) >= ey * (px[None, :] - np.float32(a[0]))
    return inside


def _background(camera: Camera) -> np.ndarray:
    """Sky above the horizon, flat far ground below (per pixel: sign of the ray's world z)."""
    h, w = camera.height, camera.width
    M = camera.R.T @ np.linalg.inv(camera.K)  # pixel -> world ray direction
    xs, ys = np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)
    rz = np.float32(M[2, 0]) * xs[None, :] + np.float32(M[2, 1]) * ys[:, None] + np.float32(M[2, 2])
    image = np.empty((h, w, 3), np.uint8)
    image[:] = SKY_BGR
    np.copyto(image, np.array(FAR_GROUND_BGR, np.uint8), where=(rz < 0)[:, :, None])
    return image


def render(camera: Camera, faces: list[Face], textures: Textures, candidates=None) -> tuple[np.ndarray, np.ndarray]:
    """``(BGR image H x W x 3 uint8, face index per pixel H x W int32, -1 = none)``; see ``render_layers``."""
    image, face_id, _ = render_layers(camera, faces, textures, candidates)
    return image, face_id


def render_layers(camera: Camera, faces: list[Face], textures: Textures,
                  candidates=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(BGR image H x W x 3 uint8, face index per pixel H x W int32 (-1 = none), depth H x W float32)``.

    Depth is along the optical axis (m), ``inf`` where no face is drawn.

    Each face is warped by the homography from its texture crop to the image, inside the
    projection of its near-clipped polygon, where it is nearer than what is drawn already.
    """
    h, w = camera.height, camera.width
    image = _background(camera)
    zbuf = np.full((h, w), np.inf, np.float32)
    face_id = np.full((h, w), -1, np.int32)
    K, R, t = camera.K, camera.R, camera.t
    f, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    for index in range(len(faces)) if candidates is None else candidates:
        face = faces[index]
        corners = face.corners() @ R.T + t
        poly = _clip_near(corners)
        if len(poly) < 3:
            continue
        pix = (poly @ K.T)[:, :2] / poly[:, 2:3]
        x0, y0 = max(math.floor(pix[:, 0].min()), 0), max(math.floor(pix[:, 1].min()), 0)
        x1, y1 = min(math.ceil(pix[:, 0].max()) + 1, w), min(math.ceil(pix[:, 1].max()) + 1, h)
        if x0 >= x1 or y0 >= y1:
            continue
        bw, bh = x1 - x0, y1 - y0
        px, py = np.arange(x0, x1, dtype=np.float32), np.arange(y0, y1, dtype=np.float32)
        inside = _inside_convex(pix, px, py)
        # Depth along the optical axis of the plane n.X = d (camera coordinates) at each pixel.
        n = (R @ face.normal).astype(np.float32)
        d = np.float32(n @ (R @ face.origin + t))
        denom = n[0] * ((px - cx) / f)[None, :] + n[1] * ((py - cy) / f)[:, None] + n[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = d / denom
        roi = zbuf[y0:y1, x0:x1]
        update = inside & (depth > 0) & (depth < roi)
        if not update.any():
            continue  # hidden behind what is drawn already
        area = 0.5 * abs(np.dot(pix[:, 0], np.roll(pix[:, 1], 1)) - np.dot(pix[:, 1], np.roll(pix[:, 0], 1)))
        block = (x0, y0, bw, bh)
        warped = _warp(textures, face.texture, face.crop, face, area, camera, block)
        if face.gain != (1.0, 1.0, 1.0):
            warped = cv2.multiply(warped, face.gain + (0.0,), dtype=cv2.CV_8U)
        if face.grain >= 0:
            grain = _warp(textures, face.grain, (0, 0, *textures.sizes[face.grain]), face, area, camera, block)
            warped = add_grain(warped, grain)
        # np.copyto with a mask: far cheaper than boolean fancy indexing on these full-size blocks.
        np.copyto(image[y0:y1, x0:x1], warped, where=update[:, :, None])
        np.copyto(roi, depth, where=update)
        np.copyto(face_id[y0:y1, x0:x1], np.int32(index), where=update)
    return image, face_id, zbuf


def _warp(textures: Textures, index: int, crop: tuple[int, int, int, int], face: Face, area: float,
          camera: Camera, block: tuple[int, int, int, int]) -> np.ndarray:
    """Texture ``index``'s region ``crop`` (x, y, w, h texels) stretched over ``face`` as ``camera``
    sees it, in the image block (x0, y0, w, h); ``area``: the face's projected area (px^2).

    The pyramid level gives about one texel per pixel (the projected area against the crop's).
    """
    x0, y0, bw, bh = block
    cx0, cy0, cw, ch = crop
    level = int(np.clip(math.floor(0.5 * math.log2(max(cw * ch / max(area, 1.0), 1.0))), 0, 2))
    scale = 2.0 ** level
    sx, sy = face.width / cw * scale, face.height / ch * scale
    origin = face.origin - face.u * (cx0 / scale) * sx - face.v * (cy0 / scale) * sy
    R, t = camera.R, camera.t
    H = camera.K @ np.stack([R @ face.u * sx, R @ face.v * sy, R @ origin + t], axis=1)
    H = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]]) @ H
    return cv2.warpPerspective(textures.level(index, level), H, (bw, bh), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REFLECT)


def candidate_faces(camera: Camera, centers: np.ndarray, radii: np.ndarray, origins: np.ndarray,
                    normals: np.ndarray) -> np.ndarray:
    """Indices of faces that may be visible: front side towards the camera, in range, not wholly behind."""
    c = camera.center
    front = np.einsum("ij,ij->i", c - origins, normals) > 1e-9
    dist = np.linalg.norm(centers - c, axis=1)
    depth = (centers - c) @ camera.R[2]
    keep = front & (dist - radii < MAX_RANGE) & (depth + radii > NEAR)
    # Far faces first is not needed (depth test); near first avoids overdraw work.
    order = np.argsort(dist[keep])
    return np.flatnonzero(keep)[order]
