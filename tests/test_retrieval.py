"""Retrieval pairs: k-means, VLAD, blocked neighbour search, the resumable global file, recall on real photos."""
import itertools
import math
import os

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import Interrupted, SekdError
from sekd_sfm.files import features as ff
from sekd_sfm.files import partstore
from sekd_sfm.stages import retrieval
from sekd_sfm.stages.pairs import PairsConfig, make_pairs, read_pairs
from sekd_sfm.stages.retrieval import (
    RetrievalConfig,
    Vocabulary,
    compute_global_descriptors,
    global_path,
    grouped_kmeans,
    kmeans,
    local_to_float,
    nearest_neighbors,
    neighbour_recall,
    pair_recall,
    share_words,
    vlad,
)

SMALL = RetrievalConfig(vocabulary_size=8, pca_dim=32, max_samples=5000)


def feature_file(path, images: dict, feature="sekd"):
    """A feature file holding ``images`` {name: N x D descriptors (float32 or uint8)}."""
    first = next(iter(images.values()), np.zeros((0, 4), np.float32))
    partstore.create_empty(path, {"format": ff.FORMAT, "feature_type": feature, "descriptor_dim": first.shape[1],
                           "descriptor_dtype": str(first.dtype), "config": "{}"})
    add_images(path, images)
    return path


def add_images(path, images: dict):
    parts = partstore.PartStore(path)
    for name, desc in images.items():
        n = len(desc)
        parts.save(name, {"keypoints": np.zeros((n, 2), np.float32), "descriptors": desc,
                          "scores": np.ones(n, np.float32), "image_size": np.array([8, 8], np.int32)})
    partstore.merge_parts(path, parts)


def scene_collection(scenes=4, per_scene=5, distractors=6, dim=32, binary=False, seed=0):
    """Images that share a scene share most of their local descriptors (noisy copies); distractors share none.

    Returns ({name: descriptors}, {name: set of true neighbours}).
    """
    rng = np.random.default_rng(seed)
    images, truth = {}, {}

    def noisy(base, keep):
        rows = base[rng.choice(len(base), keep, replace=False)]
        if binary:  # flip ~5 % of the bits
            return rows ^ np.packbits(rng.random((keep, rows.shape[1] * 8)) < 0.05, axis=1)
        return (rows + 0.1 * rng.standard_normal(rows.shape)).astype(np.float32)

    def fresh(n):
        return rng.integers(0, 256, (n, dim // 8), dtype=np.uint8) if binary else rng.standard_normal(
            (n, dim)).astype(np.float32)

    for s in range(scenes):
        base = fresh(150)
        names = [f"scene{s}/{i}.jpg" for i in range(per_scene)]
        for name in names:
            images[name] = np.concatenate([noisy(base, 110), fresh(20)])
            truth[name] = set(names) - {name}
    for i in range(distractors):
        images[f"other/{i}.jpg"] = fresh(130)
        truth[f"other/{i}.jpg"] = set()
    return images, truth


def test_kmeans_finds_separated_clusters():
    gen = torch.Generator().manual_seed(1)
    centres = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    x = torch.cat([c + 0.01 * torch.randn(200, 2, generator=gen) for c in centres])
    found = kmeans(x, 3, seed=0)
    nearest = torch.cdist(centres, found).argmin(1)
    assert sorted(nearest.tolist()) == [0, 1, 2] and torch.allclose(found[nearest], centres, atol=0.01)
    assert kmeans(x[:3], 3).shape == (3, 2)  # k = N works


@pytest.mark.parametrize("counts, words, expected", [
    ([10, 30, 60], 10, [1, 3, 6]),
    ([1, 1000], 5, [0, 5]),  # the remainder goes to the largest share left
    ([2, 2, 3], 7, [2, 2, 3]),  # every point its own word
    ([5, 5, 5], 4, [2, 1, 1]),  # equal remainders: the first group
])
def test_share_words_is_proportional_and_adds_up(counts, words, expected):
    assert share_words(counts, words) == expected


def test_grouped_kmeans_finds_separated_clusters_group_by_group(tmp_path):
    """Eight tight clusters, four groups: each group's k-means gets its clusters' share of the words and finds
    them; the folder it worked in is left empty."""
    gen = torch.Generator().manual_seed(2)
    centres = torch.tensor([[10.0 * (i % 4), 10.0 * (i // 4)] for i in range(8)])
    x = torch.cat([c + 0.01 * torch.randn(100 + 20 * i, 2, generator=gen) for i, c in enumerate(centres)])
    found = grouped_kmeans(x, 8, 4, scratch=tmp_path)
    nearest = torch.cdist(centres, found).argmin(1)
    assert sorted(nearest.tolist()) == list(range(8)) and torch.allclose(found[nearest], centres, atol=0.01)
    assert list(tmp_path.iterdir()) == []
    assert torch.equal(grouped_kmeans(x, 8, 4), found)  # the same in a temporary folder


def test_interrupted_grouped_kmeans_keeps_its_finished_groups(tmp_path, monkeypatch):
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(2000, 4, generator=gen)
    whole = grouped_kmeans(x, 40, 4, scratch=tmp_path / "whole")
    learned: list[str] = []
    real_call = retrieval.WordsWorker.__call__

    def interrupted_after_two(self, keys):
        for key in keys:
            if len(learned) == 2:
                raise KeyboardInterrupt
            learned.append(key)
            yield from real_call(self, [key])

    monkeypatch.setattr(retrieval.WordsWorker, "__call__", interrupted_after_two)
    with pytest.raises(Interrupted):
        grouped_kmeans(x, 40, 4, scratch=tmp_path / "cut", signature="run")
    monkeypatch.setattr(retrieval.WordsWorker, "__call__",
                        lambda self, keys: learned.extend(keys) or real_call(self, keys))
    assert torch.equal(grouped_kmeans(x, 40, 4, scratch=tmp_path / "cut", signature="run"), whole)
    assert learned == ["group-0", "group-1", "group-2", "group-3"]  # the first two once, before the interruption


def test_local_to_float_unpacks_binary_to_signs():
    x = local_to_float(np.array([[0b10000001]], np.uint8))
    expected = torch.tensor([[1, -1, -1, -1, -1, -1, -1, 1]], dtype=torch.float32) / math.sqrt(8)
    assert torch.allclose(x, expected)
    assert torch.allclose(local_to_float(np.array([[3.0, 4.0]], np.float16)), torch.tensor([[0.6, 0.8]]))


def test_vlad_hand_computed():
    vocab = Vocabulary(np.zeros(2, np.float32), np.eye(2, dtype=np.float32), np.eye(2, dtype=np.float32))
    # (0.6, 0.8) is nearer centroid (0, 1): residual (0.6, -0.2); intra-norm (3, -1)/sqrt(10); signed sqrt; L2.
    a, b = math.sqrt(3 / math.sqrt(10)), math.sqrt(1 / math.sqrt(10))
    expected = np.array([0, 0, a, -b]) / math.hypot(a, b)
    assert np.allclose(vlad(np.array([[6.0, 8.0]], np.float32), vocab), expected, atol=1e-6)
    assert np.array_equal(vlad(np.zeros((0, 2), np.float32), vocab), np.zeros(4, np.float32))


@pytest.mark.parametrize("binary", [False, True])
def test_synthetic_scenes_recall_is_perfect(tmp_path, binary):
    images, truth = scene_collection(binary=binary, dim=256 if binary else 32)  # ORB: 256 bits
    features = feature_file(tmp_path / "f.h5", images, feature="orb" if binary else "sekd")
    out = compute_global_descriptors(features, SMALL, progress=False)
    assert out == tmp_path / "f.global.h5"
    names = sorted(images)
    neighbours = nearest_neighbors(out, names, 4)
    assert neighbour_recall(neighbours, truth, 4) == 1.0
    with h5py.File(out, "r") as f:
        assert f["descriptors"].shape == (len(names), 8 * 32)
        assert np.allclose(np.linalg.norm(f["descriptors"][()].astype(np.float32), axis=1), 1, atol=1e-2)


def test_nearest_neighbors_blocked_equals_brute_force(tmp_path):
    images, _ = scene_collection(scenes=3, per_scene=4, distractors=5)
    features = feature_file(tmp_path / "f.h5", images)
    out = compute_global_descriptors(features, SMALL, progress=False)
    with h5py.File(out, "r") as f:
        stored = [n.decode() for n in f["names"][()]]
        g = f["descriptors"][()].astype(np.float32)
    sim = g @ g.T
    np.fill_diagonal(sim, -np.inf)
    brute = {stored[i]: [stored[j] for j in np.argsort(-sim[i], kind="stable")[:3]] for i in range(len(stored))}
    for block in (1, 4, 1000):
        found = nearest_neighbors(out, stored, 3, block=block)
        assert {n: set(v) for n, v in found.items()} == {n: set(v) for n, v in brute.items()}
    subset = stored[:5]  # only the given names are candidates
    assert all(set(v) <= set(subset) - {n} for n, v in nearest_neighbors(out, subset, 10).items())
    assert nearest_neighbors(out, stored[:1], 5) == {stored[0]: []}


def test_recall_functions_exact():
    truth = {"a": {"b", "c"}, "b": {"a", "c"}, "c": {"a", "b"}, "x": set()}
    retrieved = {"a": ["b", "x"], "b": ["x", "c"], "c": ["x", "y"], "x": ["a"]}
    assert neighbour_recall(retrieved, truth, 2) == pytest.approx(2 / 6)  # a: b; b: c; c: none
    assert neighbour_recall(retrieved, truth, 1) == pytest.approx(1 / 3)
    assert pair_recall([("a", "b"), ("c", "b"), ("x", "a")], truth) == pytest.approx(2 / 3)
    with pytest.raises(ValueError):
        neighbour_recall(retrieved, {"x": set()}, 2)


def test_resume_describes_only_new_images_and_config_change_recomputes(tmp_path, monkeypatch):
    images, _ = scene_collection(scenes=2, per_scene=4, distractors=2)
    names = sorted(images)
    features = feature_file(tmp_path / "f.h5", {n: images[n] for n in names[:6]})
    calls = []
    real_vlad = retrieval.vlad
    monkeypatch.setattr(retrieval, "vlad", lambda d, v: calls.append(1) or real_vlad(d, v))
    out = compute_global_descriptors(features, SMALL, progress=False)
    with h5py.File(out, "r") as f:
        centroids = f["vocabulary/centroids"][()]
    assert len(calls) == 6
    compute_global_descriptors(features, SMALL, progress=False)
    assert len(calls) == 6  # nothing new
    add_images(features, {n: images[n] for n in names[6:]})
    compute_global_descriptors(features, SMALL, progress=False)
    assert len(calls) == 6 + len(names) - 6
    with h5py.File(out, "r") as f:
        assert np.array_equal(f["vocabulary/centroids"][()], centroids)  # vocabulary kept
        assert sorted(n.decode() for n in f["names"][()]) == names
    compute_global_descriptors(features, RetrievalConfig(vocabulary_size=4, pca_dim=8), progress=False)
    assert len(calls) == 2 * len(names)  # another vocabulary: everything again
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix != ".lock") == ["f.global.h5", "f.h5"]


def test_an_up_to_date_file_opens_no_executor(tmp_path, monkeypatch):
    """Nothing to describe: the executor (a Ray cluster with ``--executor ray``) is not opened at all."""
    images, _ = scene_collection(scenes=2, per_scene=3, distractors=0)
    features = feature_file(tmp_path / "f.h5", images)
    compute_global_descriptors(features, SMALL, progress=False)
    monkeypatch.setattr(retrieval, "using", lambda *a, **k: pytest.fail("an executor was opened"))
    compute_global_descriptors(features, SMALL, progress=False, executor="ray")


def test_interrupted_run_keeps_finished_images_and_its_vocabulary(tmp_path, monkeypatch):
    images, _ = scene_collection(scenes=2, per_scene=4, distractors=2)
    features = feature_file(tmp_path / "f.h5", images)
    described: list[str] = []
    real_call = retrieval.VladWorker.__call__

    def interrupted_after_four(self, keys):
        for key in keys:
            if len(described) == 4:
                raise KeyboardInterrupt  # Ctrl-C
            described.append(key)
            yield from real_call(self, [key])

    monkeypatch.setattr(retrieval.VladWorker, "__call__", interrupted_after_four)
    with pytest.raises(Interrupted, match="4 more images saved"):
        compute_global_descriptors(features, SMALL, progress=False)
    parts = tmp_path / "f.global.h5.parts"
    assert (parts / "vocabulary.npz").is_file() and not (tmp_path / "f.global.h5").exists()
    monkeypatch.undo()
    calls = []
    real_vlad = retrieval.vlad
    monkeypatch.setattr(retrieval, "vlad", lambda d, v: calls.append(1) or real_vlad(d, v))
    # The interrupted run's vocabulary is reused, so its images stay valid: only the other six are described.
    out = compute_global_descriptors(features, SMALL, progress=False)
    assert len(calls) == len(images) - 4
    assert not parts.exists()
    with h5py.File(out, "r") as f:
        assert sorted(n.decode() for n in f["names"][()]) == sorted(images)
    # The same rows as an uninterrupted run.
    again = compute_global_descriptors(features, SMALL, output=tmp_path / "again.h5", progress=False)
    with h5py.File(out, "r") as a, h5py.File(again, "r") as b:
        rows = {n.decode(): r for n, r in zip(a["names"][()], a["descriptors"][()])}
        assert all(np.array_equal(rows[n.decode()], r) for n, r in zip(b["names"][()], b["descriptors"][()]))


def test_make_pairs_retrieval_sequential_and_file_union(tmp_path):
    images, truth = scene_collection(scenes=3, per_scene=4, distractors=0)
    features = feature_file(tmp_path / "f.h5", images)
    within = {frozenset((a, b)) for a, t in truth.items() for b in t}
    config = PairsConfig(mode="retrieval", num_neighbors=3, retrieval=SMALL)
    out = make_pairs(features, tmp_path / "r.txt", config, progress=False)
    assert {frozenset(p) for p in read_pairs(out)} == within
    assert global_path(features).is_file()
    # sequential window 1 in natural order + retrieval K=3
    seq = make_pairs(features, tmp_path / "s.txt", PairsConfig(mode="sequential", window=1, num_neighbors=3,
                                                             retrieval=SMALL), progress=False)
    order = sorted(images, key=lambda n: (int(n[5]), int(n.split("/")[1][0])))
    assert {frozenset(p) for p in read_pairs(seq)} == within | {frozenset(p) for p in itertools.pairwise(order)}
    (tmp_path / "mine.txt").write_text("scene0/0.jpg scene2/3.jpg\n")
    union = make_pairs(features, tmp_path / "u.txt", PairsConfig(mode="from-file", file=str(tmp_path / "mine.txt"),
                                                               num_neighbors=3, retrieval=SMALL), progress=False)
    assert read_pairs(union)[0] == ("scene0/0.jpg", "scene2/3.jpg")
    assert {frozenset(p) for p in read_pairs(union)} == within | {frozenset(("scene0/0.jpg", "scene2/3.jpg"))}


def test_auto_uses_retrieval_above_2k_plus_1(tmp_path):
    images, truth = scene_collection(scenes=3, per_scene=4, distractors=0)
    features = feature_file(tmp_path / "f.h5", images)
    within = {frozenset((a, b)) for a, t in truth.items() for b in t}
    out = make_pairs(features, tmp_path / "a.txt", PairsConfig(num_neighbors=6, retrieval=SMALL), progress=False)
    assert len(read_pairs(out)) == 66 and not global_path(features).exists()  # 12 <= 2*6+1: exhaustive
    out = make_pairs(features, tmp_path / "a.txt", PairsConfig(num_neighbors=5, retrieval=SMALL), progress=False)
    pairs = {frozenset(p) for p in read_pairs(out)}  # 12 > 2*5+1: retrieval, at most 12*5 pairs
    assert within <= pairs and len(pairs) <= 60 and global_path(features).is_file()


def test_retrieval_errors_and_empty(tmp_path):
    empty = feature_file(tmp_path / "e.h5", {})
    assert read_pairs(make_pairs(empty, tmp_path / "e.txt", PairsConfig(mode="retrieval"), progress=False)) == []
    no_keypoints = feature_file(tmp_path / "z.h5", {"a.jpg": np.zeros((0, 8), np.float32),
                                                    "b.jpg": np.zeros((0, 8), np.float32)})
    with pytest.raises(SekdError, match="fewer than 2 keypoints"):
        make_pairs(no_keypoints, tmp_path / "z.txt", PairsConfig(mode="retrieval"), progress=False)
    result = CliRunner().invoke(sekd, ["-q", "pairs", str(no_keypoints), "--pairs", "retrieval"])
    assert result.exit_code == 1 and result.output.strip().startswith("Error:") and "fewer than 2" in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_cli_retrieval(tmp_path):
    images, truth = scene_collection(scenes=3, per_scene=4, distractors=2)
    features = feature_file(tmp_path / "f.h5", images)
    result = CliRunner().invoke(sekd, ["-q", "pairs", str(features), "--pairs", "retrieval", "--num-neighbors", "3",
                                       "--no-progress"])
    assert result.exit_code == 0, result.output
    pairs = read_pairs(tmp_path / "pairs-retrieval.txt")
    assert pair_recall(pairs, truth) == 1.0 and len(pairs) <= 14 * 3
    assert (tmp_path / "f.global.h5").is_file() and os.path.getsize(tmp_path / "f.global.h5") > 0


def mixed_collection(shared, folder, distractors=30):
    """Symlinks to the shared scenes (5 homography sequences, fountain-P11, sacre_coeur) plus COCO distractors.

    Returns the ground truth {name: names of the same scene} (distractors: none).
    """
    data = shared / "data"
    scenes = {p.name: sorted(p.glob("[0-9].p*")) for p in sorted((data / "homography").glob("*/*")) if p.is_dir()}
    scenes["fountain-P11"] = sorted((data / "sfm/fountain-P11/images").glob("*.jpg"))
    scenes["sacre_coeur"] = sorted((data / "sfm/sacre_coeur/images").glob("*.jpg"))
    scenes["coco"] = sorted((data / "train/coco").glob("*.jpg"))[:distractors]
    for scene, files in scenes.items():
        (folder / scene).mkdir(parents=True)
        for file in files:
            (folder / scene / file.name).symlink_to(file)
    names = {scene: [f"{scene}/{f.name}" for f in files] for scene, files in scenes.items()}
    return {n: (set() if scene == "coco" else set(group) - {n}) for scene, group in names.items() for n in group}


@pytest.mark.slow
def test_recall_on_real_scenes_low_resolution(shared, tmp_path):
    """51 photos of 7 scenes + 30 distractors, SIFT at 320 px: same-scene neighbours are retrieved."""
    from sekd_sfm.features import FeatureConfig
    from sekd_sfm.stages.extract import extract_features

    truth = mixed_collection(shared, tmp_path / "images")
    features = extract_features(tmp_path / "images", tmp_path / "f.h5", FeatureConfig(feature="sift", resize_max=320,
                                max_keypoints=1000), num_threads=1, progress=False)
    out = compute_global_descriptors(features, progress=False)
    neighbours = nearest_neighbors(out, sorted(truth), 20)
    assert neighbour_recall(neighbours, truth, 5) >= 0.85
    assert neighbour_recall(neighbours, truth, 20) >= 0.85
