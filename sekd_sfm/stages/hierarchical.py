"""Hierarchical mapping spread over the run's executor: clusters mapped as tasks, merged into one model.

1. The view graph is cut into overlapping clusters (``partition``), in the driver.
2. Each cluster is mapped by COLMAP's incremental mapper as one task of an ``execution.Stage`` (``ClusterWorker``):
   in a worker process on this machine or on a Ray worker. A task copies its photos' rows of the database
   (keypoints and verified pairs, no descriptors or raw matches) into a small database of its own, maps it, and
   returns the cameras' poses and intrinsics: a few kilobytes. The results are saved cluster by cluster
   (``<database stem>-clusters.h5``): a killed run resumes from the clusters it finished.
3. The mapper's child process (``mapper_worker``) merges them (``merge_pieces``): the largest model first, then
   the one sharing most photos with what is merged, moved by the similarity its shared cameras give (``similarity``:
   robust to a few badly placed cameras, then least squares over the others); the points are triangulated again
   from the whole database with the merged poses held, then one global bundle adjustment fixes the seams.

The same graph gives the same clusters and the same merge, wherever the clusters ran. Photos in multi-camera rigs
keep pycolmap's own hierarchical mapper (its clusters know the rigs' frames).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import shutil
import sqlite3
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..execution import Executor, Stage, using
from ..files.pairresults import PairResults, write_pair_group
from .colmap import read_only_database, require_pycolmap
from .partition import PAIR_BASE, ClusterOptions, partition, view_graph

logger = logging.getLogger("sekd")

FORMAT = "sekd-cluster-models"
#: The tables a cluster's database copies whole (a few rows per camera); the others keep its photos' rows only.
WHOLE_TABLES = ("rigs", "rig_sensors", "cameras")
#: Cameras shared with what is merged a model needs to join it (fewer: it stays a model of its own).
MIN_SHARED = 3
#: A shared camera agrees with the similarity when its rotation is within this angle (deg) ...
MAX_ROTATION_DEG = 5.0
#: ... and its centre within this share of the shared cameras' spread (median distance to their centroid).
MAX_CENTER_SHARE = 0.1


# ----------------------------------------------------------------------------- the clusters' tasks

def can_map_clusters(database) -> bool:
    """Whether ``database``'s clusters can be mapped on the executor: COLMAP 4's frames (pycolmap and the file),
    each holding one photo. A frame of several photos (a camera rig) would be split between clusters: rigs keep
    ``pycolmap.hierarchical_mapping``, which clusters frames."""
    if not hasattr(require_pycolmap().Reconstruction, "register_frame"):
        return False
    with read_only_database(database) as db:
        if db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'frame_data'").fetchone() is None:
            return False
        row = db.execute("SELECT 1 FROM frame_data GROUP BY frame_id HAVING COUNT(*) > 1 LIMIT 1").fetchone()
    return row is None


def copy_cluster(source: Path, target: Path, image_ids: list[int]) -> None:
    """A COLMAP database at ``target`` holding ``source``'s rows for the photos ``image_ids``: their images,
    frames, pose priors, keypoints and the verified pairs among them (no descriptors, no raw matches: the
    incremental mapper reads neither)."""
    with contextlib.closing(sqlite3.connect(target)) as db:
        db.execute("ATTACH DATABASE ? AS src", (f"file:{source}?mode=ro",))
        tables = db.execute("SELECT type, name, sql FROM src.sqlite_master WHERE sql IS NOT NULL "
                            "AND name NOT LIKE 'sqlite_%' ORDER BY type = 'index'").fetchall()
        for _, _, sql in tables:
            db.execute(sql)
        db.execute("CREATE TEMP TABLE chosen (image_id INTEGER PRIMARY KEY)")
        db.executemany("INSERT INTO chosen VALUES (?)", [(int(i),) for i in image_ids])
        names = {name for kind, name, _ in tables if kind == "table"}
        for table in WHOLE_TABLES:
            db.execute(f"INSERT INTO main.{table} SELECT * FROM src.{table}")
        # frame_data's data_id is an image id for cameras (sensor_type 1), the only sensors COLMAP maps.
        db.execute("INSERT INTO main.images SELECT * FROM src.images WHERE image_id IN chosen")
        db.execute("INSERT INTO main.frame_data SELECT * FROM src.frame_data WHERE data_id IN chosen")
        db.execute("INSERT INTO main.frames SELECT * FROM src.frames WHERE frame_id IN "
                   "(SELECT frame_id FROM main.frame_data)")
        if "pose_priors" in names:
            db.execute("INSERT INTO main.pose_priors SELECT * FROM src.pose_priors WHERE corr_data_id IN chosen")
        db.execute("INSERT INTO main.keypoints SELECT * FROM src.keypoints WHERE image_id IN chosen")
        db.execute(f"INSERT INTO main.two_view_geometries SELECT * FROM src.two_view_geometries "
                   f"WHERE pair_id / {PAIR_BASE} IN chosen AND pair_id % {PAIR_BASE} IN chosen")
        db.commit()


def model_arrays(models) -> dict[str, np.ndarray]:
    """A cluster's models as arrays: per registered photo ``image_ids (K,)``, ``model (K,)`` (index of its model,
    largest first) and ``cam_from_world (K, 3, 4)``; per camera of each model ``cameras (C, 2 + P)``: model index,
    camera id, then its parameters (NaN-padded)."""
    models = sorted(models, key=lambda r: (-r.num_reg_images(), -r.num_points3D()))
    ids, index, poses, cameras = [], [], [], []
    for k, model in enumerate(models):
        for image_id in sorted(model.reg_image_ids()):
            ids.append(image_id)
            index.append(k)
            poses.append(model.image(image_id).cam_from_world().matrix())
        for camera_id in sorted({model.image(i).camera_id for i in model.reg_image_ids()}):
            cameras.append([k, camera_id, *model.camera(camera_id).params])
    width = max((len(row) for row in cameras), default=2)
    table = np.full((len(cameras), width), np.nan)
    for row, values in zip(table, cameras):
        row[:len(values)] = values
    return {"image_ids": np.array(ids, np.int64), "model": np.array(index, np.int32),
            "cam_from_world": np.array(poses, np.float64).reshape(-1, 3, 4), "cameras": table}


class ClusterWorker:
    """Hierarchical mapping's per-cluster work (an ``execution.Stage`` worker): for each key of ``clusters``
    (key -> image ids), the incremental mapping of those photos (``model_arrays``). ``options``: pycolmap
    ``IncrementalPipelineOptions``; ``log_prefix``: where COLMAP's log goes (None: nowhere)."""

    def __init__(self, database: str, image_dir: str, options, clusters: dict[str, list[int]],
                 log_prefix: str | None = None):
        from .mapper_worker import quiet_colmap_log

        self.pycolmap = require_pycolmap()
        self.database, self.image_dir, self.options, self.clusters = database, image_dir, options, clusters
        quiet_colmap_log(log_prefix, self.pycolmap)

    def __call__(self, keys: list[str]):
        for key in keys:
            with tempfile.TemporaryDirectory(prefix="sekd-cluster-") as scratch:
                database = Path(scratch) / "cluster.db"
                copy_cluster(Path(self.database), database, self.clusters[key])
                self.pycolmap.set_random_seed(max(0, int(self.options.random_seed)))
                found = self.pycolmap.incremental_mapping(str(database), self.image_dir, str(Path(scratch) / "out"),
                                                          self.options)
                yield key, model_arrays(found.values()), ""


def mapping_inputs(database: Path) -> str:
    """A digest of what the mapper reads from ``database``: cameras, images, keypoint counts and verified pairs
    (not the file's time: pycolmap's ``Database.open`` touches it)."""
    digest = hashlib.sha256()
    with read_only_database(database) as db:
        for query in ("SELECT camera_id, model, width, height, params FROM cameras ORDER BY camera_id",
                      "SELECT image_id, name, camera_id FROM images ORDER BY image_id",
                      "SELECT image_id, rows FROM keypoints ORDER BY image_id",
                      "SELECT pair_id, rows, config, data FROM two_view_geometries ORDER BY pair_id"):
            for row in db.execute(query):
                digest.update(repr(row).encode())
    return digest.hexdigest()


def cluster_keys(clusters: list[list[int]]) -> dict[str, list[int]]:
    """Each cluster under a key naming it (its index; the signature guards against another partition)."""
    return {f"cluster {k:04d}": cluster for k, cluster in enumerate(clusters)}


def map_clusters(database: str | Path, image_dir: str | Path, options, executor: str | Executor = "local", *,
                 log_prefix: str | Path | None = None, progress: bool = True,
                 record: dict | None = None) -> list[dict[str, np.ndarray]]:
    """The clusters of ``database``'s view graph each mapped on ``executor``: their ``model_arrays``, in cluster
    order. ``options``: pycolmap ``HierarchicalPipelineOptions`` (its clustering and incremental options).
    ``record`` gets the clusters' sizes (photos, overlap included), the photos each registered and the seconds."""
    start = time.perf_counter()
    database = Path(database)
    inner = options.incremental_options
    clustering = options.clustering_options
    cut = ClusterOptions(leaf_size=int(clustering.leaf_max_num_images), overlap=int(clustering.image_overlap),
                         neighbours=int(clustering.num_image_matches))
    clusters = cluster_keys(partition(*view_graph(database, int(inner.min_num_matches)), cut))
    signature = json.dumps({"database": mapping_inputs(database), "options": str(options.todict()),
                            "clusters": hashlib.sha256(json.dumps(clusters).encode()).hexdigest()}, sort_keys=True)
    results = PairResults(database.with_name(f"{database.stem}-clusters.h5"), FORMAT, signature, max_items=4)
    stage = Stage(name="mapping clusters", worker=ClusterWorker,
                  args=(str(database.resolve()), str(image_dir), inner, clusters,
                        str(log_prefix) if log_prefix else None),
                  batches=results.missing(list(clusters)), output=results.path, write_group=write_pair_group,
                  unit="cluster", items="clusters", verb="mapped", joinable=False, per_task=1,
                  local_processes=True)
    logger.info("%s: %d clusters of %s photos", database, len(clusters),
                "/".join(str(len(c)) for c in clusters.values()))
    with using(executor) as runner:
        mapped = results.compute(stage, runner, progress)
    pieces = [mapped[key] for key in clusters]
    results.remove()
    if record is not None:
        record.update(photos=[len(c) for c in clusters.values()], registered=[len(p["image_ids"]) for p in pieces],
                      seconds=round(time.perf_counter() - start, 3))
    return pieces


# ----------------------------------------------------------------------------- the merge (mapper's child)

@dataclass
class Piece:
    """One model of one cluster (or what has been merged): photo id -> ``cam_from_world`` (3 x 4), camera id ->
    parameters."""

    poses: dict[int, np.ndarray]
    cameras: dict[int, np.ndarray] = field(default_factory=dict)


def pieces_of(arrays: dict[str, np.ndarray]) -> list[Piece]:
    """The models of one cluster's ``model_arrays``, largest first."""
    pieces = [Piece({}) for _ in range(int(arrays["model"].max()) + 1 if len(arrays["model"]) else 0)]
    for image_id, k, pose in zip(arrays["image_ids"], arrays["model"], arrays["cam_from_world"]):
        pieces[int(k)].poses[int(image_id)] = pose
    for row in arrays["cameras"]:
        params = row[2:]
        pieces[int(row[0])].cameras[int(row[1])] = params[~np.isnan(params)]
    return pieces


def centers(poses: list[np.ndarray]) -> np.ndarray:
    """Camera centres ``(K, 3)`` of ``cam_from_world`` poses ``(K, 3, 4)``."""
    stacked = np.asarray(poses)
    return -np.einsum("kji,kj->ki", stacked[:, :, :3], stacked[:, :, 3])


def _mean_rotation(rotations: np.ndarray) -> np.ndarray:
    """The rotation nearest the mean of ``rotations (K, 3, 3)`` (chordal L2 mean)."""
    u, _, vt = np.linalg.svd(rotations.mean(axis=0))
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (deg) between rotations ``a (K, 3, 3)`` and ``b (3, 3)``."""
    cos = (np.einsum("kij,ij->k", a, b) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def similarity(source: dict[int, np.ndarray], target: dict[int, np.ndarray]):
    """``(scale, R, t)`` taking ``source``'s world to ``target``'s (``x_t = scale * R @ x_s + t``) from the photos
    both hold, and the ids that agree with it; None with fewer than MIN_SHARED agreeing.

    Rotation: the candidate (one per shared camera) most others agree with, averaged over those; scale: the median
    ratio of distances between shared centres; translation: the median offset. Orientations make it well posed
    even where the shared centres lie on a line (a walk's clusters meet along the path)."""
    shared = sorted(set(source) & set(target))
    if len(shared) < MIN_SHARED:
        return None
    src, tgt = np.array([source[i] for i in shared]), np.array([target[i] for i in shared])
    candidates = np.einsum("kji,kjl->kil", tgt[:, :, :3], src[:, :, :3])  # R_k = R_tgt_k^T R_src_k
    votes = [int((_angle_deg(candidates, c) < MAX_ROTATION_DEG).sum()) for c in candidates]
    best = candidates[int(np.argmax(votes))]
    agree = _angle_deg(candidates, best) < MAX_ROTATION_DEG
    if agree.sum() < MIN_SHARED:
        return None
    rotation = _mean_rotation(candidates[agree])
    c_src, c_tgt = centers(src), centers(tgt)
    a, b = np.triu_indices(len(shared), 1)
    d_src = np.linalg.norm(c_src[a] - c_src[b], axis=1)
    d_tgt = np.linalg.norm(c_tgt[a] - c_tgt[b], axis=1)
    usable = (d_src > 1e-9) & agree[a] & agree[b]
    if not usable.any():
        return None
    scale = float(np.median(d_tgt[usable] / d_src[usable]))
    offset = c_tgt - scale * c_src @ rotation.T
    translation = np.median(offset[agree], axis=0)
    spread = float(np.median(np.linalg.norm(c_tgt - c_tgt.mean(axis=0), axis=1)))
    error = np.linalg.norm(c_src @ rotation.T * scale + translation - c_tgt, axis=1)
    agree &= error <= MAX_CENTER_SHARE * max(spread, 1e-9)
    if agree.sum() < MIN_SHARED:
        return None
    # The robust estimates found the agreeing cameras; least squares over them is the precise scale and offset.
    rotated, target = c_src[agree] @ rotation.T, c_tgt[agree]
    rotated_mean, target_mean = rotated.mean(axis=0), target.mean(axis=0)
    spread_src = float(((rotated - rotated_mean) ** 2).sum())
    if spread_src > 1e-18:
        scale = float(((rotated - rotated_mean) * (target - target_mean)).sum()) / spread_src
        translation = target_mean - scale * rotated_mean
    return scale, rotation, translation, [shared[k] for k in np.flatnonzero(agree)]


def moved(pose: np.ndarray, scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """``cam_from_world`` (3 x 4) of a camera of the source world, in the target world of ``similarity``."""
    r = pose[:, :3] @ rotation.T
    return np.c_[r, scale * pose[:, 3] - r @ translation]


def merge_pieces(pieces: list[Piece]) -> list[Piece]:
    """The pieces joined into models: the largest first, then repeatedly the piece sharing most photos with it,
    moved by their ``similarity`` (photos it already holds keep their pose); pieces that join nothing start models
    of their own. Largest model first."""
    left = sorted(pieces, key=lambda p: -len(p.poses))
    models: list[Piece] = []
    while left:
        merged = Piece(dict(left[0].poses), dict(left[0].cameras))
        left = left[1:]
        while left:
            order = sorted(range(len(left)), key=lambda k: -len(set(left[k].poses) & set(merged.poses)))
            joined = None
            for k in order:
                if len(set(left[k].poses) & set(merged.poses)) < MIN_SHARED:
                    break
                found = similarity(left[k].poses, merged.poses)
                if found is not None:
                    joined = k
                    break
            if joined is None:
                break
            piece, (scale, rotation, translation, _) = left.pop(joined), found
            for image_id, pose in piece.poses.items():
                merged.poses.setdefault(image_id, moved(pose, scale, rotation, translation))
            for camera_id, params in piece.cameras.items():
                merged.cameras.setdefault(camera_id, params)
        models.append(merged)
    return sorted(models, key=lambda p: -len(p.poses))


def assemble(piece: Piece, database: str, image_dir: str, options, scratch: Path, pycolmap):
    """A Reconstruction of ``piece``'s photos at its poses and intrinsics, its points triangulated from
    ``database`` with the poses held (COLMAP's point triangulator, ``options``: IncrementalPipelineOptions)."""
    cache_options = pycolmap.DatabaseCacheOptions()
    db = pycolmap.Database.open(database) if hasattr(pycolmap.Database, "open") else pycolmap.Database(database)
    with db:
        names = {image.name for image in db.read_all_images() if image.image_id in piece.poses}
        cache_options.image_names = names
        cache = pycolmap.DatabaseCache.create(db, cache_options)
    model = pycolmap.Reconstruction()
    model.load(cache)
    for camera_id, params in piece.cameras.items():
        if model.exists_camera(camera_id):
            model.camera(camera_id).params = params
    for image_id, pose in piece.poses.items():
        if not model.exists_image(image_id):
            continue  # no verified pair left among the merged photos
        image = model.image(image_id)
        model.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(pose)
        model.register_frame(image.frame_id)
    scratch.mkdir(parents=True, exist_ok=True)
    result = pycolmap.triangulate_points(model, database, image_dir, str(scratch), clear_points=True,
                                         options=options, refine_intrinsics=False)
    shutil.rmtree(scratch, ignore_errors=True)
    return result
