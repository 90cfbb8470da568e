"""``sekd reconstruct`` (images -> COLMAP model), ``sekd relpose`` (two images -> R, t) and ``sekd export``."""
from __future__ import annotations

import json
from pathlib import Path

import click

from sekd_sfm.errors import SekdError
from sekd_sfm.features import FeatureConfig
from sekd_sfm.inference import SEKDConfig

from .match import match_config, match_options, pairs_config, pairs_options
from .options import feature_options, runtime_options, weights_option

CAMERA_MODES = ("auto", "single", "per-folder", "per-image")


def feature_config(feature, max_keypoints, threshold, nms_radius, resize_max, multi_scale, subpixel, weights,
                   device, precision) -> FeatureConfig:
    """The FeatureConfig of the shared feature options (as `sekd extract` builds it)."""
    sekd = SEKDConfig(max_keypoints=max_keypoints, threshold=threshold, nms_radius=nms_radius, subpixel=subpixel,
                      multi_scale=multi_scale, precision=precision, device=device)
    return FeatureConfig(feature=feature, max_keypoints=max_keypoints, resize_max=resize_max, sekd=sekd,
                         weights=weights)


def camera_options(f):
    """--camera-model, --camera-mode, --camera-params."""
    options = [
        click.option("--camera-model", default="SIMPLE_RADIAL", show_default=True,
                     help="COLMAP camera model (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, ...)."),
        click.option("--camera-mode", type=click.Choice(CAMERA_MODES), default="auto", show_default=True,
                     help="Cameras shared by: auto (same size and EXIF), single (all images), per-folder, per-image."),
        click.option("--camera-params", default=None,
                     help="Known intrinsics as comma-separated numbers in the model's order, e.g. "
                          "'f,cx,cy,k' for SIMPLE_RADIAL, in COLMAP pixel coordinates (pixel centre at +0.5)."),
    ]
    for option in reversed(options):
        f = option(f)
    return f


def _print_option_help(ctx: click.Context, param: click.Parameter, values) -> tuple:
    """``--mapper help`` / ``--verification help``: list the settable options and their defaults."""
    if "help" not in values:
        return values
    from sekd_sfm.sfm.colmap import option_names, require_pycolmap

    pycolmap = require_pycolmap()
    options = pycolmap.IncrementalPipelineOptions() if param.name == "mapper" else pycolmap.TwoViewGeometryOptions()
    for name in option_names(options):
        value = options
        for part in name.split("."):
            value = getattr(value, part)
        click.echo(f"{name} = {value}")
    ctx.exit(0)


mapper_option = click.option(
    "--mapper", multiple=True, metavar="KEY=VALUE", callback=_print_option_help,
    help="Set an option of pycolmap's IncrementalPipelineOptions, e.g. mapper.init_min_tri_angle=8 "
         "(repeatable; `--mapper help` lists them). The mapper runs on one thread, the only way COLMAP "
         "repeats a model for a --seed; num_threads=-1 uses all cores (faster on large scenes).")
seed_option = click.option("--seed", type=int, default=0, show_default=True,
                           help="Random seed of RANSAC and the mapper.")


@click.command()
@click.argument("images", type=click.Path(file_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output folder: features.h5, pairs.txt, matches.h5, database.db, model/, stats.json, colmap.log.")
@feature_options
@weights_option
@runtime_options
@pairs_options
@match_options
@camera_options
@mapper_option
@click.option("--verification", multiple=True, metavar="KEY=VALUE", callback=_print_option_help,
              help="Set an option of pycolmap's TwoViewGeometryOptions, e.g. ransac.max_error=2 "
                   "(repeatable; `--verification help` lists them).")
@seed_option
@click.option("--overwrite", is_flag=True, help="Recompute features and matches instead of reusing them.")
@click.option("--no-progress", is_flag=True, help="No progress bars.")
def reconstruct(images, output, feature, max_keypoints, threshold, nms_radius, resize_max, multi_scale, subpixel,
                weights, num_threads, device, precision, pairs_mode, pairs_file, window, loop_every, match_mode, ratio,
                rootsift, camera_model, camera_mode, camera_params, mapper, verification, seed, overwrite,
                no_progress) -> None:
    """Reconstruct cameras and 3D points from the images below IMAGES (COLMAP incremental SfM).

    \b
    Runs extract, pairs and match when their outputs are missing in OUTPUT (reusing them
    when present and made with the same settings), imports everything into a COLMAP
    database, verifies the matches geometrically and maps. The largest model is written
    to OUTPUT/model (COLMAP binary), statistics to OUTPUT/stats.json, COLMAP's log to
    OUTPUT/colmap.log. If no model, or several sub-models, come out, the reason and the
    match statistics behind it are printed, the database is kept and the exit code is 1.

    \b
    Examples:
      sekd reconstruct photos/ -o out/ --weights sekd.pth --resize-max 1600
      sekd reconstruct photos/ -o out/ --feature sift --camera-mode single --mapper mapper.init_min_tri_angle=8
    """
    from sekd_sfm.sfm.database import CameraConfig
    from sekd_sfm.sfm.reconstruct import ReconstructConfig, ReconstructionError
    from sekd_sfm.sfm.reconstruct import reconstruct as run
    from sekd_sfm.sfm.report import format_summary

    config = ReconstructConfig(
        features=feature_config(feature, max_keypoints, threshold, nms_radius, resize_max, multi_scale, subpixel,
                                weights, device, precision),
        pairs=pairs_config(pairs_mode, pairs_file, window, loop_every),
        matching=match_config(match_mode, ratio, rootsift, device),
        camera=CameraConfig(model=camera_model, mode=camera_mode, params=camera_params),
        mapper=list(mapper), verification=list(verification), seed=seed)
    try:
        run(images, output, config, overwrite=overwrite, num_threads=num_threads, progress=not no_progress)
    except ReconstructionError:
        _echo_summary(output, format_summary)
        raise
    _echo_summary(output, format_summary)


def _echo_summary(output: Path, format_summary) -> None:
    stats = output / "stats.json"
    if stats.is_file():
        click.echo(format_summary(json.loads(stats.read_text())))


@click.command()
@click.argument("image0", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("image1", type=click.Path(dir_okay=False, path_type=Path))
@feature_options
@weights_option
@runtime_options
@match_options
@click.option("--camera-model", default="SIMPLE_PINHOLE", show_default=True,
              help="COLMAP camera model of --camera-params.")
@click.option("--camera-params", default=None,
              help="Known intrinsics of both images, e.g. 'f,cx,cy' (SIMPLE_PINHOLE) or 'fx,fy,cx,cy' (PINHOLE), "
                   "COLMAP pixel coordinates. Default: EXIF focal length, else 1.2 x the longer side.")
@click.option("--max-error", type=click.FloatRange(min=0, min_open=True), default=4.0, show_default=True,
              help="RANSAC inlier threshold in pixels.")
@click.option("--seed", type=int, default=0, show_default=True, help="RANSAC random seed.")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the JSON to this file.")
def relpose(image0, image1, feature, max_keypoints, threshold, nms_radius, resize_max, multi_scale, subpixel, weights,
            num_threads, device, precision, match_mode, ratio, rootsift, camera_model, camera_params, max_error, seed,
            output) -> None:
    """Relative pose of IMAGE1 with respect to IMAGE0, printed as JSON.

    \b
    R and t map camera-0 coordinates to camera-1 coordinates: x1 = R x0 + t, |t| = 1.
    Also reports the matches and RANSAC inliers, and where the focal length came from.

    \b
    Example:
      sekd relpose a.jpg b.jpg --feature sift --camera-model PINHOLE --camera-params 2759.5,2764.2,1521.2,1007.3
    """
    from sekd_sfm.runtime import set_num_threads
    from sekd_sfm.sfm.relpose import RelposeConfig, relative_pose

    set_num_threads(num_threads)
    config = RelposeConfig(
        features=feature_config(feature, max_keypoints, threshold, nms_radius, resize_max, multi_scale, subpixel,
                                weights, device, precision),
        matching=match_config(match_mode, ratio, rootsift, device),
        camera_model=camera_model, camera_params=camera_params, max_error=max_error, seed=seed)
    text = json.dumps(relative_pose(image0, image1, config), indent=2)
    if output:
        output.write_text(text + "\n")
    click.echo(text)


@click.command()
@click.argument("model", type=click.Path(file_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="Folder for --format text, file (.ply) for --format ply.")
@click.option("--format", "fmt", type=click.Choice(["text", "ply"]), default="text", show_default=True,
              help="text: COLMAP text model (cameras.txt, images.txt, points3D.txt); ply: coloured point cloud.")
def export(model: Path, output: Path, fmt: str) -> None:
    """Export a COLMAP model as COLMAP text files or as a coloured PLY point cloud.

    \b
    Examples:
      sekd export out/model -o out/model_text
      sekd export out/model -o out/points.ply --format ply
    """
    from sekd_sfm.sfm.export import export_model

    if fmt == "ply" and output.suffix.lower() != ".ply":
        raise SekdError(f"{output}: a PLY export needs a file name ending in .ply")
    click.echo(str(export_model(model, output, fmt)))
