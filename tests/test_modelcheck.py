"""The model check (``sekd_sfm.stages.modelcheck``): verified pairs that a model's poses contradict."""
from __future__ import annotations

import numpy as np
import pytest

from sekd_sfm.stages.colmap import require_pycolmap
from sekd_sfm.stages.modelcheck import ModelCheckConfig, check_model, sampson2

pycolmap = require_pycolmap()


@pytest.fixture(scope="module")
def arc(tmp_path_factory):
    """The eight calibrated views of test_reconstruct on an 80 degree arc, reconstructed: model and database."""
    from test_reconstruct import CALIBRATED, SIFT, write_arc_scene

    from sekd_sfm.pipelines.reconstruct import ReconstructConfig, reconstruct

    _, images, out = write_arc_scene(tmp_path_factory.mktemp("arc"))
    model = reconstruct(images, out, ReconstructConfig(features=SIFT, camera=CALIBRATED), progress=False)
    return pycolmap.Reconstruction(str(model)), out / "database.db"


def test_a_correct_model_agrees_with_every_pair(arc):
    reconstruction, database = arc
    record = check_model(reconstruction, database)
    assert record["pairs"] == 28 and record["contradicting"] == 0 and record["strong_contradicting"] == 0
    assert not record["suspect"] and record["strongest"] == []


def test_a_folded_model_is_flagged(arc):
    """Half the cameras turned 180 deg about the vertical through the scene's centre, as a fold on look-alike
    structure would place them: the pairs across the fold contradict the model, and they are strong ones."""
    reconstruction, database = arc
    folded = pycolmap.Reconstruction(reconstruction)
    turn = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, 1.0, 0.0, 0.0])), np.zeros(3))  # xyzw: 180 deg about y
    names = sorted(image.name for image in folded.images.values())
    for image in folded.images.values():
        if image.name in names[4:]:
            image.frame.rig_from_world = image.frame.rig_from_world * turn
    record = check_model(folded, database)
    assert record["pairs"] == 28 and record["contradicting"] == 16  # the 4 x 4 pairs across the fold
    assert record["suspect"] and record["strong_contradicting"] >= 2
    first, second = record["strongest"][0]["pair"]
    assert (first in names[4:]) != (second in names[4:]) and record["strongest"][0]["agreement"] < 0.5
    lenient = check_model(folded, database, ModelCheckConfig(min_strong=17))
    assert not lenient["suspect"] and lenient["contradicting"] == 16


def test_sampson_distance_in_pixels():
    F = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # pure x translation: epipolar lines are rows
    x1 = np.array([[10.0, 20.0], [5.0, 7.0]])
    x2 = np.array([[50.0, 20.0], [9.0, 10.0]])  # the same row, then 3 px off
    assert np.allclose(sampson2(F, x1, x2), [0.0, 4.5])  # 3 px split over both photos: (3 / sqrt 2)^2
