"""Georeferencing from EXIF GPS: reading/writing the tags, WGS84 -> ENU, the robust similarity, GPS pairs,
and ``reconstruct --gps`` on fountain-P11 (6 photos, 640 px) with GPS written from its true cameras."""
from __future__ import annotations

import json
import logging
import shutil

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sekd_sfm.bench.maps.georef import DEFAULT_ORIGIN, gps_copy, random_rotation
from sekd_sfm.evaluation.strecha import read_cameras
from sekd_sfm.files.gps import GPSPosition, read_gps, write_gps
from sekd_sfm.stages.georef import (
    GpsConfig,
    camera_centres,
    degenerate_reason,
    enu_from_geodetic,
    geodetic_from_enu,
    plan_gps,
    robust_similarity,
)
from sekd_sfm.stages.pairs import PairsConfig, gps_pairs, make_pairs

pycolmap = pytest.importorskip("pycolmap")
FOUNTAIN = "data/sfm/fountain-P11"
PHOTOS = [f"{i:04d}.jpg" for i in range(6)]


# ----------------------------------------------------------------------------- EXIF GPS

@pytest.mark.parametrize("position", [GPSPosition(46.512345678, 6.6012345678, 372.125),
                                      GPSPosition(-33.8567844, -151.2152967, -12.5),
                                      GPSPosition(0.0000001, 179.9999999, None)])
def test_exif_gps_round_trip_keeps_the_pixels(shared, tmp_path, position):
    source = shared / FOUNTAIN / "images/0000.jpg"
    assert read_gps(source) is None  # the original has no GPS
    target = write_gps(source, tmp_path / "gps.jpg", position)
    found = read_gps(target)
    assert found.latitude == pytest.approx(position.latitude, abs=1e-7)
    assert found.longitude == pytest.approx(position.longitude, abs=1e-7)
    assert found.altitude == (None if position.altitude is None else pytest.approx(position.altitude, abs=1e-3))
    assert np.array_equal(cv2.imread(str(source)), cv2.imread(str(target)))  # not re-encoded
    again = write_gps(target, tmp_path / "again.jpg", GPSPosition(10.0, 20.0, 5.0))  # replaces, not duplicates
    assert read_gps(again) == GPSPosition(10.0, 20.0, 5.0)


def test_exif_gps_in_png_and_no_gps(tmp_path):
    cv2.imwrite(str(tmp_path / "plain.png"), np.full((8, 8, 3), 7, np.uint8))
    assert read_gps(tmp_path / "plain.png") is None
    assert read_gps(tmp_path / "missing.jpg") is None
    (tmp_path / "torn.jpg").write_bytes(b"\xff\xd8\xff\xe1\x00\x10Exif\x00\x00MM\x00*\x00\x00\x00\x08garbage")
    assert read_gps(tmp_path / "torn.jpg") is None  # a malformed EXIF block is no GPS, not a failure
    write_gps(tmp_path / "plain.png", tmp_path / "gps.png", GPSPosition(-1.25, 2.5, 3.0))
    assert read_gps(tmp_path / "gps.png") == GPSPosition(-1.25, 2.5, 3.0)


# ----------------------------------------------------------------------------- frames

def test_enu_of_a_point_100_m_north_and_east():
    origin = GPSPosition(46.5, 6.6, 0.0)
    a, e2 = 6378137.0, 0.00669437999014
    lat = np.radians(46.5)
    meridian = a * (1 - e2) / (1 - e2 * np.sin(lat) ** 2) ** 1.5  # radius of curvature along the meridian
    normal = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    north = enu_from_geodetic([[46.5 + np.degrees(100 / meridian), 6.6, 0.0]], origin)[0]
    east = enu_from_geodetic([[46.5, 6.6 + np.degrees(100 / (normal * np.cos(lat))), 0.0]], origin)[0]
    assert north == pytest.approx([0, 100, -100**2 / (2 * meridian)], abs=1e-3)  # the chord dips below the horizon
    assert east == pytest.approx([100, 0, -100**2 / (2 * normal)], abs=1e-3)
    up = enu_from_geodetic([[46.5, 6.6, 25.0]], origin)[0]
    assert up == pytest.approx([0, 0, 25], abs=1e-9)


def test_enu_round_trip_and_pycolmap_agree():
    origin = GPSPosition(-33.86, 151.21, 40.0)
    enu = np.random.default_rng(0).normal(0, 2000, (20, 3))
    lla = geodetic_from_enu(enu, origin)
    assert np.abs(enu_from_geodetic(lla, origin) - enu).max() < 1e-6
    reference = pycolmap.GPSTransform(pycolmap.GPSTransformEllipsoid.WGS84)
    assert np.abs(reference.ellipsoid_to_enu(lla, -33.86, 151.21, 40.0) - enu).max() < 1e-6


# ----------------------------------------------------------------------------- alignment and checks

def test_alignment_recovers_a_known_similarity_despite_an_outlier():
    rng = np.random.default_rng(3)
    src = rng.uniform(-1, 1, (12, 3))
    rotation, scale, translation = random_rotation(rng), 7.5, np.array([10.0, -20.0, 3.0])
    tgt = scale * src @ rotation.T + translation + rng.normal(0, 0.01, (12, 3))
    tgt[4] += [30.0, 0, 0]  # one GPS position 30 m off
    sim, residuals, inliers, _ = robust_similarity(src, tgt, max_error_m=1.0)
    assert float(sim.scale) == pytest.approx(scale, rel=2e-3)
    assert np.abs(sim.rotation.matrix() - rotation).max() < 3e-3
    assert np.asarray(sim.translation).ravel() == pytest.approx(translation, abs=0.03)
    assert inliers.tolist() == [i != 4 for i in range(12)] and residuals[4] > 29


def test_degenerate_positions():
    rng = np.random.default_rng(0)
    spread = np.c_[rng.uniform(0, 50, 10), rng.uniform(0, 30, 10), rng.normal(0, 1, 10)]
    assert degenerate_reason(spread, 1.0) is None
    assert "at least 3" in degenerate_reason(spread[:2], 1.0)
    assert "within 1 m" in degenerate_reason(rng.normal(0, 0.1, (10, 3)), 1.0)
    line = np.c_[np.linspace(0, 100, 10), 0.05 * rng.normal(size=10), np.zeros(10)]
    assert "on a line" in degenerate_reason(line, 1.0)


def test_gps_pairs_are_nearest_within_the_radius():
    positions = {"a": (0, 0, 0), "b": (10, 0, 0), "c": (25, 0, 0), "d": (500, 0, 0)}
    assert gps_pairs(["a", "b", "c", "d", "e"], positions, k=1, radius_m=100) == [("a", "b"), ("c", "b")]
    assert gps_pairs(list(positions), positions, k=5, radius_m=12) == [("a", "b")]
    assert len(gps_pairs(list(positions), positions, k=5, radius_m=1000)) == 6


# ----------------------------------------------------------------------------- reconstruct --gps

def _scene(shared, root, rotation_seed=1):
    """6 fountain-P11 photos + their true cameras in a Strecha-layout folder under ``root``."""
    (root / "images").mkdir(parents=True)
    (root / "gt_dense_cameras").mkdir()
    for name in PHOTOS:
        shutil.copyfile(shared / FOUNTAIN / "images" / name, root / "images" / name)
        shutil.copyfile(shared / FOUNTAIN / "gt_dense_cameras" / f"{name}.camera", root / "gt_dense_cameras" / f"{name}.camera")
    cameras = read_cameras(root / "gt_dense_cameras")
    centres = np.array([cameras[n].C for n in PHOTOS])
    rotation = random_rotation(np.random.default_rng(rotation_seed))
    return dict(zip(PHOTOS, (centres - centres.mean(0)) @ rotation.T))


def _config():
    from sekd_sfm.features import FeatureConfig
    from sekd_sfm.pipelines.reconstruct import ReconstructConfig

    # Retrieval with K=3: the GPS pairs then add pairs, so `--gps off` shows it changes nothing. The 6 cameras
    # bow 0.3 m off their line: enough for exact GPS (min_spread_m 0.1), not for the default's metre-level GPS.
    config = ReconstructConfig(features=FeatureConfig(resize_max=640), pairs=PairsConfig(mode="retrieval", num_neighbors=3),
                               gps=GpsConfig(min_spread_m=0.1))
    config.refine.enabled = False  # not what is tested here; saves a third of each run
    return config


@pytest.fixture(scope="module")
def georeferenced(shared, tmp_path_factory):
    from sekd_sfm.pipelines.reconstruct import reconstruct

    root = tmp_path_factory.mktemp("georef")
    truth = _scene(shared, root / "scene")
    gps_copy(root / "scene", root / "gps", truth, sigma_m=0.0, seed=0)
    reconstruct(root / "gps", root / "out", _config(), progress=False)
    return root, truth


def test_reconstruct_aligns_the_model_to_gps_in_metres(georeferenced):
    root, truth = georeferenced
    georef = json.loads((root / "out/georef.json").read_text())
    assert georef["georeferenced"] and georef["frame"].startswith("ENU, metres, origin")
    assert georef["inliers"] == 6 and georef["median_residual_m"] < 0.1
    model_origin = GPSPosition(**georef["origin"])
    expected = enu_from_geodetic(geodetic_from_enu(np.array([truth[n] for n in PHOTOS]), DEFAULT_ORIGIN), model_origin)
    centres = camera_centres(pycolmap.Reconstruction(str(root / "out/model")))
    errors = np.linalg.norm(np.array([centres[n] for n in PHOTOS]) - expected, axis=1)
    assert errors.max() < 0.15, errors  # metres; the cameras span ~7 m
    stats = json.loads((root / "out/stats.json").read_text())
    assert stats["georeference"]["georeferenced"] and "per_image" not in stats["georeference"]
    assert stats["config"]["gps"]["mode"] == "auto"
    pairs = (root / "out/pairs.txt").read_text().splitlines()
    assert len(pairs) == 15  # retrieval K=3 + every GPS neighbour: all 15 pairs of 6 photos


def test_export_keeps_the_georeferenced_coordinates(georeferenced, tmp_path):
    from sekd_sfm.cli.main import sekd

    root, _ = georeferenced
    result = CliRunner().invoke(sekd, ["-q", "export", str(root / "out/model"), "-o", str(tmp_path / "text")])
    assert result.exit_code == 0, result.output
    model, text = (pycolmap.Reconstruction(str(p)) for p in (root / "out/model", tmp_path / "text"))
    original, exported = camera_centres(model), camera_centres(text)
    assert np.abs(np.array([exported[n] - original[n] for n in PHOTOS])).max() < 1e-6
    points = {i: p.xyz for i, p in model.points3D.items()}
    assert max(np.abs(p.xyz - points[i]).max() for i, p in text.points3D.items()) < 1e-6


def test_gps_off_pairs_unchanged_and_no_alignment(georeferenced, tmp_path):
    from sekd_sfm.cli.main import sekd

    root, _ = georeferenced
    out = tmp_path / "off"
    out.mkdir()
    for name in ("features.h5", "features.global.h5", "matches.h5"):  # reused: only the pairs and the map differ
        shutil.copyfile(root / "out" / name, out / name)
    result = CliRunner().invoke(sekd, ["-q", "reconstruct", str(root / "gps"), "-o", str(out), "--resize-max", "640",
                                       "--pairs", "retrieval", "--num-neighbors", "3", "--gps", "off", "--no-refine",
                                       "--no-progress"])
    assert result.exit_code == 0, result.output
    expected = make_pairs(out / "features.h5", tmp_path / "pairs.txt", PairsConfig(mode="retrieval", num_neighbors=3),
                          progress=False)
    assert (out / "pairs.txt").read_bytes() == expected.read_bytes()
    assert len(expected.read_text().splitlines()) < 15
    assert not (out / "georef.json").exists()
    stats = json.loads((out / "stats.json").read_text())["georeference"]
    assert not stats["georeferenced"] and stats["reason"] == "--gps off"


@pytest.mark.parametrize("case", ["two photos", "collinear"])
def test_too_few_or_collinear_gps_gives_a_warning_and_no_alignment(georeferenced, tmp_path, caplog, case):
    from sekd_sfm.pipelines.reconstruct import reconstruct

    root, truth = georeferenced
    images = tmp_path / "images"
    images.mkdir()
    for i, name in enumerate(PHOTOS):
        source = root / "scene/images" / name
        if case == "two photos" and i >= 2:
            shutil.copyfile(source, images / name)
            continue
        east = truth[name] if case == "two photos" else np.array([3.0 * i, 0.0, 0.0])  # a straight walk east
        lat, lon, alt = geodetic_from_enu(east[None], DEFAULT_ORIGIN)[0]
        write_gps(source, images / name, GPSPosition(float(lat), float(lon), float(alt)))
    with caplog.at_level(logging.INFO, logger="sekd"):
        reconstruct(images, tmp_path / "out", _config(), progress=False, features=root / "out/features.h5",
                    matches=root / "out/matches.h5")
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(("fewer" in w or "EXIF GPS on 2 of 6" in w) if case == "two photos" else "on a line" in w
               for w in warnings), warnings
    assert not (tmp_path / "out/georef.json").exists()
    decision = json.loads((tmp_path / "out/stats.json").read_text())["georeference"]
    assert not decision["georeferenced"] and decision["reason"]
    assert pycolmap.Reconstruction(str(tmp_path / "out/model")).num_reg_images() == 6


def test_plan_without_gps_is_off_silently(shared, caplog):
    with caplog.at_level(logging.INFO, logger="sekd"):
        plan = plan_gps(shared / FOUNTAIN / "images", PHOTOS, GpsConfig())
    assert not plan.pairs and not plan.align and plan.neighbors(GpsConfig()) is None
    assert not caplog.records
    with caplog.at_level(logging.INFO, logger="sekd"):
        plan_gps(shared / FOUNTAIN / "images", PHOTOS, GpsConfig(mode="align"))
    assert "EXIF GPS on 0 of 6 photos" in caplog.text and caplog.records[0].levelno == logging.WARNING


def test_altitude_missing_on_one_photo_sets_all_to_zero(tmp_path, caplog):
    cv2.imwrite(str(tmp_path / "src.png"), np.full((8, 8, 3), 7, np.uint8))
    enu = {"a.png": (0.0, 0.0, 30.0), "b.png": (40.0, 0.0, 31.0), "c.png": (0.0, 25.0, 29.0), "d.png": (30.0, 30.0, 0)}
    for name, position in enu.items():
        lat, lon, alt = geodetic_from_enu(np.array([position]), DEFAULT_ORIGIN)[0]
        write_gps(tmp_path / "src.png", tmp_path / "images" / name,
                  GPSPosition(float(lat), float(lon), None if name == "d.png" else float(alt)))
    with caplog.at_level(logging.INFO, logger="sekd"):
        plan = plan_gps(tmp_path / "images", sorted(enu), GpsConfig())
    assert plan.pairs and plan.align and not plan.vertical_constrained and plan.origin.altitude == 0
    assert "vertical unconstrained" in caplog.text
    positions = np.array([plan.positions[n] for n in sorted(enu)])
    assert np.abs(positions[:, 2]).max() < 0.5  # the Earth's curvature over 40 m: millimetres
    assert positions[1, 0] - positions[0, 0] == pytest.approx(40, abs=0.01)
