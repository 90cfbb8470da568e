"""The scene's layout (overview in ``scene.py``). World units are metres, z up.

* ``block`` (the default): the block of box buildings and towers, the pavement tiles in front of
  them, and the cameras walking around it;
* ``ring``: a turntable series: a few textured boxes on a paved plate, photographed from a circle
  of cameras around them, all looking at the object's middle (``Ring``, ``build_ring_faces``,
  ``make_ring_cameras``). With a long lens (``hfov_deg`` about 24: 640 px at a focal length of
  1,500 px) the principal point and the camera rotations are nearly interchangeable there
  (``sfm/principal_point.py``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

import cv2
import numpy as np

from ...errors import SekdError
from .geometry import Camera, Face

MIN_PERIMETER = 200.0  # keeps the block at least ~24 m wide, so buildings of opposite sides never meet
#: What ``SceneConfig.layout`` accepts.
LAYOUTS = ("block", "ring")


@dataclass
class SceneConfig:
    """Scene generation settings. ``num_images`` counts scene photos plus distractors."""

    num_images: int = 100
    image_size: int = 640          # long side (px); the short side is 3/4 of it
    hfov_deg: float = 60.0         # horizontal field of view
    spacing: float = 1.5           # metres walked between two consecutive photos
    distance: float = 7.5          # mean distance from the street line of the facades (m)
    distractor_fraction: float = 0.03
    jpeg_quality: int = 92
    seed: int = 0
    textures: str | None = None    # folder of photos; default $SEKD_SHARED/data/train/coco
    #: ``block`` (a walk around a city block) or ``ring`` (a turntable: cameras on a circle around an
    #: object; ``spacing``, ``distance`` and ``distractor_fraction`` do not apply, there are no distractors).
    layout: str = "block"

    def __post_init__(self):
        if self.layout not in LAYOUTS:
            raise SekdError(f"unknown scene layout {self.layout!r}; choose from {', '.join(LAYOUTS)}")
        if self.num_images < 2:
            raise SekdError(f"a scene needs at least 2 images, got {self.num_images}")
        if self.image_size < 32:
            raise SekdError(f"image size {self.image_size} px is too small; use at least 32")
        if not 10 <= self.hfov_deg <= 120:
            raise SekdError(f"field of view {self.hfov_deg} deg is outside 10..120")
        if self.spacing <= 0 or self.distance <= 2:
            raise SekdError("spacing must be > 0 m and distance > 2 m")


_UP = np.array([0.0, 0.0, 1.0])
_DOWN = -_UP


def _vec(xy, z: float = 0.0) -> np.ndarray:
    return np.array([xy[0], xy[1], z], dtype=np.float64)


class Block:
    """The block's rectangle (half extents ``hx`` = 2 ``hy``) and the camera path around it."""

    TANGENTS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]], np.float64)
    NORMALS = np.array([[0, -1], [1, 0], [0, 1], [-1, 0]], np.float64)  # outward, side k

    def __init__(self, perimeter: float, distance: float):
        self.distance = distance
        # Path perimeter = 4 hx + 4 hy + 2 pi d with hx = 2 hy.
        self.hy = max(perimeter - 2 * math.pi * distance, 1.0) / 12
        self.hx = 2 * self.hy
        h = np.array([self.hx, self.hy])
        self.corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64) * h
        self.lengths = np.array([2 * self.hx, 2 * self.hy, 2 * self.hx, 2 * self.hy])
        arc = math.pi / 2 * distance
        self.segments = [length for side in self.lengths for length in (side, arc)]
        self.perimeter = float(sum(self.segments))

    def path(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """``(point on the street line offset by distance, outward normal)`` at arc length ``s`` (2-vectors)."""
        s = s % self.perimeter
        for index, length in enumerate(self.segments):
            if s <= length or index == len(self.segments) - 1:
                break
            s -= length
        k = index // 2
        if index % 2 == 0:  # straight side k
            n = self.NORMALS[k]
            return self.corners[k] + n * self.distance + self.TANGENTS[k] * s, n
        a = s / self.segments[index] * math.pi / 2  # arc around corner k+1, normal turning from n_k to n_k+1
        n = math.cos(a) * self.NORMALS[k] + math.sin(a) * self.NORMALS[(k + 1) % 4]
        return self.corners[(k + 1) % 4] + n * self.distance, n


def _wall(start2, direction2, width: float, height: float, rng, textures: int, sizes, gain=(0.7, 1.25)) -> Face:
    """A vertical face from ``start2`` along ``direction2`` (its right-to-left order seen from outside)."""
    u = _vec(direction2)
    origin = _vec(start2, height)
    return _textured(origin, u, _DOWN.copy(), width, height, rng, textures, sizes, gain)


def _textured(origin, u, v, width, height, rng, textures: int, sizes, gain) -> Face:
    index = int(rng.integers(textures))
    tw, th = sizes[index]
    aspect = width / height
    scale = rng.uniform(0.6, 1.0)
    if tw / th > aspect:
        ch = max(8, int(th * scale))
        cw = max(8, min(tw, round(ch * aspect)))
    else:
        cw = max(8, int(tw * scale))
        ch = max(8, min(th, round(cw / aspect)))
    x, y = int(rng.integers(0, tw - cw + 1)), int(rng.integers(0, th - ch + 1))
    g = tuple(float(v_) for v_ in rng.uniform(*gain, size=3))
    return Face(origin, u, v, float(width), float(height), index, (x, y, cw, ch), g)


def build_faces(block: Block, rng: np.random.Generator, textures: int, sizes) -> list[Face]:
    """Every face of the scene: building fronts and side walls, towers, pavement tiles."""
    faces: list[Face] = []
    for k in range(4):
        t2, n2, corner, length = block.TANGENTS[k], block.NORMALS[k], block.corners[k], block.lengths[k]
        edges = _split(length, rng, 6.0, 14.0)
        depth = min(10.0, block.hy - 2)
        for i, (a, b) in enumerate(pairwise(edges)):
            setback, height = rng.uniform(0, 1.5), rng.uniform(6, 18)
            base = corner + t2 * a - n2 * setback
            faces.append(_wall(base, t2, b - a, height, rng, textures, sizes))
            if i > 0:  # left wall (faces -t); skipped at the block corner where it would lie in the next side's front
                faces.append(_wall(base - n2 * depth, n2, depth, height, rng, textures, sizes))
            if i < len(edges) - 2:  # right wall (faces +t)
                faces.append(_wall(base + t2 * (b - a), -n2, depth, height, rng, textures, sizes))
        faces += _towers(block, k, rng, textures, sizes)
        faces += _pavement(block, k, rng, textures, sizes)
    return faces


def _split(length: float, rng, low: float, high: float) -> list[float]:
    """Cut ``[0, length]`` at random widths in [low, high]; the last piece is merged if shorter than ``low``/2."""
    edges = [0.0]
    while length - edges[-1] > high:
        edges.append(edges[-1] + rng.uniform(low, high))
    if length - edges[-1] < low / 2 and len(edges) > 1:
        edges.pop()
    return edges + [length]


def _towers(block: Block, k: int, rng, textures: int, sizes) -> list[Face]:
    """Tall boxes 14-20 m behind the street line, seen over the roofs (only on blocks wide enough)."""
    if block.hy < 30:
        return []
    t2, n2, corner, length = block.TANGENTS[k], block.NORMALS[k], block.corners[k], block.lengths[k]
    faces = []
    for a in np.arange(25.0, length - 40.0, 45.0):
        a += rng.uniform(0, 10)
        width, height, setback = rng.uniform(10, 16), rng.uniform(22, 35), rng.uniform(14, 20)
        base = corner + t2 * a - n2 * setback
        faces.append(_wall(base, t2, width, height, rng, textures, sizes))
        faces.append(_wall(base - n2 * 8, n2, 8, height, rng, textures, sizes))
        faces.append(_wall(base + t2 * width, -n2, 8, height, rng, textures, sizes))
    return faces


def _pavement(block: Block, k: int, rng, textures: int, sizes, width: float = 16.0, tile: float = 8.0) -> list[Face]:
    """Ground tiles in front of side k (two rows of ``tile`` m) and the corner square after it."""
    t2, n2, corner, length = block.TANGENTS[k], block.NORMALS[k], block.corners[k], block.lengths[k]
    faces = []
    # Seen from above the normal v x u must point up; flip v where u = t, v = n gives it pointing down.
    u, v = _vec(t2), _vec(n2)
    if np.cross(v, u)[2] < 0:
        v = -v
    edges = _split(length, rng, tile, tile)
    for a, b in pairwise(edges):
        for row in np.arange(0.0, width, tile):
            faces.append(_ground(corner + t2 * a + n2 * row, u, v, n2, b - a, tile, rng, textures, sizes))
    after = block.corners[(k + 1) % 4]
    for along in np.arange(0.0, width, tile):
        for row in np.arange(0.0, width, tile):
            faces.append(_ground(after + t2 * along + n2 * row, u, v, n2, tile, tile, rng, textures, sizes))
    return faces


def _ground(start2, u, v, n2, length, depth, rng, textures, sizes) -> Face:
    origin = _vec(start2)
    if v[:2] @ n2 < 0:  # v points inwards: start from the outer edge
        origin = origin + _vec(n2) * depth
    return _textured(origin, u, v, length, depth, rng, textures, sizes, gain=(0.45, 0.8))


def make_cameras(block: Block, config: SceneConfig, count: int) -> list[Camera]:
    """``count`` cameras walking around the block, looking at the facades with jitter."""
    w = config.image_size
    h = round(w * 3 / 4)
    f = 0.5 * w / math.tan(math.radians(config.hfov_deg) / 2)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    cameras = []
    for i in range(count):
        rng = np.random.default_rng([config.seed, 1, i])
        s = i * config.spacing
        point, n = block.path(s)
        offset = 1.5 * math.sin(2 * math.pi * s / 41.0) + rng.normal(0, 0.15)
        center = _vec(point + n * offset, 1.6 + 0.1 * math.sin(2 * math.pi * s / 23.0) + rng.normal(0, 0.03))
        forward = _vec(-n)
        right = np.cross(forward, _UP)
        down = np.cross(forward, right)
        R_wc = np.stack([right, down, forward], axis=1)
        pitch = math.radians(4.0 + np.clip(rng.normal(0, 2.0), -5, 5))  # +x rotation tilts the view up
        yaw = math.radians(np.clip(rng.normal(0, 8.0), -15, 15))
        roll = math.radians(np.clip(rng.normal(0, 1.5), -4, 4))
        jitter, _ = cv2.Rodrigues(np.array([pitch, yaw, roll]))
        R_wc = R_wc @ jitter
        R = R_wc.T
        cameras.append(Camera(K.copy(), R, -R @ center, w, h))
    return cameras


# ----------------------------------------------------------------------------- the ring (turntable) layout

#: The ring's object: boxes as (centre x, centre y, width along x, depth along y, height), metres, standing on
#: a plate of RING_PLATE x RING_PLATE m; a main block with three smaller ones around it, so the object hides
#: parts of itself from most directions, as a real object on a turntable does.
RING_BOXES = ((0.0, 0.0, 2.0, 1.6, 2.4), (1.6, 0.9, 1.0, 1.2, 1.4), (-1.7, -1.0, 1.2, 0.9, 1.0),
              (-0.9, 1.4, 0.8, 0.8, 1.8))
RING_PLATE = 7.0
#: The point every camera of the ring looks at (the object's middle) and the radius (m) of the sphere
#: around it that fills the short side of the photos: the camera distance follows from the field of view.
RING_TARGET = np.array([0.0, 0.0, 1.0])
RING_OBJECT_RADIUS = 2.2
#: Elevation of the ring's cameras above the target (deg): a turntable photographed from above.
RING_ELEVATION_DEG = 20.0


class Ring:
    """The ring's extent: ``distance`` (camera to target, m), half extents ``hx`` = ``hy`` of the plate,
    ``perimeter`` of the camera circle (the names of ``Block``'s, which scene.json records)."""

    def __init__(self, config: SceneConfig):
        w = config.image_size
        f = 0.5 * w / math.tan(math.radians(config.hfov_deg) / 2)
        half_short_side = math.atan(0.5 * round(w * 3 / 4) / f)
        self.focal = f
        self.distance = RING_OBJECT_RADIUS / math.tan(half_short_side)
        self.hx = self.hy = RING_PLATE / 2
        self.perimeter = 2 * math.pi * self.distance * math.cos(math.radians(RING_ELEVATION_DEG))

    def texels_per_metre(self) -> int:
        """Generated-texture density of the ring: the photos' pixels per metre at the target, at least the block's."""
        return max(48, math.ceil(self.focal / self.distance))


def _box_faces(x: float, y: float, width: float, depth: float, height: float, rng, textures: int, sizes) -> list[Face]:
    """The four walls (counter-clockwise from above, each facing out) and the top of a box standing on z = 0."""
    corners = [(x - width / 2, y - depth / 2), (x + width / 2, y - depth / 2), (x + width / 2, y + depth / 2),
               (x - width / 2, y + depth / 2)]
    faces = []
    for (ax, ay), (bx, by) in pairwise([*corners, corners[0]]):
        length = math.hypot(bx - ax, by - ay)
        faces.append(_wall((ax, ay), ((bx - ax) / length, (by - ay) / length), length, height, rng, textures, sizes))
    # Top: u = +x, v = -y, so the normal v x u points up; its top-left corner (seen from above) is at max y.
    top = _vec(corners[3], height)
    faces.append(_textured(top, _vec((1, 0)), _vec((0, -1)), width, depth, rng, textures, sizes, (0.7, 1.25)))
    return faces


def build_ring_faces(rng: np.random.Generator, textures: int, sizes) -> tuple[list[Face], list[Face]]:
    """``(object faces, plate tiles)`` of the ring: the boxes of RING_BOXES and a plate of 4 x 4 ground tiles."""
    faces = [face for box in RING_BOXES for face in _box_faces(*box, rng, textures, sizes)]
    tile = RING_PLATE / 4
    plate = []
    for i in range(4):
        for j in range(4):
            x0, y1 = -RING_PLATE / 2 + i * tile, -RING_PLATE / 2 + (j + 1) * tile
            plate.append(_textured(_vec((x0, y1)), _vec((1, 0)), _vec((0, -1)), tile, tile, rng, textures, sizes,
                                   (0.45, 0.8)))
    return faces, plate


def make_ring_cameras(ring: Ring, config: SceneConfig, count: int) -> list[Camera]:
    """``count`` cameras evenly around the target (with 1 % distance and ~0.5 deg aiming jitter), looking at it."""
    w = config.image_size
    h = round(w * 3 / 4)
    K = np.array([[ring.focal, 0, (w - 1) / 2], [0, ring.focal, (h - 1) / 2], [0, 0, 1]])
    cameras = []
    for i in range(count):
        rng = np.random.default_rng([config.seed, 1, i])
        azimuth = 2 * math.pi * i / count + math.radians(rng.normal(0, 0.5))
        elevation = math.radians(RING_ELEVATION_DEG + rng.normal(0, 1.0))
        distance = ring.distance * (1 + rng.normal(0, 0.01))
        direction = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                              math.sin(elevation)])
        center = RING_TARGET + distance * direction
        forward = -direction
        right = np.cross(forward, _UP)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R_wc = np.stack([right, down, forward], axis=1)
        jitter, _ = cv2.Rodrigues(np.radians(np.clip(rng.normal(0, [0.5, 0.5, 1.0]), -2, 2)))
        R = (R_wc @ jitter).T
        cameras.append(Camera(K.copy(), R, -R @ center, w, h))
    return cameras
