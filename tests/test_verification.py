"""Geometric verification on the executor (sekd_sfm.stages.verification): pair for pair what pycolmap writes over
the database, in this process or over worker processes, and a failed run resumes from the pairs it finished."""
from __future__ import annotations

import contextlib
import shutil
import sqlite3

import numpy as np
import pytest
from test_verify import _database_with, _random_pair, _true_pair

from sekd_sfm.errors import SekdError
from sekd_sfm.execution import LocalExecutor
from sekd_sfm.stages import verification
from sekd_sfm.stages.database import two_view_options, verify_matches


def _rows(database) -> list:
    """Every pair's two-view geometry as the database stores it (inliers, config, matrices, pose), by pair id."""
    with contextlib.closing(sqlite3.connect(database)) as db:
        return db.execute("SELECT pair_id, rows, data, config, F, E, H, qvec, tvec FROM two_view_geometries "
                          "ORDER BY pair_id").fetchall()


@pytest.fixture
def database(tmp_path):
    """Six hand-made pairs: three of one scene (40-120 inliers among outliers), two of unrelated matches, one with
    too few matches to verify."""
    rng = np.random.default_rng(4)
    pairs = [tuple(_true_pair(rng, n, 50)[:3]) for n in (40, 80, 120)]
    pairs += [_random_pair(rng, 45), _random_pair(rng, 60), tuple(_true_pair(rng, 12, 0)[:3])]
    path, _ = _database_with(tmp_path, pairs)
    return path


def test_the_stage_writes_what_pycolmap_writes_here_and_over_processes(database, tmp_path, monkeypatch):
    reference = shutil.copy(database, tmp_path / "reference.db")
    verify_matches(reference, two_view_options(), num_threads=2)
    monkeypatch.setattr(verification, "PAIRS_PER_TASK", 2)  # three tasks: both processes work
    for processes in (1, 2):
        copy = shutil.copy(database, tmp_path / f"stage{processes}.db")
        executor = LocalExecutor(processes)
        assert verification.verify_pairs(copy, two_view_options(), executor, progress=False) == copy
        assert executor.places == ["local" if processes == 1 else "local: 2 processes"]
        assert _rows(copy) == _rows(reference)
        assert sum(row[1] > 0 for row in _rows(copy)) == 3  # the three true pairs, and only those
        assert not list(tmp_path.glob(f"stage{processes}-verification.h5*"))  # the parts go once written


def test_a_failed_verification_resumes_from_the_pairs_it_finished(database, tmp_path, monkeypatch):
    reference = shutil.copy(database, tmp_path / "reference.db")
    verification.verify_pairs(reference, two_view_options(), LocalExecutor(1), progress=False)
    computed: list[str] = []
    original = verification.VerifyWorker.__call__

    def fails_on_the_fourth(self, keys):
        for key in keys:
            computed.append(key)
            if len(computed) == 4:
                raise SekdError("verification: the fourth pair fails")
            yield from original(self, [key])

    monkeypatch.setattr(verification.VerifyWorker, "__call__", fails_on_the_fourth)
    with pytest.raises(SekdError, match="fourth pair fails"):
        verification.verify_pairs(database, two_view_options(), LocalExecutor(1), progress=False, signature="s")
    assert (tmp_path / "database-verification.h5").exists() or (tmp_path / "database-verification.h5.parts").exists()
    computed.clear()
    monkeypatch.setattr(verification.VerifyWorker, "__call__",
                        lambda self, keys: (computed.extend(keys), original(self, keys))[1])
    verification.verify_pairs(database, two_view_options(), LocalExecutor(1), progress=False, signature="s")
    assert len(computed) == 3 and _rows(database) == _rows(reference)
    # A failed run's pairs are not reused for other inputs (another signature).
    computed.clear()
    monkeypatch.setattr(verification.VerifyWorker, "__call__", fails_on_the_fourth)
    with pytest.raises(SekdError, match="fourth pair fails"):
        verification.verify_pairs(database, two_view_options(), LocalExecutor(1), progress=False, signature="t")
    computed.clear()
    monkeypatch.setattr(verification.VerifyWorker, "__call__",
                        lambda self, keys: (computed.extend(keys), original(self, keys))[1])
    verification.verify_pairs(database, two_view_options(), LocalExecutor(1), progress=False, signature="u")
    assert len(computed) == 6 and _rows(database) == _rows(reference)


def test_a_finished_verification_is_reused_by_the_next_run_of_the_same_inputs(database, tmp_path, monkeypatch):
    """``sekd reconstruct`` builds its database afresh on every run: a run killed while mapping, or run again with
    other mapper settings, takes the geometries from the kept results instead of verifying every pair again."""
    pristine = shutil.copy(database, tmp_path / "pristine.db")
    verification.verify_pairs(database, two_view_options(), LocalExecutor(1), progress=False, signature="s")
    assert (tmp_path / "database-verification.h5").exists()  # kept: it says what it was computed from
    reference = _rows(database)
    computed: list[str] = []
    original = verification.VerifyWorker.__call__
    monkeypatch.setattr(verification.VerifyWorker, "__call__",
                        lambda self, keys: (computed.extend(keys), original(self, keys))[1])
    shutil.copy(pristine, database)  # the next run's fresh database: matches, no geometries
    assert not _rows(database)
    verification.verify_pairs(database, two_view_options(), LocalExecutor(1), progress=False, signature="s")
    assert computed == [] and _rows(database) == reference
    shutil.copy(pristine, database)  # other inputs (another signature), or other RANSAC options: verified again
    verification.verify_pairs(database, two_view_options(), LocalExecutor(1), progress=False, signature="t")
    assert len(computed) == 6 and _rows(database) == reference
    computed.clear()
    verification.verify_pairs(database, two_view_options(["ransac.max_error=2"]), LocalExecutor(1), progress=False,
                              signature="t")
    assert len(computed) == 6


def test_a_geometry_survives_its_arrays_with_or_without_a_pose():
    import pycolmap

    geometry = pycolmap.TwoViewGeometry({"config": 2, "tri_angle": 0.1, "F": np.arange(9.0).reshape(3, 3),
                                         "E": np.eye(3), "inlier_matches": np.array([[0, 1], [2, 3]], np.uint32)})
    geometry.cam2_from_cam1 = pycolmap.Rigid3d(np.hstack([np.eye(3), [[1.0], [2.0], [3.0]]]))
    back = verification.geometry_from_arrays(verification.geometry_arrays(geometry))
    assert int(back.config) == 2 and back.tri_angle == pytest.approx(0.1) and back.H is None
    assert np.array_equal(back.F, geometry.F) and np.array_equal(back.E, np.eye(3))
    assert np.array_equal(back.inlier_matches, geometry.inlier_matches)
    assert np.allclose(back.cam2_from_cam1.matrix(), geometry.cam2_from_cam1.matrix())
    failed = verification.geometry_from_arrays(verification.geometry_arrays(pycolmap.TwoViewGeometry({"config": 1})))
    assert int(failed.config) == 1 and len(failed.inlier_matches) == 0 and failed.F is None
