"""hloc reads sekd's files unchanged (nested names included), and sekd reads hloc's.

hloc's reader and writer functions are reproduced in tests/hloc_readers.py (hloc is not on PyPI).
"""
from __future__ import annotations

import cv2
import h5py
import hloc_readers as hloc
import numpy as np
import pytest
from click.testing import CliRunner

from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.features import FeatureConfig
from sekd_sfm.files import features as ff
from sekd_sfm.files import matches as mf
from sekd_sfm.files import partstore
from sekd_sfm.stages.extract import extract_features
from sekd_sfm.stages.match import MatchConfig, match_descriptors, match_features
from sekd_sfm.stages.pairs import write_pairs

NESTED = ["a/x.jpg", "b/y.jpg", "c.jpg"]


def _texture(seed: int, size=(240, 320)) -> np.ndarray:
    """A blob texture: many SIFT keypoints, deterministic."""
    noise = np.random.default_rng(seed).random(size).astype(np.float32)
    return cv2.normalize(cv2.GaussianBlur(noise, (0, 0), 2.0), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


@pytest.fixture(scope="module")
def sekd_files(tmp_path_factory):
    """SIFT features (resized by 2: 320 px -> 160) and matches of three images, two in subfolders."""
    root = tmp_path_factory.mktemp("hloc")
    base = _texture(0)
    images = {"a/x.jpg": base, "b/y.jpg": np.roll(base, (6, 9), axis=(0, 1)), "c.jpg": _texture(1)}
    for name, image in images.items():
        (root / "images" / name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / "images" / name), image)
    config = FeatureConfig(feature="sift", max_keypoints=300, resize_max=160)
    features = extract_features(root / "images", root / "features.h5", config, progress=False)
    pairs = write_pairs([("a/x.jpg", "b/y.jpg"), ("c.jpg", "a/x.jpg"), ("b/y.jpg", "c.jpg")], root / "pairs.txt")
    matches = match_features(features, pairs, root / "matches.h5", MatchConfig(mode="mnn"), progress=False)
    return features, matches


def test_hloc_lists_and_reads_keypoints_with_uncertainty(sekd_files):
    features, _ = sekd_files
    assert sorted(hloc.list_h5_names(features)) == NESTED
    for name in NESTED:
        keypoints, uncertainty = hloc.get_keypoints(features, name, return_uncertainty=True)
        assert np.array_equal(keypoints, ff.read_features(features, name)["keypoints"])
        assert len(keypoints) > 20
        assert uncertainty == pytest.approx(2.0)  # 1 px at 160 px x the resize scale 320/160


def test_hloc_finds_every_pair_in_both_orders(sekd_files):
    _, matches = sekd_files
    for name0, name1 in [("a/x.jpg", "b/y.jpg"), ("c.jpg", "a/x.jpg"), ("b/y.jpg", "c.jpg")]:
        for a, b in ((name0, name1), (name1, name0)):
            idx, scores = hloc.get_matches(matches, a, b)
            ours, our_scores = mf.read_matches(matches, a, b)
            assert np.array_equal(idx, ours) and np.array_equal(scores, our_scores)
    idx, _ = hloc.get_matches(matches, "a/x.jpg", "b/y.jpg")
    assert len(idx) > 10  # the shifted copy really matches


def test_hloc_keys_are_links_counted_once(sekd_files):
    _, matches = sekd_files
    with h5py.File(matches) as f:
        assert "a-x.jpg/b-y.jpg" in f and "a/x.jpg/b/y.jpg" in f
        assert f["a-x.jpg/b-y.jpg"].id == f["a/x.jpg/b/y.jpg"].id  # one object: a hard link, no copy
        assert "c.jpg/a-x.jpg" in f
    assert mf.list_pairs(matches) == [("a/x.jpg", "b/y.jpg"), ("b/y.jpg", "c.jpg"), ("c.jpg", "a/x.jpg")]
    stored = mf.stored_pairs(matches, [("b/y.jpg", "a/x.jpg"), ("a/x.jpg", "zz.jpg")])
    assert stored == {frozenset(("a/x.jpg", "b/y.jpg"))}


def test_rematching_replaces_links(sekd_files, tmp_path):
    """A pair written again (a re-merged part) leaves one group, and hloc's key follows the new data."""
    path = tmp_path / "m.h5"
    with h5py.File(path, "w") as f:
        for scores in ([0.5, 0.5], [0.25, 0.75]):
            mf.write_pair_group(f, mf.pair_key("a/x.jpg", "b/y.jpg"),
                                {"matches0": np.array([1, -1]), "matching_scores0": np.array(scores)})
    assert hloc.get_matches(path, "a/x.jpg", "b/y.jpg")[1].tolist() == [0.25]
    assert mf.list_pairs(path) == [("a/x.jpg", "b/y.jpg")]


def _write_hloc_features(path, with_descriptors=True):
    """Two images as hloc stores them (float16), the second a permutation of the first's descriptors."""
    rng = np.random.default_rng(3)
    desc = rng.standard_normal((128, 40)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=0)
    perm = rng.permutation(40)
    for name, d in (("q/one.jpg", desc), ("two.jpg", desc[:, perm])):
        pred = {"keypoints": rng.random((40, 2)).astype(np.float32) * 100,
                "scores": rng.random(40).astype(np.float32), "image_size": np.array([100, 100])}
        if with_descriptors:
            pred["descriptors"] = d
        hloc.write_features(path, name, pred, uncertainty=1.0)
    return desc, perm


def test_sekd_match_accepts_an_hloc_feature_file(tmp_path):
    features = tmp_path / "feats-superpoint.h5"
    desc, perm = _write_hloc_features(features)
    write_pairs([("q/one.jpg", "two.jpg")], tmp_path / "pairs.txt")
    result = CliRunner().invoke(sekd, ["match", str(features), str(tmp_path / "pairs.txt"), "-o",
                                       str(tmp_path / "m.h5"), "--no-progress"])
    assert result.exit_code == 0, result.output
    idx, _ = hloc.get_matches(tmp_path / "m.h5", "q/one.jpg", "two.jpg")
    assert sorted(idx.tolist()) == sorted([[int(p), i] for i, p in enumerate(perm)])  # each descriptor finds its copy
    # Exactly what the float32 values give: float16 is only widened.
    half = desc.astype(np.float16).astype(np.float32)
    expected, _ = match_descriptors(half.T, half[:, perm].T, mode="both", ratio=0.8)
    assert np.array_equal(mf.read_matches(tmp_path / "m.h5", "q/one.jpg", "two.jpg")[0][:, 1], expected[expected >= 0])
    with h5py.File(tmp_path / "m.h5") as f:
        assert f.attrs["feature_type"] == "unknown" and f.attrs["descriptor_dim"] == 128
    assert ff.read_features(features, "two.jpg")["descriptors"].dtype == np.float32


def test_hloc_file_without_descriptors_one_error_line(tmp_path):
    features = tmp_path / "loftr.h5"
    _write_hloc_features(features, with_descriptors=False)
    write_pairs([("q/one.jpg", "two.jpg")], tmp_path / "pairs.txt")
    result = CliRunner().invoke(sekd, ["match", str(features), str(tmp_path / "pairs.txt"),
                                       "-o", str(tmp_path / "m.h5")])
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: ") and "no descriptors" in lines[0], result.output


@pytest.mark.parametrize("content", ["text", "empty-hdf5"])
def test_input_that_is_not_a_feature_file(tmp_path, content):
    path = tmp_path / "features.h5"
    if content == "text":
        path.write_text("hello")
    else:
        h5py.File(path, "w").close()
    write_pairs([("a.jpg", "b.jpg")], tmp_path / "pairs.txt")
    result = CliRunner().invoke(sekd, ["match", str(path), str(tmp_path / "pairs.txt"), "-o", str(tmp_path / "m.h5")])
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"Error: {path}: not a") and "output" not in lines[0], result.output


def test_sekd_reads_hloc_match_files(tmp_path):
    path = tmp_path / "matches-hloc.h5"
    hloc.write_matches(path, "q/one.jpg", "two.jpg", np.array([2, -1, 0]), np.array([0.5, 0.0, 0.25]))
    idx, scores = mf.read_matches(path, "two.jpg", "q/one.jpg")
    assert idx.tolist() == [[2, 0], [0, 2]] and scores.dtype == np.float32 and scores.tolist() == [0.5, 0.25]
    assert mf.list_pairs(path) == [("q-one.jpg", "two.jpg")]  # hloc's key, split at its '/'


def test_sekd_reads_old_hloc_match_files(tmp_path):
    path = tmp_path / "matches-old.h5"
    with h5py.File(path, "w") as f:  # hloc before its '/' keys: names_to_pair_old
        f[hloc.names_to_pair_old("q/one.jpg", "two.jpg") + "/matches0"] = np.array([1, -1], np.int16)
        f[hloc.names_to_pair_old("q/one.jpg", "two.jpg") + "/matching_scores0"] = np.array([0.5, 0], np.float16)
    assert mf.read_matches(path, "two.jpg", "q/one.jpg")[0].tolist() == [[1, 0]]
    assert np.array_equal(hloc.get_matches(path, "two.jpg", "q/one.jpg")[0], [[1, 0]])
    with pytest.raises(SekdError, match="does not say which images it joins"):
        mf.list_pairs(path)


def test_pairs_that_hloc_cannot_tell_apart_are_refused(tmp_path):
    kp = np.zeros((3, 2), np.float32)
    parts = partstore.PartStore(tmp_path / "f.h5")
    partstore.create_empty(tmp_path / "f.h5", {"format": ff.FORMAT, "feature_type": "kaze", "descriptor_dim": 2,
                                        "descriptor_dtype": "float32", "config": "{}"})
    for name in ("a/x.jpg", "a-x.jpg", "c.jpg"):
        parts.save(name, {"keypoints": kp, "descriptors": np.eye(3, 2, dtype=np.float32),
                          "scores": np.ones(3, np.float32), "image_size": np.array([8, 8], np.int32)})
    partstore.merge_parts(tmp_path / "f.h5", parts)
    pairs = write_pairs([("a/x.jpg", "c.jpg"), ("c.jpg", "a-x.jpg")], tmp_path / "p.txt")
    with pytest.raises(SekdError, match=r"share hloc's key 'c.jpg/a-x.jpg'.*rename one"):
        match_features(tmp_path / "f.h5", pairs, tmp_path / "m.h5", progress=False)
    assert not (tmp_path / "m.h5").exists()  # refused before any work


@pytest.mark.parametrize("second", [("a-x.jpg", "c.jpg"), ("c.jpg", "a-x.jpg")])
def test_collision_with_a_pair_already_in_the_file(tmp_path, second):
    arrays = {"matches0": np.array([0]), "matching_scores0": np.array([1.0])}
    with h5py.File(tmp_path / "m.h5", "w") as f:
        mf.write_pair_group(f, mf.pair_key("a/x.jpg", "c.jpg"), arrays)
        with pytest.raises(SekdError, match=r"'a/x.jpg' - 'c.jpg' share hloc's key"):
            mf.write_pair_group(f, mf.pair_key(*second), arrays)
        assert mf._find(f, "a/x.jpg", "c.jpg")[0].attrs["name0"] == "a/x.jpg"  # the first pair is intact
