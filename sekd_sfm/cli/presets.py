"""``--conf NAME`` (a preset of sekd_sfm.confs) and ``sekd confs``; the CLI side of the one configuration builder."""
from __future__ import annotations

import click

from sekd_sfm.confs import CONFS, build_configs, describe_confs
from sekd_sfm.features import FeatureConfig
from sekd_sfm.stages.match import MatchConfig

from .options import USER_SOURCES, OptionValues

CONF_KEY = "sekd.conf"


def _keep_conf(ctx: click.Context, _param, value: str | None) -> str | None:
    if value == "list":
        click.echo(describe_confs())
        ctx.exit(0)
    if value is not None and value not in CONFS:
        raise click.BadParameter(f"unknown preset {value!r}; choose from {', '.join(CONFS)} (or `--conf list`)")
    # Kept in the context, not passed as a parameter, so commands take --conf without a new argument.
    ctx.meta[CONF_KEY] = value
    return value


def conf_option(f):
    """--conf NAME: a preset setting feature, keypoints, resize and matcher; explicit options still win."""
    return click.option(
        "--conf", metavar="NAME", default=None, expose_value=False, is_eager=True, callback=_keep_conf,
        help=f"Preset ({', '.join(CONFS)}; `--conf list` describes them): sets feature, keypoints, resize "
             "and matcher, and names the outputs feats-NAME.h5 / matches-NAME_PAIRS.h5. Options given "
             "explicitly override it.")(f)


def current_conf(ctx: click.Context | None = None) -> str | None:
    """The preset named by --conf, or None."""
    return (ctx or click.get_current_context()).meta.get(CONF_KEY)


def feature_and_match_configs(extraction: OptionValues, matching: OptionValues,
                              conf: str | None) -> tuple[FeatureConfig, MatchConfig]:
    """FeatureConfig and MatchConfig of a command's ``extraction`` and ``matching`` option groups, the preset
    ``conf`` applied to the options the user left at their defaults."""
    options = extraction | matching
    return build_configs(options.values, options.explicit, conf)


def explicit_options(ctx: click.Context) -> set[str]:
    """Names of the options the user gave (command line or environment), as opposed to defaults."""
    return {name for name in ctx.params if ctx.get_parameter_source(name) in USER_SOURCES}


def configs_from_context(ctx: click.Context | None = None) -> tuple[FeatureConfig, MatchConfig]:
    """FeatureConfig and MatchConfig of the running command: its options, with --conf applied to the defaulted ones.

    For commands that take the options one by one (extract, match); commands with option groups
    use ``feature_and_match_configs``, which reads each value once, where the command passes it.
    """
    ctx = ctx or click.get_current_context()
    return build_configs(ctx.params, explicit_options(ctx), current_conf(ctx))


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
