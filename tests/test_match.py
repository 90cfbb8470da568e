"""Matching: hand-computed float and binary cases, batching, the match file, resume, errors, CLI."""
import json

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.files import features as ff
from sekd_sfm.files import matches as mf
from sekd_sfm.files import partstore
from sekd_sfm.runtime import exact_sqrt
from sekd_sfm.stages.match import (
    MatchConfig,
    _select,
    augment_cols,
    augment_rows,
    match_batch,
    match_descriptors,
    match_features,
    prepare_descriptors,
    stack_cols,
    stack_rows,
)
from sekd_sfm.stages.pairs import write_pairs

# Float case. Rows of A, columns of B (2-D points as descriptors), distances worked out by hand:
#   a0 (0,0):   b0 1,  b4 sqrt(41), ...         nearest b0, but b0's nearest is a4 (0.5): not mutual
#   a1 (10,0):  b1 1,  b3 sqrt(41)              ratio 1/sqrt(41) = 0.156
#   a2 (0,10):  b2 2,  b4 sqrt(41)              ratio 2/sqrt(41) = 0.312
#   a3 (5,5):   b3 1,  b4 1 (tie)               nearest b3 (lowest index); ratio 1 fails any test
#   a4 (0,1.5): b0 0.5, b4 sqrt(28.25)          ratio 0.094
A = np.array([[0, 0], [10, 0], [0, 10], [5, 5], [0, 1.5]], np.float32)
B = np.array([[0, 1], [10, 1], [0, 12], [6, 5], [4, 5]], np.float32)
S41, S2825 = np.sqrt(41.0), np.sqrt(28.25)

# Binary case, one byte per descriptor; Hamming distances by hand:
#   x0 11110000: y0 1, y1 7, y2 4, y3 4   -> y0, ratio 1/4
#   x1 00001111: y0 7, y1 1, y2 4, y3 4   -> y1, ratio 1/4
#   x2 10101010: y0 5, y1 5, y2 4, y3 8   -> y2, ratio 4/5; y2 is at distance 4 from every x, and
#                                            x2 is the only row choosing y2, so the pair is mutual
X = np.array([[0b11110000], [0b00001111], [0b10101010]], np.uint8)
Y = np.array([[0b11110001], [0b00000111], [0b11111111], [0b01010101]], np.uint8)


@pytest.mark.parametrize("mode,ratio,expected", [
    ("mnn", None, [-1, 1, 2, 3, 0]),
    ("ratio", 0.8, [0, 1, 2, -1, 0]),
    ("both", 0.8, [-1, 1, 2, -1, 0]),
    ("both", 0.3, [-1, 1, -1, -1, 0]),
])
def test_float_l2_hand_computed(mode, ratio, expected):
    matches, scores = match_descriptors(A, B, mode, ratio)
    assert matches.dtype == np.int32 and scores.dtype == np.float32
    assert matches.tolist() == expected
    margin = {0: 1 - 1 / S41, 1: 1 - 1 / S41, 2: 1 - 2 / S41, 3: 0.0, 4: 1 - 0.5 / S2825}
    for i, j in enumerate(expected):
        assert scores[i] == pytest.approx(margin[i] if j >= 0 else 0.0, abs=1e-6)


@pytest.mark.parametrize("mode,ratio,expected,expected_scores", [
    ("mnn", None, [0, 1, 2], [0.75, 0.75, 0.2]),
    ("both", 0.9, [0, 1, 2], [0.75, 0.75, 0.2]),
    ("both", 0.8, [0, 1, -1], [0.75, 0.75, 0.0]),  # 4 < 0.8 * 5 is false: the test is strict
    ("ratio", 0.2, [-1, -1, -1], [0, 0, 0]),
])
def test_binary_hamming_hand_computed(mode, ratio, expected, expected_scores):
    matches, scores = match_descriptors(X, Y, mode, ratio)
    assert matches.tolist() == expected
    assert scores.tolist() == pytest.approx(expected_scores, abs=1e-6)


def test_binary_distances_are_exact_hamming():
    rng = np.random.default_rng(3)
    a, b = rng.integers(0, 256, (6, 32), dtype=np.uint8), rng.integers(0, 256, (9, 32), dtype=np.uint8)
    pa, pb = prepare_descriptors(a, True), prepare_descriptors(b, True)
    dist = torch.bmm(augment_rows(pa)[None], augment_cols(pb)[None])[0].numpy()
    expected = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(2)
    assert np.array_equal(dist, expected)


@pytest.mark.parametrize("d0,d1", [(A[:0], B), (X[:0], Y)])
def test_empty_query(d0, d1):
    matches, scores = match_descriptors(d0, d1)
    assert matches.shape == (0,) and scores.shape == (0,)


@pytest.mark.parametrize("d0,d1", [(A, B[:0]), (X, Y[:0])])
def test_empty_reference(d0, d1):
    matches, scores = match_descriptors(d0, d1)
    assert matches.tolist() == [-1] * len(d0) and scores.tolist() == [0.0] * len(d0)


def test_single_candidate_passes_ratio_with_score_one():
    matches, scores = match_descriptors(A[:2], B[1:2], "both", 0.5)
    assert matches.tolist() == [-1, 0] and scores.tolist() == [0.0, 1.0]


def test_scores_and_ratio_test_use_correctly_rounded_roots():
    """Scores 1 - d1/d2 and the ratio test from IEEE square roots of the squared distances: torch's float32 sqrt
    is 1 ulp off for some values on AVX-512 CPUs, and not the same values in every process, so two runs of one
    command flipped matches at the ratio test's border."""
    g = torch.Generator().manual_seed(0)
    n = 20_000
    best = torch.rand(1, n, generator=g) * 1e4
    second = best + torch.rand(1, n, generator=g) * 1e3 + 1
    arg = torch.arange(n)[None]
    matches, scores = _select(best, arg, second, best.clone(), False, "both", 0.95)  # each the nearest of its column
    d1, d2 = np.sqrt(best.numpy()[0]), np.sqrt(second.numpy()[0])
    keep = d1 < np.float32(0.95) * d2
    assert 0 < keep.sum() < n
    assert np.array_equal(matches.numpy()[0], np.where(keep, np.arange(n), -1))
    assert np.array_equal(scores.numpy()[0], np.where(keep, 1 - d1 / d2, np.float32(0)))


def test_exact_sqrt_is_numpys_and_reads_negatives_as_zero():
    x = torch.rand(50_000, generator=torch.Generator().manual_seed(1)) * 1e5
    assert np.array_equal(exact_sqrt(x).numpy(), np.sqrt(x.numpy())) and exact_sqrt(x).dtype == torch.float32
    assert exact_sqrt(torch.tensor([-1.0, 0.0, 4.0])).tolist() == [0.0, 0.0, 2.0]


def test_mixed_descriptor_types_refused():
    with pytest.raises(SekdError, match="cannot match"):
        match_descriptors(A, Y)
    with pytest.raises(SekdError, match="cannot match"):
        match_descriptors(A, np.zeros((2, 3), np.float32))


def brute_force(a, b, mode, ratio):
    """Reference: mutual NN (column argmin, first index) and ratio test from the full distance matrix."""
    d = np.sqrt(((a[:, None].astype(np.float64) - b[None]) ** 2).sum(-1))
    out = []
    for i in range(len(a)):
        order = np.argsort(d[i], kind="stable")
        j, d2 = order[0], d[i, order[1]] if len(order) > 1 else np.inf
        keep = (mode == "ratio" or np.argmin(d[:, j]) == i) and (mode == "mnn" or d[i, j] < ratio * d2)
        out.append(j if keep else -1)
    return out


@pytest.mark.parametrize("mode", ["mnn", "ratio", "both"])
def test_padded_chunked_batch_equals_reference(mode):
    rng = np.random.default_rng(0)
    queries = [rng.random((n, 16), dtype=np.float32) for n in (30, 5, 0, 17)]
    refs = [rng.random((n, 16), dtype=np.float32) for n in (12, 40, 9, 1)]
    a0, n0 = stack_rows([augment_rows(prepare_descriptors(q, False)) for q in queries])
    a1t, _ = stack_cols([augment_cols(prepare_descriptors(r, False)) for r in refs])
    matches, _ = match_batch(a0, a1t, n0, False, mode, 0.9, max_elements=150)  # forces row chunks
    for i, (q, r) in enumerate(zip(queries, refs)):
        assert matches[i, : len(q)].tolist() == brute_force(q, r, mode, 0.9)


# ----------------------------------------------------------------------------- feature and match files

def write_features(path, images: dict, feature="sift", dim=None, dtype=None, declared=None):
    """A feature file from ``{name: (keypoints N x 2, descriptors N x D)}``."""
    first = next(iter(images.values()))[1]
    dim, dtype = dim or first.shape[1], dtype or str(first.dtype)
    attrs = {"format": ff.FORMAT, "format_version": 1, "feature_type": declared or feature, "descriptor_dim": dim,
             "descriptor_dtype": dtype, "config": ff.json_attr({"feature": feature})}
    partstore.create_empty(path, attrs)
    parts = partstore.PartStore(path)
    for name, (kp, desc) in images.items():
        parts.save(name, {"keypoints": np.asarray(kp, np.float32), "descriptors": desc,
                          "scores": np.ones(len(desc), np.float32), "image_size": np.array([64, 48], np.int32)})
    partstore.merge_parts(path, parts)
    return path


@pytest.fixture
def small(tmp_path):
    """Features of three images (two names with spaces / folders) and all pairs."""
    kp = lambda n: np.zeros((n, 2), np.float32)
    images = {"a.jpg": (kp(5), A), "dir/bü.jpg": (kp(5), B), "z.jpg": (kp(0), A[:0])}
    features = write_features(tmp_path / "features.h5", images, feature="kaze")
    pairs = write_pairs([("a.jpg", "dir/bü.jpg"), ("z.jpg", "a.jpg"), ("dir/bü.jpg", "z.jpg")], tmp_path / "p.txt")
    return features, pairs


def test_match_file_layout_and_exact_matches(small, tmp_path):
    features, pairs = small
    out = match_features(features, pairs, tmp_path / "m.h5", MatchConfig(mode="both", ratio=0.8), progress=False)
    with h5py.File(out) as f:
        group = f["a.jpg"]["dir/bü.jpg"]  # nested name0 -> name1, '/' kept as a folder
        assert group["matches0"].dtype == np.int32 and group["matching_scores0"].dtype == np.float32
        assert group["matches0"][()].tolist() == [-1, 1, 2, -1, 0]
        assert group.attrs["name0"] == "a.jpg" and group.attrs["name1"] == "dir/bü.jpg"
        assert f["z.jpg"]["a.jpg"]["matches0"].shape == (0,)
        assert f["dir/bü.jpg"]["z.jpg"]["matches0"][()].tolist() == [-1] * 5
        assert f.attrs["format"] == mf.FORMAT and f.attrs["feature_type"] == "kaze"
        config = json.loads(f.attrs["config"])
        assert config == {"mode": "both", "ratio": 0.8, "metric": "l2", "rootsift": False}
        assert "torch" in json.loads(f.attrs["versions"])
    assert mf.list_pairs(out) == [("a.jpg", "dir/bü.jpg"), ("dir/bü.jpg", "z.jpg"), ("z.jpg", "a.jpg")]
    idx, scores = mf.read_matches(out, "dir/bü.jpg", "a.jpg")  # the reverse order works too
    assert idx.tolist() == [[1, 1], [2, 2], [0, 4]] and len(scores) == 3
    assert not (tmp_path / "m.h5.parts").exists() and not (tmp_path / "m.h5.tmp").exists()


def test_names_that_hloc_would_collide_are_refused(tmp_path):
    kp = np.zeros((5, 2), np.float32)
    images = {"a/b.jpg": (kp, A), "a-b.jpg": (kp, A), "c.jpg": (kp, B)}
    features = write_features(tmp_path / "f.h5", images)
    pairs = write_pairs([("a/b.jpg", "c.jpg"), ("a-b.jpg", "c.jpg")], tmp_path / "p.txt")
    with pytest.raises(SekdError, match="share hloc's key"):  # hloc's names_to_pair maps both to a-b.jpg/c.jpg
        match_features(features, pairs, tmp_path / "m.h5", MatchConfig(mode="mnn"), progress=False)


def test_binary_features_use_hamming(tmp_path):
    kp = lambda n: np.zeros((n, 2), np.float32)
    features = write_features(tmp_path / "f.h5", {"x.png": (kp(3), X), "y.png": (kp(4), Y)}, feature="orb")
    pairs = write_pairs([("x.png", "y.png")], tmp_path / "p.txt")
    out = match_features(features, pairs, tmp_path / "m.h5", MatchConfig(mode="both", ratio=0.8), progress=False)
    with h5py.File(out) as f:
        assert f["x.png/y.png/matches0"][()].tolist() == [0, 1, -1]
        assert json.loads(f.attrs["config"])["metric"] == "hamming"


def test_default_ratio_depends_on_feature_type(small, tmp_path):
    from sekd_sfm.stages.match import DEFAULT_RATIO

    features, pairs = small
    out = match_features(features, pairs, tmp_path / "m.h5", progress=False)
    with h5py.File(out) as f:
        assert json.loads(f.attrs["config"])["ratio"] == DEFAULT_RATIO["both"]["kaze"] == 0.7
    out = match_features(features, pairs, tmp_path / "r.h5", MatchConfig(mode="ratio"), progress=False)
    with h5py.File(out) as f:
        assert json.loads(f.attrs["config"])["ratio"] == DEFAULT_RATIO["ratio"]["kaze"] == 0.6


def test_resume_merges_parts_of_a_killed_run(small, tmp_path):
    features, pairs = small
    out = tmp_path / "m.h5"
    match_features(features, pairs, out, MatchConfig(ratio=0.8), progress=False)
    with h5py.File(out, "a") as f:  # forget one pair, as if the run had stopped before it
        del f["a.jpg"]["dir/bü.jpg"]
    # A part left by the killed run (content deliberately different from what matching would give).
    marker = {"matches0": np.array([4, 3, 2, 1, 0], np.int32), "matching_scores0": np.full(5, 0.5, np.float32)}
    partstore.PartStore(out).save(mf.pair_key("a.jpg", "dir/bü.jpg"), marker)
    match_features(features, pairs, out, MatchConfig(ratio=0.8), progress=False)
    with h5py.File(out) as f:
        assert f["a.jpg"]["dir/bü.jpg"]["matches0"][()].tolist() == [4, 3, 2, 1, 0]  # reused, not recomputed
    assert len(mf.list_pairs(out)) == 3


def test_refuses_pairs_naming_images_without_features(small, tmp_path):
    features, _ = small
    pairs = write_pairs([("a.jpg", "ghost_1.jpg"), ("ghost_2.jpg", "z.jpg")], tmp_path / "bad.txt")
    with pytest.raises(SekdError, match=r"has no features for 2 image\(s\) named in .*bad.txt: ghost_1.jpg, ghost_2.jpg"):
        match_features(features, pairs, tmp_path / "m.h5", progress=False)
    assert not (tmp_path / "m.h5").exists()


def test_refuses_mixed_descriptor_file(tmp_path):
    kp = np.zeros((3, 2), np.float32)
    images = {"a.jpg": (kp, A[:3]), "b.jpg": (kp, np.zeros((3, 32), np.uint8))}
    features = write_features(tmp_path / "f.h5", images, dim=2, dtype="float32")
    pairs = write_pairs([("a.jpg", "b.jpg")], tmp_path / "p.txt")
    with pytest.raises(SekdError, match=r"mixes descriptor types.*b.jpg \(uint8 x 32\)"):
        match_features(features, pairs, tmp_path / "m.h5", progress=False)


def test_refuses_adding_other_feature_type_or_config(small, tmp_path):
    features, pairs = small
    out = match_features(features, pairs, tmp_path / "m.h5", MatchConfig(ratio=0.8), progress=False)
    kp = np.zeros((3, 2), np.float32)
    orb = write_features(tmp_path / "orb.h5", {"a.jpg": (kp, X), "dir/bü.jpg": (kp, X), "z.jpg": (kp, X)},
                         feature="orb")
    with pytest.raises(SekdError, match="holds matches of kaze features.*feature types cannot be mixed"):
        match_features(orb, pairs, out, progress=False)
    with pytest.raises(SekdError, match="different feature or match configuration"):
        match_features(features, pairs, out, MatchConfig(ratio=0.7), progress=False)
    match_features(features, pairs, out, MatchConfig(ratio=0.7), overwrite=True, progress=False)
    with h5py.File(out) as f:
        assert json.loads(f.attrs["config"])["ratio"] == 0.7


def test_bad_match_config(small, tmp_path):
    features, pairs = small
    with pytest.raises(SekdError, match="unknown match mode"):
        match_features(features, pairs, tmp_path / "m.h5", MatchConfig(mode="knn"), progress=False)
    kp = np.zeros((3, 2), np.float32)
    orb = write_features(tmp_path / "orb.h5", {"a.jpg": (kp, X), "b.jpg": (kp, X)}, feature="orb")
    binary_pairs = write_pairs([("a.jpg", "b.jpg")], tmp_path / "p2.txt")
    with pytest.raises(SekdError, match="RootSIFT applies"):
        match_features(orb, binary_pairs, tmp_path / "m2.h5", MatchConfig(rootsift=True), progress=False)


# ----------------------------------------------------------------------------- CLI errors

def run_cli(*args):
    result = CliRunner().invoke(sekd, ["-q", *map(str, args)])
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    return result, errors


def test_cli_match_writes_file(small, tmp_path):
    features, pairs = small
    result, errors = run_cli("match", features, pairs, "-o", tmp_path / "cli.h5", "--ratio", "0.8", "--no-progress")
    assert result.exit_code == 0 and not errors, result.output
    assert result.output.strip().endswith("cli.h5") and len(mf.list_pairs(tmp_path / "cli.h5")) == 3


def test_cli_missing_features_one_line_error(small, tmp_path):
    features, _ = small
    pairs = write_pairs([("a.jpg", "nope.jpg")], tmp_path / "bad.txt")
    result, errors = run_cli("match", features, pairs, "-o", tmp_path / "m.h5")
    assert result.exit_code == 1
    assert len(errors) == 1 and "has no features for 1 image(s)" in errors[0] and "nope.jpg" in errors[0]


def test_cli_mixed_feature_types_one_line_error(small, tmp_path):
    features, pairs = small
    run_cli("match", features, pairs, "-o", tmp_path / "m.h5")
    kp = np.zeros((3, 2), np.float32)
    orb = write_features(tmp_path / "orb.h5", {"a.jpg": (kp, X), "dir/bü.jpg": (kp, X), "z.jpg": (kp, X)},
                         feature="orb")
    result, errors = run_cli("match", orb, pairs, "-o", tmp_path / "m.h5")
    assert result.exit_code == 1 and len(errors) == 1 and "feature types cannot be mixed" in errors[0]


def test_cli_unreadable_pairs_file_one_line_error(small, tmp_path):
    features, _ = small
    (tmp_path / "garbage.txt").write_bytes(b"\xff\xfe\xfa")
    result, errors = run_cli("match", features, tmp_path / "garbage.txt", "-o", tmp_path / "m.h5")
    assert result.exit_code == 1 and len(errors) == 1 and "cannot read pairs file" in errors[0]
    (tmp_path / "three.txt").write_text("a.jpg z.jpg dir/b\n")
    result, errors = run_cli("match", features, tmp_path / "three.txt", "-o", tmp_path / "m.h5")
    assert result.exit_code == 1 and len(errors) == 1 and "three.txt:1: expected two names" in errors[0]


def test_cli_missing_feature_file(tmp_path):
    (tmp_path / "p.txt").write_text("a b\n")
    result, errors = run_cli("match", tmp_path / "missing.h5", tmp_path / "p.txt")
    assert result.exit_code == 1 and len(errors) == 1 and "missing.h5: not a readable HDF5 file" in errors[0]
