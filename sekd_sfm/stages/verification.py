"""Geometric verification on the run's executor: which matches of each pair one two-view geometry explains.

Per pair, pycolmap's ``estimate_two_view_geometry`` (RANSAC on E, F and H: COLMAP's own verification, pair
for pair the geometry ``pycolmap.geometric_verification`` writes over the whole database, RANSAC seed
included) runs as an ``execution.Stage`` (``VerifyWorker``): in worker processes on this machine or on Ray
workers, saved pair by pair to ``<database stem>-verification.h5`` (a killed run resumes from the pairs it
finished). The driver then writes every pair's geometry into the database and drops that file.

Workers read the database (SQLite, read-only): on a cluster it must sit where every worker sees it, as the
feature and match files do.
"""
from __future__ import annotations

import contextlib
import json
import logging
import sqlite3
from pathlib import Path

import numpy as np

from ..execution import Executor, Stage, using
from ..files import matches as mf
from ..files.pairresults import PairResults, write_pair_group
from .colmap import open_database, require_pycolmap

logger = logging.getLogger("sekd")

FORMAT = "sekd-verification-pairs"
#: Pairs per task (a process's or Ray worker's call): ~2 s of RANSAC on pairs of no common surface.
PAIRS_PER_TASK = 32
#: The geometry's matrices, stored as 3 x 3 arrays where pycolmap gives them.
MATRICES = ("E", "F", "H")
#: pycolmap's TwoViewGeometry configs of a pair that did not verify (UNDEFINED, DEGENERATE).
FAILED = (0, 1)


def geometry_arrays(geometry) -> dict[str, np.ndarray]:
    """A ``pycolmap.TwoViewGeometry`` as arrays: ``config``, ``inlier_matches`` (``K x 2`` uint32), ``tri_angle``
    (rad), the 3 x 3 matrices it has, ``cam2_from_cam1`` (3 x 4) when it has one. A pair that failed (config
    UNDEFINED or DEGENERATE) keeps its config alone, as COLMAP's verifier stores it."""
    if int(geometry.config) in FAILED:
        return {"config": np.int64(int(geometry.config)), "tri_angle": np.float64(-1.0),
                "inlier_matches": np.zeros((0, 2), np.uint32)}
    arrays = {"config": np.int64(int(geometry.config)), "tri_angle": np.float64(geometry.tri_angle),
              "inlier_matches": np.asarray(geometry.inlier_matches, np.uint32).reshape(-1, 2)}
    arrays.update({name: np.asarray(getattr(geometry, name)) for name in MATRICES if getattr(geometry, name) is not None})
    if geometry.cam2_from_cam1 is not None:
        arrays["cam2_from_cam1"] = np.asarray(geometry.cam2_from_cam1.matrix())
    return arrays


def geometry_from_arrays(arrays: dict[str, np.ndarray]):
    """The ``pycolmap.TwoViewGeometry`` of ``geometry_arrays``."""
    pycolmap = require_pycolmap()
    fields = {"config": int(arrays["config"]), "tri_angle": float(arrays["tri_angle"]),
              "inlier_matches": np.asarray(arrays["inlier_matches"], np.uint32).reshape(-1, 2)}
    fields.update({name: np.asarray(arrays[name], np.float64) for name in MATRICES if name in arrays})
    geometry = pycolmap.TwoViewGeometry(fields)
    if "cam2_from_cam1" in arrays:
        geometry.cam2_from_cam1 = pycolmap.Rigid3d(np.asarray(arrays["cam2_from_cam1"], np.float64))
    return geometry


class VerifyWorker:
    """Verification's per-pair work (an ``execution.Stage`` worker): for each pair key (``matches.pair_key`` of
    two image names), the two-view geometry of its matches in ``database``. Built once per process."""

    def __init__(self, database: str, options):
        self.pycolmap = require_pycolmap()
        self.database, self.options = database, options
        with open_database(Path(database)) as db:
            images = db.read_all_images()
            self.cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
        self.images = {image.name: image for image in images}
        self.keypoints: dict[int, np.ndarray] = {}

    def _keypoints(self, db, image_id: int) -> np.ndarray:
        if image_id not in self.keypoints:
            if len(self.keypoints) > 256:  # a task's pairs share few images: keep memory flat on big scenes
                self.keypoints.clear()
            self.keypoints[image_id] = db.read_keypoints(image_id)[:, :2].astype(np.float64)
        return self.keypoints[image_id]

    def __call__(self, keys: list[str]):
        with open_database(Path(self.database)) as db:
            for key in keys:
                name1, name2 = json.loads(key)
                image1, image2 = self.images[name1], self.images[name2]
                matches = db.read_matches(image1.image_id, image2.image_id)
                geometry = self.pycolmap.estimate_two_view_geometry(
                    self.cameras[image1.camera_id], self._keypoints(db, image1.image_id),
                    self.cameras[image2.camera_id], self._keypoints(db, image2.image_id), matches, self.options)
                yield key, geometry_arrays(geometry), ""


def _matched_pairs(database: Path) -> list[tuple[str, str]]:
    """The pairs of ``database`` with matches, as image names, in pair-id order (the matches table read for its
    ids only: the match arrays stay on disk)."""
    pycolmap = require_pycolmap()
    with contextlib.closing(sqlite3.connect(f"file:{database}?mode=ro", uri=True)) as db:
        names = dict(db.execute("SELECT image_id, name FROM images"))
        pair_ids = [row[0] for row in db.execute("SELECT pair_id FROM matches WHERE rows > 0 ORDER BY pair_id")]
    pairs = [pycolmap.pair_id_to_image_pair(pair_id) for pair_id in pair_ids]
    return [(names[a], names[b]) for a, b in pairs]


def _parts_file(database: Path) -> Path:
    return database.with_name(f"{database.stem}-verification.h5")


def verify_pairs(database: str | Path, options, executor: str | Executor = "local", *, signature: str = "",
                 progress: bool = True) -> Path:
    """Geometric verification of every matched pair of ``database`` on ``executor``; each pair's two-view
    geometry written into the database, as ``pycolmap.geometric_verification`` writes it. Returns ``database``.

    ``options``: pycolmap ``TwoViewGeometryOptions`` (``database.two_view_options``). ``signature``: what the
    database was made from (its keypoints, matches and pairs); pairs a killed run with the same signature and
    options finished are reused.
    """
    database = Path(database)
    pairs = _matched_pairs(database)
    signature = json.dumps({"inputs": signature, "options": str(options.todict())}, sort_keys=True)
    results = PairResults(_parts_file(database), FORMAT, signature, max_items=256)
    stage = Stage(name="verification", worker=VerifyWorker, args=(str(database.resolve()), options),
                  batches=results.missing([mf.pair_key(a, b) for a, b in pairs]), output=results.path,
                  write_group=write_pair_group, unit="pair", items="pairs", verb="verified", joinable=True,
                  per_task=PAIRS_PER_TASK, local_processes=True)
    with using(executor) as runner:
        geometries = results.compute(stage, runner, progress)
    with open_database(database) as db:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        db.clear_two_view_geometries()
        for name1, name2 in pairs:
            db.write_two_view_geometry(ids[name1], ids[name2],
                                       geometry_from_arrays(geometries[mf.pair_key(name1, name2)]))
    results.remove()
    logger.info("%s: %d pairs verified", database, len(pairs))
    return database
