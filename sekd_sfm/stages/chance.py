"""The chance check, right after geometric verification: verified pairs whose inliers chance alone would give.

COLMAP verifies a pair when some fundamental matrix has 15 inlier matches within 4 px; RANSAC
keeps the best of thousands of hypotheses, so random matches reach that (100 in a 640 px photo
give 16), more when the keypoints crowd on one object. SEKD keeps tens of matches between photos
that share no surface, and such pairs verify at 15-25 inliers, wrongly (docs/reconstruction.md).

The test is empirical (an a-contrario test by permutation): for each verified pair with fewer
than ``max_inliers`` inliers, the same RANSAC (fundamental matrix, COLMAP's threshold and trial
budget) runs on its putative matches with the correspondences shuffled, ``shuffles`` times. The
shuffles keep everything but the correspondence itself (both keypoint sets, their crowding, the
photo size), so the most inliers they reach is what chance gives these matches. The pair is
dropped from the database's verified pairs (its raw matches stay) unless its own inliers exceed
``margin`` times that. Seeds derive from the pair's names: the same database gives the same
decisions in any order, in any process.

Each pair's shuffles run as an ``execution.Stage`` (``ChanceWorker``) on the run's executor: in worker processes
on this machine or on Ray workers, which read the pair's keypoints and raw matches from the database (SQLite,
read-only, as verification's workers do); the driver reads only which pairs to test and decides.
"""
from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..execution import Executor, Stage, using
from ..files import matches as mf
from ..files.pairresults import PairResults, write_pair_group
from .colmap import (
    KeypointCache,
    delete_verified_pairs,
    open_database,
    read_only_database,
    require_pycolmap,
    sqlite_matches,
)

logger = logging.getLogger("sekd")

#: The shuffles' results of a check in progress, beside the database (``<stem>-chance.h5``).
FORMAT = "sekd-chance-pairs"
#: Pairs per task: ~3 ms each (four RANSAC runs of 2,000 trials at most), so a task is ~0.1 s.
PAIRS_PER_TASK = 32


@dataclass
class ChanceConfig:
    """Settings of the chance check (``check_chance``)."""

    enabled: bool = True
    #: Shuffles of each tested pair's matches; the chance level is the most inliers any of them reaches.
    shuffles: int = 4
    #: A pair is kept when its inliers are at least ``margin`` times the chance level.
    margin: float = 1.25
    #: Pairs with at least this many inliers are not tested (chance levels measured stay under 50).
    max_inliers: int = 100
    #: RANSAC threshold (px) and trials of the shuffled runs: those of COLMAP's verification.
    max_error_px: float = 4.0
    max_num_trials: int = 2000


def pair_seed(name1: str, name2: str, seed: int) -> int:
    """A 31-bit seed from the pair's names and ``seed``: independent of the order pairs are tested in."""
    digest = hashlib.sha1(f"{seed}\0{name1}\0{name2}".encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def chance_inliers(points1: np.ndarray, points2: np.ndarray, config: ChanceConfig, seed: int,
                   stop_at: int | None = None) -> list[int]:
    """Inliers RANSAC (fundamental matrix) finds on ``config.shuffles`` shufflings of the correspondences between
    ``points1`` and ``points2`` (N x 2 each, px). Stops early once a shuffle reaches ``stop_at`` (the pair is then
    no better than chance whatever the other shuffles give)."""
    pycolmap = require_pycolmap()
    options = pycolmap.RANSACOptions()
    options.max_error, options.max_num_trials = config.max_error_px, config.max_num_trials
    rng = np.random.default_rng(seed)
    found: list[int] = []
    for trial in range(config.shuffles):
        options.random_seed = (seed + trial) & 0x7FFFFFFF
        result = pycolmap.estimate_fundamental_matrix(points1, points2[rng.permutation(len(points2))], options)
        found.append(int(result["num_inliers"]) if result else 0)
        if stop_at is not None and found[-1] >= stop_at:
            break
    return found


@dataclass
class WeakPair:
    """A verified pair the check tests: image ids and names, its inlier count."""

    image1: int
    image2: int
    name1: str
    name2: str
    inliers: int

    @property
    def key(self) -> str:
        return mf.pair_key(self.name1, self.name2)


def read_weak_pairs(database: str | Path, min_inliers: int, max_inliers: int) -> tuple[list[WeakPair], int]:
    """The verified pairs of ``database`` with ``min_inliers`` <= inliers < ``max_inliers``, and the number of
    verified pairs in all."""
    pycolmap = require_pycolmap()
    with open_database(database) as db:
        names = {image.image_id: image.name for image in db.read_all_images()}
        verified = [(pycolmap.pair_id_to_image_pair(pair_id), len(geometry.inlier_matches))
                    for pair_id, geometry in zip(*db.read_two_view_geometries())
                    if len(geometry.inlier_matches) >= min_inliers]
    weak = [WeakPair(id1, id2, names[id1], names[id2], inliers)
            for (id1, id2), inliers in verified if inliers < max_inliers]
    return weak, len(verified)


def chance_level(pair: WeakPair, points1: np.ndarray, points2: np.ndarray, config: ChanceConfig, seed: int) -> int:
    """The chance level of ``pair``: the most inliers its putative matches (keypoints ``points1``, ``points2``,
    N x 2 each, px) reach shuffled (``chance_inliers``)."""
    needed = int(np.ceil(pair.inliers / config.margin))  # a shuffle this good already condemns the pair
    return max(chance_inliers(points1, points2, config, pair_seed(pair.name1, pair.name2, seed), stop_at=needed),
               default=0)


class ChanceWorker:
    """The check's per-pair work (an ``execution.Stage`` worker): for each pair key (``matches.pair_key``), its
    chance level and putative matches (``level`` = [level, matches]). Built once per process from the pairs to
    test (``key -> WeakPair``); reads keypoints and matches from ``database`` (SQLite, read-only)."""

    def __init__(self, database: str, pairs: dict[str, WeakPair], config: ChanceConfig, seed: int):
        self.database, self.pairs, self.config, self.seed = database, pairs, config, seed
        self.keypoints = KeypointCache()

    def __call__(self, keys: list[str]):
        with read_only_database(self.database) as db:
            for key in keys:
                pair = self.pairs[key]
                matches = sqlite_matches(db, pair.image1, pair.image2).astype(np.int64)
                points1 = self.keypoints.get(db, pair.image1)[matches[:, 0]]
                points2 = self.keypoints.get(db, pair.image2)[matches[:, 1]]
                level = chance_level(pair, points1, points2, self.config, self.seed)
                yield key, {"level": np.array([level, len(matches)], np.int64)}, ""


def find_chance_pairs(database: str | Path, min_inliers: int, config: ChanceConfig | None = None, seed: int = 0,
                      executor: str | Executor = "local", progress: bool = False) -> tuple[list[WeakPair], dict]:
    """The verified pairs of ``database`` no better than chance (module doc), and the record: verified pairs, pairs
    tested, dropped (names, inliers, putative matches, chance level), the settings. Changes nothing.
    ``executor``: where the pairs' shuffles run (an open executor or a name; the same decisions on any)."""
    config = config or ChanceConfig()
    database = Path(database)
    pairs, verified = read_weak_pairs(database, min_inliers, config.max_inliers)
    tested = {pair.key: pair for pair in pairs}
    # What the levels were computed from (a digest: thousands of pairs would not fit in an HDF5 attribute): a killed
    # check resumes only on the same pairs, settings and seed.
    signature = hashlib.sha1(json.dumps({"pairs": [[p.key, p.inliers] for p in pairs], "config": asdict(config),
                                         "seed": seed}).encode()).hexdigest()
    results = PairResults(database.with_name(f"{database.stem}-chance.h5"), FORMAT, signature, max_items=256)
    stage = Stage(name="chance check", worker=ChanceWorker, args=(str(database.resolve()), tested, config, seed),
                  batches=results.missing(list(tested)), output=results.path, write_group=write_pair_group,
                  unit="pair", items="pairs", verb="tested", joinable=True, per_task=PAIRS_PER_TASK,
                  local_processes=True)
    with using(executor) as runner:
        found = results.compute(stage, runner, progress)
    results.remove()
    levels = {key: found[key]["level"] for key in tested}
    dropped = [(pair, int(levels[pair.key][0])) for pair in pairs if pair.inliers < config.margin * levels[pair.key][0]]
    return [pair for pair, _ in dropped], {
        "verified": verified, "tested": len(pairs), "dropped": len(dropped),
        "dropped_pairs": [{"pair": [p.name1, p.name2], "inliers": p.inliers, "matches": int(levels[p.key][1]),
                           "chance_inliers": level} for p, level in sorted(dropped, key=lambda d: d[0].inliers)],
        "config": asdict(config)}


def check_chance(database: str | Path, min_inliers: int, config: ChanceConfig | None = None, seed: int = 0,
                 executor: str | Executor = "local", progress: bool = False) -> dict:
    """Drop from ``database``'s verified pairs those no better than chance (``find_chance_pairs``, on ``executor``);
    their raw matches stay. Returns ``find_chance_pairs``'s record."""
    config = config or ChanceConfig()
    dropped, record = find_chance_pairs(database, min_inliers, config, seed, executor, progress)
    if dropped:
        delete_verified_pairs(database, [(pair.image1, pair.image2) for pair in dropped])
        logger.info("chance check: %d of %d verified pairs dropped, their inliers under %.2f x what their matches "
                    "reach shuffled", len(dropped), record["verified"], config.margin)
    return record
