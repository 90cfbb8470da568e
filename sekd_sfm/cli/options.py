"""Options shared by several commands, declared once."""
from __future__ import annotations

import functools

import click

from sekd_sfm.execution.raycluster import EXECUTORS, MERGES, RayOptions
from sekd_sfm.features import FEATURE_TYPES
from sekd_sfm.files.images import DEFAULT_MAX_PIXELS
from sekd_sfm.runtime import DEVICES, PRECISIONS

MODEL_KEY = "sekd.model"


def _keep_model(ctx: click.Context, _param, value: str | None) -> str | None:
    ctx.meta[MODEL_KEY] = value  # eager: read by --weights' callback, which turns it into a path
    return value


def _weights_or_model(ctx: click.Context, _param, value: str | None) -> str | None:
    """``--weights PATH`` as given, else the file of ``--model NAME``; both at once is an error."""
    from sekd_sfm.errors import SekdError
    from sekd_sfm.model.weights import embedded_model_path

    model = ctx.meta.get(MODEL_KEY)
    if model is None:
        return value
    if value is not None:
        raise SekdError(f"--model {model} and --weights {value} both name the SEKD model; give one of them")
    feature = ctx.params.get("feature")
    if feature not in (None, "sekd"):
        raise SekdError(f"--model {model} selects a SEKD model; --feature {feature} does not use it (drop --model)")
    return str(embedded_model_path(model))


def weights_option(f):
    """--weights PATH and --model own|authors, passed on as ``weights`` (None: the default embedded model)."""
    from sekd_sfm.model.weights import DEFAULT_MODEL, EMBEDDED_MODELS

    f = click.option(
        "--weights", type=click.Path(dir_okay=False), default=None, callback=_weights_or_model,
        help="SEKD checkpoint (.pth): the authors' format or ours, e.g. one made by `sekd adapt`. "
             "Default: the --model embedded in the package.",
    )(f)
    return click.option(
        "--model", type=click.Choice(tuple(EMBEDDED_MODELS)), default=None, is_eager=True, expose_value=False,
        callback=_keep_model,
        help=f"Embedded SEKD model (default {DEFAULT_MODEL}): authors = the SEKD authors' release (MIT), "
             "own = trained by this project's `sekd evolve`, lite = SEKD-Lite, distilled from authors, "
             "several times faster (docs/model_card*.md).",
    )(f)


def num_threads_option(f):
    """``--num-threads``: CPU threads of the networks and OpenCV (default: every core the process may use)."""
    return click.option("--num-threads", type=click.IntRange(min=1), default=None,
                        help="CPU threads (default: all available cores).")(f)


def runtime_options(f):
    f = num_threads_option(f)
    f = click.option("--device", type=click.Choice(DEVICES), default="auto", show_default=True,
                     help="auto uses a CUDA GPU when one is present.")(f)
    f = click.option("--precision", type=click.Choice(PRECISIONS), default="auto", show_default=True,
                     help="auto = bf16 on CPUs with native bf16 (AVX512-BF16/AMX, ~4x faster), else fp32. "
                          "int8 = quantized network (CPU; needs pip install \"sekd-sfm[int8]\"; calibrated once "
                          "per weights, cached in ~/.cache/sekd or $SEKD_CACHE).")(f)
    return f


def feature_options(f):
    """--feature and the detection options of `extract`."""
    options = [
        click.option("--feature", type=click.Choice(FEATURE_TYPES), default="sekd", show_default=True,
                     help="SEKD, or a classic OpenCV feature written in the same file format."),
        click.option("--max-keypoints", type=click.IntRange(min=1), default=2000, show_default=True,
                     help="Keep the strongest N keypoints per image."),
        click.option("--threshold", type=click.FloatRange(0, 1, min_open=True, max_open=True), default=0.4,
                     show_default=True,
                     help="SEKD: minimum keypoint probability, in (0, 1) (the authors used 0.4 for benchmarks)."),
        click.option("--nms-radius", type=click.IntRange(min=0), default=4, show_default=True,
                     help="SEKD: non-maximum suppression radius in pixels."),
        click.option("--resize-max", type=click.IntRange(min=16), default=None,
                     help="Downscale images so the long side is at most N px; keypoints are mapped back to original pixels."),
        click.option("--multi-scale", is_flag=True, help="SEKD: also detect on /2, /4, ... downscaled images."),
        click.option("--subpixel/--no-subpixel", default=True, show_default=True,
                     help="SEKD: refine keypoints to sub-pixel accuracy (quadratic fit); --no-subpixel keeps the "
                          "integer pixel of each peak, as the SEKD paper's protocol."),
    ]
    for option in reversed(options):
        f = option(f)
    return f


def max_pixels_option(f):
    """--max-pixels: the pixel cap of `extract` and `reconstruct`."""
    return click.option(
        "--max-pixels", type=click.IntRange(min=0), default=DEFAULT_MAX_PIXELS, show_default=True,
        help="Images with more pixels are decoded at 1/2, 1/4 or 1/8 size (keypoints still in original "
             "pixels); beyond 64x the cap they are skipped and listed as failed. 0 = no cap.",
    )(f)


def executor_options(f):
    """--executor, --ray-address, --threads-per-worker, --gpus-per-worker, passed on as ``executor`` and ``ray_options``."""

    @functools.wraps(f)
    def command(*args, ray_address, threads_per_worker, gpus_per_worker, ray_merge, **kwargs):
        kwargs["ray_options"] = RayOptions(address=ray_address, threads_per_worker=threads_per_worker,
                                           gpus_per_worker=gpus_per_worker, merge=ray_merge)
        return f(*args, **kwargs)

    options = [
        click.option("--executor", type=click.Choice(EXECUTORS), default="local", show_default=True,
                     help="local: this machine; ray: the workers of a Ray cluster (needs pip install "
                          "\"sekd-sfm[ray]\" and files every node sees at the same path; docs/cluster.md)."),
        click.option("--ray-address", default="auto", show_default=True,
                     help="Ray cluster: auto = $RAY_ADDRESS, else one `ray start` made on this machine, "
                          "else a new local one for this run only; or HOST:PORT of the head node."),
        click.option("--threads-per-worker", type=click.IntRange(min=1), default=1, show_default=True,
                     help="ray: CPU threads (Ray CPUs) per worker; one worker per that many CPUs of the cluster."),
        click.option("--gpus-per-worker", type=click.FloatRange(min=0), default=0, show_default=True,
                     help="ray: GPUs per worker (0 = CPU workers; 0.5 = two workers share a GPU)."),
        click.option("--ray-merge", type=click.Choice(MERGES), default="copy", show_default=True,
                     help="ray, extraction: copy = the arrays are copied into one self-contained features.h5 "
                          "(the driver copies at disk speed, ~300-440 images/s); virtual = workers write shard "
                          "files in features.h5.shards/ that features.h5 references (thousands of images/s: for "
                          "clusters of more than ~64 workers; keep the folder beside the file)."),
    ]
    for option in reversed(options):
        command = option(command)
    return command
