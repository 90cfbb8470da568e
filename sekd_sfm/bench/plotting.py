"""How benchmark plots are written (one place for every bench command's PNGs)."""
from __future__ import annotations

from pathlib import Path


def save_png(fig, path: Path, **savefig) -> Path:
    """``fig`` as a 256-colour PNG: a plot has a few dozen colours plus their anti-aliased edges, which a palette
    keeps to within one level, at a third of a full-colour PNG's size (the published results live in the tree)."""
    from PIL import Image

    fig.savefig(path, **savefig)
    with Image.open(path) as image:
        palette = image.convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    palette.save(path, optimize=True)
    return path
