"""``sekd extract``: images -> features.h5."""
from __future__ import annotations

from pathlib import Path

import click

from sekd_sfm.confs import output_names
from sekd_sfm.stages.extract import extract_features

from .options import (
    executor_options,
    feature_options,
    masks_option,
    max_pixels_option,
    runtime_options,
    weights_option,
)
from .presets import conf_option, configs_from_context, current_conf


@click.command()
@click.argument("images", type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Feature file to write. Default: IMAGES/../features-FEATURE.h5 beside the image folder "
                   "(feats-CONF.h5 with --conf).")
@conf_option
@feature_options
@max_pixels_option
@masks_option
@weights_option
@runtime_options
@executor_options
@click.option("--overwrite", is_flag=True, help="Replace an existing output file instead of resuming it.")
@click.option("--strict", is_flag=True, help="Stop at the first unreadable image instead of skipping it.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def extract(images: Path, output: Path | None, feature, max_keypoints, threshold, nms_radius, resize_max,
            multi_scale, subpixel, max_pixels, masks, weights, num_threads, device, precision, overwrite, strict,
            no_progress, executor, ray_options) -> None:
    """Detect and describe keypoints of every image below IMAGES into one HDF5 file.

    \b
    Images are found recursively (jpg, jpeg, png, ppm, pgm, tif, bmp; any case); each is
    stored under its path relative to IMAGES. Keypoints are in original-image pixels
    (OpenCV convention: integer = pixel centre). EXIF orientation is not applied, as in COLMAP.
    An interrupted run resumes where it stopped; unreadable images are skipped with a warning.
    --masks MASKS: photo NAME's mask is MASKS/NAME.png (COLMAP's convention), zero = ignore;
    keypoints there are dropped before the --max-keypoints strongest are kept (docs/masks.md).

    \b
    Examples:
      sekd extract photos/ -o out/features.h5 --weights sekd.pth
      sekd extract photos/ -o out/sift.h5 --feature sift --max-keypoints 4000
      sekd extract photos/ --conf sekd-n4000-r1600           # preset; writes feats-sekd-n4000-r1600.h5
      sekd extract photos/ -o out/features.h5 --masks masks/  # masks/a.jpg.png ignores parts of photos/a.jpg
      sekd extract /shared/photos/ -o /shared/out/features.h5 --executor ray --ray-address head:6379
    """
    config, _ = configs_from_context()
    if output is None:
        conf = current_conf()
        output = images.parent / (output_names(conf)[0] if conf else f"features-{config.feature}.h5")
    path = extract_features(images, output, config, overwrite=overwrite, strict=strict, num_threads=num_threads,
                            progress=not no_progress, executor=executor, ray_options=ray_options, masks=masks)
    click.echo(str(path))
