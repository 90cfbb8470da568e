"""``--conf NAME`` (a preset of sekd_sfm.confs) and ``sekd confs``; the CLI side of the one configuration builder."""
from __future__ import annotations

from functools import reduce
from operator import or_
from typing import Any

import click

from sekd_sfm.confs import CONFS, Configs, build_configs, describe_confs

from .options import OptionValues


def _check_conf(ctx: click.Context, _param, value: str | None) -> str | None:
    if value == "list":
        click.echo(describe_confs())
        ctx.exit(0)
    if value is not None and value not in CONFS:
        raise click.BadParameter(f"unknown preset {value!r}; choose from {', '.join(CONFS)} (or `--conf list`)")
    return value


def conf_option(f):
    """--conf NAME, passed on as ``conf``: a preset setting feature, keypoints, resize and matcher; explicit options
    still win (``feature_and_match_configs``)."""
    return click.option(
        "--conf", metavar="NAME", default=None, is_eager=True, callback=_check_conf,
        help=f"Preset ({', '.join(CONFS)}; `--conf list` describes them): sets feature, keypoints, resize "
             "and matcher, and names the outputs feats-NAME.h5 / matches-NAME_PAIRS.h5. Options given "
             "explicitly override it.")(f)


def feature_and_match_configs(*groups: OptionValues, conf: str | None,
                              defaults: dict[str, Any] | None = None) -> Configs:
    """FeatureConfig, MatchConfig and the fields the user set (``confs.Configs``) of a command's option groups
    (extraction and/or matching), the preset ``conf`` applied to the options the user left at their defaults;
    ``defaults``: the command's own defaults where they differ from the configurations' (``build_configs``)."""
    options = reduce(or_, groups)
    return build_configs(options.values, options.explicit, conf, defaults)


@click.command()
def confs() -> None:
    """List the presets that --conf NAME selects (extract, match, reconstruct).

    \b
    A preset sets the feature, its keypoint budget, the resize and the matcher in one
    word and names the output files hloc-style: feats-NAME.h5, matches-NAME_PAIRS.h5.
    Options given explicitly override the preset.

    \b
    Examples:
      sekd confs
      sekd extract photos/ --conf sift-n8000                 # writes feats-sift-n8000.h5 beside photos/
      sekd reconstruct photos/ -o out/ --conf sekd-fast --max-keypoints 3000
    """
    click.echo(describe_confs())
