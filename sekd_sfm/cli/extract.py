"""``sekd extract``: images -> features.h5."""
from __future__ import annotations

from pathlib import Path

import click

from sekd_sfm.confs import output_names
from sekd_sfm.files.video import list_videos
from sekd_sfm.stages.extract import extract_features

from .options import (
    OptionValues,
    executor_options,
    extraction_options,
    num_threads_option,
    video_options,
)
from .presets import conf_option, feature_and_match_configs


@click.command()
@click.argument("images", type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Feature file to write. Default: IMAGES/../features-FEATURE.h5 beside the image folder "
                   "(feats-CONF.h5 with --conf).")
@conf_option
@extraction_options(masks=True)
@video_options
@num_threads_option
@executor_options
@click.option("--overwrite", is_flag=True, help="Replace an existing output file instead of resuming it.")
@click.option("--strict", is_flag=True, help="Stop at the first unreadable image instead of skipping it.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def extract(images: Path, output: Path | None, conf: str | None, extraction: OptionValues, video: OptionValues,
            num_threads: int | None, overwrite: bool, strict: bool, no_progress: bool, executor: str, ray_options) -> None:
    """Detect and describe keypoints of every image below IMAGES into one HDF5 file.

    \b
    Images are found recursively (jpg, jpeg, png, ppm, pgm, tif, bmp; any case); each is
    stored under its path relative to IMAGES. Keypoints are in original-image pixels
    (OpenCV convention: integer = pixel centre). EXIF orientation is not applied, as in COLMAP.
    An interrupted run resumes where it stopped; unreadable images are skipped with a warning.
    --masks MASKS: photo NAME's mask is MASKS/NAME.png (COLMAP's convention), zero = ignore;
    keypoints there are dropped before the --max-keypoints strongest are kept (docs/masks.md).
    IMAGES may be a video or hold videos: their keyframes (--keyframes) are written to an
    images/ folder beside OUTPUT, the folder's photos linked there, and that folder extracted.

    \b
    Examples:
      sekd extract photos/ -o out/features.h5 --weights sekd.pth
      sekd extract photos/ -o out/sift.h5 --feature sift --max-keypoints 4000
      sekd extract photos/ --conf sekd-n4000-r1600           # preset; writes feats-sekd-n4000-r1600.h5
      sekd extract photos/ -o out/features.h5 --masks masks/  # masks/a.jpg.png ignores parts of photos/a.jpg
      sekd extract /shared/photos/ -o /shared/out/features.h5 --executor ray --ray-address head:6379
      sekd extract walk.mp4 -o out/features.h5                # keyframes to out/images/walk/, then extracted
    """
    config = feature_and_match_configs(extraction, conf=conf).features
    if output is None:
        output = images.parent / (output_names(conf)[0] if conf else f"features-{config.feature}.h5")
    if list_videos(images):
        from sekd_sfm.stages.keyframes import KeyframeConfig, prepare_captures

        root = output.parent / "images"
        prepare_captures(images, root, KeyframeConfig(count=video["keyframes"], max_fps=video["max_fps"]),
                         progress=not no_progress)
        images = root
    path = extract_features(images, output, config, overwrite=overwrite, strict=strict, num_threads=num_threads,
                            progress=not no_progress, executor=executor, ray_options=ray_options,
                            masks=extraction["masks"])
    click.echo(str(path))
