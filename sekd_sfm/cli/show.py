"""``sekd show matches``, ``keypoints`` and ``model``: pictures of a feature or match file, or of a model."""
from __future__ import annotations

from pathlib import Path

import click

IMAGES_HELP = ("Folder the features were extracted from (image NAME is IMAGES/NAME). "
               "Default: grey canvases of the recorded image sizes.")
MAX_SIDE_HELP = "Reduce each image to at most N px on its long side for drawing (0 = full size)."


@click.group()
def show() -> None:
    """Draw keypoints or matches of sekd (or hloc) files on the images, as PNG, or a model's cameras and points.

    \b
    Examples:
      sekd show keypoints out/features.h5 a/x.jpg --images photos/ -o kp.png
      sekd show matches out/features.h5 out/matches.h5 a/x.jpg b/y.jpg --images photos/ -o pair.png --inliers
      sekd show model out/splat -o view.html
    """


@show.command()
@click.argument("features", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("matches", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("name0")
@click.argument("name1")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="PNG file to write.")
@click.option("--images", type=click.Path(file_okay=False, path_type=Path), default=None, help=IMAGES_HELP)
@click.option("--inliers", is_flag=True,
              help="Colour by geometric check: green = inlier of a fundamental matrix (OpenCV USAC MAGSAC++), "
                   "red = outlier. Default: colour by match score (blue = ambiguous, red = distinctive).")
@click.option("--max-error", type=click.FloatRange(min=0, min_open=True), default=4.0, show_default=True,
              help="--inliers: epipolar error threshold in pixels.")
@click.option("--max-side", type=click.IntRange(min=0), default=1600, show_default=True, help=MAX_SIDE_HELP)
def matches(features: Path, matches: Path, name0: str, name1: str, output: Path, images: Path | None, inliers: bool,
            max_error: float, max_side: int) -> None:
    """Draw the matches of the pair NAME0 NAME1: the two images side by side, one line per match.

    \b
    The pair is found in either order, in sekd's and hloc's match files. With --inliers
    the matches are checked against one fundamental matrix (as COLMAP's verification
    does) and the inlier count is printed.

    \b
    Example:
      sekd show matches out/features.h5 out/matches.h5 a/x.jpg b/y.jpg --images photos/ -o pair.png --inliers
    """
    from sekd_sfm.viz import draw_pair, write_png

    picture = draw_pair(features, matches, name0, name1, images, inliers, max_error, max_side or None)
    write_png(picture.image, output)
    if inliers and picture.inliers is None:
        click.echo(f"{output}: {picture.matches} matches (fewer than 8: no geometric check)")
    elif inliers:
        click.echo(f"{output}: {picture.matches} matches, {picture.inliers} inliers "
                   f"(fundamental matrix, {max_error:g} px)")
    else:
        click.echo(f"{output}: {picture.matches} matches")


@show.command()
@click.argument("features", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("name")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="PNG file to write.")
@click.option("--images", type=click.Path(file_okay=False, path_type=Path), default=None, help=IMAGES_HELP)
@click.option("--max-side", type=click.IntRange(min=0), default=1600, show_default=True, help=MAX_SIDE_HELP)
def keypoints(features: Path, name: str, output: Path, images: Path | None, max_side: int) -> None:
    """Draw the keypoints of image NAME, coloured by score rank (red = strongest).

    \b
    Example:
      sekd show keypoints out/features.h5 a/x.jpg --images photos/ -o kp.png
    """
    from sekd_sfm.files import features as ff
    from sekd_sfm.viz import check_inputs, draw_keypoints, load_canvas, write_png

    check_inputs(features)
    arrays = ff.read_features(features, name)
    canvas = draw_keypoints(load_canvas(name, features, images), arrays["keypoints"], arrays.get("scores"),
                            max_side or None)
    write_png(canvas, output)
    click.echo(f"{output}: {len(arrays['keypoints'])} keypoints")


@show.command()
@click.argument("model", type=click.Path(file_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Page (.html: interactive, needs plotly) or picture (.png) to write.")
@click.option("--max-points", type=click.IntRange(min=1), default=None,
              help="Draw at most N of the 3D points (a seeded random subset). Default: 200,000 in a page, "
                   "30,000 in a picture.")
def model(model: Path, output: Path, max_points: int | None) -> None:
    """Draw a model's cameras (one frustum per registered image) and coloured 3D points.

    \b
    MODEL is a COLMAP model folder (e.g. out/model) or a folder written by
    `sekd export --format nerfstudio` (its sparse/0 is drawn). The .html page can be
    rotated and zoomed in a browser (offline: plotly.js is embedded); the .png picture
    looks over the cameras' shoulders.

    \b
    Examples:
      sekd show model out/splat -o view.html
      sekd show model out/model -o view.png
    """
    from sekd_sfm.errors import SekdError
    from sekd_sfm.stages.export import (
        HTML_MAX_POINTS,
        export_html,
        model_folder,
        read_model,
    )
    from sekd_sfm.viz import MODEL_PNG_MAX_POINTS, draw_model, write_png

    suffix = output.suffix.lower()
    if suffix not in (".html", ".htm", ".png"):
        raise SekdError(f"{output}: give a file name ending in .html (interactive page) or .png (picture)")
    reconstruction, title = read_model(model), str(model_folder(model))
    if suffix == ".png":
        write_png(draw_model(reconstruction, title, max_points or MODEL_PNG_MAX_POINTS), output)
    else:
        export_html(reconstruction, output, title=title, max_points=max_points or HTML_MAX_POINTS)
    click.echo(f"{output}: {reconstruction.num_reg_images()} registered images, "
               f"{reconstruction.num_points3D():,} points")
