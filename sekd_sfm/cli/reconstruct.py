"""``sekd reconstruct`` (images -> COLMAP model) and ``sekd relpose`` (two images -> R, t).

The SfM commands (these and ``sekd bench sfm``) take their options in groups, each passed to the
command as one argument (``options.option_group``): extraction, pairing, matching, camera,
mapping, execution. ``reconstruct_config`` and ``run_options`` turn the groups into the typed
settings of ``sekd_sfm.pipelines.reconstruct``: the one place where an option becomes a setting.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import click

from sekd_sfm.confs import output_names
from sekd_sfm.stages.database import (
    CAMERA_MODES,
    PRINCIPAL_POINT_MIN_IMAGES,
    PRINCIPAL_POINT_MODES,
    CameraConfig,
)
from sekd_sfm.stages.pairs import PairsConfig

from .adapt import adapt_in_line, adapt_option
from .match import matching_options, pairing_options, pairs_config
from .options import (
    Decorator,
    OptionValues,
    executor_declarations,
    extraction_options,
    num_threads_option,
    option_group,
    ray_options,
    video_options,
)
from .presets import conf_option, feature_and_match_configs

if TYPE_CHECKING:  # imported where used: the CLI starts without torch and pycolmap
    from sekd_sfm.pipelines.reconstruct import ReconstructConfig, RunOptions

#: reconstruct's own words on --resize-max: its default differs from extract's (full size).
RECONSTRUCT_RESIZE_HELP = (
    "Downscale images so the long side is at most N px (keypoints are mapped back to original "
    "pixels). Default 1600, as hloc: full-size photos cost far more to extract for little "
    "gain in pose accuracy; give e.g. 100000 for full size.")

camera_options = option_group(
    "camera",
    click.option("--camera-model", default="SIMPLE_RADIAL", show_default=True,
                 help="COLMAP camera model (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, ...). "
                      "2:1 photos are 360-degree panoramas whatever it says; EQUIRECTANGULAR: every photo is one."),
    click.option("--camera-mode", type=click.Choice(list(CAMERA_MODES)), default="auto", show_default=True,
                 help="Cameras shared by: auto (same size and EXIF), single (all images), per-folder, per-image."),
    click.option("--camera-params", default=None,
                 help="Known intrinsics as comma-separated numbers in the model's order, e.g. "
                      "'f,cx,cy,k' for SIMPLE_RADIAL, in COLMAP pixel coordinates (pixel centre at +0.5)."),
    click.option("--principal-point", type=click.Choice(PRINCIPAL_POINT_MODES), default="auto", show_default=True,
                 help="Bundle adjustment refines each camera's principal point from the start of mapping (refine) "
                      "or keeps it at the image centre (fixed, COLMAP's default). auto: map with it fixed, refine it "
                      "in one more adjustment and keep that only where the photos determine it (it moves at least "
                      "4 standard deviations and lowers the reprojection error by 0.5%); tried when every camera "
                      f"has at least {PRINCIPAL_POINT_MIN_IMAGES} photos and --camera-params is not given. "
                      "stats.json says why (principal_point_decision)."),
)


def camera_config(camera: OptionValues) -> CameraConfig:
    """The CameraConfig of the group ``camera``."""
    return CameraConfig(model=camera["camera_model"], mode=camera["camera_mode"], params=camera["camera_params"],
                        principal_point=camera["principal_point"])


def _print_option_help(ctx: click.Context, param: click.Parameter, values) -> tuple:
    """``--mapper help`` / ``--verification help``: list the settable options and their defaults."""
    if "help" not in values:
        return values
    from sekd_sfm.stages.colmap import option_values, require_pycolmap

    pycolmap = require_pycolmap()
    if param.name == "mapper":  # the options of the chosen mapper (--mapper-type is eager: already parsed)
        from sekd_sfm.stages.mapping import default_options

        kind = ctx.params.get("mapper_type") or "auto"
        if kind == "auto":
            click.echo("# --mapper-type auto: these options up to 250 photos (incremental); above, those of "
                       "`--mapper-type hierarchical --mapper help`")
        options = default_options("incremental" if kind == "auto" else kind)
    else:
        options = pycolmap.TwoViewGeometryOptions()
    for name, value in option_values(options):
        click.echo(f"{name} = {value}")
    ctx.exit(0)


mapper_option = click.option(
    "--mapper", multiple=True, metavar="KEY=VALUE", callback=_print_option_help,
    help="Set an option of the chosen mapper's pycolmap options (IncrementalPipelineOptions, "
         "GlobalPipelineOptions or HierarchicalPipelineOptions), e.g. mapper.init_min_tri_angle=8 "
         "(repeatable; `--mapper-type global --mapper help` lists them). An option the chosen mapper lacks "
         "is an error before any work. The mapper runs on one thread, the only way COLMAP repeats a model "
         "for a --seed; num_threads=-1 uses all cores (faster on large scenes).")
mapper_type_option = click.option(
    "--mapper-type", type=click.Choice(("auto", "incremental", "global", "hierarchical")), default="auto",
    show_default=True, is_eager=True,  # eager: `--mapper help` lists the options of this type
    help="auto: incremental up to 250 photos, hierarchical above; incremental: COLMAP's mapper, one image at "
         "a time; global: GLOMAP (rotation averaging + global positioning, all cameras at once); "
         "hierarchical: clusters of up to 125 photos mapped incrementally, one per worker process (--num-threads "
         "caps them) or Ray worker (--executor ray), merged, then one global bundle adjustment (mapping time "
         "grows linearly with the photos).")
refine_option = click.option(
    "--refine/--no-refine", default=True, show_default=True,
    help="Move each keypoint to where its matches' image patches agree (sub-pixel patch alignment, then one "
         "least-squares fit per keypoint; written to features-refined.h5) before the database. Learned "
         "keypoints sit ~0.25 px off; refined, long walks drift less. --no-refine maps the detections as they are.")
final_filter_option = click.option(
    "--final-filter/--no-final-filter", default=True, show_default=True,
    help="After mapping, drop the observations whose reprojection error exceeds max(0.5 px, 3 robust standard "
         "deviations of the model's errors) and adjust the model again (up to 3 rounds): a wrong match within "
         "COLMAP's 4 px still bends a model whose keypoints are good to a tenth of a pixel. Pose AUC@5 on a "
         "generated 250-photo walk 0.972 -> 0.993; stats.json final_filter says what it removed.")
seed_option = click.option("--seed", type=int, default=0, show_default=True,
                           help="Random seed of RANSAC and the mapper.")

verification_option = click.option(
    "--verification", multiple=True, metavar="KEY=VALUE", callback=_print_option_help,
    help="Set an option of pycolmap's TwoViewGeometryOptions, e.g. ransac.max_error=2 "
         "(repeatable; `--verification help` lists them).")


view_graph_option = click.option(
    "--view-graph/--no-view-graph", default=False, show_default=True,
    help="Before mapping, drop the verified pairs whose relative rotation disagrees with the rest of the view graph "
         "(robust rotation averaging; focal lengths first estimated from the pairs where EXIF gives none, the check "
         "skipped where they cannot be): look-alike matches on repeated structure pass verification and can fold "
         "or split a model. Experimental, off by default: on fountain-P11 it drops exactly the wrong pairs, on a "
         "generated walk also right ones, and no model measured got better. stats.json view_graph lists the drops.")


chance_option = click.option(
    "--chance-check/--no-chance-check", default=True, show_default=True,
    help="After verification, drop the verified pairs whose inliers RANSAC also reaches on their matches shuffled "
         "(chance: learned features keep more matches between unrelated photos than SIFT, and such pairs split or "
         "fold models). stats.json chance lists the drops.")


capture_order_option = click.option(
    "--capture-order/--no-capture-order", default=True, show_default=True,
    help="When the photos' names give an order in which nearly every photo is verified with the next, and shares "
         "no less with it than with photos far apart (a walk, a turntable, a video's keyframes; not photo-site ids): "
         "map in that order, first the photos at most 3 apart (a chain), then drop "
         "the farther pairs that do not fit its poses and triangulate the rest onto them. Look-alikes far apart in a "
         "capture then cannot fold the model. Above 250 photos all pairs are mapped first and only a folded or split "
         "model is mapped again in order. Photos in no order are mapped all at once (a folded model is "
         "reported). stats.json sequence lists the drops.")


def mapping_options(*, verification: bool = True) -> Decorator:
    """The group ``mapping``: --mapper-type, --mapper, --refine, --verification (if ``verification``) and --seed,
    how matches become a model."""
    declarations = [mapper_type_option, mapper_option, refine_option, chance_option, view_graph_option,
                    capture_order_option, final_filter_option]
    declarations += [verification_option] if verification else []
    return option_group("mapping", *declarations, seed_option)


execution_options = option_group(
    "execution",
    click.option("--overwrite", is_flag=True, help="Recompute features and matches instead of reusing them."),
    click.option("--no-progress", is_flag=True, help="No progress bars."),
    executor_declarations,
)


def reconstruct_config(extraction: OptionValues, matching: OptionValues, camera: OptionValues, mapping: OptionValues,
                       *, pairs: PairsConfig, conf: str | None = None) -> tuple[ReconstructConfig, frozenset[str]]:
    """The ReconstructConfig of the option groups of `reconstruct` and `bench sfm`, the --conf preset ``conf``
    applied to the options left at their defaults, and the fields of its ``features`` and ``matching`` that the
    user set (explicitly or through ``conf``; ``confs.build_configs``)."""
    from sekd_sfm.pipelines.reconstruct import DEFAULT_RESIZE_MAX, ReconstructConfig

    # resize_max: see RECONSTRUCT_RESIZE_HELP
    features, matcher, given = feature_and_match_configs(extraction, matching, conf=conf,
                                                         defaults={"resize_max": DEFAULT_RESIZE_MAX})
    masks = extraction.get("masks")  # an absolute path: stats.json records it for later commands (export)
    config = ReconstructConfig(features=features, pairs=pairs, matching=matcher, camera=camera_config(camera),
                               mapper_type=mapping["mapper_type"], mapper=list(mapping["mapper"]),
                               verification=list(mapping.get("verification", ())), seed=mapping["seed"],
                               masks=str(Path(masks).resolve()) if masks else None)
    config.refine.enabled = mapping["refine"]
    config.final_filter = mapping.get("final_filter", True)
    config.chance.enabled = mapping.get("chance_check", True)
    config.view_graph.enabled = mapping.get("view_graph", False)
    config.sequence.enabled = mapping.get("capture_order", True)
    if conf:  # hloc-style names, so the files of several presets coexist in OUTPUT
        config.file_names = output_names(conf, "pairs")
    return config, given


def run_options(execution: OptionValues, num_threads: int | None) -> RunOptions:
    """The RunOptions of the group ``execution`` and --num-threads."""
    from sekd_sfm.pipelines.reconstruct import RunOptions

    return RunOptions(overwrite=execution["overwrite"], num_threads=num_threads,
                      progress=not execution["no_progress"], executor=execution["executor"],
                      ray_options=ray_options(execution))


@click.command()
@click.argument("images", type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output folder: features.h5, pairs.txt, matches.h5, database.db, model/, stats.json, colmap.log.")
@conf_option
@extraction_options(resize_help=RECONSTRUCT_RESIZE_HELP, masks=True)
@video_options
@num_threads_option
@pairing_options
@matching_options
@camera_options
@mapping_options()
@adapt_option
@click.option("--features", "features_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Use this existing feature file (sekd's or hloc's) instead of extracting; read in place.")
@click.option("--matches", "matches_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Use this existing match file instead of pairing and matching (needs --features); its pairs "
                   "are those of --pairs-file when given, else all it holds.")
@click.option("--gps", type=click.Choice(("auto", "off", "pairs", "align")), default="auto", show_default=True,
              help="Use the photos' EXIF GPS: pairs (each photo also matched with its 10 nearest photos within "
                   "100 m), align (the model moved to a local east-north-up frame in metres about the photos' mean "
                   "position, a robust similarity; OUTPUT/georef.json gives the origin and residuals), auto (both "
                   "when at least 3 photos carry GPS), off. docs/georef.md.")
@click.option("--rig-config", type=click.Path(dir_okay=False, exists=True, path_type=Path), default=None,
              help="Cameras fixed together (COLMAP's rig_configurator JSON: each camera's image_prefix, one "
                   "ref_sensor, optional cam_from_rig_rotation [w,x,y,z] / cam_from_rig_translation): the photos "
                   "with one file name under each prefix are one instant; given poses are kept, others estimated. "
                   "docs/captures.md.")
@click.option("--extend", is_flag=True,
              help="OUTPUT holds a model: add the photos of IMAGES it lacks (extracted, paired, matched and "
                   "registered with the settings the model was built with) without moving its cameras or changing "
                   "their ids; new points are triangulated, model/ replaced atomically. docs/extend.md.")
@click.option("--extend-refine", is_flag=True,
              help="With --extend: let the earlier cameras' poses and intrinsics move too (the mapper's bundle "
                   "adjustments refine them with the new ones); by default they stay bitwise as they were.")
@execution_options
def reconstruct(images: Path, output: Path, conf: str | None, extraction: OptionValues, video: OptionValues,
                num_threads: int | None, pairing: OptionValues, matching: OptionValues, camera: OptionValues, mapping: OptionValues,
                adapt: bool, features_file: Path | None, matches_file: Path | None, gps: str, rig_config: Path | None,
                extend: bool, extend_refine: bool, execution: OptionValues) -> None:
    """Reconstruct cameras and 3D points from the images below IMAGES (COLMAP SfM through pycolmap).

    IMAGES is a folder of photos, a video, or a folder of videos and photos: each video's
    keyframes (--keyframes) become photos in OUTPUT/images, one camera per video, paired in
    sequence and by retrieval (the loops a walk closes). 360-degree panoramas (2:1 photos)
    are mapped as rigs of perspective views (OUTPUT/views; poses in OUTPUT/panoramas.txt);
    --rig-config maps photos of cameras fixed together as one rig.

    \b
    Runs extract, pairs and match when their outputs are missing in OUTPUT (reusing them
    when present and made with the same settings; --features/--matches use existing files
    instead), moves each keypoint to where its matches' patches agree (--no-refine skips
    it), imports everything into a COLMAP database, verifies the matches geometrically and
    maps (--mapper-type). Images are reduced to 1600 px on the long side unless
    --resize-max says otherwise. --masks MASKS ignores the pixels of photo NAME where
    MASKS/NAME.png is zero (COLMAP's convention; recorded in stats.json, docs/masks.md).
    Photos of the same size, EXIF make, model and focal length share a camera (--camera-mode
    auto). The largest model is written to OUTPUT/model (COLMAP binary); if the photos
    split into several models, the others go to OUTPUT/models/1, 2, ... and the split is
    explained. Statistics (with the photos in no model and their match counts) go to
    OUTPUT/stats.json, COLMAP's log to OUTPUT/colmap.log.
    If no model comes out, the reason and the match statistics behind it are printed, the
    database is kept and the exit code is 1. Ctrl-C stops at once; rerun to continue.

    \b
    Examples:
      sekd reconstruct photos/ -o out/
      sekd reconstruct photos/ -o out/ --conf sekd-fast           # a preset (`sekd confs` lists them)
      sekd reconstruct photos/ -o out/ --mapper-type global
      sekd reconstruct photos/ -o out/ --masks masks/             # masks/a.jpg.png: zero = ignore in photos/a.jpg
      sekd reconstruct photos/ -o out/ --gps off                  # ignore EXIF GPS (default: use it when present)
      sekd reconstruct photos/ -o out/ --feature sift --camera-mode single --mapper mapper.init_min_tri_angle=8
      sekd reconstruct photos/ -o out/ --features hloc/feats.h5 --matches hloc/matches.h5 --pairs-file hloc/pairs.txt
      sekd reconstruct photos/ -o out/ --extend                   # add photos copied into photos/ since the run
      sekd reconstruct walk.mp4 -o out/                           # a video: its keyframes mapped
      sekd reconstruct clips/ -o out/ --keyframes 80              # 80 keyframes from each video in clips/
      sekd reconstruct rig/ -o out/ --rig-config rig.json         # rig/cam0/0001.jpg, rig/cam1/0001.jpg, ...
    """
    from sekd_sfm.pipelines.reconstruct import ReconstructionError
    from sekd_sfm.pipelines.reconstruct import reconstruct as run

    config, given = reconstruct_config(extraction, matching, camera, mapping, pairs=pairs_config(**pairing.values),
                                       conf=conf)
    # What --extend checks, of the configuration the options made (before --gps and --adapt's weights)
    extension = _extend_options(config, given, pairing, extend_refine) if extend else None
    config.gps.mode = gps
    config.rig = str(rig_config.resolve()) if rig_config else None
    config.keyframes.count, config.keyframes.max_fps = video["keyframes"], video["max_fps"]
    options = run_options(execution, num_threads)
    if adapt:  # new weights
        adapt_in_line(images, output, config.features, options.num_threads, options.progress)
    if extend_refine and not extend:
        raise click.UsageError("--extend-refine goes with --extend")
    try:
        run(images, output, config, features=features_file, matches=matches_file, options=options, extend=extension)
    except ReconstructionError:
        _echo_summary(output)
        raise
    _echo_summary(output)


def _extend_options(config: ReconstructConfig, given: frozenset[str], pairing: OptionValues, refine: bool):
    """``--extend``'s settings: the configuration fields the user set, to be checked against the model's record.

    Those of ``features`` and ``matching`` are ``given`` (``confs.build_configs``: the options given explicitly
    and the --conf preset, where they change a field); every other field is set by one option of its own, which
    left out takes the field's default (the options declare the configuration's defaults), and counts where it
    differs from that default (--conf: the file names).
    """
    from dataclasses import asdict

    from sekd_sfm.pipelines.extend import ExtendOptions, flatten
    from sekd_sfm.pipelines.reconstruct import ReconstructConfig

    fields, defaults = flatten(asdict(config)), flatten(asdict(ReconstructConfig()))
    chosen = {f: v for f, v in fields.items()
              if (f in given if f.startswith(("features.", "matching.")) else v != defaults[f])}
    if pairing["num_neighbors"] is not None:  # --num-neighbors itself is not checked (the default K that
        chosen.pop("pairs.num_neighbors", None)  # --pairs retrieval adds to a --pairs-file is)
    return ExtendOptions(refine=refine, given=chosen)


def _echo_summary(output: Path) -> None:
    """Print the run's summary from OUTPUT/stats.json (written on success and on a failure to explain)."""
    from sekd_sfm.pipelines.report import format_summary

    stats = output / "stats.json"
    if stats.is_file():
        click.echo(format_summary(json.loads(stats.read_text())))


@click.command()
@click.argument("image0", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("image1", type=click.Path(dir_okay=False, path_type=Path))
@conf_option
@extraction_options(max_pixels=False)
@num_threads_option
@matching_options
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
def relpose(image0: Path, image1: Path, conf: str | None, extraction: OptionValues, num_threads: int | None,
            matching: OptionValues, camera_model: str, camera_params: str | None, max_error: float, seed: int,
            output: Path | None) -> None:
    """Relative pose of IMAGE1 with respect to IMAGE0, printed as JSON.

    \b
    R and t map camera-0 coordinates to camera-1 coordinates: x1 = R x0 + t, |t| = 1.
    Also reports the matches and RANSAC inliers, and where the focal length came from.

    \b
    Example:
      sekd relpose a.jpg b.jpg --feature sift --camera-model PINHOLE --camera-params 2759.5,2764.2,1521.2,1007.3
    """
    from sekd_sfm.pipelines.relpose import RelposeConfig, relative_pose
    from sekd_sfm.runtime import set_num_threads

    set_num_threads(num_threads)
    features, matcher, _ = feature_and_match_configs(extraction, matching, conf=conf)
    config = RelposeConfig(features=features, matching=matcher, camera_model=camera_model, camera_params=camera_params,
                           max_error=max_error, seed=seed)
    text = json.dumps(relative_pose(image0, image1, config), indent=2)
    if output:
        output.write_text(text + "\n")
    click.echo(text)
