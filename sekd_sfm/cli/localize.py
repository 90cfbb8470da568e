"""``sekd localize``: new photos + a reconstruction folder -> their camera poses (hloc's format)."""
from __future__ import annotations

import json
from pathlib import Path

import click

from .options import executor_options, num_threads_option, weights_option


@click.command()
@click.argument("queries", type=click.Path(exists=True, path_type=Path))
@click.option("--reference", "-r", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output folder of `sekd reconstruct` (its model, features and global descriptors are reused, "
                   "never modified).")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Poses file to write (e.g. results.txt); its log results_log.json and work folder "
                   "results-localize/ go beside it.")
@click.option("--num-neighbors", "-k", type=click.IntRange(min=1), default=10, show_default=True,
              help="Reference images retrieved (and matched) per query.")
@click.option("--camera-model", default=None,
              help="COLMAP camera model of --camera-params, or of the estimated camera. Default: the reference's.")
@click.option("--camera-params", default=None,
              help="Known intrinsics of every query, comma-separated in COLMAP pixel coordinates (e.g. "
                   "\"f,cx,cy,k\" for SIMPLE_RADIAL). Default: the reference's camera for photos of the same camera "
                   "(size and EXIF), else a prior (EXIF) with the focal length estimated.")
@click.option("--max-error", type=click.FloatRange(min=0, min_open=True), default=12.0, show_default=True,
              help="RANSAC inlier threshold (pixels).")
@click.option("--min-inliers", type=click.IntRange(min=4), default=12, show_default=True,
              help="Fewest pose inliers for a query to count as localized.")
@click.option("--seed", type=int, default=0, show_default=True, help="RANSAC seed.")
@weights_option
@num_threads_option
@executor_options
@click.option("--overwrite", is_flag=True, help="Start again instead of keeping the queries an earlier run localized.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def localize(queries: Path, reference: Path, output: Path, num_neighbors: int, camera_model: str | None,
             camera_params: str | None, max_error: float, min_inliers: int, seed: int, weights: str | None,
             num_threads: int | None, overwrite: bool, no_progress: bool, executor: str, ray_options) -> None:
    """Localize new photos against a model made by `sekd reconstruct`: one camera pose per photo.

    \b
    QUERIES is a folder of photos, or a text file listing photo paths (one per line; relative
    to the list's folder). For each photo: features with the reference's settings, the
    --num-neighbors most similar reference images by its global descriptors (every registered
    image for a reference of at most 2K+1 photos without them), matches with the reference's
    settings, the model's 3D points of the matched keypoints, then an absolute pose by
    LO-RANSAC and refinement (pycolmap's estimate_and_refine_absolute_pose).

    \b
    OUTPUT gets one line per localized photo, hloc's format (world-to-camera, COLMAP's convention):
      NAME qw qx qy qz tx ty tz
    and OUTPUT's stem + _log.json per photo: retrieved images, matches, 2D-3D correspondences,
    inliers, camera used, or why it failed. Photos that fail are logged and skipped. A rerun
    keeps the photos already localized (same reference and settings); nothing in --reference
    is ever written. docs/localize.md has the details.

    \b
    Examples:
      sekd reconstruct photos/ -o out
      sekd localize new_photos/ --reference out -o out_loc/results.txt
      sekd localize list.txt -r out -o results.txt --camera-params 2759,1520,1006,0
      sekd localize /shared/new/ -r /shared/out -o /shared/loc/results.txt --executor ray
    """
    from sekd_sfm.pipelines.localize import LocalizeConfig, log_path
    from sekd_sfm.pipelines.localize import localize as run

    config = LocalizeConfig(num_neighbors=num_neighbors, camera_model=camera_model, camera_params=camera_params,
                            max_error_px=max_error, min_inliers=min_inliers, seed=seed)
    path = run(queries, reference, output, config, weights=weights, overwrite=overwrite, num_threads=num_threads,
               progress=not no_progress, executor=executor, ray_options=ray_options)
    summary = json.loads(log_path(path).read_text())["summary"]
    click.echo(f"{path}: {summary['localized']} of {summary['queries']} photos localized"
               + (f", {summary['failed']} failed (reasons in {log_path(path).name})" if summary["failed"] else ""))


@click.command("localize")
@click.argument("scenes", nargs=-1)
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("bench-maps-localize"),
              show_default=True, help="Folder for results.json, results.md and the work files.")
@click.option("--resize-max", type=click.IntRange(min=16), default=1600, show_default=True,
              help="Long side limit (px) of every pipeline's extraction.")
@click.option("--no-baseline", is_flag=True, help="Skip pycolmap's SIFT pipeline.")
@click.option("--seed", type=int, default=0, show_default=True)
@num_threads_option
def localize_benchmark(scenes: tuple[str, ...], output: Path, resize_max: int, no_baseline: bool, seed: int,
                       num_threads: int | None) -> None:
    """Hold out every third photo of each scene, build a reference of the rest, localize the held-out ones.

    \b
    SCENES are folders with images/ (and gt_dense_cameras/ for ground truth), or names under
    $SEKD_SHARED/data/sfm; default fountain-P11 and sacre_coeur. The held-out photos are
    names[2::3] of the sorted names. Both sekd (`reconstruct` + `localize`) and pycolmap's SIFT
    pipeline run on the same split. Errors after aligning each reference model to the known
    cameras (a similarity of the reference camera centres): localized / queries, median rotation
    error (deg), median position error (units of the known cameras, and % of the scene radius =
    median distance of the known camera centres to their centroid). A scene without ground truth
    is scored against each method's reconstruction of all its photos (pseudo ground truth).
    Writes results.json (with the run's record) and results.md.

    \b
    Example:
      sekd bench maps localize fountain-P11 sacre_coeur -o bench-localize
    """
    from sekd_sfm.bench.maps.localize import benchmark_localize, markdown

    report = benchmark_localize(output, list(scenes) or ["fountain-P11", "sacre_coeur"], resize_max,
                                sift=not no_baseline, seed=seed, num_threads=num_threads)
    click.echo(markdown(report))
