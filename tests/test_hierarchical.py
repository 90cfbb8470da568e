"""Hierarchical mapping on the executor (sekd_sfm.stages.hierarchical, and the merge: sekd_sfm.stages.cluster_merge):
clusters mapped in worker processes and merged into the true cameras; the same model from one process or two; a
killed run resumes from its clusters."""
from __future__ import annotations

import contextlib
import json
import shutil
import sqlite3

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_reconstruct import (
    CALIBRATED,
    SIFT,
    arc,
    look_at,
    scene_points,
    synthetic_views,
    write_scene,
)

from sekd_sfm.errors import SekdError
from sekd_sfm.evaluation.metrics import rotation_error_deg
from sekd_sfm.execution import LocalExecutor
from sekd_sfm.pipelines.reconstruct import ReconstructConfig, reconstruct
from sekd_sfm.stages import cluster_merge, hierarchical, mapper_worker
from sekd_sfm.stages.colmap import require_pycolmap
from sekd_sfm.stages.mapper_worker import bundle_adjust_merged, merged_model
from sekd_sfm.stages.mapping import mapper_options, run_mapper
from sekd_sfm.stages.partition import ClusterOptions, partition, view_graph

pycolmap = require_pycolmap()

#: 24 views on a 200-degree arc, clusters of at most 8 photos (+4 shared): three clusters or more.
VIEWS = 24
OPTIONS = ["clustering_options.leaf_max_num_images=8", "clustering_options.image_overlap=4",
           "incremental_options.min_model_size=4"]


def _pose(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    return np.c_[rotation, translation]


def _true_poses(n: int = 12) -> dict[int, np.ndarray]:
    return {k + 1: _pose(*look_at(c)) for k, c in enumerate(arc(n, span_deg=120))}


def _in_other_world(poses: dict[int, np.ndarray], scale: float, rotation: np.ndarray, translation: np.ndarray):
    """The same cameras in a world ``x' = scale * rotation @ x + translation``."""
    return {k: cluster_merge.moved(p, scale, rotation, translation) for k, p in poses.items()}


def test_the_similarity_of_two_worlds_from_shared_cameras_on_a_line():
    truth = {k + 1: _pose(*look_at(np.array([k * 0.5, 0.0, -5.0]))) for k in range(8)}  # centres on a line
    rotation = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix()
    other = _in_other_world(truth, 3.0, rotation, np.array([1.0, -2.0, 0.5]))
    other[4] = _pose(np.eye(3), np.array([9.0, 9.0, 9.0]))  # one badly placed camera
    scale, found_rotation, translation, agreeing = cluster_merge.similarity(truth, other)
    assert scale == pytest.approx(3.0) and np.allclose(found_rotation, rotation) and 4 not in agreeing
    assert np.allclose(translation, [1.0, -2.0, 0.5]) and len(agreeing) == 7
    assert cluster_merge.similarity({1: truth[1], 2: truth[2]}, other) is None  # too few shared


def test_pieces_in_their_own_worlds_merge_into_one_and_strangers_stay_apart():
    truth = _true_poses(12)
    rng = np.random.default_rng(3)

    def piece(ids, camera: int) -> cluster_merge.Piece:
        world = (rng.uniform(0.5, 2), Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
        return cluster_merge.Piece(_in_other_world({k: truth[k] for k in ids}, *world), {camera: np.array([camera])})

    # Overlaps of two photos: too few to align by, three models.
    assert len(cluster_merge.merge_pieces([piece(range(1, 7), 1), piece(range(5, 10), 2), piece(range(8, 13), 3)])) == 3
    # The middle one sharing 4 and 3 photos: one model, the largest piece's world, every camera's intrinsics.
    largest = piece(range(3, 11), 2)
    merged = cluster_merge.merge_pieces([piece(range(1, 7), 1), largest, piece(range(8, 13), 3)])
    assert len(merged) == 1 and sorted(merged[0].poses) == list(range(1, 13)) and sorted(merged[0].cameras) == [1, 2, 3]
    assert all(np.array_equal(merged[0].poses[k], largest.poses[k]) for k in range(3, 11))  # the base stays
    scale, rotation, translation, agreeing = cluster_merge.similarity(truth, merged[0].poses)
    assert len(agreeing) == 12
    moved = _in_other_world(truth, scale, rotation, translation)
    assert all(np.allclose(moved[k], merged[0].poses[k], atol=1e-9) for k in truth)


@pytest.fixture(scope="module")
def arc_scene(tmp_path_factory):
    """VIEWS calibrated views on a 200-degree arc, their true poses, and the verified database of a run."""
    rng = np.random.default_rng(8)
    points, descriptors = scene_points(rng, 500)
    centres = arc(VIEWS, span_deg=200)
    views = {f"v{i:02d}.png": v for i, v in enumerate(synthetic_views(rng, points, descriptors, centres))}
    images, out = write_scene(tmp_path_factory.mktemp("hierarchical"), views, SIFT)
    reconstruct(images, out, ReconstructConfig(features=SIFT, camera=CALIBRATED), progress=False)
    truth = {f"v{i:02d}.png": _pose(*look_at(c)) for i, c in enumerate(centres)}
    return images, out / "database.db", truth


def _map(arc_scene, tmp_path, executor, name: str) -> list:
    images, database, _ = arc_scene
    copy = shutil.copy(database, tmp_path / f"{name}.db")
    options = mapper_options(OPTIONS, mapper_type="hierarchical")
    return run_mapper(copy, images, options, progress=False, final_filter=True, executor=executor)


def _poses(model) -> dict[str, np.ndarray]:
    return {model.image(i).name: model.image(i).cam_from_world().matrix() for i in model.reg_image_ids()}


def test_clusters_mapped_in_two_processes_merge_into_the_true_cameras(arc_scene, tmp_path):
    _, database, truth = arc_scene
    clusters = partition(*view_graph(database, 15), ClusterOptions(leaf_size=8, overlap=4))
    assert len(clusters) >= 3
    executor = LocalExecutor(2)
    models = _map(arc_scene, tmp_path, executor, "two")
    assert executor.places == ["local: 2 processes"]
    assert len(models) == 1 and models[0].num_reg_images() == VIEWS and models[0].num_points3D() > 300
    found = _poses(models[0])
    scale, rotation, translation, agreeing = cluster_merge.similarity(truth, found)
    assert len(agreeing) == VIEWS
    expected = _in_other_world(truth, scale, rotation, translation)
    for name, pose in found.items():  # 0.2 px of keypoint noise: poses to a small fraction of a degree
        assert rotation_error_deg(pose[:, :3], expected[name][:, :3]) < 0.1
    assert not list(tmp_path.glob("two-clusters.h5*"))  # the clusters' results go once merged
    # One process maps the same clusters to the same model.
    again = _poses(_map(arc_scene, tmp_path, LocalExecutor(1), "one")[0])
    assert again.keys() == found.keys() and all(np.allclose(again[k], found[k], atol=1e-6) for k in found)


def test_a_cluster_database_holds_its_photos_rows_only(arc_scene, tmp_path):
    _, database, _ = arc_scene
    target = tmp_path / "cluster.db"
    hierarchical.copy_cluster(database, target, [2, 3, 5])
    with contextlib.closing(sqlite3.connect(target)) as db:
        assert [r[0] for r in db.execute("SELECT image_id FROM images ORDER BY image_id")] == [2, 3, 5]
        assert [r[0] for r in db.execute("SELECT image_id FROM keypoints ORDER BY image_id")] == [2, 3, 5]
        pairs = [r[0] for r in db.execute("SELECT pair_id FROM two_view_geometries ORDER BY pair_id")]
        assert [pycolmap.pair_id_to_image_pair(p) for p in pairs] == [(2, 3), (2, 5), (3, 5)]
        assert db.execute("SELECT COUNT(*) FROM matches").fetchone()[0] == 0
        assert db.execute("SELECT COUNT(*) FROM frames").fetchone()[0] == 3


def test_a_failed_mapping_resumes_from_the_clusters_it_mapped(arc_scene, tmp_path, monkeypatch):
    mapped: list[str] = []
    original = hierarchical.ClusterWorker.__call__

    def fails_on_the_second(self, keys):
        for key in keys:
            mapped.append(key)
            if len(mapped) == 2:
                raise SekdError("the second cluster fails")
            yield from original(self, [key])

    monkeypatch.setattr(hierarchical.ClusterWorker, "__call__", fails_on_the_second)
    with pytest.raises(SekdError, match="second cluster fails"):
        _map(arc_scene, tmp_path, LocalExecutor(1), "resumed")
    monkeypatch.setattr(hierarchical.ClusterWorker, "__call__",
                        lambda self, keys: (mapped.extend(keys), original(self, keys))[1])
    mapped.clear()
    database = tmp_path / "resumed.db"
    options = mapper_options(OPTIONS, mapper_type="hierarchical")
    models = run_mapper(database, arc_scene[0], options, progress=False, executor=LocalExecutor(1))
    clusters = partition(*view_graph(database, 15), ClusterOptions(leaf_size=8, overlap=4))
    assert len(mapped) == len(clusters) - 1 and models[0].num_reg_images() == VIEWS


def test_photos_of_a_camera_rig_are_not_cut_apart(arc_scene, tmp_path):
    _, database, _ = arc_scene
    assert hierarchical.can_map_clusters(database)
    rig = shutil.copy(database, tmp_path / "rig.db")
    with contextlib.closing(sqlite3.connect(rig)) as db:  # photos 1 and 2 taken together: one frame
        db.execute("UPDATE frame_data SET frame_id = 1 WHERE data_id = 2")
        db.commit()
    assert not hierarchical.can_map_clusters(rig)  # pycolmap's hierarchical mapper keeps the frame whole


def _drifted_piece(arc_scene, degrees: float) -> tuple[cluster_merge.Piece, dict[str, int]]:
    """The arc's true poses as one merged piece whose second half drifted: turned by ``degrees`` about the
    centre of the last photo of the first half (a seam between two clusters), and the photo ids by name."""
    _, database, truth = arc_scene
    with contextlib.closing(sqlite3.connect(database)) as db:
        ids = dict(db.execute("SELECT name, image_id FROM images"))
    names = sorted(truth)
    seam = cluster_merge.centers([truth[names[VIEWS // 2 - 1]]])[0]
    turn = Rotation.from_euler("x", degrees, degrees=True).as_matrix()  # across the epipolar lines: no depth absorbs it
    poses = {ids[n]: truth[n] if k < VIEWS // 2 else cluster_merge.moved(truth[n], 1.0, turn, seam - turn @ seam)
             for k, n in enumerate(names)}
    return cluster_merge.Piece(poses), ids


def _points_across(model, first: set[int]) -> int:
    """Points seen both by a photo of ``first`` (ids) and by another photo."""
    return sum(1 for point in model.points3D.values()
               if len({e.image_id in first for e in point.track.elements}) == 2)


def _seam_error_deg(model, truth) -> float:
    """How far (deg) the relative rotation of the two photos either side of the arc's seam is from the truth."""
    a, b = sorted(truth)[VIEWS // 2 - 1], sorted(truth)[VIEWS // 2]
    found = _poses(model)
    relative_found, relative_true = (p[b][:, :3] @ p[a][:, :3].T for p in (found, truth))
    return rotation_error_deg(relative_found, relative_true)


def test_a_seam_where_two_clusters_drifted_apart_is_closed_by_the_merge(arc_scene, tmp_path):
    images, database, truth = arc_scene
    piece, ids = _drifted_piece(arc_scene, 2.0)  # ~17 px at the seam (focal length 500 px)
    first = {ids[n] for n in sorted(truth)[:VIEWS // 2]}
    options = mapper_options(OPTIONS, mapper_type="hierarchical").incremental_options
    model = cluster_merge.assemble(piece, str(database), str(images), options, tmp_path / "merge", pycolmap)
    assert _points_across(model, first) > 100  # tracks cross the seam despite its ~17 px (none did at 4 px)
    bundle_adjust_merged(model, 1, pycolmap)
    assert _seam_error_deg(model, truth) < 0.05  # the seam closed (2 degrees before)
    errors = [point.error for point in model.points3D.values()]
    assert max(errors) <= 4.0 and np.median(errors) < 0.5  # nothing beyond COLMAP's 4 px is left


def test_the_merged_adjustment_with_inner_iterations_ends_where_the_plain_one_does(arc_scene, tmp_path, monkeypatch):
    """Ceres' inner iterations (``MERGE_INNER_ITERATIONS``) change how the merged adjustment gets to its optimum,
    not where it ends: every pose within 5e-5 deg and 1e-6 of the scene of plain Levenberg-Marquardt run to a
    tight tolerance (measured: 8e-6 deg, 2e-7; stopped at a relative decrease of 1e-5 instead of 1e-7, 1.1e-4 deg
    and 2.8e-6)."""
    images, database, truth = arc_scene
    piece, _ = _drifted_piece(arc_scene, 2.0)
    options = mapper_options(OPTIONS, mapper_type="hierarchical").incremental_options
    model = cluster_merge.assemble(piece, str(database), str(images), options, tmp_path / "merge", pycolmap)
    plain = pycolmap.Reconstruction(model)
    bundle_adjust_merged(model, 1, pycolmap)
    monkeypatch.setattr(mapper_worker, "MERGE_INNER_ITERATIONS", False)
    monkeypatch.setattr(mapper_worker, "MERGE_FUNCTION_TOLERANCE", 1e-10)
    bundle_adjust_merged(plain, 1, pycolmap)
    fast, slow = _poses(model), _poses(plain)
    assert set(fast) == set(slow) == set(truth)
    centres = {name: cluster_merge.centers([pose])[0] for name, pose in slow.items()}
    extent = np.ptp(np.array(list(centres.values())), axis=0).max()
    for name in truth:
        assert rotation_error_deg(fast[name][:, :3], slow[name][:, :3]) < 5e-5
        assert np.linalg.norm(cluster_merge.centers([fast[name]])[0] - centres[name]) < 1e-6 * extent
    assert _seam_error_deg(model, truth) < 0.05


def test_a_seam_too_wide_for_one_pass_is_closed_by_the_second(arc_scene, tmp_path):
    images, database, truth = arc_scene
    piece, ids = _drifted_piece(arc_scene, 4.0)  # ~35 px at the seam: few tracks cross it within 16 px
    first = {ids[n] for n in sorted(truth)[:VIEWS // 2]}
    options = mapper_options(OPTIONS, mapper_type="hierarchical").incremental_options
    once = merged_model(piece, str(database), str(images), options, tmp_path / "once", pycolmap, passes=1)
    twice = merged_model(piece, str(database), str(images), options, tmp_path / "twice", pycolmap, passes=2)
    assert _points_across(once, first) < 50  # measured: 8
    assert _points_across(twice, first) > 300  # measured: all 500 points of the scene
    assert _seam_error_deg(twice, truth) < min(0.05, _seam_error_deg(once, truth) / 2)  # measured: 0.018, 0.072


def test_a_seam_too_wide_for_two_passes_is_closed_by_the_third_at_twice_the_tolerance(arc_scene, tmp_path):
    images, database, truth = arc_scene
    piece, ids = _drifted_piece(arc_scene, 6.0)  # ~52 px at the seam: no track within 16 px, a few within 32
    first = {ids[n] for n in sorted(truth)[:VIEWS // 2]}
    options = mapper_options(OPTIONS, mapper_type="hierarchical").incremental_options
    twice = merged_model(piece, str(database), str(images), options, tmp_path / "twice", pycolmap, passes=2)
    thrice = merged_model(piece, str(database), str(images), options, tmp_path / "thrice", pycolmap)
    assert _seam_error_deg(twice, truth) > 1.0  # still open after two passes at 16 px
    assert _points_across(thrice, first) > 100  # measured: 173
    assert _seam_error_deg(thrice, truth) < 0.05


def test_a_merge_without_passes_keeps_the_poses_as_merged_and_no_point(arc_scene, tmp_path):
    """``passes=0`` (the capture order's chain, closed and adjusted afterwards, which triangulates from scratch):
    every photo registered at the pose the merge gave it, seam included, and no point triangulated for nothing."""
    images, database, truth = arc_scene
    piece, _ = _drifted_piece(arc_scene, 2.0)
    options = mapper_options(OPTIONS, mapper_type="hierarchical").incremental_options
    model = merged_model(piece, str(database), str(images), options, tmp_path / "none", pycolmap, passes=0)
    assert model.num_reg_images() == VIEWS and model.num_points3D() == 0
    assert abs(_seam_error_deg(model, truth) - 2.0) < 1e-6  # not adjusted: the 2-degree seam is still there


def test_an_ordered_capture_in_clusters_is_closed_once(arc_scene, tmp_path):
    """The hierarchical mapper on an ordered capture: the chain's clusters merged without adjusting (merge passes
    0), then closed over every pair and adjusted once: every photo, true to a tenth of a degree."""
    images, database, truth = arc_scene
    (tmp_path / "out").mkdir()
    for name in ("features.h5", "matches.h5", "pairs.txt"):  # the fixture's run: only the mapping differs
        shutil.copy(database.parent / name, tmp_path / "out" / name)
    config = ReconstructConfig(features=SIFT, camera=CALIBRATED, mapper_type="hierarchical", mapper=OPTIONS)
    model = reconstruct(images, tmp_path / "out", config, progress=False)
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert stats["sequence"]["reason"] == "ordered" and stats["sequence"]["kept"] == "closed"
    assert stats["hierarchical"]["merge"]["passes"] == 0 and len(stats["hierarchical"]["clusters"]["photos"]) >= 3
    found = _poses(pycolmap.Reconstruction(str(model)))
    assert len(found) == VIEWS
    scale, rotation, translation, _ = cluster_merge.similarity(truth, found)
    expected = _in_other_world(truth, scale, rotation, translation)
    assert max(rotation_error_deg(pose[:, :3], expected[name][:, :3]) for name, pose in found.items()) < 0.1
