"""``sekd triangulate``: photos + known poses (a COLMAP model or an hloc poses file) -> 3D points, poses fixed.

Options come in the groups of ``sekd reconstruct`` (``cli/reconstruct.py``), so extraction and matching
take the same defaults and ``--conf`` presets; ``triangulate_config`` turns them into a TriangulateConfig.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import click

from sekd_sfm.confs import output_names

from .match import matching_options
from .options import (
    OptionValues,
    extraction_options,
    num_threads_option,
    option_group,
    ray_options,
)
from .presets import conf_option, feature_and_match_configs
from .reconstruct import (
    RECONSTRUCT_RESIZE_HELP,
    execution_options,
    refine_option,
    seed_option,
    verification_option,
)

if TYPE_CHECKING:  # imported where used: the CLI starts without torch and pycolmap
    from sekd_sfm.pipelines.triangulate import TriangulateConfig

#: Kept in step with sekd_sfm.pipelines.triangulate (not imported: the CLI starts without pycolmap).
PAIR_SOURCES = ("covisibility", "retrieval")
DEFAULT_NEIGHBORS = 20
DEFAULT_MAX_ANGLE_DEG = 60.0


def _print_triangulator_options(ctx: click.Context, _param, values) -> tuple:
    """``--mapper help``: the settable options of the triangulator (pycolmap IncrementalPipelineOptions)."""
    if "help" not in values:
        return values
    from sekd_sfm.stages.colmap import option_values, require_pycolmap

    options = require_pycolmap().IncrementalPipelineOptions()
    for name, value in option_values(options):
        click.echo(f"{name} = {value}")
    ctx.exit(0)


pose_pairing_options = option_group(
    "pairing",
    click.option("--pairs", "pair_source", type=click.Choice(PAIR_SOURCES), default="covisibility",
                 show_default=True,
                 help="covisibility: from the poses. A model with 3D points pairs each photo with the K photos "
                      "sharing the most points with it; otherwise (a poses file, a model without points, a photo "
                      "left without partner) each photo is paired with its K nearest cameras (centre distance) "
                      "among those whose optical axis is within --max-angle of its own. retrieval: each photo with "
                      "its K most similar photos by global descriptor, as `sekd pairs --pairs retrieval`."),
    click.option("--num-neighbors", type=click.IntRange(min=1), default=DEFAULT_NEIGHBORS, show_default=True,
                 help="K: partners per photo."),
    click.option("--max-angle", type=click.FloatRange(0, 180), default=DEFAULT_MAX_ANGLE_DEG, show_default=True,
                 help="covisibility from camera poses: largest angle (degrees) between two photos' optical axes."),
)

pose_camera_options = option_group(
    "camera",
    click.option("--camera-model", default="SIMPLE_RADIAL", show_default=True,
                 help="With a poses file: COLMAP camera model of --camera-params (PINHOLE, SIMPLE_RADIAL, OPENCV, ...)."),
    click.option("--camera-params", default=None,
                 help="With a poses file: the photos' intrinsics, comma-separated in the model's order, COLMAP pixel "
                      "coordinates (centre of the first pixel at 0.5), e.g. 'fx,fy,cx,cy' for PINHOLE. Without "
                      "it: COLMAP's prior (EXIF focal length, else 1.2 x the long side), kept as it is, with a "
                      "warning. A COLMAP model's own cameras are always used."),
    click.option("--refine-intrinsics", is_flag=True,
                 help="Let the final bundle adjustment refine focal length and distortion (never the poses nor the "
                      "principal point); by default the intrinsics are kept exactly."),
)

triangulation_options = option_group(
    "triangulation",
    click.option("--mapper", multiple=True, metavar="KEY=VALUE", callback=_print_triangulator_options,
                 help="Set an option of the triangulator's pycolmap IncrementalPipelineOptions, e.g. "
                      "triangulation.ignore_two_view_tracks=false (repeatable; `--mapper help` lists them)."),
    refine_option, verification_option, seed_option,
)


def triangulate_config(extraction: OptionValues, matching: OptionValues, pairing: OptionValues,
                       camera: OptionValues, triangulation: OptionValues, conf: str | None) -> TriangulateConfig:
    """The TriangulateConfig of the option groups, the --conf preset ``conf`` applied to the defaulted options."""
    from sekd_sfm.pipelines.reconstruct import DEFAULT_RESIZE_MAX
    from sekd_sfm.pipelines.triangulate import TriangulateConfig

    # resize_max: as reconstruct (RECONSTRUCT_RESIZE_HELP)
    features, matcher, _ = feature_and_match_configs(extraction, matching, conf=conf,
                                                     defaults={"resize_max": DEFAULT_RESIZE_MAX})
    config = TriangulateConfig(
        features=features, matching=matcher, pairs=pairing["pair_source"], num_neighbors=pairing["num_neighbors"],
        max_angle_deg=pairing["max_angle"], camera_model=camera["camera_model"], camera_params=camera["camera_params"],
        refine_intrinsics=camera["refine_intrinsics"], mapper=list(triangulation["mapper"]),
        verification=list(triangulation["verification"]), seed=triangulation["seed"])
    config.refine.enabled = triangulation["refine"]
    if conf:
        config.file_names = output_names(conf, "pairs")
    return config


@click.command()
@click.argument("photos", type=click.Path(file_okay=False, path_type=Path))
@click.option("--poses", type=click.Path(path_type=Path), required=True,
              help="A COLMAP model folder (cameras, images[, points3D] .bin or .txt) or a poses file: one line "
                   "'NAME qw qx qy qz tx ty tz' per photo (world-to-camera, COLMAP's convention, as hloc writes).")
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output folder: model/, stats.json, features.h5, pairs.txt, matches.h5, database.db, colmap.log.")
@conf_option
@extraction_options(resize_help=RECONSTRUCT_RESIZE_HELP)
@num_threads_option
@pose_pairing_options
@matching_options
@pose_camera_options
@triangulation_options
@execution_options
def triangulate(photos: Path, poses: Path, output: Path, conf: str | None, extraction: OptionValues,
                num_threads: int | None, pairing: OptionValues, matching: OptionValues, camera: OptionValues,
                triangulation: OptionValues, execution: OptionValues) -> None:
    """Triangulate 3D points from the photos below PHOTOS with known camera poses, which stay exactly as given.

    \b
    Extracts (reconstruct's defaults: 1600 px long side), pairs the photos from the poses
    (--pairs), matches, moves keypoints to where their matches agree (--no-refine skips it),
    verifies the matches geometrically and triangulates with COLMAP's point triangulator,
    every pose and (unless --refine-intrinsics) every intrinsic held fixed. OUTPUT/model
    (COLMAP binary) holds the given poses bit for bit, with the given image and camera ids
    when --poses is a model, and the new points; OUTPUT/stats.json the points, track lengths
    and reprojection error. Photos named in POSES but not below PHOTOS (and the reverse) are
    listed in a warning and left out. Features and matches of an earlier run with the same
    settings are reused; Ctrl-C stops, rerun to continue.

    \b
    Examples:
      sekd triangulate photos/ --poses survey/sparse/0 -o out/
      sekd triangulate photos/ --poses poses.txt --camera-model PINHOLE --camera-params 2759.5,2764.2,1521.2,1007.3 -o out/
      sekd triangulate photos/ --poses poses.txt -o out/ --pairs retrieval --num-neighbors 30
    """
    from sekd_sfm.pipelines.triangulate import format_triangulation
    from sekd_sfm.pipelines.triangulate import triangulate as run

    config = triangulate_config(extraction, matching, pairing, camera, triangulation, conf)
    run(photos, poses, output, config, overwrite=execution["overwrite"], num_threads=num_threads,
        progress=not execution["no_progress"], executor=execution["executor"], ray_options=ray_options(execution))
    click.echo(format_triangulation(json.loads((output / "stats.json").read_text())))


@click.command("triangulate")
@click.argument("scene", default="fountain-P11")
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("bench-triangulate"),
              show_default=True, help="Folder for results.json, results.md and the work folders.")
@conf_option
@extraction_options(resize_help=RECONSTRUCT_RESIZE_HELP)
@num_threads_option
@matching_options
@triangulation_options
def triangulate_benchmark(scene: str, output: Path, conf: str | None, extraction: OptionValues,
                          num_threads: int | None, matching: OptionValues, triangulation: OptionValues) -> None:
    """Triangulate SCENE from its ground-truth poses and intrinsics; compare with its free reconstruction.

    \b
    SCENE: a folder with images/ and gt_dense_cameras/ (Strecha .camera files), or a name under
    $SEKD_SHARED/data/sfm (fountain-P11). The ground truth is written as a COLMAP model and as
    a poses file in OUTPUT; `sekd triangulate` runs on each, then `sekd reconstruct` on the same
    photos with the same settings (and the same features and matches). Reports points,
    observations, mean and median track length, mean reprojection error, and the free model's
    pose errors against the ground truth. Writes results.json and results.md.

    \b
    Example:
      sekd bench maps triangulate fountain-P11 -o /tmp/bench-triangulate
    """
    from sekd_sfm.bench.maps.triangulate import (
        benchmark_triangulation,
        triangulation_markdown,
    )

    pairing = OptionValues({"pair_source": "covisibility", "num_neighbors": DEFAULT_NEIGHBORS,
                            "max_angle": DEFAULT_MAX_ANGLE_DEG})
    camera = OptionValues({"camera_model": "SIMPLE_RADIAL", "camera_params": None, "refine_intrinsics": False})
    config = triangulate_config(extraction, matching, pairing, camera, triangulation, conf)
    report = benchmark_triangulation(scene, output, config, num_threads=num_threads)
    click.echo(triangulation_markdown(report))
