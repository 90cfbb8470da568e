"""Geometric verification on the run's executor: which matches of each pair one two-view geometry explains.

Per pair, pycolmap's ``estimate_two_view_geometry`` (RANSAC on E, F and H: COLMAP's own verification, pair
for pair the geometry ``pycolmap.geometric_verification`` writes over the whole database, RANSAC seed
included) runs as an ``execution.Stage`` (``VerifyWorker``): in worker processes on this machine or on Ray
workers, saved pair by pair to ``<database stem>-verification.h5`` (a killed run resumes from the pairs it
finished). The driver then writes every pair's geometry into the database. The file stays beside it when the
caller says what the database was made from (``signature``): ``sekd reconstruct`` builds its database afresh on
every run, and a run killed while mapping, or run again with other mapper settings, reuses the geometries
instead of verifying every pair again (at 2,000 photos, ten minutes of two cores).

Workers read the database (SQLite, read-only): on a cluster it must sit where every worker sees it, as the
feature and match files do.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..execution import Executor, Stage, using
from ..files import matches as mf
from ..files.pairresults import PairResults, write_pair_group
from .colmap import KeypointCache, open_database, read_only_database, require_pycolmap, sqlite_matches

logger = logging.getLogger("sekd")

FORMAT = "sekd-verification-pairs"
#: Pairs per task (a process's or Ray worker's call): ~0.8 s of RANSAC on pairs of no common surface, so the
#: last tasks leave few cores idle; a Ray cluster grows it with its size (``execution.task_size``).
PAIRS_PER_TASK = 8
#: The geometry's 3 x 3 matrices.
MATRICES = ("E", "F", "H")
#: pycolmap's TwoViewGeometry configs of a pair that did not verify (UNDEFINED, DEGENERATE).
FAILED = (0, 1)


#: The layout of a pair's ``geometry`` array: config, tri_angle (rad), F, E, H (row-major 3 x 3),
#: cam2_from_cam1 (3 x 4); NaN where pycolmap gives none. One array, not seven: HDF5's cost is per dataset.
GEOMETRY_SLICES = {"config": slice(0, 1), "tri_angle": slice(1, 2), "F": slice(2, 11), "E": slice(11, 20),
                   "H": slice(20, 29), "cam2_from_cam1": slice(29, 41)}


def geometry_arrays(geometry) -> dict[str, np.ndarray]:
    """A ``pycolmap.TwoViewGeometry`` as two arrays: ``inlier_matches`` (``K x 2`` uint32) and ``geometry``
    (``GEOMETRY_SLICES``). A pair that failed (config UNDEFINED or DEGENERATE) keeps its config alone, as COLMAP's
    verifier stores it."""
    values = np.full(41, np.nan)
    values[0] = int(geometry.config)
    if int(geometry.config) in FAILED:
        values[1] = -1.0
        return {"inlier_matches": np.zeros((0, 2), np.uint32), "geometry": values}
    values[1] = geometry.tri_angle
    for name in MATRICES:
        if getattr(geometry, name) is not None:
            values[GEOMETRY_SLICES[name]] = np.asarray(getattr(geometry, name)).ravel()
    if geometry.cam2_from_cam1 is not None:
        values[GEOMETRY_SLICES["cam2_from_cam1"]] = np.asarray(geometry.cam2_from_cam1.matrix()).ravel()
    return {"inlier_matches": np.asarray(geometry.inlier_matches, np.uint32).reshape(-1, 2), "geometry": values}


def geometry_from_arrays(arrays: dict[str, np.ndarray]):
    """The ``pycolmap.TwoViewGeometry`` of ``geometry_arrays``."""
    pycolmap = require_pycolmap()
    values = arrays["geometry"]
    fields = {"config": int(values[0]), "tri_angle": float(values[1]),
              "inlier_matches": np.asarray(arrays["inlier_matches"], np.uint32).reshape(-1, 2)}
    fields.update({name: values[GEOMETRY_SLICES[name]].reshape(3, 3) for name in MATRICES
                   if not np.isnan(values[GEOMETRY_SLICES[name]]).any()})
    geometry = pycolmap.TwoViewGeometry(fields)
    pose = values[GEOMETRY_SLICES["cam2_from_cam1"]]
    if not np.isnan(pose).any():
        geometry.cam2_from_cam1 = pycolmap.Rigid3d(pose.reshape(3, 4))
    return geometry


class VerifyWorker:
    """Verification's per-pair work (an ``execution.Stage`` worker): for each pair key (``matches.pair_key`` of
    two image names), the two-view geometry of its matches. Built once per process from the driver's cameras
    (``camera_id -> pycolmap.Camera``) and images (``name -> (image_id, camera_id)``); reads keypoints and
    matches from ``database`` through SQLite read-only, since pycolmap's ``Database.open`` writes (its schema)
    and fails with "database is locked" when several workers open the file at once (``colmap.read_only_database``)."""

    def __init__(self, database: str, cameras: dict, images: dict[str, tuple[int, int]], options):
        self.pycolmap = require_pycolmap()
        self.database, self.cameras, self.images, self.options = database, cameras, images, options
        self.keypoints = KeypointCache()

    def __call__(self, keys: list[str]):
        with read_only_database(self.database) as db:
            for key in keys:
                name1, name2 = json.loads(key)
                (id1, camera1), (id2, camera2) = self.images[name1], self.images[name2]
                geometry = self.pycolmap.estimate_two_view_geometry(
                    self.cameras[camera1], self.keypoints.get(db, id1), self.cameras[camera2], self.keypoints.get(db, id2),
                    sqlite_matches(db, id1, id2), self.options)
                yield key, geometry_arrays(geometry), ""


def _matched_pairs(database: Path, names: dict[int, str]) -> list[tuple[str, str]]:
    """The pairs of ``database`` with matches, as image names (``names``: image id -> name), in pair-id order (the
    matches table read for its ids only: the match arrays stay on disk)."""
    pycolmap = require_pycolmap()
    with read_only_database(database) as db:
        pair_ids = [row[0] for row in db.execute("SELECT pair_id FROM matches WHERE rows > 0 ORDER BY pair_id")]
    return [tuple(names[image_id] for image_id in pycolmap.pair_id_to_image_pair(pair_id)) for pair_id in pair_ids]


def _parts_file(database: Path) -> Path:
    return database.with_name(f"{database.stem}-verification.h5")


def verify_pairs(database: str | Path, options, executor: str | Executor = "local", *, signature: str = "",
                 progress: bool = True) -> Path:
    """Geometric verification of every matched pair of ``database`` on ``executor``; each pair's two-view
    geometry written into the database, as ``pycolmap.geometric_verification`` writes it. Returns ``database``.

    ``options``: pycolmap ``TwoViewGeometryOptions`` (``database.two_view_options``). ``signature``: what the
    database was made from (its keypoints, matches and pairs); pairs an earlier run with the same signature and
    options verified, finished or killed, are reused. Without a signature the results go once written.
    """
    database = Path(database)
    with open_database(database) as db:
        cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
        images = {image.name: (image.image_id, image.camera_id) for image in db.read_all_images()}
    pairs = _matched_pairs(database, {image_id: name for name, (image_id, _) in images.items()})
    keyed = bool(signature)
    signature = json.dumps({"inputs": signature, "options": str(options.todict())}, sort_keys=True)
    results = PairResults(_parts_file(database), FORMAT, signature, max_items=256)
    missing = results.missing([mf.pair_key(a, b) for a, b in pairs])
    stage = Stage(name="verification", worker=VerifyWorker, args=(str(database.resolve()), cameras, images, options),
                  batches=missing, output=results.path,
                  write_group=write_pair_group, unit="pair", items="pairs", verb="verified", joinable=True,
                  per_task=PAIRS_PER_TASK, local_processes=True)
    with using(executor) as runner:
        geometries = results.compute(stage, runner, progress)
    with open_database(database) as db:
        db.clear_two_view_geometries()
        for name1, name2 in pairs:
            db.write_two_view_geometry(images[name1][0], images[name2][0],
                                       geometry_from_arrays(geometries[mf.pair_key(name1, name2)]))
    if not keyed:  # nothing says what they were computed from: a later call could not tell them apart
        results.remove()
    reused = len(pairs) - len(missing)
    logger.info("%s: %d pairs verified%s", database, len(pairs),
                f" ({reused} as an earlier run with the same inputs verified them)" if reused else "")
    return database
