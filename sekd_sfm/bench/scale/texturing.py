"""The scene's textures (overview in ``scene.py``): a photo region for every facade
(``assign_textures``; one for every group of faces that repeat a texture: ``assign_shared_textures``),
generated pavement and facade grain, and the texture pyramids the renderer draws from (``Textures``)."""
from __future__ import annotations

import logging
import math
import typing
from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np

from ...errors import SekdError
from .geometry import Face

logger = logging.getLogger("sekd")

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


def assign_shared_textures(faces: list[Face], groups: list[int], sizes: list[tuple[int, int]],
                           rng: np.random.Generator, cells: list[np.ndarray] | None = None,
                           priority: np.ndarray | None = None) -> list[int]:
    """``assign_textures`` for faces in groups that share one texture, in place; returns the representative
    (first face) of each face's group.

    Faces with equal ``groups`` entries show the same photo region with the same colour gain (their
    grain is the caller's to share): the first face of each group takes a region as
    ``assign_textures`` gives it (at the group's largest ``priority``, default area), the others
    copy it. A group is one region, so the photos go round as many groups, not faces. With every
    group a single face this is ``assign_textures``, draw for draw.
    """
    if priority is None:
        priority = np.array([face.width * face.height for face in faces])
    first: dict[int, int] = {}
    best: dict[int, float] = {}
    for i, group in enumerate(groups):
        first.setdefault(group, i)
        best[group] = max(best.get(group, -math.inf), float(priority[i]))
    leaders = sorted(set(first.values()))
    assign_textures([faces[i] for i in leaders], sizes, rng, cells, priority=np.array([best[groups[i]] for i in leaders]))
    representative = [first[group] for group in groups]
    for face, lead in zip(faces, representative):
        face.texture, face.crop, face.gain = faces[lead].texture, faces[lead].crop, faces[lead].gain
    return representative


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
