"""Model export (``sekd export``): a COLMAP model -> COLMAP text files, or a coloured PLY point cloud."""
from __future__ import annotations

from pathlib import Path

from ..errors import SekdError
from .colmap import require_pycolmap

EXPORT_FORMATS = ("text", "ply")


def read_model(model: str | Path):
    """A COLMAP model folder (binary or text) as a pycolmap Reconstruction; SekdError if it is not one."""
    model = Path(model)
    names = ("cameras.bin", "images.bin", "points3D.bin", "cameras.txt", "images.txt", "points3D.txt")
    if not model.is_dir() or not any((model / n).is_file() for n in names):
        raise SekdError(f"{model}: not a COLMAP model folder (no cameras/images/points3D .bin or .txt files)")
    try:
        return require_pycolmap().Reconstruction(str(model))
    except (ValueError, RuntimeError) as exc:
        raise SekdError(f"{model}: cannot read the COLMAP model ({exc})") from None


def export_model(model: str | Path, output: str | Path, fmt: str = "text") -> Path:
    """Write ``model`` as COLMAP text files in the folder ``output``, or as a PLY file ``output``.

    The PLY holds the 3D points with their RGB colours (binary little-endian). Returns ``output``.
    """
    if fmt not in EXPORT_FORMATS:
        raise SekdError(f"unknown export format {fmt!r}; choose from {', '.join(EXPORT_FORMATS)}")
    reconstruction, output = read_model(model), Path(output)
    if fmt == "text":
        output.mkdir(parents=True, exist_ok=True)
        reconstruction.write_text(str(output))
    else:
        output.parent.mkdir(parents=True, exist_ok=True)
        reconstruction.export_PLY(str(output))
    return output
