"""The scene's layout (overview in ``scene.py``). World units are metres, z up.

* ``block`` (the default): the block of box buildings and towers, the pavement tiles in front of
  them, and the cameras walking around it;
* ``ring``: a turntable series: a few textured boxes on a paved plate, photographed from a circle
  of cameras around them, all looking at the object's middle (``Ring``, ``build_ring_faces``,
  ``make_ring_cameras``). With a long lens (``hfov_deg`` about 24: 640 px at a focal length of
  1,500 px) the principal point and the camera rotations are nearly interchangeable there
  (``sfm/principal_point.py``).

Repeated and symmetric structure (``SceneConfig.repeats`` / ``symmetric``; the default builds
neither): the faces come with texture groups, the faces of a group sharing one texture (photo
region, colour gain and grain), so a local feature cannot tell them apart.

* block: the buildings (and towers) along the street repeat with the period 1 / ``repeats`` of
  the street (``build_repeated_faces``): the walk passes the same sequence of facades ``repeats``
  times, on different sides of the block; with ``symmetric`` the street is also mirrored across
  the block's long axis, so the opposite long sides carry the same facades in mirror order.
* ring: with ``repeats`` N > 1 the object is a round temple, N like columns evenly around a
  square core (``build_symmetric_ring_faces``), the same from every 360 / N degrees; with
  ``symmetric`` the boxes are mirrored across a vertical plane (N = 1) or every column is
  mirror-symmetric as well (N > 1).

The ground (pavement tiles, the ring's plate) never repeats: it is what a real street or
turntable has that tells the copies apart.
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
#: Most faces per texture (``SceneConfig.repeats``): beyond it the copies of a block's period
#: become shorter than a building and the ring's columns thinner than a post.
MAX_REPEATS = 8


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
    #: How many faces carry each texture (photo region, colour gain and grain): 1 (the default) gives
    #: every face its own; N > 1 repeats the block's buildings N times around the street (the ring:
    #: N like columns around a core), the copies far apart, as repeated architecture is.
    repeats: int = 1
    #: Mirror the layout: the block's opposite long sides carry the same facades in mirror order (the
    #: short sides are mirrored about their middle); the ring's boxes are mirrored across a vertical plane.
    symmetric: bool = False

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
        if not 1 <= self.repeats <= MAX_REPEATS:
            raise SekdError(f"repeats {self.repeats} is outside 1..{MAX_REPEATS} (faces per texture)")


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


class _Groups:
    """Union-find over hashable keys: the faces of joined keys share one texture."""

    def __init__(self):
        self.parent: dict = {}

    def find(self, key):
        self.parent.setdefault(key, key)
        while self.parent[key] != key:
            self.parent[key] = key = self.parent[self.parent[key]]
        return key

    def union(self, a, b) -> None:
        self.parent[self.find(a)] = self.find(b)

    def numbers(self, keys) -> list[int]:
        """Group number of each key, numbered in order of first appearance."""
        ids: dict = {}
        return [ids.setdefault(self.find(key), len(ids)) for key in keys]


def build_repeated_faces(block: Block, rng: np.random.Generator, textures: int, sizes, repeats: int,
                         symmetric: bool) -> tuple[list[Face], list[int]]:
    """The block's faces with its buildings repeated ``repeats`` times around the street and, with
    ``symmetric``, mirrored across its long axis; returns ``(faces, groups)``, the faces of a group
    to share one texture (the pavement tiles each their own group).

    The street is a loop of arc length s (the four sides' street lines, corner to corner; L in
    all). Buildings and towers are drawn in one fundamental piece of it and copied by the
    symmetry group: s -> s + j L / repeats and, with ``symmetric``, s -> j L / repeats + M - s
    (M = where side 3 starts: y -> -y, side 0 onto side 2 in mirror order, each short side onto
    itself). Every image of a block corner is a break of the piece, so each copy stands on one
    side; a copy at a block corner has no side wall there (as in ``build_faces``). The building
    next to a mirror axis that never falls on a corner is joined with its mirror image into one
    building centred on the axis (its two side walls then one texture), not shown twice side by side.
    """
    length = float(block.lengths.sum())
    starts = np.concatenate([[0.0], np.cumsum(block.lengths)[:-1]])
    period = length / repeats
    mirror = float(starts[3])
    elements = [(False, j * period) for j in range(repeats)] + [(True, j * period) for j in range(repeats) if symmetric]
    lo, span = (mirror / 2, period / 2) if symmetric else (0.0, period)
    tol = 1e-6

    def image(g, s: float) -> float:
        return (g[1] + (mirror - s if g[0] else s)) % length

    def distance(a: float, b: float) -> float:
        return abs((a - b + length / 2) % length - length / 2)

    cuts = sorted((image(g, c) - lo) % length for c in starts for g in elements)
    breaks = [0.0]
    for x in [*cuts, span]:
        if x <= span + tol and x - breaks[-1] > 1e-3:
            breaks.append(min(x, span))
    breaks[-1] = span
    # At a mirror axis that is nowhere a block corner, one building 6-14 m wide stands across the axis.
    pavilion = [symmetric and all(distance(image(g, axis), c) > tol for g in elements for c in starts)
                for axis in (lo, lo + span)]
    designs = []  # (start, end) in s, height, setback, depth, tower
    for a, b in pairwise(breaks):
        head = rng.uniform(3, 7) if pavilion[0] and a == 0 else 0.0  # half the pavilion at the piece's start
        tail = rng.uniform(3, 7) if pavilion[1] and b == span else 0.0
        if b - a - head - tail >= 3:
            edges = [*([0.0] if head else []), *(head + e for e in _split(b - a - head - tail, rng, 6.0, 14.0)),
                     *([b - a] if tail else [])]
        else:  # no room between: the pavilions' halves share the interval
            edges = [0.0, *([(b - a) * head / (head + tail)] if head and tail else []), b - a]
        for index, (e0, e1) in enumerate(pairwise(edges)):
            s0, s1 = lo + a + e0, lo + a + e1
            if head and index == 0:  # with its mirror image across the axis at lo
                s0 = lo - (s1 - lo)
            elif tail and index == len(edges) - 2:  # across the axis at lo + span
                s1 = lo + span + (lo + span - s0)
            designs.append((s0, s1, rng.uniform(6, 18), rng.uniform(0, 1.5), min(10.0, block.hy - 2), False))
    if block.hy >= 30:  # towers 14-20 m behind the street line (8 m deep), 30 m from the piece's ends: clear of
        for a, b in pairwise(breaks):  # their copies and of the next side's towers round a corner
            for along in np.arange(30.0, b - a - 46.0, 45.0):
                along += rng.uniform(0, 10)
                width, height, setback = rng.uniform(10, 16), rng.uniform(22, 35), rng.uniform(14, 20)
                if along + width <= b - a - 30:
                    designs.append((lo + a + along, lo + a + along + width, height, setback, 8.0, True))
    faces: list[Face] = []
    keys: list = []
    groups = _Groups()
    placed: dict = {}
    for d, (s0, s1, height, setback, depth, tower) in enumerate(designs):
        width = s1 - s0
        for g in elements:
            first = image(g, s1 if g[0] else s0)  # the copy's lower end in s
            walls = {"front": (d, "front"), "low": (d, "high" if g[0] else "low"), "high": (d, "low" if g[0] else "high")}
            key = (d, round(first, 4) % round(length, 4))
            if key in placed:  # this copy is the building itself (its own mirror image)
                for part, other in placed[key].items():
                    groups.union(walls[part], other)
                continue
            placed[key] = walls
            k = int(np.searchsorted(starts, (first + width / 2) % length, side="right") - 1)
            a = (first - starts[k]) % length
            if a > block.lengths[k] - tol:
                a -= length
            t2, n2 = block.TANGENTS[k], block.NORMALS[k]
            base = block.corners[k] + t2 * a - n2 * setback
            faces.append(_wall(base, t2, width, height, rng, textures, sizes))
            keys.append(walls["front"])
            if tower or a > tol:  # the wall facing -t, skipped at the block corner
                faces.append(_wall(base - n2 * depth, n2, depth, height, rng, textures, sizes))
                keys.append(walls["low"])
            if tower or a + width < block.lengths[k] - tol:  # the wall facing +t
                faces.append(_wall(base + t2 * width, -n2, depth, height, rng, textures, sizes))
                keys.append(walls["high"])
    for k in range(4):
        ground = _pavement(block, k, rng, textures, sizes)
        keys += [("ground", len(faces) + i) for i in range(len(ground))]
        faces += ground
    return faces, groups.numbers(keys)


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


#: The ring's boxes with a mirror plane (x = 0; ``SceneConfig.symmetric``, one repeat): RING_BOXES' main box and
#: a smaller one on the plane, and two pairs of mirror images. Every box facing the plane has its twin behind it.
RING_MIRRORED_BOXES = ((0.0, 0.0, 2.0, 1.6, 2.4), (0.0, 1.4, 0.8, 0.8, 1.8), (1.6, 0.9, 1.0, 1.2, 1.4),
                       (-1.6, 0.9, 1.0, 1.2, 1.4), (1.7, -1.0, 1.2, 0.9, 1.0), (-1.7, -1.0, 1.2, 0.9, 1.0))
#: The round temple of ``SceneConfig.repeats`` N > 1: N like columns (square, at most RING_COLUMN[0] wide,
#: RING_COLUMN[1] high, m) whose centres stand on a circle of RING_COLUMN_RADIUS m, column k at 360 (k + 1/2) / N
#: deg turned with it, around a square core (RING_CORE: side, height; its walls face 0, 90, 180, 270 deg, between
#: columns for N = 4). The core's walls share a texture where a turn by a multiple of 360 / N deg (or the mirror)
#: takes one onto another: all four for N = 4 or 8, opposite ones for other even N; for odd N they stay unique.
RING_COLUMN_RADIUS = 1.55
RING_COLUMN = (0.7, 2.1)
RING_CORE = (1.5, 1.9)


def _box_faces(x: float, y: float, width: float, depth: float, height: float, rng, textures: int, sizes,
               angle: float = 0.0) -> list[Face]:
    """The four walls (counter-clockwise from above, each facing out) and the top of a box standing on z = 0,
    its width along x turned by ``angle`` (rad) about its centre."""
    corners = [(x - width / 2, y - depth / 2), (x + width / 2, y - depth / 2), (x + width / 2, y + depth / 2),
               (x - width / 2, y + depth / 2)]
    c, s = math.cos(angle), math.sin(angle)
    if angle:
        corners = [(x + c * (px - x) - s * (py - y), y + s * (px - x) + c * (py - y)) for px, py in corners]
    faces = []
    for (ax, ay), (bx, by) in pairwise([*corners, corners[0]]):
        length = math.hypot(bx - ax, by - ay)
        faces.append(_wall((ax, ay), ((bx - ax) / length, (by - ay) / length), length, height, rng, textures, sizes))
    # Top: u = +x, v = -y (turned), so the normal v x u points up; its top-left corner (seen from above) is at max y.
    top = _vec(corners[3], height)
    faces.append(_textured(top, _vec((c, s)), _vec((s, -c)), width, depth, rng, textures, sizes, (0.7, 1.25)))
    return faces


def build_ring_faces(rng: np.random.Generator, textures: int, sizes) -> tuple[list[Face], list[Face]]:
    """``(object faces, plate tiles)`` of the ring: the boxes of RING_BOXES and a plate of 4 x 4 ground tiles."""
    faces = [face for box in RING_BOXES for face in _box_faces(*box, rng, textures, sizes)]
    return faces, _ring_plate(rng, textures, sizes)


def build_symmetric_ring_faces(rng: np.random.Generator, textures: int, sizes, repeats: int,
                               symmetric: bool) -> tuple[list[Face], list[Face], list[int]]:
    """``(object faces, plate tiles, groups)`` of a ring with repeated or mirrored structure: the faces of
    a group (``groups``, per object face) share one texture; the plate's tiles stay unique.

    ``repeats`` N > 1: the round temple (RING_COLUMN...), N-fold: a turn of 360 / N deg takes the
    columns onto themselves (and the square core, for N = 2 and 4), so photos that far apart differ
    only by the plate (and the core's outline for N = 3 or >= 5); with ``symmetric`` also
    mirrored across the vertical plane y = 0 (between columns 0 and N - 1), every column mirror-symmetric
    about its own radial plane. N = 1 with ``symmetric``: the boxes of
    RING_MIRRORED_BOXES, mirrored across the plane x = 0.
    """
    if repeats > 1:
        column = min(RING_COLUMN[0], 0.5 * 2 * math.pi * RING_COLUMN_RADIUS / repeats)
        boxes = [(0.0, 0.0, RING_CORE[0], RING_CORE[0], RING_CORE[1], 0.0)]
        boxes += [(RING_COLUMN_RADIUS * math.cos(a), RING_COLUMN_RADIUS * math.sin(a), column, column, RING_COLUMN[1], a)
                  for a in (2 * math.pi * (k + 0.5) / repeats for k in range(repeats))]
        turns = [np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
                 for a in (2 * math.pi * k / repeats for k in range(1, repeats))]
        mirrors = [np.diag([1.0, -1.0])] if symmetric else []
    else:
        boxes = [(*box, 0.0) for box in (RING_MIRRORED_BOXES if symmetric else RING_BOXES)]
        turns, mirrors = [], [np.diag([-1.0, 1.0])] if symmetric else []
    faces = [face for *box, angle in boxes for face in _box_faces(*box, rng, textures, sizes, angle=angle)]
    transforms = turns + mirrors + [m @ t for m in mirrors for t in turns]
    return faces, _ring_plate(rng, textures, sizes), symmetry_groups(faces, transforms)


def symmetry_groups(faces: list[Face], transforms: list[np.ndarray]) -> list[int]:
    """Per face, its group: faces that one of ``transforms`` (2 x 2 maps of the ground plane, about the
    origin, vertical unchanged) takes onto one another (same centre, normal and size) are in one group."""
    centers = np.array([face.corners().mean(0) for face in faces])
    normals = np.array([face.normal for face in faces])
    shapes = np.array([sorted((face.width, face.height)) for face in faces])
    groups = _Groups()
    for T in transforms:
        M = np.eye(3)
        M[:2, :2] = T
        moved_centers, moved_normals = centers @ M.T, normals @ M.T
        for i in range(len(faces)):
            same = (np.abs(centers - moved_centers[i]).max(1) < 1e-6) & (np.abs(normals - moved_normals[i]).max(1) < 1e-6)
            same &= np.abs(shapes - shapes[i]).max(1) < 1e-6
            for j in np.flatnonzero(same):
                groups.union(i, int(j))
    return groups.numbers(range(len(faces)))


def _ring_plate(rng: np.random.Generator, textures: int, sizes) -> list[Face]:
    """The ring's plate: 4 x 4 ground tiles."""
    tile = RING_PLATE / 4
    plate = []
    for i in range(4):
        for j in range(4):
            x0, y1 = -RING_PLATE / 2 + i * tile, -RING_PLATE / 2 + (j + 1) * tile
            plate.append(_textured(_vec((x0, y1)), _vec((1, 0)), _vec((0, -1)), tile, tile, rng, textures, sizes,
                                   (0.45, 0.8)))
    return plate


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
