"""Options shared by several commands, declared once, and option groups.

An option group (``option_group``) adds a set of options to a command and hands the command
their values as ONE argument, an ``OptionValues``: a command's signature then names its groups
(extraction, matching, execution, ...) instead of dozens of options, and one function per
command turns the groups into its typed settings.
"""
from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource

from sekd_sfm.execution import EXECUTORS, MERGES, RayOptions
from sekd_sfm.features import FEATURE_TYPES
from sekd_sfm.files.images import DEFAULT_MAX_PIXELS
from sekd_sfm.runtime import DEVICES, PRECISIONS

#: A function that adds options to a click command function (``click.option(...)`` and the groups below).
Decorator = Callable[[Callable], Callable]
#: Where a value the user chose comes from; any other source is a default, which a --conf preset may replace.
USER_SOURCES = (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT, ParameterSource.PROMPT)


@dataclass(frozen=True)
class OptionValues:
    """The values of one option group, by parameter name, and the names of those the user gave (``explicit``)."""

    values: Mapping[str, Any]
    explicit: frozenset[str] = frozenset()

    def __getitem__(self, name: str) -> Any:
        return self.values[name]

    def get(self, name: str, default: Any = None) -> Any:
        return self.values.get(name, default)

    def __or__(self, other: OptionValues) -> OptionValues:
        """Both groups' values: a --conf preset sets extraction and matching options together."""
        return OptionValues({**self.values, **other.values}, self.explicit | other.explicit)


def option_group(name: str, *declarations: Decorator) -> Decorator:
    """A decorator adding the options of ``declarations`` (in this order) to a command, which receives their
    values as one keyword argument ``name``, an OptionValues, instead of one parameter per option."""
    keys = _value_names(declarations)

    def decorate(command: Callable) -> Callable:
        @functools.wraps(command)
        def grouped(*args, **kwargs):
            values = {key: kwargs.pop(key) for key in keys}
            ctx = click.get_current_context()
            explicit = frozenset(key for key in keys if ctx.get_parameter_source(key) in USER_SOURCES)
            return command(*args, **{name: OptionValues(values, explicit)}, **kwargs)

        return _stack(declarations, grouped)

    return decorate


def _value_names(declarations: Iterable[Decorator]) -> tuple[str, ...]:
    """The parameter names click passes the values of ``declarations`` under (read off a throwaway function, so a
    group never repeats the names its options already declare); options with expose_value=False pass none."""
    probe = _stack(declarations, lambda: None)
    return tuple(param.name for param in getattr(probe, "__click_params__", ()) if param.expose_value)


def _stack(declarations: Iterable[Decorator], f: Callable) -> Callable:
    """``f`` decorated by ``declarations`` as if written one above the other, the first on top (first in --help)."""
    for declare in reversed(list(declarations)):
        f = declare(f)
    return f


def model_weights(model: str | None, weights: str | None, feature: str | None = None) -> str | None:
    """The SEKD network of ``--model NAME`` and ``--weights PATH``: the path as given, else the file of the
    embedded model (None: neither, the default embedded model); SekdError for both at once, or for --model with a
    ``feature`` other than SEKD."""
    from sekd_sfm.errors import SekdError
    from sekd_sfm.model.weights import embedded_model_path

    if model is None:
        return weights
    if weights is not None:
        raise SekdError(f"--model {model} and --weights {weights} both name the SEKD model; give one of them")
    if feature not in (None, "sekd"):
        raise SekdError(f"--model {model} selects a SEKD model; --feature {feature} does not use it (drop --model)")
    return str(embedded_model_path(model))


def weights_declarations(f):
    """--model own|authors|lite and --weights PATH, each passed as itself (``model_weights`` makes them one)."""
    from sekd_sfm.model.weights import DEFAULT_MODEL, EMBEDDED_MODELS

    return _stack([
        # eager, as before: a wrong --model is reported before the other options
        click.option(
            "--model", type=click.Choice(tuple(EMBEDDED_MODELS)), default=None, is_eager=True,
            help=f"Embedded SEKD model (default {DEFAULT_MODEL}): authors = the SEKD authors' release (MIT), "
                 "own = trained by this project's `sekd evolve`, lite = SEKD-Lite, distilled from authors, "
                 "several times faster (docs/model_card*.md)."),
        click.option(
            "--weights", type=click.Path(dir_okay=False), default=None,
            help="SEKD checkpoint (.pth): the authors' format or ours, e.g. one made by `sekd adapt`. "
                 "Default: the --model embedded in the package."),
    ], f)


def weights_option(f):
    """--weights PATH and --model own|authors|lite, passed on as ``weights`` (None: the default embedded model)."""

    @functools.wraps(f)
    def command(*args, model: str | None, weights: str | None, **kwargs):
        return f(*args, weights=model_weights(model, weights, kwargs.get("feature")), **kwargs)

    return weights_declarations(command)


num_threads_option = click.option(
    "--num-threads", type=click.IntRange(min=1), default=None, help="CPU threads (default: all available cores).")
device_option = click.option("--device", type=click.Choice(DEVICES), default="auto", show_default=True,
                             help="auto uses a CUDA GPU when one is present.")
precision_option = click.option(
    "--precision", type=click.Choice(PRECISIONS), default="auto", show_default=True,
    help="auto = bf16 on CPUs with native bf16 (AVX512-BF16/AMX, ~4x faster), else fp32. "
         "int8 = quantized network (CPU; needs pip install \"sekd-sfm[int8]\"; calibrated once "
         "per weights, cached in ~/.cache/sekd or $SEKD_CACHE).")


RESIZE_HELP = "Downscale images so the long side is at most N px; keypoints are mapped back to original pixels."


def feature_options(f, *, resize_help: str = RESIZE_HELP):
    """--feature and the detection options of `extract` (``resize_help``: a command's own words on --resize-max)."""
    return _stack([
        click.option("--feature", type=click.Choice(FEATURE_TYPES), default="sekd", show_default=True,
                     help="SEKD, or a classic OpenCV feature written in the same file format."),
        click.option("--max-keypoints", type=click.IntRange(min=1), default=2000, show_default=True,
                     help="Keep the strongest N keypoints per image."),
        click.option("--threshold", type=click.FloatRange(0, 1, min_open=True, max_open=True), default=0.4,
                     show_default=True,
                     help="SEKD: minimum keypoint probability, in (0, 1) (the authors used 0.4 for benchmarks)."),
        click.option("--nms-radius", type=click.IntRange(min=0), default=4, show_default=True,
                     help="SEKD: non-maximum suppression radius in pixels."),
        click.option("--resize-max", type=click.IntRange(min=16), default=None, help=resize_help),
        click.option("--multi-scale", is_flag=True, help="SEKD: also detect on /2, /4, ... downscaled images."),
        click.option("--subpixel/--no-subpixel", default=True, show_default=True,
                     help="SEKD: refine keypoints to sub-pixel accuracy (quadratic fit); --no-subpixel keeps the "
                          "integer pixel of each peak, as the SEKD paper's protocol."),
    ], f)


max_pixels_option = click.option(
    "--max-pixels", type=click.IntRange(min=0), default=DEFAULT_MAX_PIXELS, show_default=True,
    help="Images with more pixels are decoded at 1/2, 1/4 or 1/8 size (keypoints still in original "
         "pixels); beyond 64x the cap they are skipped and listed as failed. 0 = no cap.")


masks_option = click.option(
    "--masks", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
    help="Folder of masks, COLMAP's convention: photo NAME (its path below IMAGES, extension included) has the "
         "mask MASKS/NAME.png, e.g. masks/sub/a.jpg.png for IMAGES/sub/a.jpg, the photo's size (or resized to it); "
         "zero pixels are ignored: no keypoint there, and the --max-keypoints strongest come from the rest. Photos "
         "without a mask file are used whole. A changed mask re-extracts its photo on resume (docs/masks.md).")


def extraction_options(*, max_pixels: bool = True, masks: bool = False, resize_help: str = RESIZE_HELP) -> Decorator:
    """The group ``extraction``: --feature ... --subpixel, --max-pixels (if ``max_pixels``), --masks (if ``masks``),
    --model/--weights (passed as one value, ``weights``), --precision and --device; what
    ``presets.feature_and_match_configs`` makes a FeatureConfig of (and the matcher's device; ``masks`` is read by
    the command itself)."""
    declarations = [functools.partial(feature_options, resize_help=resize_help)]
    declarations += [max_pixels_option] if max_pixels else []
    declarations += [masks_option] if masks else []
    group = option_group("extraction", *declarations, weights_declarations, precision_option, device_option)

    def decorate(command: Callable) -> Callable:
        @functools.wraps(command)
        def with_weights(*args, extraction: OptionValues, **kwargs):
            return command(*args, extraction=_model_as_weights(extraction), **kwargs)

        return group(with_weights)

    return decorate


def _model_as_weights(extraction: OptionValues) -> OptionValues:
    """The group ``extraction`` with --model turned into its ``weights`` (``model_weights``)."""
    values = dict(extraction.values)
    model = values.pop("model")
    values["weights"] = model_weights(model, values["weights"], values.get("feature"))
    return OptionValues(values, extraction.explicit - {"model"})


def executor_declarations(f):
    """--executor, --ray-address, --threads-per-worker, --gpus-per-worker, --ray-merge, each passed as itself."""
    return _stack([
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
    ], f)


def ray_options(execution: OptionValues) -> RayOptions:
    """The RayOptions of the values of ``executor_declarations``."""
    return RayOptions(address=execution["ray_address"], threads_per_worker=execution["threads_per_worker"],
                      gpus_per_worker=execution["gpus_per_worker"], merge=execution["ray_merge"])


def executor_options(f):
    """``executor_declarations``, passed on as ``executor`` and ``ray_options`` (extract, match)."""

    @functools.wraps(f)
    def command(*args, execution: OptionValues, **kwargs):
        return f(*args, executor=execution["executor"], ray_options=ray_options(execution), **kwargs)

    return option_group("execution", executor_declarations)(command)


def _keyframe_count(ctx, param, value: str) -> int | None:
    """--keyframes: ``auto`` (None) or a count of at least 2."""
    if value == "auto":
        return None
    try:
        count = int(value)
    except ValueError:
        count = 0
    if count < 2:
        raise click.BadParameter(f"{value!r}: give auto or a number of keyframes per video (2 or more)")
    return count


video_options = option_group(
    "video",
    click.option("--keyframes", default="auto", show_default=True, callback=_keyframe_count, metavar="auto|N",
                 help="Videos in IMAGES (mp4, mov, avi, mkv, ...): which frames become photos, written as "
                      "OUTPUT/images/<video>/<frame>.jpg. auto: a sharp frame whenever the view moved 5% of the "
                      "image since the last keyframe (blurred frames skipped); N: the sharpest frame of each of N "
                      "equal spans of every video. docs/captures.md."),
    click.option("--max-fps", type=click.FloatRange(min=0.1), default=10.0, show_default=True,
                 help="Frames of a video looked at per second, at most."),
)
