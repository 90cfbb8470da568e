"""Readers for benchmark data in the standard layouts.

HPatches layout: a folder per sequence with images ``1.*`` .. ``N.*`` (ppm, png, jpg; sizes
may differ) and text files ``H_1_k``: a 3x3 matrix mapping image-1 pixels to image k.
The prefix ``i_`` / ``v_`` of the folder name gives the subset (illumination / viewpoint).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..files.images import IMAGE_EXTENSIONS
from .strecha import read_cameras


@dataclass
class Sequence:
    """One homography sequence: its name, subset ('i', 'v' or '?'), images by index, H_1_k by k."""

    name: str
    folder: Path
    images: dict[int, Path]
    homographies: dict[int, np.ndarray] = field(default_factory=dict)

    @property
    def subset(self) -> str:
        return self.name[0] if self.name[:2] in ("i_", "v_") else "?"


def is_sequence(folder: Path) -> bool:
    """Whether ``folder`` is one sequence (it holds ``H_1_2``)."""
    return (folder / "H_1_2").is_file()


def read_sequence(folder: Path) -> Sequence:
    """Read one sequence folder; SekdError when an image named by an ``H_1_k`` is missing."""
    images = {int(p.stem): p for p in folder.iterdir() if p.stem.isdigit() and p.suffix.lower() in IMAGE_EXTENSIONS}
    homographies = {}
    for file in sorted(folder.glob("H_1_*")):
        k = int(file.name.split("_")[-1])
        if 1 not in images or k not in images:
            raise SekdError(f"{file}: image 1 or {k} of this sequence is missing")
        homographies[k] = np.loadtxt(file).reshape(3, 3)
    return Sequence(folder.name, folder, images, homographies)


def find_sequences(roots: list[Path]) -> list[Sequence]:
    """All sequences in ``roots`` (each a sequence folder or a folder of them), sorted by name."""
    sequences = []
    for root in map(Path, roots):
        if not root.is_dir():
            raise SekdError(f"{root}: folder not found; give HPatches-layout sequence folders or their parent")
        folders = [root] if is_sequence(root) else sorted(p for p in root.iterdir() if p.is_dir() and is_sequence(p))
        sequences += [read_sequence(f) for f in folders]
    if not sequences:
        raise SekdError(f"no homography sequences (folders with 1.*, 2.*, H_1_2) found in {', '.join(map(str, roots))}")
    names = [s.name for s in sequences]
    if len(set(names)) != len(names):
        raise SekdError("two sequences share a folder name; rename one so results can be told apart")
    return sorted(sequences, key=lambda s: s.name)


@dataclass
class PoseScene:
    """Images with ground-truth cameras: name -> (K 3x3, R_cw 3x3, t_cw 3) with x_cam = R_cw X + t_cw."""

    name: str
    image_dir: Path
    cameras: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]


def _strecha_scene(folder: Path) -> PoseScene:
    cameras = {name: (c.K, *c.cam_from_world) for name, c in read_cameras(folder / "gt_dense_cameras").items()}
    images = folder / "images" if (folder / "images").is_dir() else folder
    return PoseScene(folder.name, images, cameras)


def _colmap_scene(folder: Path, model: Path) -> PoseScene:
    from ..stages.colmap import require_pycolmap

    reconstruction = require_pycolmap().Reconstruction(str(model))
    cameras = {}
    for image in reconstruction.images.values():
        if image.has_pose:
            pose = image.cam_from_world()
            K = np.array(image.camera.calibration_matrix(), dtype=np.float64)
            K[:2, 2] -= 0.5  # COLMAP puts the first pixel's centre at 0.5; our keypoints at 0 (OpenCV)
            cameras[image.name] = (K, pose.rotation.matrix(), np.asarray(pose.translation))
    return PoseScene(folder.name, folder / "images", cameras)


def read_pose_scene(folder: Path) -> PoseScene:
    """A scene in the Strecha layout (images + ``gt_dense_cameras/*.camera``) or with a COLMAP
    model as ground truth (``images/`` + ``sparse/`` or ``sparse/0/``)."""
    folder = Path(folder)
    if (folder / "gt_dense_cameras").is_dir():
        return _strecha_scene(folder)
    for model in (folder / "sparse" / "0", folder / "sparse"):
        if (model / "images.bin").is_file() or (model / "images.txt").is_file():
            return _colmap_scene(folder, model)
    raise SekdError(f"{folder}: no ground truth found (expected gt_dense_cameras/ or images/ + sparse/[0/])")
