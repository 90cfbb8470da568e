"""``sekd extract``: images -> features.h5."""
from __future__ import annotations

from pathlib import Path

import click

from sekd_sfm.extract import extract_features
from sekd_sfm.features import FeatureConfig
from sekd_sfm.inference import SEKDConfig

from .options import feature_options, runtime_options, weights_option


@click.command()
@click.argument("images", type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Feature file to write. Default: IMAGES/../features-FEATURE.h5 beside the image folder.")
@feature_options
@weights_option
@runtime_options
@click.option("--overwrite", is_flag=True, help="Replace an existing output file instead of resuming it.")
@click.option("--strict", is_flag=True, help="Stop at the first unreadable image instead of skipping it.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def extract(images: Path, output: Path | None, feature, max_keypoints, threshold, nms_radius, resize_max,
            multi_scale, subpixel, weights, num_threads, device, precision, overwrite, strict, no_progress) -> None:
    """Detect and describe keypoints of every image below IMAGES into one HDF5 file.

    \b
    Images are found recursively (jpg, jpeg, png, ppm, pgm, tif, bmp; any case); each is
    stored under its path relative to IMAGES. Keypoints are in original-image pixels
    (OpenCV convention: integer = pixel centre). EXIF orientation is not applied, as in COLMAP.
    An interrupted run resumes where it stopped; unreadable images are skipped with a warning.

    \b
    Examples:
      sekd extract photos/ -o out/features.h5 --weights sekd.pth
      sekd extract photos/ -o out/sift.h5 --feature sift --max-keypoints 4000
    """
    if output is None:
        output = images.parent / f"features-{feature}.h5"
    sekd = SEKDConfig(max_keypoints=max_keypoints, threshold=threshold, nms_radius=nms_radius, subpixel=subpixel,
                      multi_scale=multi_scale, precision=precision, device=device)
    config = FeatureConfig(feature=feature, max_keypoints=max_keypoints, resize_max=resize_max, sekd=sekd,
                           weights=weights)
    path = extract_features(images, output, config, overwrite=overwrite, strict=strict, num_threads=num_threads,
                            progress=not no_progress)
    click.echo(str(path))
