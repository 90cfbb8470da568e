"""Shard files referenced by virtual datasets (``--ray-merge virtual``), without Ray: the worker's writer and the merge."""
import os
import shutil

import h5py
import numpy as np
import pytest
from hloc_readers import get_keypoints, list_h5_names
from test_files_linear import feature_attrs, features_of

from sekd_sfm.errors import SekdError
from sekd_sfm.execution.ray_run import _TaskParts
from sekd_sfm.files import features as ff
from sekd_sfm.files import partstore, shards


def _items(first: int, count: int) -> list[tuple[str, dict[str, np.ndarray]]]:
    items = []
    for i in range(first, first + count):
        arrays = features_of(i)
        arrays["uncertainty"] = np.float32(1.5)
        items.append((f"seq/{i:04d}.jpg", arrays))
    return items


@pytest.fixture
def virtual_file(tmp_path):
    """A feature file referencing 2 shards of 3 images (written as Ray workers write them), and the expected arrays."""
    output = tmp_path / "features.h5"
    partstore.create_empty(output, feature_attrs())
    for first in (0, 3):
        name, problem = _TaskParts(str(output), "virtual", ff.write_image_group).write(_items(first, 3))
        assert problem == "" and name.endswith(".h5")
    assert partstore.merge_parts(output, partstore.PartStore(output)) == 6
    return output, dict(_items(0, 6))


def test_virtual_file_reads_like_a_copied_one(virtual_file, tmp_path):
    output, expected = virtual_file
    copied = tmp_path / "copied.h5"
    partstore.create_empty(copied, feature_attrs())
    parts = partstore.PartStore(copied)
    for key, arrays in expected.items():
        parts.save(key, arrays)
    partstore.merge_parts(copied, parts)
    assert ff.list_keys(output) == ff.list_keys(copied) == sorted(expected)
    assert sorted(list_h5_names(output)) == sorted(list_h5_names(copied)) == sorted(expected)  # hloc's listing
    for key in expected:
        ours, theirs = ff.read_features(output, key), ff.read_features(copied, key)
        assert ours.keys() == theirs.keys()
        for name in ours:
            assert ours[name].dtype == theirs[name].dtype and np.array_equal(ours[name], theirs[name])
        keypoints, uncertainty = get_keypoints(output, key, return_uncertainty=True)
        assert np.array_equal(keypoints, expected[key]["keypoints"]) and uncertainty == pytest.approx(1.5)
    with h5py.File(output, "r") as f:
        assert f["seq/0000.jpg/descriptors"].is_virtual
    assert os.path.getsize(output) < os.path.getsize(copied)  # references, not arrays


def test_virtual_file_moves_with_its_folder_and_refuses_to_read_without_it(virtual_file, tmp_path):
    output, expected = virtual_file
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    shutil.move(output, moved / "features.h5")
    shutil.move(shards.shard_root(output), shards.shard_root(moved / "features.h5"))
    cwd = os.getcwd()
    try:
        os.chdir("/")  # sources resolve against the file's folder, not the working directory
        assert np.array_equal(ff.read_features(moved / "features.h5", "seq/0004.jpg")["descriptors"],
                              expected["seq/0004.jpg"]["descriptors"])
    finally:
        os.chdir(cwd)
    shutil.rmtree(shards.shard_root(moved / "features.h5"))
    with pytest.raises(SekdError, match=r"2 shard files under features.h5.shards/.*0 found"):
        ff.read_attrs(moved / "features.h5")
    with pytest.raises(SekdError, match="shard file that is missing"):
        ff.read_features(moved / "features.h5", "seq/0004.jpg")


def test_shards_count_as_done_before_a_merge_and_are_referenced_once(tmp_path):
    output = tmp_path / "features.h5"
    partstore.create_empty(output, feature_attrs())
    _TaskParts(str(output), "virtual", ff.write_image_group).write(_items(0, 2))  # a driver killed before its merge
    assert shards.all_keys(output) == {"seq/0000.jpg", "seq/0001.jpg"}
    assert ff.list_keys(output) == []
    parts = partstore.PartStore(output)
    parts.save("seq/0002.jpg", features_of(2))  # the rerun's own (local) item
    assert partstore.merge_parts(output, parts) == 3
    assert ff.list_keys(output) == ["seq/0000.jpg", "seq/0001.jpg", "seq/0002.jpg"]
    before = os.stat(output).st_mtime_ns
    assert partstore.merge_parts(output, partstore.PartStore(output)) == 0  # nothing new: the file is left alone
    assert os.stat(output).st_mtime_ns == before


def test_overwrite_drops_the_old_shards_after_the_new_file_is_in_place(virtual_file):
    output, _ = virtual_file
    partstore.prepare_output(output, feature_attrs(), partstore.PartStore(output), overwrite=True, compare=("config",))
    assert ff.list_keys(output) == [] and not shards.shard_root(output).exists()


def test_a_torn_shard_never_counts(tmp_path):
    output = tmp_path / "features.h5"
    partstore.create_empty(output, feature_attrs())
    root = shards.shard_root(output)
    root.mkdir()
    (root / ".00001-123-x.h5.123.tmp").write_bytes(b"half a shard")  # a worker killed mid-write
    assert shards.shard_files(output) == [] and shards.all_keys(output) == set()
    assert partstore.merge_parts(output, partstore.PartStore(output)) == 0
    _TaskParts(str(output), "virtual", ff.write_image_group).write(_items(0, 1))
    partstore.prepare_output(output, feature_attrs(), partstore.PartStore(output), overwrite=False, compare=("config",))
    assert [p.suffix for p in root.iterdir()] == [".h5"]  # the next run removes the torn one, keeps the shard


def test_unwritable_shard_folder_is_reported_not_raised(tmp_path):
    output = tmp_path / "features.h5"
    partstore.create_empty(output, feature_attrs())
    shards.shard_root(output).write_text("a file where the folder should be")
    name, problem = _TaskParts(str(output), "virtual", ff.write_image_group).write(_items(0, 1))
    assert name == "" and "features.h5.shards: the Ray worker" in problem and "shared storage" in problem


def test_merge_references_described_shards_without_opening_them(tmp_path, monkeypatch):
    output = tmp_path / "features.h5"
    partstore.create_empty(output, feature_attrs())
    writer = _TaskParts(str(output), "virtual", ff.write_image_group)
    described = {}
    for first in (0, 2):
        name, _ = writer.write(_items(first, 2))
        described[name] = writer.meta  # what a worker sends with its keys
    assert writer.meta["seq/0002.jpg"]["keypoints"] == [[50, 2], "<f4", {"uncertainty": 1.5}]
    assert writer.meta["seq/0002.jpg"]["descriptors"][:2] == [[16, 50], "<f4"]  # D x N, as hloc stores it
    shards.write_manifest(output, described)

    def no_reading(path):
        raise AssertionError(f"{path} was opened")

    monkeypatch.setattr(shards, "describe", no_reading)
    assert partstore.merge_parts(output, partstore.PartStore(output)) == 4
    monkeypatch.undo()
    for key, arrays in _items(0, 4):
        read = ff.read_features(output, key)
        assert np.array_equal(read["descriptors"], arrays["descriptors"]) and read["keypoints"].dtype == np.float32


def _virtual_layout(path, key):
    """Per array of ``key``: dtype, shape, fill value (NaN as a string), attributes, VDS source (file, dataset)."""
    with h5py.File(path, "r") as f:
        out = {}
        for name, d in f[key].items():
            (source,) = d.virtual_sources()
            fill = d.fillvalue
            out[name] = (d.dtype.str, d.shape, "nan" if np.isnan(fill) else fill, dict(d.attrs),
                         source.file_name, source.dset_name)
        return out


def test_ready_made_links_give_the_same_file_as_links_built_from_descriptions(tmp_path, monkeypatch):
    items = _items(0, 3)
    output = tmp_path / "features.h5"
    partstore.create_empty(output, feature_attrs())
    name, problem = _TaskParts(str(output), "virtual", ff.write_image_group).write(items)
    assert problem == ""
    with h5py.File(shards.shard_root(output) / name, "r") as shard:
        assert sorted(shard[shards.LINKS]["seq"]) == ["0000.jpg", "0001.jpg", "0002.jpg"]
    assert sorted(shards.describe(shards.shard_root(output) / name)) == [k for k, _ in items]  # not the links
    built = tmp_path / "built" / "features.h5"  # the same shard, merged without its ready-made links
    built.parent.mkdir()
    partstore.create_empty(built, feature_attrs())
    shutil.copytree(shards.shard_root(output), shards.shard_root(built))
    copies = []
    real_copy = shards._copy_links
    monkeypatch.setattr(shards, "_copy_links", lambda *a: copies.append(1) or set())
    assert partstore.merge_parts(built, partstore.PartStore(built)) == 3
    monkeypatch.setattr(shards, "_copy_links", lambda *a: copies.append(2) or real_copy(*a))
    assert partstore.merge_parts(output, partstore.PartStore(output)) == 3
    assert copies == [1, 2]
    for key, arrays in items:
        assert _virtual_layout(output, key) == _virtual_layout(built, key)
        assert _virtual_layout(output, key)["keypoints"][4] == f"features.h5.shards/{name}"
        read = ff.read_features(output, key)
        assert all(np.array_equal(read[n], arrays[n]) for n in ("keypoints", "descriptors", "scores"))
    assert sorted(list_h5_names(output)) == [k for k, _ in items]  # hloc sees the images only


def test_a_shard_without_ready_made_links_is_linked_from_its_description(tmp_path):
    output = tmp_path / "features.h5"
    partstore.create_empty(output, feature_attrs())
    name, _ = _TaskParts(str(output), "virtual", ff.write_image_group).write(_items(0, 2))
    with h5py.File(shards.shard_root(output) / name, "a") as shard:  # as a shard of an older sekd
        del shard[shards.LINKS]
    assert partstore.merge_parts(output, partstore.PartStore(output)) == 2
    for key, arrays in _items(0, 2):
        assert np.array_equal(ff.read_features(output, key)["keypoints"], arrays["keypoints"])
