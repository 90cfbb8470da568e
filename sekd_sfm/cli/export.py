"""``sekd export``: a COLMAP model -> COLMAP text files, a point cloud, an interactive 3D page, or a
folder for Gaussian Splatting and NeRF training."""
from __future__ import annotations

from pathlib import Path

import click

from sekd_sfm.errors import SekdError

FORMATS = ["text", "ply", "html", "nerfstudio", "3dgs"]
TRAINING_FORMATS = ("nerfstudio", "3dgs")


@click.command()
@click.argument("model", type=click.Path(file_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="Folder for --format text and nerfstudio/3dgs, file (.ply) for --format ply, "
                   "file (.html) for --format html.")
@click.option("--format", "fmt", type=click.Choice(FORMATS), default="text", show_default=True,
              help="text: COLMAP text model (cameras.txt, images.txt, points3D.txt); ply: coloured point cloud; "
                   "html: interactive 3D page of the points and cameras (needs plotly: pip install \"sekd-sfm[viz]\"); "
                   "nerfstudio (or its alias 3dgs): undistorted photos, COLMAP model and transforms.json for "
                   "Gaussian Splatting and NeRF trainers.")
@click.option("--images", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="nerfstudio/3dgs: the photos' folder (photo NAME is IMAGES/NAME). "
                   "Default: the one recorded by the `sekd reconstruct` run that wrote MODEL.")
@click.option("--masks", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="nerfstudio/3dgs: the masks' folder (MASKS/NAME.png, zero = ignore), exported undistorted to "
                   "OUTPUT/masks. Default: the one `sekd reconstruct --masks` recorded, if any.")
@click.option("--max-size", type=click.IntRange(min=16), default=None,
              help="nerfstudio/3dgs: reduce the exported images (and their intrinsics) to at most N px on the "
                   "long side. Default: full size.")
@click.option("--overwrite", is_flag=True,
              help="nerfstudio/3dgs: replace the export in a non-empty OUTPUT (other files there are kept).")
def export(model: Path, output: Path, fmt: str, images: Path | None, masks: Path | None, max_size: int | None,
           overwrite: bool) -> None:
    """Export a COLMAP model as COLMAP text files, a coloured PLY point cloud, an interactive 3D page,
    or a folder that Gaussian Splatting and NeRF trainers load.

    \b
    MODEL is a COLMAP model folder (e.g. OUT/model of `sekd reconstruct`) or an export folder.
    The HTML page shows the coloured 3D points and one frustum per registered image (hover
    for its name); it embeds plotly.js, so it opens offline in any browser.

    \b
    --format nerfstudio (alias 3dgs) writes into the folder OUTPUT:
      images/           the registered photos, undistorted (pycolmap)
      masks/NAME.png    their masks undistorted, when the reconstruction had masks
      sparse/0/         the undistorted model: pinhole cameras, poses, 3D points
      transforms.json   cameras as nerfstudio's COLMAP converter writes them
      sparse_pc.ply     3D points for the splats' initialisation
    The photos are found through the record of the run in OUT (--images overrides). Then e.g.
    `ns-train splatfacto --data OUTPUT` or `python train.py -s OUTPUT` (3DGS).

    \b
    Examples:
      sekd export out/model -o out/model_text
      sekd export out/model -o out/points.ply --format ply
      sekd export out/model -o out/model.html --format html
      sekd export out/model -o out/splat --format nerfstudio --max-size 1600
    """
    training = fmt in TRAINING_FORMATS
    if not training and (images or masks or max_size or overwrite):
        raise SekdError("--images, --masks, --max-size and --overwrite apply to --format nerfstudio/3dgs only")
    if training:
        _export_for_training(model, output, images, masks, max_size, overwrite)
        return
    from sekd_sfm.stages.export import export_model

    if fmt == "ply" and output.suffix.lower() != ".ply":
        raise SekdError(f"{output}: a PLY export needs a file name ending in .ply")
    click.echo(str(export_model(model, output, fmt)))


def _export_for_training(model: Path, output: Path, images: Path | None, masks: Path | None, max_size: int | None,
                         overwrite: bool) -> None:
    """Run the nerfstudio/3dgs export and print what it wrote."""
    from sekd_sfm.stages.export_nerfstudio import export_nerfstudio

    images, masks = _source_folders(model, images, masks)
    result = export_nerfstudio(model, output, images, masks, max_size, overwrite)
    sizes = sorted(set(result.sizes))
    size = f"{sizes[0][0]}x{sizes[0][1]}" if len(sizes) == 1 else f"{len(sizes)} sizes"
    masked = f", masks for {result.masks}" if result.masks else ""
    click.echo(f"{result.folder}: {result.images} undistorted images ({size} px, pinhole){masked}, "
               f"{result.points:,} points; sparse/0, transforms.json, sparse_pc.ply")


def _source_folders(model: Path, images: Path | None, masks: Path | None) -> tuple[Path, Path | None]:
    """The photo folder and the mask folder (None: no masks) of the export: the given ones, else those named by
    the record of the reconstruction that wrote ``model`` (``images_dir``, ``config.masks``)."""
    from sekd_sfm.pipelines.record import STATS, Record
    from sekd_sfm.stages.export import model_folder
    from sekd_sfm.stages.export_nerfstudio import read_exportable

    folder = model_folder(model)
    record = Record.of_model(folder)
    if images is None:
        if record is None:
            read_exportable(folder)  # a folder without a (registered) model says that first
            raise SekdError(f"{folder}: no {STATS} of `sekd reconstruct` beside the model to find the photos in; "
                            "give the photos' folder with --images")
        images = record.folder(str(record.images_dir))
        if not images.is_dir():
            read_exportable(folder)
            raise SekdError(f"{images}: the photo folder recorded in {record.path} does not exist; "
                            "give the photos' folder with --images")
    if masks is None and record is not None:
        masks = record.masks_folder()
    return images, masks
