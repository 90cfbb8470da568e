"""``sekd localize``: held-out photos of fountain-P11 localized against a reference of the others.

One reference (8 photos at 800 px, built once for the module); queries are photos 2, 5 and 8.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sekd_sfm.bench.maps.localize import (
    TARGET_POSITION_PCT,
    TARGET_ROTATION_DEG,
    link_photos,
    model_poses,
    poses_file,
    score,
    split,
)
from sekd_sfm.cli.main import sekd
from sekd_sfm.evaluation.strecha import read_cameras
from sekd_sfm.features import FeatureConfig
from sekd_sfm.pipelines.localize import log_path
from sekd_sfm.pipelines.reconstruct import ReconstructConfig, reconstruct
from sekd_sfm.stages.pairs import PairsConfig

pycolmap = pytest.importorskip("pycolmap")


@pytest.fixture(scope="module")
def scene(shared, tmp_path_factory):
    """Reference folder (8 photos, 800 px), query folder (3 held-out photos), ground truth, work folder."""
    root = shared / "data/sfm/fountain-P11"
    work = tmp_path_factory.mktemp("localize")
    parts = split(sorted(p.name for p in (root / "images").glob("*.jpg")))
    assert parts.queries == ["0002.jpg", "0005.jpg", "0008.jpg"]
    reference_photos = link_photos(root / "images", parts.reference, work / "reference-photos")
    queries = link_photos(root / "images", parts.queries, work / "queries")
    out = work / "reference"
    # Retrieval pairs (7 neighbours: every pair of 8 photos) so that OUT has global descriptors, as a large
    # reference has: localize retrieves with them.
    config = ReconstructConfig(features=FeatureConfig(resize_max=800), pairs=PairsConfig(mode="retrieval",
                                                                                        num_neighbors=7))
    reconstruct(reference_photos, out, config, progress=False)
    assert (out / "features.global.h5").is_file()
    truth = {n: c.cam_from_world for n, c in read_cameras(root / "gt_dense_cameras").items()}
    return {"out": out, "queries": queries, "truth": truth, "work": work, "images": root / "images"}


def folder_hashes(folder: Path) -> dict[str, str]:
    """SHA-256 of every file below ``folder`` by relative path (a new, changed or removed file changes it)."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_localizes_held_out_photos_accurately_and_leaves_the_reference_alone(scene):
    before = folder_hashes(scene["out"])
    results = scene["work"] / "loc" / "results.txt"
    run = CliRunner().invoke(sekd, ["-q", "localize", str(scene["queries"]), "--reference", str(scene["out"]),
                                    "-o", str(results), "--no-progress"])
    assert run.exit_code == 0, run.output
    assert "3 of 3 photos localized" in run.output
    assert folder_hashes(scene["out"]) == before

    # hloc's format: NAME and 7 numbers, a unit quaternion
    lines = results.read_text().splitlines()
    assert [line.split()[0] for line in lines] == ["0002.jpg", "0005.jpg", "0008.jpg"]
    for line in lines:
        values = np.array([float(v) for v in line.split()[1:]])
        assert len(values) == 7 and abs(np.linalg.norm(values[:4]) - 1) < 1e-6

    reference = model_poses(pycolmap.Reconstruction(str(scene["out"] / "model")))
    result = score(reference, poses_file(results), scene["truth"], ["0002.jpg", "0005.jpg", "0008.jpg"])
    assert result["localized"] == 3
    assert result["median_rotation_deg"] <= TARGET_ROTATION_DEG, result
    assert result["median_position_pct"] <= TARGET_POSITION_PCT, result

    log = json.loads(log_path(results).read_text())
    record = log["queries"]["0005.jpg"]
    assert record["status"] == "localized" and record["inliers"] >= 100
    assert record["camera_source"].startswith("reference camera")
    assert log["retrieval"].startswith("reference global descriptors")
    assert set(record["retrieved"]) == set(reference)  # K = 10 > 8 photos: every registered image, best first
    assert record["retrieved"][0] in ("0004.jpg", "0006.jpg")  # its neighbours in the sequence come first
    assert log["identity"]["reference_model_sha1"] and log["versions"]["pycolmap"]


def test_a_bad_photo_is_logged_and_the_others_localize_then_a_rerun_resumes(scene):
    work = scene["work"] / "bad"
    work.mkdir()
    (work / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    listing = work / "list.txt"
    listing.write_text(f"{scene['images'] / '0005.jpg'}\nbroken.jpg\n")
    results = work / "out" / "poses.txt"
    args = ["-q", "localize", str(listing), "-r", str(scene["out"]), "-o", str(results), "--no-progress"]
    run = CliRunner().invoke(sekd, args)
    assert run.exit_code == 0, run.output
    assert "1 of 2 photos localized, 1 failed" in run.output
    log = json.loads(log_path(results).read_text())
    assert log["queries"]["broken.jpg"]["status"] == "failed"
    assert "broken.jpg" in log["queries"]["broken.jpg"]["reason"]
    assert [line.split()[0] for line in results.read_text().splitlines()] == ["0005.jpg"]

    first = log["queries"]["0005.jpg"]
    assert CliRunner().invoke(sekd, args).exit_code == 0
    again = json.loads(log_path(results).read_text())["queries"]["0005.jpg"]
    assert again == first  # kept, not recomputed (its timing would differ)

    other = CliRunner().invoke(sekd, args + ["--num-neighbors", "3"])  # other settings: refused, not mixed
    assert other.exit_code == 1 and "--overwrite" in other.output


def test_camera_params_and_focal_estimation(scene):
    """Known intrinsics (the ground truth's) and no camera at all (focal estimated from a prior) both localize."""
    from sekd_sfm.evaluation.strecha import read_camera

    K = read_camera(scene["images"].parent / "gt_dense_cameras/0002.jpg.camera").K
    # COLMAP pixel convention: the centre of the top-left pixel is (0.5, 0.5)
    params = f"{K[0, 0]},{K[0, 2] + 0.5},{K[1, 2] + 0.5}"
    # A reference without global descriptors and more than 2K+1 photos: they are made in the work folder.
    bare = scene["work"] / "bare-reference"
    bare.mkdir()
    for name in ("stats.json", "model", "features.h5"):
        (bare / name).symlink_to(scene["out"] / name)
    results = scene["work"] / "known" / "results.txt"
    run = CliRunner().invoke(sekd, ["-q", "localize", str(scene["queries"]), "-r", str(bare), "-o", str(results),
                                    "--camera-model", "SIMPLE_PINHOLE", "--camera-params", params, "-k", "3"])
    assert run.exit_code == 0, run.output
    log = json.loads(log_path(results).read_text())
    assert {r["camera_source"] for r in log["queries"].values()} == {"--camera-params"}
    assert log["retrieval"].startswith("global descriptors learned in") and not (bare / "features.global.h5").exists()
    assert sorted(log["queries"]["0005.jpg"]["retrieved"]) == ["0004.jpg", "0006.jpg", "0007.jpg"]
    reference = model_poses(pycolmap.Reconstruction(str(scene["out"] / "model")))
    result = score(reference, poses_file(results), scene["truth"], sorted(log["queries"]))
    assert result["localized"] == 3 and result["median_rotation_deg"] <= 1.0, result

    # a photo of another camera (half the size): no camera to reuse, the focal length is estimated
    import cv2

    small = scene["work"] / "small"
    small.mkdir()
    image = cv2.imread(str(scene["images"] / "0005.jpg"))
    cv2.imwrite(str(small / "0005.jpg"), cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2),
                                                    interpolation=cv2.INTER_AREA))
    results = scene["work"] / "estimated" / "results.txt"
    run = CliRunner().invoke(sekd, ["-q", "localize", str(small), "-r", str(scene["out"]), "-o", str(results)])
    assert run.exit_code == 0, run.output
    record = json.loads(log_path(results).read_text())["queries"]["0005.jpg"]
    assert record["status"] == "localized" and record["camera_source"].startswith("prior")
    assert record["camera"]["params"][0] == pytest.approx(K[0, 0] / 2, rel=0.03)
    pose = poses_file(results)["0005.jpg"]
    result = score(reference, {"0005.jpg": pose}, scene["truth"], ["0005.jpg"])
    assert result["localized"] == 1 and result["median_rotation_deg"] <= 1.0, result


def test_bad_reference_is_one_error_line(scene, tmp_path):
    (tmp_path / "not-sekd").mkdir()
    (tmp_path / "not-sekd" / "notes.txt").write_text("hello")
    run = CliRunner().invoke(sekd, ["localize", str(scene["queries"]), "-r", str(tmp_path / "not-sekd"),
                                    "-o", str(tmp_path / "r.txt")])
    assert run.exit_code == 1
    assert run.output.startswith("Error:") and "not an output folder of `sekd reconstruct`" in run.output
    assert len(run.output.strip().splitlines()) == 1

    # a model whose feature file is gone: named, nothing written into the reference
    broken = tmp_path / "no-features"
    broken.mkdir()
    for name in ("stats.json", "model"):
        (broken / name).symlink_to(scene["out"] / name)
    run = CliRunner().invoke(sekd, ["localize", str(scene["queries"]), "-r", str(broken), "-o", str(tmp_path / "s.txt")])
    assert run.exit_code == 1 and "feature file is missing" in run.output
    assert sorted(p.name for p in broken.iterdir()) == ["model", "stats.json"]


def test_an_output_in_use_is_refused(scene, tmp_path):
    from sekd_sfm.files.locking import exclusive_lock

    results = tmp_path / "results.txt"
    with exclusive_lock(results):  # another run writing the same results
        run = CliRunner().invoke(sekd, ["localize", str(scene["queries"]), "-r", str(scene["out"]), "-o", str(results)])
    assert run.exit_code == 1 and "in use by another sekd process" in run.output
    assert not results.exists()
