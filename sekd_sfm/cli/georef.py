"""``sekd bench maps georef``: camera-centre error of GPS-georeferenced models against the GPS noise."""
from __future__ import annotations

from pathlib import Path

import click

from .options import num_threads_option


@click.command("georef")
@click.argument("scenes", nargs=-1)
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("bench-georef"),
              show_default=True, help="Folder for the GPS copies, the reconstructions, results.json and results.md.")
@click.option("--noise", "noise_m", type=click.FloatRange(min=0), multiple=True,
              help="GPS noise levels: sigma in metres per axis (repeatable). Default: 0, 0.1, 0.5, 2, 5.")
@click.option("--repeats", type=click.IntRange(min=0), default=20, show_default=True,
              help="Further noise draws aligned to each level's model (alignment only, no reconstruction).")
@click.option("--resize-max", type=click.IntRange(min=16), default=1600, show_default=True,
              help="Long side of the photos for the reconstruction, in pixels.")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seed of the scene's rotation, the GPS noise, RANSAC and the mapper.")
@num_threads_option
def georef_benchmark(scenes: tuple[str, ...], output: Path, noise_m: tuple[float, ...], repeats: int,
                     resize_max: int, seed: int, num_threads: int | None) -> None:
    """Write noisy EXIF GPS into copies of SCENES, reconstruct with --gps auto, measure the camera centres.

    \b
    SCENES (default fountain-P11) are folders with images/ and gt_dense_cameras/ (Strecha .camera
    files, metres; a `sekd bench scale` scene folder works), or names under $SEKD_SHARED/data/sfm.
    The true camera centres are rotated at random about their centroid, placed at 46.5 N 6.6 E,
    400 m, and perturbed by Gaussian noise of each --noise sigma (metres per axis); each level is
    reconstructed and its georeferenced camera centres compared with the true ones in metres.
    Writes OUTPUT/results.json and results.md (docs/georef.md explains the columns).

    \b
    Examples:
      sekd bench maps georef -o bench-georef
      sekd bench maps georef fountain-P11 scale/n250/scene --noise 2 --noise 5 -o bench-georef
    """
    from sekd_sfm.bench.maps.georef import (
        DEFAULT_NOISE_M,
        benchmark_georef,
        georef_markdown,
    )
    from sekd_sfm.features import FeatureConfig
    from sekd_sfm.pipelines.reconstruct import ReconstructConfig

    config = ReconstructConfig(features=FeatureConfig(resize_max=resize_max), seed=seed)
    report = benchmark_georef(list(scenes) or ["fountain-P11"], output, config, noise_m=noise_m or DEFAULT_NOISE_M,
                              repeats=repeats, seed=seed, num_threads=num_threads)
    click.echo(georef_markdown(report))
