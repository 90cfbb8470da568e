"""Feature and match files: linear write cost, crash safety of the part store and the merge, locks, --overwrite."""
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from test_extract import write_images

from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.features import FeatureConfig
from sekd_sfm.files import features as ff
from sekd_sfm.files import matches as mf
from sekd_sfm.files import partstore
from sekd_sfm.stages.extract import extract_features
from sekd_sfm.stages.match import MatchConfig, match_features
from sekd_sfm.stages.pairs import write_pairs

SIFT = FeatureConfig(feature="sift", max_keypoints=100)


def written_bytes() -> int:
    """Bytes this process has passed to write() / sendfile() so far (Linux /proc accounting, all threads)."""
    with open("/proc/self/io") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("wchar:"))


def features_of(i: int, n: int = 50, dim: int = 16) -> dict[str, np.ndarray]:
    """Deterministic fake features of image ``i`` (N keypoints, D-dim unit descriptors)."""
    rng = np.random.default_rng(i)
    desc = rng.normal(size=(n, dim)).astype(np.float32)
    return {"keypoints": rng.uniform(0, 100, (n, 2)).astype(np.float32),
            "descriptors": desc / np.linalg.norm(desc, axis=1, keepdims=True),
            "scores": np.sort(rng.uniform(size=n).astype(np.float32))[::-1].copy(),
            "image_size": np.array([100, 100], np.int32)}


def feature_attrs(dim: int = 16) -> dict:
    return {"format": ff.FORMAT, "format_version": 1, "feature_type": "sift", "descriptor_dim": dim,
            "descriptor_dtype": "float32", "config": ff.json_attr({"feature": "sift"})}


def fake_feature_file(path, count: int, n: int = 50):
    partstore.create_empty(path, feature_attrs())
    parts = partstore.PartStore(path)
    for i in range(count):
        parts.save(f"{i:04d}.jpg", features_of(i, n))
    partstore.merge_parts(path, parts)
    return path


# ----------------------------------------------------------------------------- linear cost

@pytest.mark.parametrize("checkpoint_seconds", [0.0, 10.0])
def test_extraction_writes_bytes_linear_in_images(tmp_path, checkpoint_seconds):
    """100 images cost twice the bytes of 50, even saving every image at once (the old merge: ~4x)."""
    images = write_images(tmp_path / "im", [f"{i:03d}.png" for i in range(100)], shape=(64, 80))
    cost = {}
    for count in (50, 100):
        folder = tmp_path / f"im{count}"
        folder.mkdir()
        for i in range(count):
            os.link(images / f"{i:03d}.png", folder / f"{i:03d}.png")
        before = written_bytes()
        out = extract_features(folder, tmp_path / f"f{count}.h5", SIFT, progress=False,
                               checkpoint_seconds=checkpoint_seconds)
        cost[count] = written_bytes() - before
        assert len(ff.list_keys(out)) == count and not (tmp_path / f"f{count}.h5.parts").exists()
    data = os.path.getsize(tmp_path / "f100.h5")
    assert 1.7 < cost[100] / cost[50] < 2.3, cost
    assert cost[100] < 3 * data, (cost, data)  # parts + the file, each written once


def test_matching_writes_bytes_linear_in_pairs(tmp_path):
    cost = {}
    for count in (50, 100):
        features = fake_feature_file(tmp_path / f"f{count}.h5", count)
        names = [f"{i:04d}.jpg" for i in range(count)]
        pairs = write_pairs([(names[i], names[j]) for i in range(count) for j in range(i + 1, min(count, i + 4))],
                            tmp_path / f"p{count}.txt")
        before = written_bytes()
        out = match_features(features, pairs, tmp_path / f"m{count}.h5", MatchConfig(mode="mnn"), progress=False,
                             checkpoint_seconds=0.0)
        cost[count] = written_bytes() - before
        assert len(mf.list_pairs(out)) == 3 * count - 6
    assert 1.7 < cost[100] / cost[50] < 2.3, cost


def test_part_store_batches_items_into_chunks(tmp_path):
    out = tmp_path / "f.h5"
    parts = partstore.PartStore(out, max_items=4, max_seconds=1e9)
    for i in range(10):
        parts.save(f"{i}.jpg", features_of(i, 3))
    assert len(parts.chunks()) == 2 and parts.keys() == {f"{i}.jpg" for i in range(10)}  # 2 left in memory
    parts.flush()
    assert len(parts.chunks()) == 3
    parts.save("3.jpg", features_of(99, 3))  # saved again: the last version wins, counted once
    parts.flush()
    items = dict(parts.items())
    assert sorted(items) == sorted(f"{i}.jpg" for i in range(10))
    assert np.array_equal(items["3.jpg"]["keypoints"], features_of(99, 3)["keypoints"])
    partstore.create_empty(out, feature_attrs())
    assert partstore.merge_parts(out, parts) == 10
    assert ff.list_keys(out) == sorted(f"{i}.jpg" for i in range(10)) and not parts.root.exists()
    assert np.array_equal(ff.read_features(out, "3.jpg")["descriptors"], features_of(99, 3)["descriptors"])


def test_part_store_empty_and_damaged_chunks(tmp_path):
    out = fake_feature_file(tmp_path / "f.h5", 2)
    parts = partstore.PartStore(out)
    assert parts.keys() == set() and parts.chunks() == [] and partstore.merge_parts(out, parts) == 0
    parts.save("x.jpg", features_of(5))
    parts.root.joinpath("00000000000000000000-1-000001.npz").write_bytes(b"torn")  # not a zip
    parts.root.joinpath(".00000000000000000000-1-000002.npz.999999999.tmp").write_bytes(b"half")  # dead writer
    assert parts.keys() == {"x.jpg"}
    assert [p.name for p in parts.root.iterdir()] == [parts.chunks()[0].name]
    assert partstore.merge_parts(out, parts) == 1 and ff.list_keys(out) == ["0000.jpg", "0001.jpg", "x.jpg"]


def test_merge_killed_after_its_rename_is_not_merged_twice(tmp_path):
    """The MERGING marker + merge_id attribute tell a landed merge from one that did not land."""
    out = fake_feature_file(tmp_path / "f.h5", 2)
    parts = partstore.PartStore(out)
    parts.save("x.jpg", features_of(5))
    real_drop = partstore.PartStore.drop
    partstore.PartStore.drop = lambda self, chunks: None  # killed right after the rename
    try:
        partstore.merge_parts(out, parts)
    finally:
        partstore.PartStore.drop = real_drop
    assert parts.keys() == {"x.jpg"} and (parts.root / partstore.MERGING).exists()
    size = os.path.getsize(out)
    parts.save("y.jpg", features_of(6))  # saved after that merge: must survive its recovery
    partstore.prepare_output(out, feature_attrs(), partstore.PartStore(out), False, ("config",))
    assert partstore.PartStore(out).keys() == {"y.jpg"} and not (parts.root / partstore.MERGING).exists()
    assert os.path.getsize(out) == size and len(ff.list_keys(out)) == 3
    partstore.merge_parts(out, parts)
    assert not parts.root.exists() and len(ff.list_keys(out)) == 4
    # A marker whose merge did not land (killed before the rename) is dropped, the parts kept.
    parts.save("z.jpg", features_of(7))
    (parts.root / partstore.MERGING).write_text(json.dumps({"merge_id": "0123", "chunks": [parts.chunks()[0].name]}))
    partstore.prepare_output(out, feature_attrs(), partstore.PartStore(out), False, ("config",))
    assert partstore.PartStore(out).keys() == {"z.jpg"} and not (parts.root / partstore.MERGING).exists()


MERGE_SCRIPT = """
import sys
from pathlib import Path
from sekd_sfm import featurefile as ff
out = Path(sys.argv[1])
partstore.merge_parts(out, partstore.PartStore(out), {"stage": "merged"})
"""


def _file_arrays(path) -> dict:
    with h5py.File(path, "r") as f:
        out = {}
        f.visititems(lambda n, o: out.__setitem__(n, o[()].tobytes()) if isinstance(o, h5py.Dataset) else None)
        return out


def test_merge_fed_during_the_run_equals_one_merge_at_the_end(tmp_path):
    """``partstore.Merge``: chunks added as they come (one not visible yet), the rest at ``finish``: the file of ``merge_parts``."""
    files = {name: fake_feature_file(tmp_path / f"{name}.h5", 2) for name in ("once", "fed")}
    stores = {name: partstore.PartStore(path) for name, path in files.items()}
    for parts in stores.values():
        for i in range(10, 16):
            parts.save(f"{i:04d}.jpg", features_of(i))  # one chunk per image
    assert partstore.merge_parts(files["once"], stores["once"]) == 6

    parts = stores["fed"]
    chunks = parts.chunks()
    merge = partstore.Merge(files["fed"], parts)
    merge.add(chunks[:2])
    merge.add([chunks[1], parts.root / "reported-but-not-visible-yet.npz"])  # again, and one not there: skipped
    with h5py.File(files["fed"], "r") as f:  # the file itself is untouched until finish
        assert sorted(f.keys()) == ["0000.jpg", "0001.jpg"]
    assert merge.finish({"failed_images": "[]"}) == 6
    merge.discard()  # nothing left to discard after finish
    assert _file_arrays(files["fed"]) == _file_arrays(files["once"])
    assert not parts.root.exists() and not list(tmp_path.glob("*.tmp"))


def test_merge_discarded_leaves_the_file_and_the_chunks(tmp_path):
    out = fake_feature_file(tmp_path / "f.h5", 2)
    before = out.read_bytes()
    parts = partstore.PartStore(out)
    for i in range(10, 13):
        parts.save(f"{i:04d}.jpg", features_of(i))
    merge = partstore.Merge(out, parts)
    merge.add(parts.chunks())
    merge.discard()  # the run failed
    assert out.read_bytes() == before and len(parts.chunks()) == 3 and not list(tmp_path.glob("*.tmp"))
    assert partstore.merge_parts(out, parts) == 3  # the next run merges them
    assert ff.list_keys(out) == ["0000.jpg", "0001.jpg", "0010.jpg", "0011.jpg", "0012.jpg"]


def test_kill_9_during_the_merge_of_a_large_file(tmp_path):
    """SIGKILL at several moments of a merge (copy, append, rename): the file opens, the rerun is exact."""
    import shutil

    expected = {f"{i:04d}.jpg": features_of(i, 200, 64) for i in range(400)}  # ~50 KB each
    base = tmp_path / "base"
    base.mkdir()
    parts = partstore.PartStore(base / "f.h5", max_items=100)
    partstore.create_empty(base / "f.h5", feature_attrs(64))
    for key in sorted(expected)[:200]:
        parts.save(key, expected[key])
    partstore.merge_parts(base / "f.h5", parts)  # 10 MB already in the file, 10 MB more in parts
    for key in sorted(expected)[200:]:
        parts.save(key, expected[key])
    parts.flush()
    outcomes = []
    for k, delay in enumerate([0.0, 0.03, 0.1, 0.3, 1.0, 3.0]):
        work = shutil.copytree(base, tmp_path / f"run{k}")
        out = work / "f.h5"
        proc = subprocess.Popen([sys.executable, "-c", MERGE_SCRIPT, str(out)])
        deadline = time.monotonic() + 30
        while not list(work.glob("f.h5.*.tmp")) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.002)  # the merge has begun
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        keys = ff.list_keys(out)  # opens, whatever the moment
        with h5py.File(out) as f:
            landed = f.attrs.get("stage") == "merged"
        assert keys == (sorted(expected) if landed else sorted(expected)[:200])
        outcomes.append(landed)
        partstore.prepare_output(out, feature_attrs(64), partstore.PartStore(out), False, ("config",))  # the rerun
        assert partstore.merge_parts(out, partstore.PartStore(out)) == (0 if landed else 200)
        assert ff.list_keys(out) == sorted(expected)
        assert sorted(p.name for p in work.iterdir()) == ["f.h5"]  # no temporaries, no parts left
        for key in ("0000.jpg", "0199.jpg", "0200.jpg", "0399.jpg"):
            got = ff.read_features(out, key)
            assert all(np.array_equal(got[name], expected[key][name]) for name in expected[key])
        shutil.rmtree(work)
        if landed:
            break
    assert outcomes[0] is False  # the first kill hit the merge itself


# ----------------------------------------------------------------------------- locks

def test_second_extract_on_the_same_output_is_refused(tmp_path):
    images = write_images(tmp_path / "im", [f"{i:03d}.png" for i in range(40)], shape=(240, 320))
    out = tmp_path / "f.h5"
    first = subprocess.Popen([sys.executable, "-m", "sekd_sfm.cli.main", "-q", "extract", str(images), "-o", str(out),
                              "--feature", "sift", "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    lock = tmp_path / "f.h5.lock"
    deadline = time.monotonic() + 60
    while not (lock.exists() and lock.read_text().strip()) and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    # The second process is this one (no start-up delay, so the first is surely still running).
    second = CliRunner().invoke(sekd, ["-q", "extract", str(images), "-o", str(out), "--feature", "sift", "--no-progress"])
    assert first.poll() is None, "the first run ended before the second started: give it more images"
    lines = second.output.strip().splitlines()
    assert second.exit_code == 1 and len(lines) == 1, lines
    assert lines[0].startswith("Error: ") and f"PID {first.pid}" in lines[0] and "in use" in lines[0]
    assert first.wait(timeout=120) == 0, first.stderr.read()
    assert ff.list_keys(out) == [f"{i:03d}.png" for i in range(40)]
    (tmp_path / "two").mkdir()
    for key in ("000.png", "039.png"):
        os.link(images / key, tmp_path / "two" / key)
    clean = extract_features(tmp_path / "two", tmp_path / "clean.h5", FeatureConfig(feature="sift"), progress=False)
    for key in ("000.png", "039.png"):
        a, b = ff.read_features(out, key), ff.read_features(clean, key)
        assert all(np.array_equal(a[k], b[k]) for k in a)


def test_match_holds_the_lock_of_its_output(tmp_path):
    features = fake_feature_file(tmp_path / "f.h5", 3)
    pairs = write_pairs([("0000.jpg", "0001.jpg")], tmp_path / "p.txt")
    script = ("import time; from sekd_sfm.files.locking import exclusive_lock\n"
              f"with exclusive_lock({str(tmp_path / 'm.h5')!r}):\n print('ok', flush=True); time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "ok"
        with pytest.raises(SekdError, match=rf"m.h5: this matches file is in use by another sekd process \(PID {holder.pid}\)"):
            match_features(features, pairs, tmp_path / "m.h5", progress=False)
        assert not (tmp_path / "m.h5").exists()
    finally:
        holder.kill()
        holder.wait()
    assert len(mf.list_pairs(match_features(features, pairs, tmp_path / "m.h5", progress=False))) == 1


def test_output_in_a_folder_that_is_a_file(tmp_path):
    (tmp_path / "file").write_text("x")
    write_images(tmp_path / "im", ["a.png"])
    with pytest.raises(SekdError, match=r"f.h5: cannot be written: .*file is a file, not a folder; choose another"):
        extract_features(tmp_path / "im", tmp_path / "file" / "f.h5", SIFT, progress=False)


# ----------------------------------------------------------------------------- safe --overwrite

def colmap_database(path):
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE cameras (camera_id INTEGER PRIMARY KEY, model INTEGER)")
    return path


@pytest.mark.parametrize("kind", ["text", "colmap", "matches", "other_hdf5", "folder"])
def test_overwrite_refuses_what_is_not_a_features_file(tmp_path, kind):
    images = write_images(tmp_path / "im", ["a.png"])
    target = tmp_path / "target"
    if kind == "text":
        target.write_text("my notes\n")
    elif kind == "colmap":
        colmap_database(target)
    elif kind == "matches":
        partstore.create_empty(target, {"format": mf.FORMAT, "feature_type": "sift"})
    elif kind == "other_hdf5":
        with h5py.File(target, "w") as f:
            f["x"] = 1
    else:
        target.mkdir()
        (target / "keep.txt").write_text("keep")
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    message = {"text": "is not an HDF5 file", "colmap": "is not an HDF5 file", "matches": "is a sekd-matches file",
               "other_hdf5": "is an HDF5 file without a sekd format", "folder": "is a folder"}[kind]
    refusal = ", not a features file" if kind == "folder" else ".*--overwrite only replaces a sekd features file"
    with pytest.raises(SekdError, match=f"target: {message}{refusal}"):
        extract_features(images, target, SIFT, overwrite=True, progress=False)
    after = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file() and p.name != "target.lock"}
    assert after == before  # untouched, nothing added


def test_cli_overwrite_of_a_text_file_is_one_error_line(tmp_path):
    images = write_images(tmp_path / "im", ["a.png"])
    (tmp_path / "notes.h5").write_text("my notes\n")
    result = CliRunner().invoke(sekd, ["-q", "extract", str(images), "-o", str(tmp_path / "notes.h5"), "--feature",
                                       "sift", "--overwrite", "--no-progress"])
    assert result.exit_code == 1 and result.output.strip().splitlines() == [
        (f"Error: {tmp_path / 'notes.h5'}: is not an HDF5 file; --overwrite only replaces a sekd features file; "
         "delete it yourself or choose another output")]
    assert (tmp_path / "notes.h5").read_text() == "my notes\n"


def test_overwrite_replaces_a_features_file_and_refuses_one_for_match(tmp_path):
    images = write_images(tmp_path / "im", ["a.png", "b.png"])
    out = extract_features(images, tmp_path / "f.h5", FeatureConfig(feature="sift", max_keypoints=20), progress=False)
    partstore.PartStore(out).save("stale.png", features_of(1))  # a part of the old configuration
    extract_features(images, out, FeatureConfig(feature="orb", max_keypoints=20), overwrite=True, progress=False)
    assert ff.list_keys(out) == ["a.png", "b.png"] and ff.read_attrs(out)["feature_type"] == "orb"
    pairs = write_pairs([("a.png", "b.png")], tmp_path / "p.txt")
    with pytest.raises(SekdError, match=r"f.h5: is a sekd-features file, not a sekd matches file; --overwrite only"):
        match_features(out, pairs, out, overwrite=True, progress=False)
    db = colmap_database(tmp_path / "database.db")
    with pytest.raises(SekdError, match="database.db: is not an HDF5 file; --overwrite only replaces a sekd matches"):
        match_features(out, pairs, db, overwrite=True, progress=False)
    assert ff.read_attrs(out)["feature_type"] == "orb" and ff.list_keys(out) == ["a.png", "b.png"]
    matches = match_features(out, pairs, tmp_path / "m.h5", progress=False)
    match_features(out, pairs, matches, MatchConfig(mode="mnn"), overwrite=True, progress=False)
    assert mf.list_pairs(matches) == [("a.png", "b.png")]


def test_matching_memory_does_not_grow_with_the_collection(tmp_path, monkeypatch):
    """Results stream to the part store and descriptors through the bounded cache: peak Python memory of
    matching 4x more images stays flat (it would grow ~4x if results or descriptors accumulated)."""
    import tracemalloc

    import sekd_sfm.stages.match as match_module

    monkeypatch.setattr(match_module, "CACHE_IMAGES", 8)
    monkeypatch.setattr(match_module, "PART_PAIRS", 32)
    peak = {}
    for count in (40, 160):
        features = fake_feature_file(tmp_path / f"f{count}.h5", count, n=300)
        names = [f"{i:04d}.jpg" for i in range(count)]
        pairs = write_pairs([(names[i], names[j]) for i in range(count) for j in range(i + 1, min(count, i + 4))],
                            tmp_path / f"p{count}.txt")
        tracemalloc.start()
        match_features(features, pairs, tmp_path / f"m{count}.h5", MatchConfig(mode="mnn"), progress=False)
        peak[count] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert len(mf.list_pairs(tmp_path / f"m{count}.h5")) == 3 * count - 6
    # 477 pairs x 300 matches x 8 bytes = 1.1 MB of results; 160 x 300 x 16 x 4 = 3 MB of descriptors.
    assert peak[160] < 1.5 * peak[40] and peak[160] < 1.0e6, peak
