"""Hierarchical mapping spread over the run's executor: clusters mapped as tasks, merged into one model.

1. The view graph is cut into overlapping clusters (``partition``), in the driver.
2. Each cluster is mapped by COLMAP's incremental mapper as one task of an ``execution.Stage`` (``ClusterWorker``):
   in a worker process on this machine or on a Ray worker. A task copies its photos' rows of the database
   (keypoints and verified pairs, no descriptors or raw matches) into a small database of its own, maps it, and
   returns the cameras' poses and intrinsics: a few kilobytes. The results are saved cluster by cluster
   (``<database stem>-clusters.h5``): a killed run resumes from the clusters it finished.
3. The mapper's child process (``mapper_worker``) merges them (``cluster_merge``): the largest model first, then
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
import sqlite3
import tempfile
import time
from pathlib import Path

import numpy as np

from ..execution import Executor, Stage, using
from ..files.pairresults import PairResults, write_pair_group
from .colmap import read_only_database, require_pycolmap
from .mapper_worker import quiet_colmap_log
from .partition import ClusterOptions, partition, view_graph

logger = logging.getLogger("sekd")

FORMAT = "sekd-cluster-models"
#: The tables a cluster's database copies whole (a few rows per camera); the others keep its photos' rows only.
WHOLE_TABLES = ("rigs", "rig_sensors", "cameras")
#: Pair id of COLMAP's database: ``image_id1 * PAIR_BASE + image_id2`` with ``image_id1 < image_id2``.
PAIR_BASE = 2147483647


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
