"""``sekd export``: a COLMAP model -> COLMAP text files, a point cloud, or an interactive 3D page."""
from __future__ import annotations

from pathlib import Path

import click

from sekd_sfm.errors import SekdError


@click.command()
@click.argument("model", type=click.Path(file_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="Folder for --format text, file (.ply) for --format ply, file (.html) for --format html.")
@click.option("--format", "fmt", type=click.Choice(["text", "ply", "html"]), default="text", show_default=True,
              help="text: COLMAP text model (cameras.txt, images.txt, points3D.txt); ply: coloured point cloud; "
                   "html: interactive 3D page of the points and cameras (needs plotly: pip install \"sekd-sfm[viz]\").")
def export(model: Path, output: Path, fmt: str) -> None:
    """Export a COLMAP model as COLMAP text files, a coloured PLY point cloud or an interactive 3D page.

    \b
    The HTML page shows the coloured 3D points and one frustum per registered image (hover
    for its name); it embeds plotly.js, so it opens offline in any browser.

    \b
    Examples:
      sekd export out/model -o out/model_text
      sekd export out/model -o out/points.ply --format ply
      sekd export out/model -o out/model.html --format html
    """
    from sekd_sfm.sfm.export import export_model

    if fmt == "ply" and output.suffix.lower() != ".ply":
        raise SekdError(f"{output}: a PLY export needs a file name ending in .ply")
    click.echo(str(export_model(model, output, fmt)))
