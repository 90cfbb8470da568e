"""Mapping in capture order (``sekd_sfm.stages.sequence``): a model folded on look-alikes, unfolded."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from test_reconstruct import CALIBRATED, SIFT, look_at, project_view, write_scene

from sekd_sfm.bench.strecha import rotation_angle_deg
from sekd_sfm.pipelines.reconstruct import ReconstructConfig, reconstruct
from sekd_sfm.stages.colmap import require_pycolmap
from sekd_sfm.stages.sequence import (
    SequenceConfig,
    VerifiedPair,
    better,
    capture_order,
    chain_database,
    disagreeing_pairs,
    far_pairs,
    is_ordered,
    linked_share,
    order_contrast,
    remap_reason,
    verified_pairs,
)

pycolmap = require_pycolmap()

#: Photos round the ring (15 deg apart, give or take 3 deg).
RING = 24


def twin_ring(rng) -> dict:
    """A ring of RING photos round a column that is the same on opposite sides: 400 points on its front half and
    their copies turned 180 deg about its axis (same descriptors), each seen from within 60 deg of its normal.
    Photo k and photo k + 12 see the same; photos at most 3 apart never see a point and its copy."""
    angles = rng.uniform(0, np.pi, 400)
    heights = rng.uniform(-1.2, 1.2, 400)
    half = np.c_[2.5 * np.sin(angles), heights, -2.5 * np.cos(angles)]
    points = np.concatenate([half, half * [-1, 1, -1]])
    normals = points * [1, 0, 1] / 2.5
    descriptors = np.tile(rng.uniform(0, 255, (400, 128)), (2, 1))
    views = {}
    for k in range(RING):
        a = np.radians(15 * k + rng.uniform(-3, 3))
        centre = np.array([5 * np.sin(a), rng.uniform(-0.5, 0.5), -5 * np.cos(a)])
        rays = (centre - points) / np.linalg.norm(centre - points, axis=1, keepdims=True)
        seen = np.einsum("ij,ij->i", normals, rays) > 0.5
        views[f"photo{k + 1}.png"] = project_view(rng, *look_at(centre), points[seen], descriptors[seen])
    return views


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    """The twin ring reconstructed without the capture order ("plain"), in capture order from the start ("ordered",
    the default), and in capture order only after all pairs gave a folded model ("after"): (views, (out, model)
    each)."""
    root = tmp_path_factory.mktemp("twins")
    views = twin_ring(np.random.default_rng(3))
    runs = {}
    for name, enabled, first in (("plain", False, False), ("ordered", True, True), ("after", True, False)):
        images, out = write_scene(root / name, views, SIFT)
        config = ReconstructConfig(features=SIFT, camera=CALIBRATED)
        config.sequence.enabled, config.sequence.order_first = enabled, first
        runs[name] = out, reconstruct(images, out, config, progress=False)
    return views, runs


def rotation_errors(views: dict, model) -> list[float]:
    """Relative rotation errors (deg) of every pair of photos registered in ``model``."""
    reconstruction = pycolmap.Reconstruction(str(model))
    poses = {im.name: im.cam_from_world().rotation.matrix() for im in reconstruction.images.values() if im.has_pose}
    names = sorted(poses)
    return [rotation_angle_deg((poses[b] @ poses[a].T).T @ (views[b]["R"] @ views[a]["R"].T))
            for i, a in enumerate(names) for b in names[i + 1:]]


def test_look_alikes_fold_the_model_without_the_order(twins):
    views, runs = twins
    out, model = runs["plain"]
    stats = json.loads((out / "stats.json").read_text())
    assert stats["model_check"][0]["suspect"]
    assert np.median(rotation_errors(views, model)) > 20


def test_mapped_in_capture_order_the_model_never_folds(twins):
    """The chain of near photos mapped, the far look-alike pairs dropped against it, the rest triangulated onto
    its poses: one model, every photo, within a degree, and no mapping of all pairs before it."""
    views, runs = twins
    out, model = runs["ordered"]
    stats = json.loads((out / "stats.json").read_text())
    record = stats["sequence"]
    assert record["reason"] == "ordered" and record["remapped"] and record["kept"] == "closed"
    assert record["dropped"] >= 6 and all(p["apart"] > 3 for p in record["dropped_pairs"])
    assert not record["models"]["closed"]["suspect"] and record["models"]["closed"]["registered"] == RING
    assert pycolmap.Reconstruction(str(model)).num_reg_images() == RING
    assert max(rotation_errors(views, model)) < 1.0
    assert not stats["model_check"][0]["suspect"]
    assert "capture order" not in stats["timings_s"]  # part of mapping: no second mapping after it
    assert stats["final_filter"]["observations"] > 0


def test_a_chain_that_leaves_photos_out_falls_back_to_all_pairs(tmp_path):
    """When the chain of near photos does not hold (nearly) every photo, all pairs are mapped at once instead,
    and the record says why."""
    views = twin_ring(np.random.default_rng(3))
    images, out = write_scene(tmp_path / "scene", views, SIFT)
    config = ReconstructConfig(features=SIFT, camera=CALIBRATED)
    config.sequence.max_left_out = -0.01  # a chain of every photo is not enough: as if it had left one out
    model = reconstruct(images, out, config, progress=False)
    record = json.loads((out / "stats.json").read_text())["sequence"]
    assert record["reason"] == "ordered" and not record["remapped"]
    assert record["chain_registered"] == RING and record["photos"] == RING
    assert pycolmap.Reconstruction(str(model)).num_reg_images() >= RING // 2


def test_a_long_capture_maps_all_pairs_first_and_the_order_unfolds_it(tmp_path, caplog):
    """Above ``order_first_max_photos`` the chain is not mapped first (its drift would drop true loop-closing pairs):
    all pairs are mapped, the look-alikes fold the model, and the capture order maps it again afterwards."""
    views = twin_ring(np.random.default_rng(3))
    images, out = write_scene(tmp_path / "scene", views, SIFT)
    config = ReconstructConfig(features=SIFT, camera=CALIBRATED)
    config.sequence.order_first_max_photos = RING - 1
    with caplog.at_level(logging.INFO, logger="sekd"):
        model = reconstruct(images, out, config, progress=False)
    # The remap is announced with its reason before it runs (it maps the collection twice more).
    announced = [r.getMessage() for r in caplog.records if "mapping again in capture order" in r.getMessage()]
    assert len(announced) == 1 and announced[0].startswith("capture order: the model looks folded (its largest of ")
    stats = json.loads((out / "stats.json").read_text())
    assert stats["sequence"]["reason"] == "folded" and stats["sequence"]["remapped"]
    assert "capture order" in stats["timings_s"]  # the step after mapping all pairs
    assert pycolmap.Reconstruction(str(model)).num_reg_images() == RING
    assert max(rotation_errors(views, model)) < 1.0


def test_when_the_far_pairs_fold_the_closed_model_the_chain_alone_is_kept(tmp_path, monkeypatch):
    """The closed model judged folded (as on a mirror-symmetric walk, whose far mirror pairs fit the chain): the
    chain is kept, adjusted and filtered over its own pairs, and the database holds only those."""
    import sekd_sfm.pipelines.ordered as ordered

    real = ordered.check_model

    def closed_folds(model, database, config):
        return {**real(model, database, config), "suspect": Path(database).name == "closed.db"}

    monkeypatch.setattr(ordered, "check_model", closed_folds)
    views = twin_ring(np.random.default_rng(3))
    images, out = write_scene(tmp_path / "scene", views, SIFT)
    model = reconstruct(images, out, ReconstructConfig(features=SIFT, camera=CALIBRATED), progress=False)
    stats = json.loads((out / "stats.json").read_text())
    record = stats["sequence"]
    assert record["kept"] == "chain" and record["models"]["closed"]["suspect"]
    assert all(pair.gap <= 3 for pair in verified_pairs(out / "database.db", 1))
    assert pycolmap.Reconstruction(str(model)).num_reg_images() == RING
    assert max(rotation_errors(views, model)) < 1.0
    assert stats["final_filter"]["observations"] > 0  # the chain kept is filtered too


def test_the_capture_order_unfolds_a_folded_model(twins):
    views, runs = twins
    out, model = runs["after"]
    stats = json.loads((out / "stats.json").read_text())
    record = stats["sequence"]
    assert record["reason"] == "folded" and record["remapped"] and record["kept"] in ("remapped", "chain")
    assert record["dropped"] >= 6 and all(p["apart"] > 3 for p in record["dropped_pairs"])
    assert record["models"]["before"]["suspect"] and not record["models"][record["kept"]]["suspect"]
    assert pycolmap.Reconstruction(str(model)).num_reg_images() == RING
    assert max(rotation_errors(views, model)) < 1.0
    assert not stats["model_check"][0]["suspect"]
    assert "capture order" in stats["timings_s"]


def test_chain_database_keeps_near_pairs_only(twins, tmp_path):
    _, runs = twins
    database = runs["after"][0] / "database.db"
    far = chain_database(database, tmp_path / "chain.db", window=3)
    kept = verified_pairs(tmp_path / "chain.db", 1)
    assert far and all(p.gap > 3 for p in far) and kept and all(p.gap <= 3 for p in kept)
    assert linked_share(verified_pairs(database, 15)) == 1.0


def test_far_pairs_that_fit_the_model_are_kept(twins):
    """The unfolded model explains its own far pairs: none of them disagrees."""
    _, runs = twins
    out, model = runs["ordered"]
    pairs = far_pairs(verified_pairs(out / "database.db", 15), 3)
    assert pairs and disagreeing_pairs([pycolmap.Reconstruction(str(model))], out / "database.db", pairs,
                                       SequenceConfig()) == []


def test_capture_order_compares_numbers_as_numbers():
    assert capture_order(["img10.jpg", "img2.jpg", "a/img1.jpg", "img1.jpg"]) == \
        ["a/img1.jpg", "img1.jpg", "img2.jpg", "img10.jpg"]


def test_linked_share_counts_consecutive_pairs():
    pairs = [VerifiedPair(1, 2, "a", "b", 50, 1), VerifiedPair(2, 3, "b", "c", 50, 1), VerifiedPair(1, 4, "a", "d", 50, 3)]
    assert linked_share(pairs) == pytest.approx(2 / 3)
    assert far_pairs(pairs, 2) == pairs[2:]


def _pairs(inliers_by_gap: dict[int, list[int]]) -> list[VerifiedPair]:
    """Verified pairs of photos ``gap`` apart with the given inlier counts (names and ids made up)."""
    pairs = []
    for gap, counts in inliers_by_gap.items():
        for k, inliers in enumerate(counts):
            pairs.append(VerifiedPair(k, k + gap, f"{k:03d}", f"{k + gap:03d}", inliers, gap))
    return pairs


def test_an_order_counts_only_where_neighbours_share_more_than_far_photos():
    config = SequenceConfig()
    # A walk: the next photo shares hundreds of inliers, photos far apart a few look-alike ones.
    walk = _pairs({1: [900, 850, 1000], 2: [600, 640], 5: [40, 30], 9: [25]})
    assert order_contrast(walk, config.window) == pytest.approx(900 / 30)
    assert is_ordered(1.0, order_contrast(walk, config.window), config)
    # Ten photos of one facade named by photo-site ids (sacre_coeur): every pair verifies, the next name sharing
    # less than far ones.
    facade = _pairs({1: [54, 40, 60], 2: [114, 90], 5: [170, 160], 8: [180]})
    assert order_contrast(facade, config.window) == pytest.approx(54 / 170)
    assert not is_ordered(1.0, order_contrast(facade, config.window), config)
    assert is_ordered(1.0, order_contrast(_pairs({1: [500, 500], 6: [500]}), config.window), config)  # a tie: kept
    assert order_contrast(_pairs({1: [100], 2: [80]}), config.window) == float("inf")  # no far pair: no evidence
    assert order_contrast(_pairs({5: [100]}), config.window) == 0.0  # no consecutive pair
    assert not is_ordered(0.5, float("inf"), config)  # too few neighbours linked, however strong


class _Model:
    def __init__(self, n: int):
        self.n = n

    def num_reg_images(self) -> int:
        return self.n


def test_when_a_model_is_mapped_again():
    config = SequenceConfig()
    assert remap_reason([_Model(10)], True, 10, config) == "folded"
    assert remap_reason([_Model(10), _Model(5)], False, 15, config) == "split"
    assert remap_reason([_Model(90)], False, 100, config) == "split"
    assert remap_reason([_Model(96)], False, 100, config) is None
    assert better((False, 80), (True, 97)) and better((False, 98), (False, 97))
    assert not better((True, 97), (True, 97)) and not better((True, 99), (False, 10))



def test_the_summary_line_says_what_was_done():
    from sekd_sfm.pipelines.report import sequence_line
    from sekd_sfm.stages.sequence import sequence_record

    config = SequenceConfig()
    unordered = sequence_record("split", 0.4, config, remapped=False)
    assert "no ordered capture (40% of consecutive photos verified, 80% needed)" in sequence_line(unordered)
    named = sequence_record("folded", 0.89, config, remapped=False, contrast=0.32)
    assert sequence_line(named) == ("the model is folded; the names are no capture order (89% of consecutive photos "
                                    "verified, but they share fewer inliers than photos far apart: 0.32 times "
                                    "theirs), so it stays")
    models = {"before": {"suspect": True, "registered": 97}, "chain": {"suspect": False, "registered": 97},
              "remapped": {"suspect": False, "registered": 97}}
    done = sequence_record("folded", 1.0, config, remapped=True, far_pairs=552, dropped=336, dropped_pairs=[],
                           kept="remapped", models=models)
    assert sequence_line(done) == ("the model was folded (97 photos); mapped again in capture order, 336 of 552 pairs "
                                   "over 3 photos apart dropped (their inliers do not fit the order's poses); kept: "
                                   "97 photos, not folded")
    assert sequence_line({**done, "kept": "before"}).endswith("no better model came of it, the first stays")
    models = {"closed": {"suspect": False, "registered": 24}, "chain": {"suspect": False, "registered": 24}}
    ordered = sequence_record("ordered", 1.0, config, remapped=True, far_pairs=210, dropped=206, dropped_pairs=[],
                              kept="closed", models=models)
    assert sequence_line(ordered) == ("photos at most 3 apart mapped first; 206 of 210 farther pairs dropped (their "
                                      "inliers do not fit that chain's poses), the rest triangulated onto its poses: "
                                      "24 photos")
    assert "the chain alone is kept: 24 photos" in sequence_line({**ordered, "kept": "chain"})
    broken = sequence_record("ordered", 0.9, config, remapped=False, chain_registered=40, photos=97)
    assert sequence_line(broken) == ("the chain of photos at most 3 apart in the order holds 40 of 97 photos: all "
                                     "pairs mapped at once instead")
