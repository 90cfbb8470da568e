"""``sekd reconstruct --extend``: fountain-P11 at 640 px, 8 photos reconstructed, then the other 3 added.

The earlier cameras must come back bitwise (poses, intrinsics, image and camera ids, keypoints),
the new photos registered with new points; kill -9 during the extension, then the same command
again, must give the uninterrupted run's model, and model/ must be complete at every moment.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from sekd_sfm.errors import SekdError
from sekd_sfm.features import FeatureConfig
from sekd_sfm.pipelines import extend_commit
from sekd_sfm.pipelines.extend import ExtendOptions, pose_matrix
from sekd_sfm.pipelines.reconstruct import ReconstructConfig, reconstruct

FIRST, ALL = 8, 11
#: SIFT keeps the test fast on a CPU; the extension is the same for every feature type.
CONFIG = {"features": FeatureConfig(feature="sift", resize_max=640)}


def _photos(shared: Path, folder: Path, count: int) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for source in sorted((shared / "data/sfm/fountain-P11/images").glob("*.jpg"))[:count]:
        (folder / source.name).symlink_to(source)
    return folder


@pytest.fixture(scope="module")
def scene(shared, tmp_path_factory):
    """(folder of 11 photos, OUT of a model of the first 8)."""
    root = tmp_path_factory.mktemp("extend")
    base = root / "base"
    reconstruct(_photos(shared, root / "first", FIRST), base, ReconstructConfig(**CONFIG), progress=False)
    return _photos(shared, root / "all", ALL), base


@pytest.fixture(scope="module")
def extended(scene, tmp_path_factory):
    """OUT after an uninterrupted extension."""
    photos, base = scene
    out = tmp_path_factory.mktemp("extended") / "out"
    shutil.copytree(base, out)
    reconstruct(photos, out, extend=ExtendOptions(), progress=False)
    return out


def _model(out: Path):
    return pycolmap.Reconstruction(str(out / "model"))


def _poses(model) -> dict[str, tuple[int, np.ndarray]]:
    return {model.image(i).name: (i, pose_matrix(model.image(i))) for i in model.reg_image_ids()}


def _db_images(out: Path) -> dict[str, tuple[int, int]]:
    with pycolmap.Database.open(str(out / "database.db")) as db:
        return {image.name: (image.image_id, image.camera_id) for image in db.read_all_images()}


def test_earlier_cameras_stay_bitwise_and_new_photos_register(scene, extended):
    _, base = scene
    before, after = _model(base), _model(extended)
    old, new = _poses(before), _poses(after)
    assert len(old) == FIRST and len(new) == ALL  # every new photo registered
    for name, (image_id, pose) in old.items():
        assert new[name][0] == image_id and new[name][1].tobytes() == pose.tobytes()
    for camera_id, camera in before.cameras.items():
        assert after.camera(camera_id).params.tobytes() == camera.params.tobytes()
    assert after.num_points3D() > before.num_points3D()
    # The database keeps its ids; the new photos joined the camera of the earlier ones (same size, same EXIF).
    ids_before, ids_after = _db_images(base), _db_images(extended)
    assert {n: ids_after[n] for n in ids_before} == ids_before
    assert {camera for _, camera in ids_after.values()} == {camera for _, camera in ids_before.values()}
    # The earlier photos' keypoints are those the model was built with.
    with h5py.File(base / "features-refined.h5") as f0, h5py.File(extended / "features-refined.h5") as f1:
        assert set(f1) == set(ids_after)
        for name in ids_before:
            assert np.array_equal(f0[name]["keypoints"][()], f1[name]["keypoints"][()])
    stats = __import__("json").loads((extended / "stats.json").read_text())
    record = stats["extensions"][-1]
    assert sorted(record["registered"]) == sorted(set(ids_after) - set(ids_before)) and record["unregistered"] == []
    # The final filter ran on the extended model with the earlier cameras constant (they are bitwise above).
    assert record["final_filter"]["threshold_px"] >= 0.5 and record["final_filter"]["observations"] > 0
    assert record["model_check"]["pairs"] > 0 and not record["model_check"]["suspect"]  # the extended model agrees
    assert record["chance"]["verified"] > 0  # the chance check ran on the new pairs too
    assert stats["model"]["registered_images"] == ALL
    assert not (extended / "extend").exists() and not (extended / "model.backup").exists()


def test_nothing_to_add_leaves_the_folder_alone(scene, extended, caplog):
    photos, _ = scene
    before = {p.name: p.stat().st_mtime_ns for p in extended.iterdir() if p.is_file() and p.name != ".lock"}
    reconstruct(photos, extended, extend=ExtendOptions(), progress=False)
    assert "nothing to add" in caplog.text
    assert {p.name: p.stat().st_mtime_ns for p in extended.iterdir() if p.is_file() and p.name in before} == before


def test_bad_input_is_one_error_line(scene, tmp_path):
    photos, base = scene
    cli = [sys.executable, "-m", "sekd_sfm.cli.main", "reconstruct", str(photos), "--no-progress"]
    empty = subprocess.run([*cli, "-o", str(tmp_path / "none"), "--extend"], capture_output=True, text=True,
                           check=False)
    out = tmp_path / "copy"
    shutil.copytree(base, out)
    conflict = subprocess.run([*cli, "-o", str(out), "--extend", "--resize-max", "800"], capture_output=True,
                              text=True, check=False)
    for result, words in ((empty, "no model to extend"), (conflict, "features.resize_max = 800 (built with 640)")):
        errors = [line for line in result.stderr.splitlines() if line.startswith("Error:")]
        assert result.returncode == 1 and len(errors) == 1 and words in errors[0], result.stderr
    assert _poses(_model(out)).keys() == _poses(_model(base)).keys()  # refused before any change


def _kill_when_mapping(command: list[str], out: Path, base_poses: dict) -> None:
    """Run ``command``; SIGKILL it once the mapper's child has started; model/ is complete and unchanged then."""
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 300
    while not list((out / "extend").glob("mapping-*")):
        assert process.poll() is None, process.stderr.read().decode()
        assert time.monotonic() < deadline
        time.sleep(0.02)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert _poses(_model(out)).keys() == base_poses.keys()  # read at the kill: complete, the earlier model


def test_kill_during_extend_then_rerun_gives_the_uninterrupted_model(scene, extended, tmp_path, monkeypatch):
    photos, base = scene
    out = tmp_path / "out"
    shutil.copytree(base, out)
    base_poses = _poses(_model(base))
    command = [sys.executable, "-m", "sekd_sfm.cli.main", "reconstruct", str(photos), "-o", str(out), "--extend",
               "--no-progress"]
    _kill_when_mapping(command, out, base_poses)
    assert len(_db_images(out)) == FIRST

    # The rerun dies in its commit, after the model exchange, before the database moves (as a kill would).
    real_replace = os.replace

    def crash(source, target):
        if Path(target).name == "database.db":
            raise KeyboardInterrupt
        real_replace(source, target)

    monkeypatch.setattr(extend_commit.os, "replace", crash)
    with pytest.raises(KeyboardInterrupt):
        reconstruct(photos, out, extend=ExtendOptions(), progress=False)
    monkeypatch.setattr(extend_commit.os, "replace", real_replace)
    assert len(_poses(_model(out))) == ALL and (out / "extend" / "commit.json").is_file()

    reconstruct(photos, out, extend=ExtendOptions(), progress=False)  # finishes the commit; nothing left to add
    expected, got = _poses(_model(extended)), _poses(_model(out))
    assert got.keys() == expected.keys()
    for name, (image_id, pose) in expected.items():
        assert got[name][0] == image_id and got[name][1].tobytes() == pose.tobytes()
    assert _model(out).num_points3D() == _model(extended).num_points3D()
    assert _db_images(out) == _db_images(extended)
    assert not (out / "extend").exists() and not (out / "model.backup").exists()


def test_unknown_output_folder_is_refused(scene, tmp_path):
    photos, _ = scene
    (tmp_path / "stats.json").write_text("{}")
    with pytest.raises(SekdError, match="no finished model"):
        reconstruct(photos, tmp_path, extend=ExtendOptions(), progress=False)


@pytest.mark.slow
def test_extend_refine_moves_the_earlier_cameras_only_a_little_in_their_frame(scene, tmp_path):
    photos, base = scene
    out = tmp_path / "out"
    shutil.copytree(base, out)
    reconstruct(photos, out, extend=ExtendOptions(refine=True), progress=False)
    before, after = _poses(_model(base)), _poses(_model(out))
    assert len(after) == ALL and all(after[name][0] == image_id for name, (image_id, _) in before.items())
    centres = {n: -p[:, :3].T @ p[:, 3] for n, (_, p) in before.items()}
    spread = np.median([np.linalg.norm(c - np.mean(list(centres.values()), 0)) for c in centres.values()])
    moved = max(np.linalg.norm(centres[n] + after[n][1][:, :3].T @ after[n][1][:, 3]) for n in before)
    assert 0 < moved < 0.01 * spread  # refined, in the earlier frame (COLMAP's renormalisation undone)
