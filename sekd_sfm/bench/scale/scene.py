"""A large scene with known cameras: a city block of box buildings textured with photos
(``SceneConfig(layout="block")``, the default), or a turntable ring (``layout="ring"``, below).

Layout (``layout.py``; world units are metres, z up): a rectangular block, twice as long as
wide, whose perimeter grows with the number of photos. Along each side stand box buildings
(6-14 m wide, 6-18 m high, set back 0-1.5 m from the street line, so their side walls show),
with taller towers behind them on large blocks, and a textured pavement strip in front. Every
upright face carries its own region of a photo (``texturing.assign_textures``: tiles of the
photos, never one region twice while the photos last; the faces that fill most of a view take
whole photos first, far towers and side walls the finer tiles; every crop at least 70 %
textured, so no photo of the walk sees only sky or a black screen) with its own colour
gain, and every pavement tile its own generated texture (``pavement_texture``), so no two
faces share content: repeated content (even mirrored: symmetric structures match across the
mirror) would hand retrieval and matching look-alikes that no real street has this often.
Unless asked for: ``SceneConfig.repeats`` N > 1 repeats the buildings (front, side walls: photo
region, gain and grain) N times around the street, the copies on other sides of the block, and
``symmetric`` mirrors the street across the block's long axis (opposite long sides carry the same
facades in mirror order); on the ring, N like columns around a core, or mirrored boxes
(``layout.py``). Look-alikes that pass geometric verification while being wrong: the test of
repeated and symmetric structure. The pavement stays unique, the ground truth geometric (a texture
seen on two faces makes no pair co-visible), and scene.json counts the copies (``repeated``).
Every facade also carries a surface grain of its own (``grain_texture``, ``GRAIN_TEXELS``
per metre, added to the photo by ``add_grain``): the fixed pool of photos cannot texture a long walk at
the camera's resolution (at 1,000 photos the median facade gets 22 photo texels per metre,
the photos see 74 pixels per metre), and a photo magnified three to seven times is a blank
wall to any local feature, unlike a real facade photographed from the street.

The camera walks once around the block (one photo every ``spacing`` m, 6-9 m from the
facades, 1.5-1.7 m high), looking at the buildings with small yaw / pitch / roll jitter,
and each photo gets its own exposure (gain and gamma) and sensor noise
(``evaluation.samplers.expose_u8``). A few unrelated photos (distractors, never used as
textures) are mixed in at random positions.

The ring (``layout.py``: ``Ring``, ``build_ring_faces``, ``make_ring_cameras``): a few box
"buildings" (the largest 2 x 1.6 x 2.4 m) on a 7 x 7 m paved plate, photographed by ``num_images``
cameras evenly spaced on a circle around them, 20 deg above their middle and looking at it, at the
distance where the object fills the photos' short side (0.5 deg aiming and 1 % distance jitter, no
distractors). Its faces take photo textures and grain as the block's, its plate generated pavement,
both at the photos' pixels per metre. With ``hfov_deg=24`` at 640 px (focal length 1,505 px) it is a
long lens around one object, where the principal point is not observable (``sfm/principal_point.py``).

Rendering is exact (``rendering.py``: each face by the homography of its plane, with a depth
test). Pixel coordinates follow OpenCV (integer = pixel centre); COLMAP's convention puts the
centre of the first pixel at 0.5, so its principal point is ours + 0.5.

Files written into the scene folder::

    images/NNNNN.jpg            the photos (scene photos and distractors, in one name sequence)
    gt_dense_cameras/*.camera   Strecha-format ground truth of the scene photos (evaluation/strecha.py)
    scene.json                  configuration, per-photo K / R / t (world-to-camera), distractors
    covisibility.txt            "name0 name1 shared overlap overlap01 overlap10" for every pair of
                                scene photos that see a common face sample point: overlap =
                                shared / min(visible); overlap01 = the fraction of photo 0's
                                surface pixels (an 8 px grid, back-projected with the rendered
                                depth) that photo 1 sees unoccluded, from a direction at most
                                MATCHABLE_ANGLE_DEG away; overlap10 the converse
                                (``covisibility.py`` says why the direction matters)

This module generates and reads a scene; the names of its parts (geometry, layout, texturing,
rendering, co-visibility) are importable from here too.
"""
from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ...errors import SekdError
from ...evaluation.samplers import expose_u8
from .covisibility import (
    MATCHABLE_ANGLE_DEG,
    SurfaceView,
    covisibility_counts,
    pair_ray_angles,
    pixel_overlap,
    read_covisibility,
    visible_points,
    write_covisibility,
)
from .geometry import NEAR, Camera, Face
from .layout import (
    LAYOUTS,
    MIN_PERIMETER,
    Block,
    Ring,
    SceneConfig,
    build_faces,
    build_repeated_faces,
    build_ring_faces,
    build_symmetric_ring_faces,
    make_cameras,
    make_ring_cameras,
)
from .rendering import candidate_faces, render, render_layers
from .texturing import (
    GRAIN_SCALE,
    GRAIN_TEXELS,
    MIN_TEXTURED,
    PAVEMENT_TEXELS,
    Textures,
    add_grain,
    apparent_size,
    assign_shared_textures,
    assign_textures,
    grain_texture,
    pavement_texture,
    texture_cells,
    textured_fraction,
)

__all__ = [
    "FORMAT", "GRAIN_SCALE", "GRAIN_TEXELS", "LAYOUTS", "MATCHABLE_ANGLE_DEG", "MIN_TEXTURED", "NEAR",
    "PAVEMENT_TEXELS", "Block", "Camera", "Face", "Layout", "Ring", "SceneConfig", "SurfaceView", "Textures",
    "add_grain", "apparent_size", "assign_shared_textures", "assign_textures", "build_faces", "build_repeated_faces",
    "build_ring_faces", "build_symmetric_ring_faces", "covisibility_counts",
    "generate_scene", "grain_texture", "layout_scene", "make_cameras", "make_ring_cameras", "pair_ray_angles",
    "pavement_texture", "photo_paths", "pixel_overlap", "read_covisibility", "read_scene", "render", "render_layers",
    "texture_cells", "textured_fraction", "write_covisibility",
]

logger = logging.getLogger("sekd")
FORMAT = "sekd-scale-scene/5"
DISTRACTOR_POOL = 32  # photos set aside as distractors, never used as textures


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


def _fit(photo: np.ndarray, width: int, height: int) -> np.ndarray:
    """Scale a photo to cover width x height and crop its centre."""
    ph, pw = photo.shape[:2]
    s = max(width / pw, height / ph)
    resized = cv2.resize(photo, (max(width, round(pw * s)), max(height, round(ph * s))), interpolation=cv2.INTER_AREA)
    y, x = (resized.shape[0] - height) // 2, (resized.shape[1] - width) // 2
    return resized[y: y + height, x: x + width]


@dataclass
class Layout:
    """Everything a scene's photos are rendered from (``layout_scene``)."""

    block: Block | Ring
    faces: list[Face]
    cameras: list[Camera]           # the scene photos' cameras, in name order
    textures: Textures
    pool: list[Path]                # photos set aside as distractors
    names: list[str]                # every photo's name, scene photos and distractors
    distractor_slots: set[int]      # positions of the distractors in ``names``
    apparent: np.ndarray            # per face, ``apparent_size`` (sr): how much of a view it can fill
    #: Per face, the face whose texture it shows (itself unless ``SceneConfig.repeats`` / ``symmetric`` made it a copy).
    shown: list[int] | None = None

    def repeated(self) -> dict:
        """How the faces share textures: photo-textured faces, their distinct textures, the most faces on one."""
        shown = self.shown or list(range(len(self.faces)))
        photo = [i for i, face in enumerate(self.faces) if self.textures.paths[face.texture] is not None]
        counts = np.bincount([shown[i] for i in photo])
        return {"faces": len(photo), "textures": int((counts > 0).sum()), "most_copies": int(counts.max(initial=0))}

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
    if config.layout == "ring":
        return _layout_ring(config, rng, textures, texture_paths, pool)
    num_distractors = min(DISTRACTOR_POOL, max(1, round(config.num_images * config.distractor_fraction)))
    num_scene = config.num_images - num_distractors
    if num_scene < 2:
        raise SekdError(f"{config.num_images} images leave {num_scene} scene photos after {num_distractors} distractors")
    block = Block(max(MIN_PERIMETER, num_scene * config.spacing), config.distance)
    cameras = make_cameras(block, config, num_scene)
    cells = [texture_cells(textures.level(i, 0)) for i in range(len(texture_paths))]
    if config.repeats == 1 and not config.symmetric:
        faces = build_faces(block, rng, len(texture_paths), textures.sizes)
        groups = list(range(len(faces)))
    else:
        faces, groups = build_repeated_faces(block, rng, len(texture_paths), textures.sizes, config.repeats,
                                             config.symmetric)
    centers = np.array([camera.center for camera in cameras[::4]])
    apparent = apparent_size(faces, centers)
    ground = [abs(face.normal[2]) > 0.5 for face in faces]
    upright = [i for i, flat in enumerate(ground) if not flat]  # facades and towers: photos
    shared = assign_shared_textures([faces[i] for i in upright], [groups[i] for i in upright],
                                    textures.sizes[:len(texture_paths)], np.random.default_rng([config.seed, 3]), cells,
                                    priority=apparent[upright])
    for i in (i for i, flat in enumerate(ground) if flat):  # pavement: a generated texture of its own
        face = faces[i]
        width, height = round(face.width * PAVEMENT_TEXELS), round(face.height * PAVEMENT_TEXELS)
        face.texture, face.crop = textures.add_generated("pavement", width, height, (config.seed, 4, i)), (0, 0, width, height)
    for i, lead in zip(upright, shared):  # facades and towers: a surface grain of their own (their group's), over the photo
        face = faces[i]
        if upright[lead] != i:
            face.grain = faces[upright[lead]].grain
            continue
        size = (max(2, round(face.width * GRAIN_TEXELS)), max(2, round(face.height * GRAIN_TEXELS)))
        face.grain = textures.add_generated("grain", *size, (config.seed, 5, i))
    distractor_slots = set(rng.choice(config.num_images, num_distractors, replace=False).tolist())
    names = [f"{i:05d}.jpg" for i in range(config.num_images)]
    shown = list(range(len(faces)))
    for i, lead in zip(upright, shared):
        shown[i] = upright[lead]
    return Layout(block, faces, cameras, textures, pool, names, distractor_slots, apparent, shown)


def _layout_ring(config: SceneConfig, rng: np.random.Generator, textures: Textures, texture_paths: list[Path],
                 pool: list[Path]) -> Layout:
    """The ring (turntable) scene of ``config``: boxes on a plate, every photo a scene photo (no distractors).

    Textures as on the block: the object's faces take photo regions (the largest apparent faces
    whole photos), with a grain of their own; the plate's tiles generated pavement. Generated
    textures have the photos' pixels per metre at the object (``Ring.texels_per_metre``), so
    they stay sharp under a long lens.
    """
    ring = Ring(config)
    cameras = make_ring_cameras(ring, config, config.num_images)
    if config.repeats == 1 and not config.symmetric:
        objects, plate = build_ring_faces(rng, len(texture_paths), textures.sizes)
        groups = list(range(len(objects)))
    else:
        objects, plate, groups = build_symmetric_ring_faces(rng, len(texture_paths), textures.sizes, config.repeats,
                                                            config.symmetric)
    faces = objects + plate
    cells = [texture_cells(textures.level(i, 0)) for i in range(len(texture_paths))]
    apparent = apparent_size(faces, np.array([camera.center for camera in cameras]))
    shared = assign_shared_textures(objects, groups, textures.sizes[:len(texture_paths)],
                                    np.random.default_rng([config.seed, 3]), cells, priority=apparent[:len(objects)])
    texels = ring.texels_per_metre()
    for i, face in enumerate(faces):
        size = (max(2, round(face.width * texels)), max(2, round(face.height * texels)))
        if i >= len(objects):  # plate tiles: a pavement texture of their own
            face.texture, face.crop = textures.add_generated("pavement", *size, (config.seed, 4, i)), (0, 0, *size)
        elif shared[i] != i:  # a copy: its group's grain
            face.grain = faces[shared[i]].grain
        else:
            face.grain = textures.add_generated("grain", *size, (config.seed, 5, i))
    names = [f"{i:05d}.jpg" for i in range(config.num_images)]
    return Layout(ring, faces, cameras, textures, pool, names, set(), apparent, shared + list(range(len(objects), len(faces))))


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
              **({"ring_distance_m": round(block.distance, 3)} if config.layout == "ring" else {}),
              **({"repeated": layout.repeated()} if config.repeats > 1 or config.symmetric else {}),
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
    if data["layout"] == "block":
        data.pop("layout")  # the block's record as before the ring existed: its scenes stay reusable
    if data["repeats"] == 1:
        data.pop("repeats")  # likewise for scenes from before repeated and symmetric structure
    if not data["symmetric"]:
        data.pop("symmetric")
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
            visible.append(visible_points(camera, face_id, samples, offsets, np.unique(face_id[face_id >= 0])))
            views.append(SurfaceView.of(camera, face_id, depth))
            (out / "gt_dense_cameras" / f"{name}.camera").write_text(_strecha_text(camera))
        _write_image(out / "images" / name, expose_u8(image, rng), config.jpeg_quality)
    return visible, views


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
