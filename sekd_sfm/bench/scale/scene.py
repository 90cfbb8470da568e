"""A large scene with known cameras: a city block of box buildings textured with photos.

Layout (world units are metres, z up): a rectangular block, twice as long as wide, whose
perimeter grows with the number of photos. Along each side stand box buildings (6-14 m
wide, 6-18 m high, set back 0-1.5 m from the street line, so their side walls show), with
taller towers behind them on large blocks, and a textured pavement strip in front. Every
upright face carries its own region of a photo (``assign_textures``: tiles of the photos,
never one region twice while the photos last; the faces that fill most of a view take
whole photos first, far towers and side walls the finer tiles; every crop at least 70 %
textured, so no photo of the walk sees only sky or a black screen) with its own colour
gain, and every pavement tile its own generated texture (``pavement_texture``), so no two
faces share content: repeated content (even mirrored: symmetric structures match across the
mirror) would hand retrieval and matching look-alikes that no real street has this often.
Every facade also carries a surface grain of its own (``grain_texture``, ``GRAIN_TEXELS``
per metre, added to the photo by ``add_grain``): the fixed pool of photos cannot texture a long walk at
the camera's resolution (at 1,000 photos the median facade gets 22 photo texels per metre,
the photos see 74 pixels per metre), and a photo magnified three to seven times is a blank
wall to any local feature, unlike a real facade photographed from the street.

The camera walks once around the block (one photo every ``spacing`` m, 6-9 m from the
facades, 1.5-1.7 m high), looking at the buildings with small yaw / pitch / roll jitter,
and each photo gets its own exposure (gain and gamma) and sensor noise. A few unrelated
photos (distractors, never used as textures) are mixed in at random positions.

Rendering is exact: each visible face is drawn with ``cv2.warpPerspective`` by the
homography of its plane, clipped to the near plane, with a per-pixel depth test; sky and
the far ground are flat colours (they carry no features). Pixel coordinates follow OpenCV
(integer = pixel centre); COLMAP's convention puts the centre of the first pixel at 0.5,
so its principal point is ours + 0.5.

Files written into the scene folder::

    images/NNNNN.jpg            the photos (scene photos and distractors, in one name sequence)
    gt_dense_cameras/*.camera   Strecha-format ground truth of the scene photos (bench/strecha.py)
    scene.json                  configuration, per-photo K / R / t (world-to-camera), distractors
    covisibility.txt            "name0 name1 shared overlap overlap01 overlap10" for every pair of
                                scene photos that see a common face sample point: overlap =
                                shared / min(visible); overlap01 = the fraction of photo 0's
                                surface pixels (an 8 px grid, back-projected with the rendered
                                depth) that photo 1 sees unoccluded, from a direction at most
                                MATCHABLE_ANGLE_DEG away; overlap10 the converse

Co-visibility is measured on points sampled over every face (about one per 0.5 m, at
most 600 per face): a point is seen by a camera when it falls in the image and the face
drawn at its pixel is its own face (so occlusion counts). A surface point seen from two
directions far apart (a facade from both ends of a street, a corner from two sides) is
co-visible but not matchable by local features. On these scenes (N = 250, both SIFT and
SEKD) pairs whose shared points are seen within 60 degrees of each other (median ray angle)
verify 97-100 % of the time, pairs beyond 90 degrees 0-2 %; hence the pixel overlap
(points seen within MATCHABLE_ANGLE_DEG, MegaDepth-style depth reprojection) that the
retrieval ground truth uses.
"""
from __future__ import annotations

import json
import logging
import math
import time
import typing
from collections import OrderedDict
from dataclasses import asdict, dataclass, field
from itertools import pairwise
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ...errors import SekdError

logger = logging.getLogger("sekd")
FORMAT = "sekd-scale-scene/5"
NEAR = 0.1          # near clipping plane (m)
MAX_RANGE = 90.0    # faces farther than this are not drawn (m); they would be a few pixels
DISTRACTOR_POOL = 32  # photos set aside as distractors, never used as textures
MIN_PERIMETER = 200.0  # keeps the block at least ~24 m wide, so buildings of opposite sides never meet
SKY_BGR = (235, 206, 170)
#: Largest angle (deg) between the two viewing rays of a surface point for the point to count
#: as matchable between two photos (see the module docstring).
MATCHABLE_ANGLE_DEG = 60.0
FAR_GROUND_BGR = (96, 100, 104)


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

    def __post_init__(self):
        if self.num_images < 2:
            raise SekdError(f"a scene needs at least 2 images, got {self.num_images}")
        if self.image_size < 32:
            raise SekdError(f"image size {self.image_size} px is too small; use at least 32")
        if not 10 <= self.hfov_deg <= 120:
            raise SekdError(f"field of view {self.hfov_deg} deg is outside 10..120")
        if self.spacing <= 0 or self.distance <= 2:
            raise SekdError("spacing must be > 0 m and distance > 2 m")


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


# ----------------------------------------------------------------------------- layout

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


#: Texture cells (16 x 16 texels) count as textured when their mean gradient magnitude reaches this
#: many grey levels per texel: sky, blank walls and black screens stay below it.
TEXTURED_GRADIENT = 2.0
#: Smallest fraction of textured cells in a face's crop. Crops below it (half sky, a dark
#: screen) leave whole photos without features when the face fills the view, which breaks the
#: camera chain for a reason no benchmark of scale should measure.
MIN_TEXTURED = 0.7
TEXTURE_CELL = 16
#: Texels per metre of the generated pavement textures (about the facades' median).
PAVEMENT_TEXELS = 48
#: Texels per metre of the facades' surface grain: near the photos' 74 pixels per metre at the
#: walk's mean distance, so the grain is sharp where the photo textures are magnified.
GRAIN_TEXELS = 64
#: The grain's standard deviation in grey levels is GRAIN_CONTRAST x brightness + GRAIN_FLOOR
#: (6 % of the brightness, plus 6 levels that dark paint still shows in daylight): weaker than
#: the photo textures' own structure, stronger than the sensor noise (2 levels).
GRAIN_CONTRAST, GRAIN_FLOOR = 0.06, 6.0
#: Grain textures store 128 + GRAIN_SCALE x a unit-variance noise (clipped at 4 standard deviations).
GRAIN_SCALE = 32.0


def texture_cells(photo: np.ndarray, cell: int = TEXTURE_CELL) -> np.ndarray:
    """Mean gradient magnitude (grey levels per texel) of each ``cell`` x ``cell`` block of a BGR photo.

    Returns an (H // cell, W // cell) float32 array.
    """
    grey = cv2.cvtColor(photo, cv2.COLOR_BGR2GRAY) if photo.ndim == 3 else photo
    grey = grey.astype(np.float32)
    # Sobel 3x3 sums 8 neighbour differences: divide by 8 for grey levels per texel.
    magnitude = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3)) / 8
    h, w = magnitude.shape[0] // cell * cell, magnitude.shape[1] // cell * cell
    return magnitude[:h, :w].reshape(h // cell, cell, w // cell, cell).mean(axis=(1, 3))


def textured_fraction(cells: np.ndarray, crop: tuple[int, int, int, int], cell: int = TEXTURE_CELL) -> float:
    """Fraction of the cells inside ``crop`` (x, y, w, h in texels) that are textured (1.0 for crops under one cell)."""
    x, y, w, h = crop
    block = cells[y // cell:(y + h) // cell, x // cell:(x + w) // cell]
    return float((block >= TEXTURED_GRADIENT).mean()) if block.size else 1.0


def _tile_slots(num_faces: int, num_photos: int, rng: np.random.Generator, slack: float) -> list[tuple[int, int, int, int]]:
    """(photo, grid, row, col) tiles, largest first, enough for ``slack`` x ``num_faces``.

    Every photo is cut into a g x g grid; the coarsest g that gives enough tiles, with only as
    many photos cut one level finer (g + 1) as needed: textures stay as large (as sharp) as the
    pool allows, instead of every photo dropping to the finer grid.
    """
    order = rng.permutation(num_photos)
    need = math.ceil(num_faces * slack)
    g = 1
    while g < 16 and num_photos * (g + 1) ** 2 < need:
        g += 1  # at 16 x 16 tiles of a few dozen texels carry no features: stop refining
    finer = 0 if num_photos * g * g >= need or g == 16 else \
        min(num_photos, math.ceil((need - num_photos * g * g) / ((g + 1) ** 2 - g * g)))
    coarse, fine = [], []
    for rank, photo in enumerate(order.tolist()):
        grid = g + 1 if rank < finer else g
        tiles = [(photo, grid, r, c) for r in range(grid) for c in range(grid)]
        (fine if grid > g else coarse).extend(tiles)
    shuffle = rng.permutation
    return [coarse[i] for i in shuffle(len(coarse))] + [fine[i] for i in shuffle(len(fine))]


def apparent_size(faces: list[Face], centers: np.ndarray) -> np.ndarray:
    """Per face, its largest apparent size from the camera centres (N x 3): area x cos(view angle) / distance^2.

    About the solid angle (sr) the face covers from its best viewpoint: near facades rank
    first; pavement seen at a grazing angle and far towers need fewer texels per metre.
    """
    sizes = np.zeros(len(faces))
    for i, face in enumerate(faces):
        middle = face.origin + (face.u * face.width + face.v * face.height) / 2
        rays = centers - middle
        distance = np.maximum(np.linalg.norm(rays, axis=1), 1.0)
        cos = np.clip(rays @ face.normal / distance, 0.0, 1.0)
        sizes[i] = float(np.max(face.width * face.height * cos / distance**2))
    return sizes


def assign_textures(faces: list[Face], sizes: list[tuple[int, int]], rng: np.random.Generator,
                    cells: list[np.ndarray] | None = None, tries: int = 8,
                    priority: np.ndarray | None = None) -> list[Face]:
    """Give every face its own texture region, in place; returns ``faces``.

    Photos (``sizes``: width, height) are cut into tiles
    (``_tile_slots``); faces in decreasing ``priority`` (default: area; ``apparent_size``
    in a scene) take the largest tiles first, each tile used once while
    they last (then reused, with a warning). A face's crop is the largest region of its own
    aspect inside its tile, scaled 0.8-1.0. With ``cells`` (``texture_cells`` of each photo)
    a crop must be at least ``MIN_TEXTURED`` textured: ``tries`` placements, then the next tile.
    """
    if not faces:
        return faces
    slots = _tile_slots(len(faces), len(sizes), rng, slack=1.0 if cells is None else 1.3)
    if priority is None:
        priority = np.array([face.width * face.height for face in faces])
    by_size = np.argsort(-np.asarray(priority), kind="stable")
    next_slot = 0
    for i in by_size:
        face = faces[i]
        while True:
            if next_slot >= len(slots):
                logger.warning("scene: %d faces for %d texture tiles; tiles are reused", len(faces), len(slots))
                next_slot, cells = 0, None  # reuse from the start, textured or not
            photo, grid, row, col = slots[next_slot]
            next_slot += 1
            crop = _crop_in_tile(face, sizes[photo], grid, row, col, rng, None if cells is None else cells[photo], tries)
            if crop is not None:
                face.texture, face.crop = photo, crop
                break
    return faces


def _crop_in_tile(face: Face, size: tuple[int, int], grid: int, row: int, col: int, rng: np.random.Generator,
                  cells: np.ndarray | None, tries: int) -> tuple[int, int, int, int] | None:
    """A crop of the face's aspect inside tile (row, col) of a ``grid`` x ``grid`` photo, textured enough, or None."""
    tw, th = size[0] // grid, size[1] // grid
    aspect = face.width / face.height
    cw0, ch0 = (round(th * aspect), th) if tw / th > aspect else (tw, round(tw / aspect))
    for _ in range(tries if cells is not None else 1):
        scale = rng.uniform(0.8, 1.0)
        cw, ch = max(8, min(tw, round(cw0 * scale))), max(8, min(th, round(ch0 * scale)))
        crop = (col * tw + int(rng.integers(0, tw - cw + 1)), row * th + int(rng.integers(0, th - ch + 1)), cw, ch)
        if cells is None or textured_fraction(cells, crop) >= MIN_TEXTURED:
            return crop
    return None


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


# ----------------------------------------------------------------------------- rendering

class Textures:
    """Texture images with a 3-level pyramid each: photos (kept once loaded) and generated
    textures (pavement, facade grain: made on first use, deterministic for their seed, the least
    recently used dropped beyond ``GENERATED_BYTES``; a walk meets its faces in order)."""

    GENERATED_BYTES = 256 << 20
    MAKERS: typing.ClassVar[dict] = {"pavement": lambda w, h, rng: pavement_texture(w, h, rng),
              "grain": lambda w, h, rng: grain_texture(w, h, rng)}

    def __init__(self, paths: list[Path]):
        self.paths: list[Path | None] = list(paths)
        self._cache: dict[int, list[np.ndarray]] = {}
        self._generated: dict[int, tuple[str, int, int, tuple]] = {}
        self._recent: OrderedDict[int, int] = OrderedDict()  # generated index -> bytes, least recent first
        self.sizes = [_image_size(p) for p in paths]

    def add_generated(self, kind: str, width: int, height: int, seed: tuple) -> int:
        """Register a generated texture of ``kind`` (a key of ``MAKERS``), width x height texels; returns its index."""
        index = len(self.sizes)
        self.paths.append(None)
        self.sizes.append((width, height))
        self._generated[index] = (kind, width, height, seed)
        return index

    def level(self, index: int, level: int) -> np.ndarray:
        if index not in self._cache:
            if index in self._generated:
                kind, width, height, seed = self._generated[index]
                image = self.MAKERS[kind](width, height, np.random.default_rng(list(seed)))
            else:
                image = cv2.imread(str(self.paths[index]), cv2.IMREAD_COLOR)
            if image is None:
                raise SekdError(f"{self.paths[index]}: cannot read this texture photo; remove it or fix it")
            pyramid = [image]
            for _ in range(2):
                pyramid.append(cv2.pyrDown(pyramid[-1]))
            self._cache[index] = pyramid
            if index in self._generated:
                self._recent[index] = sum(p.nbytes for p in pyramid)
                while sum(self._recent.values()) > self.GENERATED_BYTES and len(self._recent) > 1:
                    del self._cache[self._recent.popitem(last=False)[0]]
        if index in self._recent:
            self._recent.move_to_end(index)
        return self._cache[index][level]


def _value_noise(width: int, height: int, rng: np.random.Generator, cells: tuple[int, ...],
                 decay: float) -> np.ndarray:
    """Zero-mean, unit-std multi-octave value noise, H x W float32: per octave a random grid of
    ``cells`` cells along the long side, upsampled (cubic), the amplitude times ``decay`` per octave."""
    grey = np.zeros((height, width), np.float32)
    amplitude = 1.0
    for n in cells:
        grid = rng.standard_normal((max(2, height * n // max(width, height)), max(2, width * n // max(width, height))))
        grey += amplitude * cv2.resize(grid.astype(np.float32), (width, height), interpolation=cv2.INTER_CUBIC)
        amplitude *= decay
    return (grey - grey.mean()) / max(float(grey.std()), 1e-6)


def grain_texture(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """A facade's surface grain (H x W x 1 uint8, 128 + ``GRAIN_SCALE`` x unit noise): plaster-like
    noise from 3 texels (5 cm at ``GRAIN_TEXELS``) to a metre, unique for ``rng``. ``add_grain``
    puts it on the face's photo texture."""
    longest = max(width, height)
    octaves = tuple(n for n in (longest // 64, longest // 16, longest // 6, longest // 3) if n >= 2) or (2,)
    grey = _value_noise(width, height, rng, octaves, decay=1.0)
    return np.clip(128 + GRAIN_SCALE * grey, 0, 255).astype(np.uint8)[..., None]


def add_grain(image: np.ndarray, grain: np.ndarray) -> np.ndarray:
    """``image`` (H x W x 3 uint8) + its grain (H x W uint8, ``grain_texture``): each pixel moves by
    the unit noise x (``GRAIN_CONTRAST`` x its brightness + ``GRAIN_FLOOR``) grey levels."""
    noise = (grain.astype(np.float32) - 128) / GRAIN_SCALE
    image = image.astype(np.float32)
    return np.clip(image + noise[..., None] * (GRAIN_CONTRAST * image + GRAIN_FLOOR) + 0.5, 0, 255).astype(np.uint8)


def pavement_texture(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """A paving texture (H x W x 3 uint8 BGR), unique for ``rng``: smooth multi-octave noise, grain,
    stones and cracks. Pavement takes no photo, so the photos go to the facades at full size."""
    grey = 128 + 22 * _value_noise(width, height, rng, (4, 8, 16, 32, 64), decay=0.6)
    grey += rng.normal(0, 9, (height, width)).astype(np.float32)  # grain
    for _ in range(int(rng.integers(20, 60)) * width * height // (384 * 384)):  # stones: small light or dark blobs
        center = (int(rng.integers(width)), int(rng.integers(height)))
        axes = (int(rng.integers(2, 7)), int(rng.integers(2, 7)))
        cv2.ellipse(grey, center, axes, float(rng.uniform(0, 180)), 0, 360, float(rng.uniform(60, 210)), -1)
    for _ in range(int(rng.integers(1, 4))):  # cracks: dark random walks
        point = np.array([rng.uniform(0, width), rng.uniform(0, height)])
        heading = rng.uniform(0, 2 * np.pi)
        for _ in range(int(rng.integers(10, 40))):
            heading += rng.normal(0, 0.5)
            nxt = point + rng.uniform(4, 12) * np.array([np.cos(heading), np.sin(heading)])
            cv2.line(grey, tuple(int(v) for v in point), tuple(int(v) for v in nxt), float(rng.uniform(30, 70)),
                     int(rng.integers(1, 3)))
            point = nxt
    tint = rng.uniform(0.9, 1.1, 3).astype(np.float32)
    return np.clip(grey[..., None] * tint, 0, 255).astype(np.uint8)


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) of a JPEG/PNG without decoding the pixels when possible."""
    try:
        from PIL import Image

        with Image.open(path) as image:
            return image.size
    except Exception:  # noqa: BLE001 - PIL missing or cannot parse: decode with OpenCV below
        image = cv2.imread(str(path))
        if image is None:
            raise SekdError(f"{path}: cannot read this texture photo; remove it or fix it") from None
        return image.shape[1], image.shape[0]


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


def photometric(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One exposure per photo: gain 0.75-1.25, gamma 0.8-1.25, Gaussian noise sigma 2 grey levels."""
    gain, gamma = rng.uniform(0.75, 1.25), rng.uniform(0.8, 1.25)
    lut = np.clip(255.0 * np.clip(gain * np.arange(256) / 255.0, 0, 1) ** gamma, 0, 255).astype(np.uint8)
    image = cv2.LUT(image, lut)
    noise = rng.normal(0.0, 2.0, size=image.shape).astype(np.int16)
    return np.clip(image.astype(np.int16) + noise, 0, 255).astype(np.uint8)


def _fit(photo: np.ndarray, width: int, height: int) -> np.ndarray:
    """Scale a photo to cover width x height and crop its centre."""
    ph, pw = photo.shape[:2]
    s = max(width / pw, height / ph)
    resized = cv2.resize(photo, (max(width, round(pw * s)), max(height, round(ph * s))), interpolation=cv2.INTER_AREA)
    y, x = (resized.shape[0] - height) // 2, (resized.shape[1] - width) // 2
    return resized[y: y + height, x: x + width]


# ----------------------------------------------------------------------------- scene files

def photo_paths(folder: Path) -> list[Path]:
    """Sorted JPEG/PNG photos of ``folder``; SekdError when too few to texture a scene."""
    if not folder.is_dir():
        raise SekdError(f"{folder}: texture folder not found; pass a folder of photos (default $SEKD_SHARED/data/train/coco)")
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    if len(paths) < DISTRACTOR_POOL + 8:
        raise SekdError(f"{folder}: {len(paths)} photos; a scene needs at least {DISTRACTOR_POOL + 8} "
                        f"({DISTRACTOR_POOL} are kept aside as distractors)")
    return paths


def _write_image(path: Path, image: np.ndarray, quality: int) -> None:
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    try:
        if not ok:
            raise OSError("JPEG encoding failed")
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(data.tobytes())
        tmp.replace(path)
    except OSError as exc:
        raise SekdError(f"{path}: cannot write the image ({exc}); check free space and permissions") from None


def _strecha_text(camera: Camera) -> str:
    rows = [*camera.K.tolist(), [0.0, 0.0, 0.0], *camera.R.T.tolist(), camera.center.tolist()]
    return "".join(" ".join(f"{v:.12g}" for v in row) + "\n" for row in rows) + f"{camera.width} {camera.height}\n"


@dataclass
class Layout:
    """Everything a scene's photos are rendered from (``layout_scene``)."""

    block: Block
    faces: list[Face]
    cameras: list[Camera]           # the scene photos' cameras, in name order
    textures: Textures
    pool: list[Path]                # photos set aside as distractors
    names: list[str]                # every photo's name, scene photos and distractors
    distractor_slots: set[int]      # positions of the distractors in ``names``
    apparent: np.ndarray            # per face, ``apparent_size`` (sr): how much of a view it can fill

    def texture_density(self) -> dict:
        """Texels per metre of the facades' photo textures, quantiles weighted by apparent size, of
        their grain, and the pixels per metre of a photo at the walk's mean distance: textures
        sharper than the photos where texels >= pixels. (The generated pavement has ``PAVEMENT_TEXELS``.)"""
        photo = [i for i, face in enumerate(self.faces) if self.textures.paths[face.texture] is not None]
        density = np.array([self.faces[i].crop[2] / self.faces[i].width for i in photo])
        weights = self.apparent[photo]
        order = np.argsort(density)
        weight = np.cumsum(weights[order]) / max(float(weights.sum()), 1e-12)
        quantile = {q: float(density[order][min(np.searchsorted(weight, q), len(order) - 1)]) for q in (0.1, 0.5, 0.9)}
        camera = self.cameras[0]
        return {"texels_per_m_p10": round(quantile[0.1], 1), "texels_per_m_p50": round(quantile[0.5], 1),
                "texels_per_m_p90": round(quantile[0.9], 1),
                "grain_texels_per_m": GRAIN_TEXELS,
                "pixels_per_m_at_walk_distance": round(float(camera.K[0, 0]) / self.block.distance, 1)}


def layout_scene(config: SceneConfig) -> Layout:
    """The scene of ``config``: block, faces, cameras and photo names (deterministic for the seed)."""
    from ...runtime import shared_dir

    folder = Path(config.textures) if config.textures else shared_dir() / "data/train/coco"
    paths = photo_paths(folder)
    rng = np.random.default_rng([config.seed, 0])
    order = rng.permutation(len(paths))
    pool, texture_paths = [paths[i] for i in order[:DISTRACTOR_POOL]], [paths[i] for i in order[DISTRACTOR_POOL:]]
    textures = Textures(texture_paths)
    num_distractors = min(DISTRACTOR_POOL, max(1, round(config.num_images * config.distractor_fraction)))
    num_scene = config.num_images - num_distractors
    if num_scene < 2:
        raise SekdError(f"{config.num_images} images leave {num_scene} scene photos after {num_distractors} distractors")
    block = Block(max(MIN_PERIMETER, num_scene * config.spacing), config.distance)
    cameras = make_cameras(block, config, num_scene)
    cells = [texture_cells(textures.level(i, 0)) for i in range(len(texture_paths))]
    faces = build_faces(block, rng, len(texture_paths), textures.sizes)
    centers = np.array([camera.center for camera in cameras[::4]])
    apparent = apparent_size(faces, centers)
    ground = [abs(face.normal[2]) > 0.5 for face in faces]
    upright = [i for i, flat in enumerate(ground) if not flat]  # facades and towers: photos
    assign_textures([faces[i] for i in upright], textures.sizes[:len(texture_paths)],
                    np.random.default_rng([config.seed, 3]), cells, priority=apparent[upright])
    for i in (i for i, flat in enumerate(ground) if flat):  # pavement: a generated texture of its own
        face = faces[i]
        width, height = round(face.width * PAVEMENT_TEXELS), round(face.height * PAVEMENT_TEXELS)
        face.texture, face.crop = textures.add_generated("pavement", width, height, (config.seed, 4, i)), (0, 0, width, height)
    for i in upright:  # facades and towers: a surface grain of their own, over the photo
        face = faces[i]
        size = (max(2, round(face.width * GRAIN_TEXELS)), max(2, round(face.height * GRAIN_TEXELS)))
        face.grain = textures.add_generated("grain", *size, (config.seed, 5, i))
    distractor_slots = set(rng.choice(config.num_images, num_distractors, replace=False).tolist())
    names = [f"{i:05d}.jpg" for i in range(config.num_images)]
    return Layout(block, faces, cameras, textures, pool, names, distractor_slots, apparent)


def generate_scene(output_dir: str | Path, config: SceneConfig, progress: bool = True) -> Path:
    """Render the scene of ``config`` into ``output_dir``; returns the path of scene.json.

    A folder that already holds a finished scene of the same configuration is reused
    (scene.json is written last). Deterministic: the same configuration gives the same files.
    """
    out = Path(output_dir)
    done = out / "scene.json"
    if done.is_file():
        try:
            previous = json.loads(done.read_text())
        except (OSError, ValueError) as exc:
            raise SekdError(f"{done}: unreadable ({exc}); delete the folder {out} to generate the scene again") from None
        if previous.get("config") == _config_record(config) and previous.get("format") == FORMAT:
            logger.info("%s: scene already generated", out)
            return done
        raise SekdError(f"{out}: holds a scene of another configuration; choose another folder or delete it")
    start = time.perf_counter()
    layout = layout_scene(config)
    names, distractor_slots, cameras, faces = layout.names, layout.distractor_slots, layout.cameras, layout.faces
    textures, pool, block = layout.textures, layout.pool, layout.block
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "gt_dense_cameras").mkdir(exist_ok=True)
    visible, views = _render_all(out, names, distractor_slots, cameras, faces, textures, pool, config, progress)
    scene_names = [n for i, n in enumerate(names) if i not in distractor_slots]
    write_covisibility(out / "covisibility.txt", scene_names, visible, sum(len(f.samples()) for f in faces),
                       cameras, views)
    record = {"format": FORMAT, "config": _config_record(config), "faces": len(faces),
              "texture_density": layout.texture_density(),
              "block_m": [2 * block.hx, 2 * block.hy], "path_perimeter_m": block.perimeter,
              "pixel_convention": "OpenCV (integer = pixel centre); COLMAP principal point = ours + 0.5",
              "distractors": sorted(names[i] for i in distractor_slots),
              "distractor_sources": {names[i]: pool[j].name for j, i in enumerate(sorted(distractor_slots))},
              "images": [{"name": n, "K": c.K.tolist(), "R": c.R.tolist(), "t": c.t.tolist(), "width": c.width,
                          "height": c.height} for n, c in zip(scene_names, cameras)],
              "generation_s": round(time.perf_counter() - start, 2)}
    tmp = done.with_name("scene.json.tmp")
    tmp.write_text(json.dumps(record, indent=1))
    tmp.replace(done)
    logger.info("%s: %d images (%d distractors) in %.1f s", out, config.num_images, len(distractor_slots),
                record["generation_s"])
    return done


def _config_record(config: SceneConfig) -> dict:
    data = asdict(config)
    data.pop("textures")  # a local path; the photos are recorded by name
    return data


def _render_all(out, names, distractor_slots, cameras, faces, textures, pool, config,
                progress) -> tuple[list[np.ndarray], list[SurfaceView]]:
    """Write every photo and its .camera file; returns the visible sample-point ids and surface view of each scene photo."""
    centers = np.array([f.corners().mean(0) for f in faces])
    radii = np.array([0.5 * math.hypot(f.width, f.height) for f in faces])
    origins, normals = np.array([f.origin for f in faces]), np.array([f.normal for f in faces])
    samples = [f.samples() for f in faces]
    offsets = np.cumsum([0] + [len(s) for s in samples])
    visible, views, cams = [], [], iter(cameras)
    pool_index = {slot: j for j, slot in enumerate(sorted(distractor_slots))}
    for i, name in enumerate(tqdm(names, desc="rendering", unit="image", disable=not progress)):
        rng = np.random.default_rng([config.seed, 2, i])
        if i in distractor_slots:
            j = pool_index[i]
            photo = cv2.imread(str(pool[j]), cv2.IMREAD_COLOR)
            if photo is None:
                raise SekdError(f"{pool[j]}: cannot read this photo; remove it or fix it")
            w = config.image_size
            image = _fit(photo, w, round(w * 3 / 4))
        else:
            camera = next(cams)
            candidates = candidate_faces(camera, centers, radii, origins, normals)
            image, face_id, depth = render_layers(camera, faces, textures, candidates)
            visible.append(_visible_points(camera, face_id, samples, offsets, np.unique(face_id[face_id >= 0])))
            views.append(SurfaceView.of(camera, face_id, depth))
            (out / "gt_dense_cameras" / f"{name}.camera").write_text(_strecha_text(camera))
        _write_image(out / "images" / name, photometric(image, rng), config.jpeg_quality)
    return visible, views


def _visible_points(camera: Camera, face_id: np.ndarray, samples, offsets, drawn) -> np.ndarray:
    """Global ids of the sample points whose pixel shows their own face."""
    ids = []
    for index in drawn:
        pix, z = camera.project(samples[index])
        col, row = np.round(pix[:, 0]), np.round(pix[:, 1])
        inside = (z > NEAR) & (col >= 0) & (row >= 0) & (col < camera.width) & (row < camera.height)
        k = np.flatnonzero(inside)
        seen = face_id[row[k].astype(int), col[k].astype(int)] == index
        ids.append(offsets[index] + k[seen])
    return np.concatenate(ids) if ids else np.zeros(0, np.int64)


def covisibility_counts(visible: list[np.ndarray], num_points: int):
    """``(shared, seen)``: shared[i, j] = points seen by both i and j (sparse, symmetric); seen[i] per image."""
    from scipy import sparse

    rows = np.concatenate([np.full(len(v), i) for i, v in enumerate(visible)]) if visible else np.zeros(0, int)
    cols = np.concatenate(visible) if visible else np.zeros(0, int)
    matrix = sparse.csr_matrix((np.ones(len(cols), np.int32), (rows, cols)), shape=(len(visible), num_points))
    matrix.data[:] = 1  # a point counts once per image
    return (matrix @ matrix.T).tocoo(), np.asarray(matrix.sum(axis=1)).ravel()


@dataclass
class SurfaceView:
    """What one photo sees: surface points on a pixel grid, and which face each pixel shows.

    ``points``: M x 3 world points, one per 8 x 8 pixel cell centre showing a face;
    ``point_faces``: M face indices of those points; ``faces``: the face index at every
    ``step``-th pixel (-1 = sky), (H / step) x (W / step) int32.
    """

    points: np.ndarray
    point_faces: np.ndarray
    faces: np.ndarray
    step: int

    @classmethod
    def of(cls, camera: Camera, face_id: np.ndarray, depth: np.ndarray, grid: int = 8, step: int = 2) -> SurfaceView:
        d, f = depth[grid // 2::grid, grid // 2::grid], face_id[grid // 2::grid, grid // 2::grid]
        rows, cols = np.nonzero(f >= 0)
        z = d[rows, cols].astype(np.float64)
        pix = np.stack([cols * grid + grid // 2, rows * grid + grid // 2, np.ones_like(z)], 1)
        cam = (pix @ np.linalg.inv(camera.K).T) * z[:, None]
        points = (cam - camera.t) @ camera.R  # R^T (x - t), row by row
        return cls(points, f[rows, cols], np.ascontiguousarray(face_id[step // 2::step, step // 2::step]), step)


def pixel_overlap(view_a: SurfaceView, camera_a: Camera, view_b: SurfaceView, camera_b: Camera,
                  max_angle: float = MATCHABLE_ANGLE_DEG) -> float:
    """Fraction of photo a's surface pixels that photo b sees unoccluded (b's pixel there shows the
    point's own face) from a direction at most ``max_angle`` deg from a's (the two viewing rays)."""
    if len(view_a.points) == 0:
        return 0.0
    pix, z = camera_b.project(view_a.points)
    col, row = np.floor(pix[:, 0] / view_b.step), np.floor(pix[:, 1] / view_b.step)
    h, w = view_b.faces.shape
    inside = (z > NEAR) & (col >= 0) & (row >= 0) & (col < w) & (row < h)
    k = np.flatnonzero(inside)
    k = k[view_b.faces[row[k].astype(int), col[k].astype(int)] == view_a.point_faces[k]]
    angles = pair_ray_angles(view_a.points[k], camera_a.center, camera_b.center)
    return float((angles <= max_angle).sum() / len(view_a.points))


def pair_ray_angles(points: np.ndarray, center_a: np.ndarray, center_b: np.ndarray) -> np.ndarray:
    """Angle (deg) between the viewing rays from ``center_a`` and ``center_b`` to each of ``points`` (M x 3)."""
    ra, rb = points - center_a, points - center_b
    cos = (ra * rb).sum(1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def write_covisibility(path: Path, names: list[str], visible: list[np.ndarray], num_points: int,
                       cameras: list[Camera], views: list[SurfaceView]) -> Path:
    """Write "name0 name1 shared overlap overlap01 overlap10" for every pair sharing a sample point.

    ``visible[i]``: ids of the face sample points photo i sees (of ``num_points``);
    ``overlap01``: ``pixel_overlap`` of photo 0 in photo 1, ``overlap10`` the converse.
    """
    shared, seen = covisibility_counts(visible, num_points)
    lines = []
    for i, j, count in sorted(zip(shared.row.tolist(), shared.col.tolist(), shared.data.tolist())):
        if i < j and count > 0:
            o01 = pixel_overlap(views[i], cameras[i], views[j], cameras[j])
            o10 = pixel_overlap(views[j], cameras[j], views[i], cameras[i])
            lines.append(f"{names[i]} {names[j]} {count} {count / max(1, min(seen[i], seen[j])):.4f} "
                         f"{o01:.4f} {o10:.4f}\n")
    path.write_text("".join(lines))
    return path


def read_scene(scene_dir: str | Path) -> dict:
    """scene.json of a generated scene, with ``cameras``: name -> Camera; SekdError if missing or malformed."""
    path = Path(scene_dir) / "scene.json"
    try:
        data = json.loads(path.read_text())
        if data.get("format") != FORMAT:
            raise ValueError(f"format {data.get('format')!r}, expected {FORMAT!r}")
        data["cameras"] = {im["name"]: Camera(np.array(im["K"]), np.array(im["R"]), np.array(im["t"]),
                                              im["width"], im["height"]) for im in data["images"]}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SekdError(f"{path}: not a generated scene ({exc}); generate it with `sekd bench scale`") from None
    return data


def read_covisibility(scene_dir: str | Path, min_overlap: float = 0.1,
                      matchable: bool = False) -> dict[frozenset, float]:
    """Ground-truth pairs ``{frozenset((a, b)): overlap}`` with overlap >= ``min_overlap``.

    ``matchable=False``: every co-visible pair (shared face sample points over the smaller
    view's); ``matchable=True``: the pixel overlap, the smaller of the two directions: the
    fraction of each photo's surface pixels that the other sees from at most
    MATCHABLE_ANGLE_DEG away (the pairs local features can match; the retrieval ground truth).
    """
    path = Path(scene_dir) / "covisibility.txt"
    try:
        pairs = {}
        for line in path.read_text().splitlines():
            fields = line.split()
            if len(fields) != 6:
                raise ValueError(f"{len(fields)} columns, expected 6")
            overlap = min(float(fields[4]), float(fields[5])) if matchable else float(fields[3])
            if overlap >= min_overlap:
                pairs[frozenset(fields[:2])] = overlap
    except (OSError, ValueError) as exc:
        raise SekdError(f"{path}: cannot read the co-visibility file ({exc}); generate the scene again") from None
    return pairs
