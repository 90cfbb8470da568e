"""Keypoint refinement (sekd_sfm.stages.refine): exact fixtures for each step, then a real photo under a known homography."""
from __future__ import annotations

import json
import os
import shutil

import cv2
import h5py
import hloc_readers
import numpy as np
import pytest

from sekd_sfm.errors import SekdError
from sekd_sfm.features import FeatureConfig
from sekd_sfm.stages.extract import extract_features
from sekd_sfm.stages.match import MatchConfig, match_features
from sekd_sfm.stages.refine import (
    AlignImage,
    RefineConfig,
    align_patches,
    bilinear,
    is_current,
    local_affines,
    patch_grid,
    refine_keypoints,
    refine_summary,
    solve_offsets,
)


def test_bilinear_is_exact_on_a_ramp_and_clamps():
    ys, xs = np.mgrid[0:6, 0:8].astype(np.float32)
    ramp = 2 * xs + 10 * ys
    points = np.array([[1.25, 2.5], [0, 0], [6.75, 4.125], [-3, 1], [20, 2]], np.float32)
    assert np.allclose(bilinear(ramp, points), [27.5, 0, 13.5 + 41.25, 10, 2 * 6.999 + 20], atol=1e-3)


def test_patch_grid_offsets_and_weights():
    offsets, weights = patch_grid(1, 1.0)
    assert offsets.shape == (9, 2) and offsets[0].tolist() == [-1, -1] and offsets[4].tolist() == [0, 0]
    assert np.isclose(weights[4], 1) and np.isclose(weights[0], np.exp(-1)) and np.isclose(weights[1], np.exp(-0.5))


def test_local_affines_recover_an_exact_affine():
    rng = np.random.default_rng(0)
    xa = rng.uniform(0, 100, (30, 2))
    A_true = np.array([[0.9, -0.2], [0.15, 1.1]])
    A, error = local_affines(xa, xa @ A_true.T + [5, -3], neighbours=8)
    assert A.shape == (30, 2, 2) and np.allclose(A, A_true, atol=1e-4) and error.max() < 1e-3


def test_solve_offsets_hand_computed():
    # Two keypoints, one match saying b lies 1 px right of where a's patch is: minimise
    # (d1 - d0 - 1)^2 + p^2 (d0^2 + d1^2)  ->  d1 = -d0 = 1 / (2 + p^2), in x only.
    shifts, residual = solve_offsets(2, np.array([0]), np.array([1]), np.eye(2)[None], np.array([[1.0, 0.0]]),
                                     prior=0.1, reweightings=0)
    expected = 1 / (2 + 0.01)
    assert np.allclose(shifts, [[-expected, 0], [expected, 0]], atol=1e-6)
    assert np.isclose(residual[0], 1 - 2 * expected, atol=1e-6)
    empty, none = solve_offsets(3, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2, 2)), np.zeros((0, 2)), 0.1)
    assert empty.shape == (3, 2) and not empty.any() and none.size == 0


def _dense_offsets(num_points, ia, ib, A, t, prior, reweightings, fixed):
    """``solve_offsets`` the plain way: every equation in one dense matrix, least squares, Huber reweighting."""
    E, free = len(ia), np.flatnonzero(~fixed)
    design = np.zeros((2 * E, 2 * num_points))
    for e in range(E):
        design[2 * e: 2 * e + 2, 2 * ib[e]: 2 * ib[e] + 2] += np.eye(2)
        design[2 * e: 2 * e + 2, 2 * ia[e]: 2 * ia[e] + 2] -= A[e]
    columns = np.stack([2 * free, 2 * free + 1], 1).ravel()
    design = design[:, columns]
    weight = np.ones(E)
    for _ in range(reweightings + 1):
        w = np.repeat(weight, 2)[:, None]
        stacked = np.vstack([w * design, prior * np.eye(len(columns))])
        target = np.concatenate([w[:, 0] * t.ravel(), np.zeros(len(columns))])
        solution = np.linalg.lstsq(stacked, target, rcond=None)[0]
        d = np.zeros(2 * num_points)
        d[columns] = solution
        d = d.reshape(-1, 2)
        residual = np.linalg.norm(d[ib] - np.einsum("eij,ej->ei", A, d[ia]) - t, axis=1)
        weight = 1 / np.maximum(1, residual / 0.25)
    return d, residual


def test_solve_offsets_track_by_track_is_the_least_squares_solution():
    # Tracks of 1-6 points, one of 70 (over MAX_DENSE_TRACK: the sparse path), fixed points, unmatched points, and
    # outlying matches for the reweighting: the same shifts as one dense least-squares problem.
    from sekd_sfm.stages.refine import MAX_DENSE_TRACK

    rng = np.random.default_rng(3)
    sizes = [2, 2, 3, 4, 5, 6, 2, 3, MAX_DENSE_TRACK + 6]
    ia, ib, start = [], [], 1  # point 0: unmatched
    for size in sizes:
        members = np.arange(start, start + size)
        extra = rng.integers(0, size, (size, 2))
        edges = [(members[j], members[j + 1]) for j in range(size - 1)]  # a chain holds the track together,
        edges += [(members[x], members[y]) for x, y in extra if x != y]  # and more matches within it
        ia += [x for x, _ in edges]
        ib += [y for _, y in edges]
        start += size
    num_points, ia, ib = start + 1, np.array(ia), np.array(ib)
    A = np.eye(2) + rng.normal(0, 0.1, (len(ia), 2, 2))
    t = rng.normal(0, 0.3, (len(ia), 2))
    t[::7] += 3.0  # wrong matches, weighed down by the reweighting
    fixed = np.zeros(num_points, bool)
    fixed[[2, 9, num_points - 20]] = True  # in two short tracks and the long one
    for fix in (None, fixed):
        shifts, residual = solve_offsets(num_points, ia, ib, A, t, 0.1, reweightings=2, fixed=fix)
        expected, expected_residual = _dense_offsets(num_points, ia, ib, A, t, 0.1, 2,
                                                     fix if fix is not None else np.zeros(num_points, bool))
        assert np.allclose(shifts, expected, atol=1e-10) and np.allclose(residual, expected_residual, atol=1e-10)
        assert not shifts[0].any() and not shifts[-1].any()  # unmatched points stay
    assert not shifts[fixed].any() and np.abs(shifts).max() > 0.1


def _texture(x, y):
    """A smooth texture defined everywhere, so a sub-pixel shift of it is exact."""
    return (120 + 40 * np.sin(0.45 * x + 0.3 * y) + 30 * np.cos(0.21 * x - 0.5 * y)
            + 25 * np.sin(0.4 * y + 0.002 * x * x))


def _align_image(image: np.ndarray) -> AlignImage:
    image = image.astype(np.float32)
    return AlignImage(image, cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8),
                      cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8), 1.0, 1.0)


def test_align_patches_recovers_a_subpixel_shift_under_a_lighting_change():
    ys, xs = np.mgrid[0:64, 0:64].astype(np.float64)
    shift = np.array([0.3, -0.2])
    a = _align_image(_texture(xs, ys))
    b = _align_image(0.7 * _texture(xs - shift[0], ys - shift[1]) + 20)  # b(x) = a(x - shift), darker
    xa = np.array([[20.0, 20.0], [32.0, 40.0], [45.0, 25.0]], np.float32)
    t, ncc = align_patches(a, b, xa, xa.copy(), np.repeat(np.eye(2, dtype=np.float32)[None], 3, 0), RefineConfig())
    assert np.allclose(t, shift, atol=0.03) and (ncc > 0.99).all()


def test_align_patches_on_a_blank_patch_is_not_trusted():
    blank = _align_image(np.full((32, 32), 90.0))
    _, ncc = align_patches(blank, blank, np.array([[16.0, 16.0]], np.float32), np.array([[16.0, 16.0]], np.float32),
                           np.eye(2, dtype=np.float32)[None], RefineConfig())
    assert ncc[0] < RefineConfig().min_ncc


@pytest.fixture(scope="module")
def warped_pair(shared, tmp_path_factory):
    """A COCO photo and its warp by a known homography, with SEKD features and mutual-NN matches."""
    root = tmp_path_factory.mktemp("refine")
    images = root / "images"
    images.mkdir()
    photo = cv2.imread(str(sorted((shared / "data/train/coco").glob("*.jpg"))[3]), cv2.IMREAD_GRAYSCALE)
    h, w = photo.shape
    angle = np.radians(8)
    centre = np.array([[1, 0, -w / 2], [0, 1, -h / 2], [0, 0, 1]])
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [1e-4, -5e-5, 1]])
    H = np.linalg.inv(centre) @ rotation @ centre
    H[:2, 2] += [0.37, -0.21]
    cv2.imwrite(str(images / "a.png"), photo)
    cv2.imwrite(str(images / "b.png"), cv2.warpPerspective(photo, H, (w, h), flags=cv2.INTER_LINEAR))
    features = extract_features(images, root / "features.h5", FeatureConfig(), progress=False, num_threads=1)
    (root / "pairs.txt").write_text("a.png b.png\n")
    matches = match_features(features, root / "pairs.txt", root / "matches.h5", MatchConfig(mode="mnn"),
                             progress=False, num_threads=1)
    return root, images, features, matches, H


def _residuals(keypoints_file, matches_file, H) -> np.ndarray:
    """Distances (px) between b's matched keypoints and a's keypoints mapped by H, for the correct matches."""
    with h5py.File(keypoints_file, "r") as f:
        ka, kb = f["a.png/keypoints"][()], f["b.png/keypoints"][()]
    with h5py.File(matches_file, "r") as f:
        m0 = f["a.png/b.png/matches0"][()]
    ia = np.nonzero(m0 >= 0)[0]
    mapped = cv2.perspectiveTransform(ka[ia][None].astype(np.float64), H)[0]
    distance = np.linalg.norm(mapped - kb[m0[ia]], axis=1)
    return distance[distance < 2]


def test_refinement_brings_matched_keypoints_closer_on_a_real_photo(warped_pair):
    root, images, features, matches, H = warped_pair
    refined = refine_keypoints(features, matches, [("a.png", "b.png")], images, root / "refined.h5", progress=False)
    before, after = _residuals(features, matches, H), _residuals(refined, matches, H)
    summary = refine_summary(refined)
    assert summary["aligned"] > 0.8 * summary["matches"] > 300
    assert len(after) >= len(before) > 300
    assert np.median(after) < 0.6 * np.median(before)  # measured: 0.27 -> under 0.1 px
    with h5py.File(refined, "r") as f, h5py.File(features, "r") as g:
        assert f.attrs["format"] == "sekd-keypoints" and sorted(f) == ["a.png", "b.png"]
        assert f["a.png/image_size"][()].tolist() == g["a.png/image_size"][()].tolist()
        assert f["a.png/keypoints"].shape == g["a.png/keypoints"].shape
    # hloc reads it as a feature file (its triangulation takes keypoints and their uncertainty from it).
    keypoints, uncertainty = hloc_readers.get_keypoints(refined, "b.png", return_uncertainty=True)
    assert sorted(hloc_readers.list_h5_names(refined)) == ["a.png", "b.png"]
    assert keypoints.shape[1] == 2 and uncertainty == hloc_readers.get_keypoints(features, "b.png", True)[1] > 0


def test_refinement_is_reused_until_its_inputs_or_settings_change(warped_pair):
    root, images, features, matches, _ = warped_pair
    output = root / "reuse.h5"
    refine_keypoints(features, matches, [("a.png", "b.png")], images, output, progress=False)
    stamp = output.stat().st_mtime_ns
    refine_keypoints(features, matches, [("a.png", "b.png")], images, output, progress=False)
    assert output.stat().st_mtime_ns == stamp
    refine_keypoints(features, matches, [("a.png", "b.png")], images, output, RefineConfig(patch_radius=5), progress=False)
    assert output.stat().st_mtime_ns != stamp and not list(root.glob("reuse.h5.*.tmp"))


def test_refinement_in_a_moved_folder_is_reused(warped_pair, tmp_path):
    """The signature names its input files without their folder: a project folder moved elsewhere (``mv`` keeps
    the files' times) keeps its refined keypoints; a copy with new times refines again."""
    root, images, features, matches, _ = warped_pair
    project = tmp_path / "project"
    project.mkdir()
    for path in (features, matches):
        shutil.copy2(path, project / path.name)
    output = refine_keypoints(project / features.name, project / matches.name, [("a.png", "b.png")], images,
                              project / "refined.h5", progress=False)
    stamp = output.stat().st_mtime_ns
    moved = shutil.move(project, tmp_path / "renamed")
    again = refine_keypoints(moved / features.name, moved / matches.name, [("a.png", "b.png")], images,
                             moved / "refined.h5", progress=False)
    assert again.stat().st_mtime_ns == stamp
    os.utime(moved / matches.name)  # the matches written again: refined again
    refine_keypoints(moved / features.name, moved / matches.name, [("a.png", "b.png")], images, moved / "refined.h5",
                     progress=False)
    assert again.stat().st_mtime_ns != stamp


def test_refinement_without_pairs_keeps_every_keypoint(warped_pair):
    root, images, features, matches, _ = warped_pair
    output = refine_keypoints(features, matches, [], images, root / "none.h5", progress=False)
    with h5py.File(output, "r") as f, h5py.File(features, "r") as g:
        assert np.array_equal(f["b.png/keypoints"][()], g["b.png/keypoints"][()])
    assert refine_summary(output)["aligned"] == 0


def test_a_missing_photo_is_one_clear_error(warped_pair, tmp_path):
    root, _, features, matches, _ = warped_pair
    with pytest.raises(SekdError, match="keypoint refinement: .*elsewhere.a.png: cannot read"):
        refine_keypoints(features, matches, [("a.png", "b.png")], root / "elsewhere", tmp_path / "k.h5", progress=False)
    assert not os.listdir(tmp_path) and not is_current(tmp_path / "k.h5", "")


def test_match_distances_and_summary_hand_computed():
    from sekd_sfm.bench.localization import match_distances, summarize

    k0 = np.array([[10.0, 10.0], [20.0, 5.0], [0.0, 0.0]])
    k1 = np.array([[12.3, 10.0], [22.0, 5.4], [0.0, 0.0]])
    H = np.array([[1.0, 0, 2], [0, 1, 0], [0, 0, 1]])  # a shift of 2 px in x
    distances = match_distances(k0, k1, np.array([[0, 0], [1, 1], [2, 2]]), H, correct_px=2.0)
    assert np.allclose(distances, [0.3, 0.4])  # the third match is 2 px off: not correct
    summary = summarize(np.array([0.3, 0.4, 0.9]))
    assert summary == {"correct": 3, "median_px": 0.4, "rms_px": round(float(np.sqrt((0.09 + 0.16 + 0.81) / 3)), 4),
                       "under_0_5px": round(2 / 3, 4)}
    assert summarize(np.zeros(0))["median_px"] is None and match_distances(k0, k1, np.zeros((0, 2), int), H, 2).size == 0


def test_bench_localization_on_two_real_photos(shared, tmp_path):
    from click.testing import CliRunner

    from sekd_sfm.cli.main import sekd

    result = CliRunner().invoke(sekd, ["bench", "localization", "--num-images", "2", "-o", str(tmp_path)])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "results.json").read_text())
    for label in ("sift", "sekd"):
        detected, refined = report["results"][label]["detected"], report["results"][label]["refined"]
        assert detected["correct"] > 200 and refined["correct"] >= 0.95 * detected["correct"]
        assert refined["median_px"] < detected["median_px"]
    # measured: SEKD 0.25 -> 0.06 px, SIFT 0.11 -> 0.05 px on three photos
    assert report["results"]["sekd"]["detected"]["median_px"] > report["results"]["sift"]["detected"]["median_px"]
    assert "| sekd |" in (tmp_path / "results.md").read_text()


def _three_photos(images, tmp_path):
    """The warped pair plus a copy of its second photo (three pairs): image folder, features, matches, pairs."""
    import shutil

    three = tmp_path / "images"
    shutil.copytree(images, three)
    shutil.copy(three / "b.png", three / "c.png")
    features = extract_features(three, tmp_path / "features.h5", FeatureConfig(), progress=False, num_threads=1)
    pairs = [("a.png", "b.png"), ("a.png", "c.png"), ("b.png", "c.png")]
    (tmp_path / "pairs.txt").write_text("".join(f"{a} {b}\n" for a, b in pairs))
    matches = match_features(features, tmp_path / "pairs.txt", tmp_path / "matches.h5", MatchConfig(mode="mnn"),
                             progress=False, num_threads=1)
    return three, features, matches, pairs


def test_a_failed_refinement_resumes_from_the_pairs_it_finished(warped_pair, tmp_path, monkeypatch):
    """The per-pair alignments run as an execution Stage: finished pairs survive a failure, the rerun computes only
    the rest, and the keypoints equal those of an uninterrupted run."""
    from sekd_sfm.stages import refine as refine_module

    root, images, _, _, _ = warped_pair
    three, features, matches, pairs = _three_photos(images, tmp_path)
    clean = refine_keypoints(features, matches, pairs, three, tmp_path / "clean.h5", progress=False)
    computed: list[int] = []
    original = refine_module._pair_edges

    def fails_on_the_third(*args):
        computed.append(1)
        if len(computed) == 3:
            raise SekdError("keypoint refinement: the third pair fails")
        return original(*args)

    monkeypatch.setattr(refine_module, "_pair_edges", fails_on_the_third)
    with pytest.raises(SekdError, match="the third pair fails"):
        refine_keypoints(features, matches, pairs, three, tmp_path / "resumed.h5", progress=False)
    assert not (tmp_path / "resumed.h5").exists() and (tmp_path / "resumed-pairs.h5").exists()
    computed.clear()
    monkeypatch.setattr(refine_module, "_pair_edges", lambda *args: computed.append(1) or original(*args))
    resumed = refine_keypoints(features, matches, pairs, three, tmp_path / "resumed.h5", progress=False)
    assert len(computed) == 1 and not (tmp_path / "resumed-pairs.h5").exists()
    with h5py.File(clean, "r") as f, h5py.File(resumed, "r") as g:
        for name in ("a.png", "b.png", "c.png"):
            assert np.array_equal(f[name]["keypoints"][()], g[name]["keypoints"][()])
    assert refine_summary(clean)["aligned"] == refine_summary(resumed)["aligned"] > 0


def test_refinement_over_worker_processes_writes_the_same_keypoints(warped_pair, tmp_path, monkeypatch):
    """A local run spreads the pairs over processes (one task per pair here): the same file as one process."""
    from sekd_sfm.execution import LocalExecutor
    from sekd_sfm.stages import refine as refine_module

    _, images, _, _, _ = warped_pair
    three, features, matches, pairs = _three_photos(images, tmp_path)
    monkeypatch.setattr(refine_module, "PAIRS_PER_TASK", 1)
    one, two = LocalExecutor(1), LocalExecutor(2)
    here = refine_keypoints(features, matches, pairs, three, tmp_path / "here.h5", progress=False, executor=one)
    spread = refine_keypoints(features, matches, pairs, three, tmp_path / "spread.h5", progress=False, executor=two)
    assert one.places == ["local"] and two.places == ["local: 2 processes"]
    with h5py.File(here, "r") as f, h5py.File(spread, "r") as g:
        for name in ("a.png", "b.png", "c.png"):
            assert np.array_equal(f[name]["keypoints"][()], g[name]["keypoints"][()])
    assert refine_summary(here)["aligned"] == refine_summary(spread)["aligned"] > 0
