"""Options shared by several commands, declared once."""
from __future__ import annotations

import click

from sekd_sfm.features import FEATURE_TYPES
from sekd_sfm.runtime import DEVICES, PRECISIONS


def weights_option(f):
    return click.option(
        "--weights", type=click.Path(dir_okay=False), default=None,
        help="SEKD checkpoint (.pth): the authors' format or ours. Default: the model embedded in the package.",
    )(f)


def runtime_options(f):
    f = click.option("--num-threads", type=int, default=None, help="CPU threads (default: all available cores).")(f)
    f = click.option("--device", type=click.Choice(DEVICES), default="auto", show_default=True,
                     help="auto uses a CUDA GPU when one is present.")(f)
    f = click.option("--precision", type=click.Choice(PRECISIONS), default="auto", show_default=True,
                     help="auto = bf16 on CPUs with native bf16 (AVX512-BF16/AMX, ~4x faster), else fp32.")(f)
    return f


def feature_options(f):
    """--feature and the detection options of `extract`."""
    options = [
        click.option("--feature", type=click.Choice(FEATURE_TYPES), default="sekd", show_default=True,
                     help="SEKD, or a classic OpenCV feature written in the same file format."),
        click.option("--max-keypoints", type=click.IntRange(min=1), default=2000, show_default=True,
                     help="Keep the strongest N keypoints per image."),
        click.option("--threshold", type=float, default=0.4, show_default=True,
                     help="SEKD: minimum keypoint probability (the authors used 0.4 for benchmarks)."),
        click.option("--nms-radius", type=click.IntRange(min=0), default=4, show_default=True,
                     help="SEKD: non-maximum suppression radius in pixels."),
        click.option("--resize-max", type=click.IntRange(min=16), default=None,
                     help="Downscale images so the long side is at most N px; keypoints are mapped back to original pixels."),
        click.option("--multi-scale", is_flag=True, help="SEKD: also detect on /2, /4, ... downscaled images."),
        click.option("--subpixel", is_flag=True, help="SEKD: refine keypoints to sub-pixel accuracy (quadratic fit)."),
    ]
    for option in reversed(options):
        f = option(f)
    return f
