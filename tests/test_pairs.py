"""Pairs: generators with exact expected lists, the pairs file format, `sekd pairs`."""
import numpy as np
import pytest
from click.testing import CliRunner

from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.files import features as ff
from sekd_sfm.files import partstore
from sekd_sfm.stages.pairs import (
    PairsConfig,
    auto_mode,
    exhaustive_pairs,
    make_pairs,
    natural_key,
    read_pairs,
    sequential_pairs,
    split_writable,
    unique_pairs,
    unwritable_reason,
    write_pairs,
)


def write_feature_file(path, names, feature="sift"):
    """A minimal valid feature file holding ``names`` (one keypoint each)."""
    partstore.create_empty(path, {"format": ff.FORMAT, "feature_type": feature, "descriptor_dim": 4,
                           "descriptor_dtype": "float32", "config": "{}"})
    parts = partstore.PartStore(path)
    for name in names:
        parts.save(name, {"keypoints": np.zeros((1, 2), np.float32), "descriptors": np.ones((1, 4), np.float32),
                          "scores": np.ones(1, np.float32), "image_size": np.array([8, 8], np.int32)})
    partstore.merge_parts(path, parts)
    return path


def test_exhaustive_exact():
    assert exhaustive_pairs(["a", "b c", "sub/d.jpg"]) == [("a", "b c"), ("a", "sub/d.jpg"), ("b c", "sub/d.jpg")]
    assert exhaustive_pairs(["x"]) == [] and exhaustive_pairs([]) == []
    assert len(exhaustive_pairs([str(i) for i in range(7)])) == 21


def test_unique_pairs_collapses_duplicates_reverses_and_self_pairs():
    pairs = [("a", "b"), ("b", "a"), ("a", "b"), ("a", "a"), ("c", "a"), ("a", "c")]
    assert unique_pairs(pairs) == [("a", "b"), ("c", "a")]
    assert unique_pairs([]) == []


def test_sequential_natural_order_and_window():
    names = ["f10.jpg", "f9.jpg", "f1.jpg", "f2.jpg"]
    assert sorted(names, key=natural_key) == ["f1.jpg", "f2.jpg", "f9.jpg", "f10.jpg"]
    assert sequential_pairs(names, window=2) == [
        ("f1.jpg", "f2.jpg"), ("f1.jpg", "f9.jpg"), ("f2.jpg", "f9.jpg"), ("f2.jpg", "f10.jpg"), ("f9.jpg", "f10.jpg")]
    assert sequential_pairs(names, window=1) == [("f1.jpg", "f2.jpg"), ("f2.jpg", "f9.jpg"), ("f9.jpg", "f10.jpg")]
    assert sequential_pairs(["only"], window=3) == [] and sequential_pairs([], window=3) == []


def test_sequential_loop_closure_pairs_keyframes():
    names = [f"{i}.png" for i in range(5)]
    assert sequential_pairs(names, window=1, loop_every=2) == [
        ("0.png", "1.png"), ("1.png", "2.png"), ("2.png", "3.png"), ("3.png", "4.png"),
        ("0.png", "2.png"), ("0.png", "4.png"), ("2.png", "4.png")]
    # A keyframe pair already inside the window is not repeated.
    assert sequential_pairs(names[:3], window=2, loop_every=2) == [("0.png", "1.png"), ("0.png", "2.png"),
                                                                   ("1.png", "2.png")]


def test_sequential_rejects_empty_window():
    with pytest.raises(SekdError, match="window of at least 1"):
        sequential_pairs(["a", "b"], window=0)


def test_read_pairs_tabs_spaces_comments_crlf(tmp_path):
    path = tmp_path / "pairs.txt"
    path.write_bytes(b"# a comment\r\nimg one.jpg\tsub dir/img two.jpg\r\n\n  \na.jpg   b.jpg\n"
                     b"b.jpg a.jpg\nsub dir/img two.jpg\timg one.jpg\n")
    assert read_pairs(path) == [("img one.jpg", "sub dir/img two.jpg"), ("a.jpg", "b.jpg")]


def test_read_pairs_empty_file(tmp_path):
    (tmp_path / "p.txt").write_text("")
    assert read_pairs(tmp_path / "p.txt") == []


@pytest.mark.parametrize("text,line", [("a b\nx y z\n", 2), ("a\n", 1), ("a\tb\tc\n", 1), ("a\t\n", 1)])
def test_read_pairs_malformed_line_names_file_and_line(tmp_path, text, line):
    (tmp_path / "p.txt").write_text(text)
    with pytest.raises(SekdError, match=rf"p.txt:{line}: expected two names"):
        read_pairs(tmp_path / "p.txt")


def test_read_pairs_unreadable(tmp_path):
    with pytest.raises(SekdError, match="cannot read pairs file"):
        read_pairs(tmp_path / "missing.txt")
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(SekdError, match="cannot read pairs file"):
        read_pairs(tmp_path / "bin.txt")


def test_write_pairs_space_separated_roundtrip(tmp_path):
    pairs = [("a.jpg", "c.jpg"), ("sub/ü.png", "a.jpg")]
    path = write_pairs(pairs, tmp_path / "out" / "pairs.txt")
    assert path.read_text(encoding="utf-8") == "a.jpg c.jpg\nsub/ü.png a.jpg\n"
    assert read_pairs(path) == pairs
    assert list((tmp_path / "out").iterdir()) == [path]  # no temporary file left


@pytest.mark.parametrize("bad,why", [("has\ttab.jpg", "tab"), ("new\nline.jpg", "newline"), (" edge.jpg", "leading"),
                                     ("", "empty"), ("a b.jpg", "space"), ("#x.jpg", "comment")])
def test_write_pairs_rejects_unwritable_names(tmp_path, bad, why):
    assert why in unwritable_reason(bad)
    with pytest.raises(SekdError, match="cannot be written to a pairs file"):
        write_pairs([(bad, "b.jpg")], tmp_path / "p.txt")
    assert not (tmp_path / "p.txt").exists()


def test_split_writable():
    assert split_writable(["a.jpg", "b c.jpg", "d.jpg", "e\n.jpg"]) == (
        ["a.jpg", "d.jpg"], {"b c.jpg": "space", "e\n.jpg": "newline"})
    assert split_writable([]) == ([], {})


def test_make_pairs_skips_unwritable_names_with_one_warning(tmp_path, caplog):
    features = write_feature_file(tmp_path / "f.h5", ["a.jpg", " lead.jpg", "b.jpg", "two words.jpg", "c.jpg"])
    with caplog.at_level("WARNING", logger="sekd"):
        out = make_pairs(features, tmp_path / "pairs.txt", PairsConfig(mode="exhaustive"))
    assert out.read_text() == "a.jpg b.jpg\na.jpg c.jpg\nb.jpg c.jpg\n"
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "skipping 2 image(s)" in warnings[0]
    assert "' lead.jpg' (leading/trailing space)" in warnings[0] and "'two words.jpg' (space)" in warnings[0]
    assert "\n" not in warnings[0]


def test_colmap_reads_our_pairs_file(tmp_path):
    """COLMAP's own pair importer (ImportedPairGenerator, used by verify_matches) accepts the file."""
    pycolmap = pytest.importorskip("pycolmap")
    names = ["a.jpg", "sub/b.jpg", "c.png"]
    features = write_feature_file(tmp_path / "f.h5", names)
    pairs_file = make_pairs(features, tmp_path / "pairs.txt", PairsConfig(mode="exhaustive"))
    database = pycolmap.Database.open(str(tmp_path / "db.db"))
    camera = database.write_camera(pycolmap.Camera(model="SIMPLE_PINHOLE", width=8, height=8, params=[8, 4, 4]))
    ids = {database.write_image(pycolmap.Image(name=name, camera_id=camera)): name for name in names}
    generator = pycolmap.ImportedPairGenerator(pycolmap.ImportedPairingOptions(match_list_path=pairs_file), database)
    read = {frozenset((ids[a], ids[b])) for a, b in generator.all_pairs()}
    assert read == {frozenset(p) for p in read_pairs(pairs_file)} and len(read) == 3
    # The old tab-separated lines are what COLMAP could not read (one unknown name per line).
    (tmp_path / "tabs.txt").write_text("a.jpg\tc.png\n")
    generator = pycolmap.ImportedPairGenerator(pycolmap.ImportedPairingOptions(match_list_path=tmp_path / "tabs.txt"),
                                               database)
    assert generator.all_pairs() == []
    database.close()


def test_make_pairs_from_feature_file(tmp_path):
    features = write_feature_file(tmp_path / "f.h5", ["c.jpg", "a.jpg", "sub/b.jpg"])
    out = make_pairs(features, tmp_path / "pairs.txt")  # auto: 3 images -> exhaustive
    assert read_pairs(out) == [("a.jpg", "c.jpg"), ("a.jpg", "sub/b.jpg"), ("c.jpg", "sub/b.jpg")]
    mtime = out.stat().st_mtime_ns
    make_pairs(features, out)  # same pairs: the file is reused, not rewritten
    assert out.stat().st_mtime_ns == mtime
    make_pairs(features, out, PairsConfig(mode="sequential", window=1))
    assert read_pairs(out) == [("a.jpg", "c.jpg"), ("c.jpg", "sub/b.jpg")]


def test_make_pairs_from_file_normalises(tmp_path):
    features = write_feature_file(tmp_path / "f.h5", ["a.jpg", "b.jpg"])
    (tmp_path / "in.txt").write_text("a.jpg b.jpg\nb.jpg a.jpg\n")
    out = make_pairs(features, tmp_path / "out.txt", PairsConfig(mode="from-file", file=str(tmp_path / "in.txt")))
    assert out.read_text() == "a.jpg b.jpg\n"


def test_make_pairs_from_old_tab_file_skips_names_with_spaces(tmp_path, caplog):
    features = write_feature_file(tmp_path / "f.h5", ["a.jpg", "b.jpg", "c d.jpg"])
    (tmp_path / "in.txt").write_text("a.jpg\tb.jpg\nc d.jpg\ta.jpg\n")
    out = make_pairs(features, tmp_path / "out.txt", PairsConfig(mode="from-file", file=str(tmp_path / "in.txt")))
    assert out.read_text() == "a.jpg b.jpg\n"
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "skipping 1 image(s)" in warnings[0] and "'c d.jpg' (space)" in warnings[0]


def test_auto_mode_rule():
    assert [auto_mode(n) for n in (0, 2, 41, 42, 10_000)] == ["exhaustive"] * 3 + ["retrieval"] * 2
    assert auto_mode(11, num_neighbors=5) == "exhaustive" and auto_mode(12, num_neighbors=5) == "retrieval"


def test_make_pairs_errors(tmp_path):
    features = write_feature_file(tmp_path / "f.h5", ["a.jpg", "b.jpg"])
    with pytest.raises(SekdError, match="needs a pairs file"):
        make_pairs(features, tmp_path / "o.txt", PairsConfig(mode="from-file"))
    with pytest.raises(SekdError, match="unknown pairs mode"):
        make_pairs(features, tmp_path / "o.txt", PairsConfig(mode="nearest"))
    with pytest.raises(SekdError, match="at least 1, got 0"):
        make_pairs(features, tmp_path / "o.txt", PairsConfig(mode="retrieval", num_neighbors=0))
    (tmp_path / "not.h5").write_text("x")
    with pytest.raises(SekdError, match="not a readable HDF5 file"):
        make_pairs(tmp_path / "not.h5", tmp_path / "o.txt")


def test_cli_pairs(tmp_path):
    features = write_feature_file(tmp_path / "f.h5", ["1.jpg", "2.jpg", "3.jpg"])
    result = CliRunner().invoke(sekd, ["-q", "pairs", str(features), "--pairs", "sequential", "--window", "1"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "pairs-sequential.txt").read_text() == "1.jpg 2.jpg\n2.jpg 3.jpg\n"
    result = CliRunner().invoke(sekd, ["-q", "pairs", str(features), "--pairs", "from-file"])
    assert result.exit_code == 2 and "--pairs from-file needs --pairs-file" in result.output
    result = CliRunner().invoke(sekd, ["-q", "pairs", str(features), "--pairs", "exhaustive", "--num-neighbors", "3"])
    assert result.exit_code == 2 and "--num-neighbors has no effect" in result.output
    result = CliRunner().invoke(sekd, ["-q", "pairs", str(features), "--pairs", "sequential", "--pairs-file", "x.txt"])
    assert result.exit_code == 2 and "--pairs-file is read with" in result.output
    result = CliRunner().invoke(sekd, ["-q", "pairs", str(features)])  # default auto: 3 images -> exhaustive
    assert result.exit_code == 0, result.output
    assert (tmp_path / "pairs-auto.txt").read_text() == "1.jpg 2.jpg\n1.jpg 3.jpg\n2.jpg 3.jpg\n"
