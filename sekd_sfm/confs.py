"""Named presets (``--conf NAME``), as hloc's ``confs``, and the one builder from options to configurations.

A preset sets the feature, its keypoint budget, the resize and the matcher in one word, and
names the output files hloc-style (``feats-<conf>.h5``, ``matches-<conf>_<pairs>.h5``).
Options given explicitly still win over the preset::

    sekd extract photos/ --conf sekd-n4000-r1600                      # -> feats-sekd-n4000-r1600.h5
    sekd extract photos/ --conf sekd-n4000-r1600 --max-keypoints 3000  # the preset, 3000 keypoints

From Python::

    from sekd_sfm.confs import build_configs
    features_config, match_config, given = build_configs(conf="sift-n8000")
"""
from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, NamedTuple

from .errors import SekdError
from .features import FeatureConfig
from .model.inference import SEKDConfig
from .stages.match import DEFAULT_RATIO, MatchConfig


@dataclass(frozen=True)
class Preset:
    """One named configuration: ``settings`` maps option names (as the CLI spells them, ``_`` for ``-``) to values."""

    name: str
    description: str
    settings: dict[str, Any]


def _preset(name: str, description: str, feature: str, max_keypoints: int, resize_max: int, **extra) -> Preset:
    # The ratio is the measured default of the feature (sekd_sfm.stages.match.DEFAULT_RATIO), written out
    # so that `sekd confs` shows the number that is used.
    settings = {"feature": feature, "max_keypoints": max_keypoints, "resize_max": resize_max,
                "match_mode": "both", "ratio": DEFAULT_RATIO["both"][feature], **extra}
    return Preset(name, description, settings)


CONFS: dict[str, Preset] = {p.name: p for p in (
    _preset("sekd-n2000-r1600", "SEKD, 2000 keypoints, long side 1600 px (the defaults of `sekd reconstruct`)",
            "sekd", 2000, 1600),
    _preset("sekd-n4000-r1600", "SEKD, 4000 keypoints, 1600 px: more matches on large or weakly textured scenes",
            "sekd", 4000, 1600),
    _preset("sekd-fast", "SEKD at 1024 px (2.4x fewer pixels than 1600), 2000 keypoints, bf16 on CPUs with native bf16",
            "sekd", 2000, 1024, precision="auto"),
    _preset("sift-n8000", "OpenCV SIFT, 8000 keypoints, 1600 px, RootSIFT matching (the classic baseline)",
            "sift", 8000, 1600),
    _preset("disk-n2000", "DISK (kornia), 2000 keypoints, 1600 px", "disk", 2000, 1600),
    _preset("aliked-n2000", "ALIKED (kornia), 2000 keypoints, 1024 px", "aliked", 2000, 1024),
)}
DEFAULT_CONF = "sekd-n2000-r1600"


def get_conf(name: str) -> Preset:
    """The preset called ``name``; SekdError listing the presets if there is none."""
    if name not in CONFS:
        raise SekdError(f"unknown preset {name!r}; choose from {', '.join(CONFS)} (`sekd confs` describes them)")
    return CONFS[name]


def resolve_options(options: Mapping[str, Any], explicit: Collection[str] = (), conf: str | None = None) -> dict:
    """``options`` with the preset ``conf`` applied to every option not in ``explicit`` (the ones the user gave)."""
    settings = dict(options)
    if conf:
        preset = get_conf(conf).settings
        settings.update({k: v for k, v in preset.items() if k not in explicit})
        # The preset's ratio was measured for its feature and mode: another one, given
        # explicitly, gets its own measured default instead (unless --ratio is given too).
        if "ratio" not in explicit and any(settings.get(k) != preset[k] for k in ("feature", "match_mode")):
            settings["ratio"] = options.get("ratio")
    return settings


class Configs(NamedTuple):
    """What ``build_configs`` makes: the feature and match configurations, and ``given``, the fields of the two
    the user set (dotted as a run's record has them: ``features.max_keypoints``, ``matching.ratio``)."""

    features: FeatureConfig
    matching: MatchConfig
    given: frozenset[str] = frozenset()


#: Option name -> MatchConfig field; every other option sets the FeatureConfig and SEKDConfig fields of its name.
MATCH_FIELDS = {"match_mode": "mode", "ratio": "ratio", "rootsift": "rootsift", "device": "device"}
_FEATURE_FIELDS = frozenset(f.name for f in fields(FeatureConfig)) - {"sekd"}
_SEKD_FIELDS = frozenset(f.name for f in fields(SEKDConfig))


def _fields_of(option: str) -> tuple[str, ...]:
    """The configuration fields the option ``option`` sets (``device``: the network's and the matcher's)."""
    return (((f"features.{option}",) if option in _FEATURE_FIELDS else ())
            + ((f"features.sekd.{option}",) if option in _SEKD_FIELDS else ())
            + ((f"matching.{MATCH_FIELDS[option]}",) if option in MATCH_FIELDS else ()))


def _config_default(option: str) -> Any:
    """The value the configurations have for ``option`` when it is not given."""
    if option in MATCH_FIELDS:
        return getattr(MatchConfig(), MATCH_FIELDS[option])
    if option in _SEKD_FIELDS:
        return getattr(SEKDConfig(), option)
    return getattr(FeatureConfig(), option, None)


def _field_value(option: str, value: Any) -> Any:
    """The configuration's value of an option's value: the CLI's ``max_pixels`` 0 means no cap."""
    return (value or None) if option == "max_pixels" else value


def build_configs(options: Mapping[str, Any] | None = None, explicit: Collection[str] = (),
                  conf: str | None = None, defaults: Mapping[str, Any] | None = None) -> Configs:
    """The feature and match configurations of a command's options, a preset applied first, and the fields the
    user set (``Configs``).

    ``options`` uses the CLI option names (``feature``, ``max_keypoints``, ``resize_max``,
    ``threshold``, ``nms_radius``, ``multi_scale``, ``subpixel``, ``precision``, ``device``,
    ``weights``, ``max_pixels`` (0 = no cap), ``match_mode``, ``ratio``, ``rootsift``); missing
    ones keep the dataclass defaults; other keys are ignored. ``defaults``: what an option not in
    ``explicit`` stands for where a command's default differs from the dataclasses' (reconstruct:
    ``resize_max`` 1600). Every command builds its configurations here, so an option means the
    same everywhere.

    A field counts as set (``given``) when the user's choice decides it: an option in ``explicit``
    whose value differs from the one it would have without it (the preset's, else the default),
    or the preset, where it differs from the options' values.
    """
    defaults = dict(defaults or {})
    options = {**(options or {}), **{k: v for k, v in defaults.items() if k not in explicit}}
    settings = resolve_options(options, explicit, conf)
    sekd = SEKDConfig(**{f.name: settings[f.name] for f in fields(SEKDConfig) if f.name in settings})
    feature = FeatureConfig(sekd=sekd, **{f.name: settings[f.name] for f in fields(FeatureConfig)
                                          if f.name in settings and f.name != "sekd"})
    if "max_pixels" in settings:
        feature.max_pixels = _field_value("max_pixels", settings["max_pixels"])
    matching = MatchConfig(**{field: settings[option] for option, field in MATCH_FIELDS.items() if option in settings})
    return Configs(feature, matching, _given(options, explicit, conf, defaults, settings))


def _given(options: Mapping[str, Any], explicit: Collection[str], conf: str | None, defaults: Mapping[str, Any],
           settings: Mapping[str, Any]) -> frozenset[str]:
    """The fields of ``build_configs``'s configurations that the user's choices decide (its docstring)."""
    preset = get_conf(conf).settings if conf else {}

    def default(option: str) -> Any:
        return defaults.get(option, _config_default(option))

    def without_choice(option: str) -> Any:  # the setting had the user not chosen it
        return preset.get(option, default(option)) if option in explicit else options.get(option, default(option))

    chosen = {option for option, value in settings.items() if option != "ratio"
              and _field_value(option, value) != _field_value(option, without_choice(option))}
    if "ratio" in settings:
        undone = [without_choice("ratio")]
        if conf:  # the ratio follows the preset, --feature, --match-mode and --ratio together (resolve_options):
            # set when undoing any one of them changes it
            undone = [options.get("ratio")] + [
                resolve_options({**options, option: default(option)}, set(explicit) - {option}, conf).get("ratio")
                for option in ("feature", "match_mode", "ratio") if option in explicit]
        if any(settings["ratio"] != ratio for ratio in undone):
            chosen.add("ratio")
    return frozenset(field for option in chosen for field in _fields_of(option))


def output_names(conf: str, pairs: str | Path | None = None) -> tuple[str, str]:
    """hloc-style file names of a preset: ``feats-<conf>.h5`` and ``matches-<conf>_<pairs stem>.h5``."""
    get_conf(conf)
    stem = Path(pairs).stem if pairs else "pairs"
    return f"feats-{conf}.h5", f"matches-{conf}_{stem}.h5"


def describe_confs() -> str:
    """The presets as an aligned table (what `sekd confs` prints)."""
    head = ("name", "feature", "keypoints", "resize", "precision", "matcher", "description")
    rows = [head] + [(p.name, p.settings["feature"], str(p.settings["max_keypoints"]), str(p.settings["resize_max"]),
                      p.settings.get("precision", "auto"), f"{p.settings['match_mode']} {p.settings['ratio']}",
                      p.description) for p in CONFS.values()]
    widths = [max(len(r[i]) for r in rows) for i in range(len(head) - 1)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)) + "  " + r[-1] for r in rows)
