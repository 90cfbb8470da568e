"""Strecha et al. (2008) ground-truth cameras and pose errors: moved to :mod:`sekd_sfm.evaluation.strecha`
(the dataset readers below both ``bench/`` and ``train/`` read them); the names stay importable here."""
from __future__ import annotations

from ..evaluation.metrics import rotation_angle_deg
from ..evaluation.strecha import (
    StrechaCamera,
    angle_between_deg,
    pairwise_errors,
    read_camera,
    read_cameras,
    relative_pose,
)

__all__ = ["StrechaCamera", "angle_between_deg", "pairwise_errors", "read_camera", "read_cameras", "relative_pose",
           "rotation_angle_deg"]
