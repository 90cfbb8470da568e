"""Shared fixtures: the read-only project data in ``$SEKD_SHARED`` (default ``../shared``)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("SEKD_SHARED", ROOT.parent / "shared")).resolve()
SEKD_WEIGHTS = SHARED / "weights/sekd/sekd.pth"
GRAFFITI = SHARED / "data/homography/hpatches/v_graffiti"


def pytest_configure(config):
    # Commands run by tests resolve the shared folder the same way.
    os.environ.setdefault("SEKD_SHARED", str(SHARED))


@pytest.fixture(scope="session")
def shared() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"shared data not found at {SHARED} (set SEKD_SHARED)")
    return SHARED


@pytest.fixture(scope="session")
def authors_net(shared):
    """The authors' released network, eval mode, CPU."""
    from sekd_sfm.model.weights import load_model

    return load_model(SEKD_WEIGHTS)[0]
