"""``sekd bench sfm`` (our pipeline vs pycolmap's SIFT on a scene with ground truth) and ``sekd bench ratios``."""
from __future__ import annotations

from pathlib import Path

import click

from sekd_sfm.confs import build_configs
from sekd_sfm.features import FEATURE_TYPES

from .match import matching_options
from .options import (
    OptionValues,
    extraction_options,
    num_threads_option,
    weights_option,
)
from .reconstruct import camera_options, mapping_options, reconstruct_config


@click.command()
@click.argument("scene")
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Folder for results.json, results.md and the work files. Default: bench-sfm-SCENE.")
@extraction_options(max_pixels=False)
@num_threads_option
@matching_options
@camera_options
@mapping_options(verification=False)
@click.option("--no-baseline", is_flag=True, help="Skip pycolmap's SIFT pipeline.")
@click.option("-m", "--method", "methods", multiple=True,
              help="Run our pipeline once per method ([LABEL=]FEATURE[:WEIGHTS], as `bench homography`), "
                   "instead of once with --feature/--weights.")
def sfm(scene: str, output: Path | None, extraction: OptionValues, num_threads: int | None, matching: OptionValues,
        camera: OptionValues, mapping: OptionValues, no_baseline: bool, methods: tuple[str, ...]) -> None:
    """Reconstruct SCENE with our pipeline and with pycolmap's SIFT; compare with ground-truth cameras.

    \b
    SCENE is a folder with images/ and gt_dense_cameras/ (Strecha .camera files), or a name
    under $SEKD_SHARED/data/sfm (fountain-P11). Reports registered images, the median
    pairwise rotation and translation-direction errors against the ground truth, and wall
    time of both pipelines (from scratch, on the same images limited to --resize-max px;
    default 1600). Writes results.json and results.md.

    \b
    Example:
      sekd bench sfm fountain-P11 --weights ../shared/weights/sekd/sekd.pth
      sekd bench sfm fountain-P11 --feature sift --max-keypoints 8000
      sekd bench sfm fountain-P11 -m sift -m disk -m sekd:../shared/weights/sekd/sekd.pth
    """
    from sekd_sfm.bench.methods import available, parse_method, with_weights
    from sekd_sfm.bench.sfm import benchmark_sfm, sfm_markdown
    from sekd_sfm.stages.pairs import PairsConfig

    # Every pair, as the pycolmap baseline (exhaustive matching): the pipelines differ in features, not pairs.
    config, _ = reconstruct_config(extraction, matching, camera, mapping, pairs=PairsConfig(mode="exhaustive"))
    to_run = available([parse_method(m) for m in with_weights(methods, config.features.weights)])
    report = benchmark_sfm(scene, output or Path(f"bench-sfm-{Path(scene).name}"), config, baseline=not no_baseline,
                           num_threads=num_threads, methods=to_run)
    click.echo(sfm_markdown(report))


@click.command()
@click.argument("scene", default="fountain-P11")
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("bench-ratios"),
              show_default=True, help="Folder for the feature files, ratios.json and ratios.md.")
@click.option("--features", "feature_list", default=",".join(FEATURE_TYPES), show_default=True,
              help="Comma-separated feature types to measure (sekd needs --weights).")
@click.option("--max-keypoints", type=click.IntRange(min=1), default=4000, show_default=True)
@click.option("--resize-max", type=click.IntRange(min=16), default=1600, show_default=True)
@click.option("--max-gap", type=click.IntRange(min=1), default=4, show_default=True,
              help="Pairs (i, i+1) .. (i, i+GAP) of the scene's images in name order.")
@weights_option
@num_threads_option
def ratios(scene: str, output: Path, feature_list: str, max_keypoints: int, resize_max: int, max_gap: int,
           weights: str | None, num_threads: int | None) -> None:
    """Measure the ratio-test threshold per feature type on SCENE's ground truth (the matcher's defaults).

    \b
    For each feature type and each ratio in 0.60..1.00: matches and correct matches per
    pair (symmetric epipolar distance < 4 px under the ground-truth cameras) and their
    precision, for mutual nearest neighbours + ratio test and for the ratio test alone.
    The chosen ratio gives the most correct matches at a precision >= 0.9.

    \b
    Example:
      sekd bench ratios fountain-P11 --weights ../shared/weights/sekd/sekd.pth
    """
    from sekd_sfm.bench.sfm import benchmark_ratios, ratios_markdown

    base = build_configs({"max_keypoints": max_keypoints, "resize_max": resize_max, "weights": weights}).features
    features = [f.strip() for f in feature_list.split(",") if f.strip()]
    unknown = sorted(set(features) - set(FEATURE_TYPES))
    if unknown:
        raise click.BadParameter(f"unknown feature types {', '.join(unknown)}", param_hint="--features")
    report = benchmark_ratios(scene, output, features, base, max_gap=max_gap, num_threads=num_threads)
    click.echo(ratios_markdown(report))
