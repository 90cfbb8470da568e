"""Presets (--conf): each resolves to its documented settings; explicit options win; output names."""
from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from sekd_sfm.cli import extract as extract_cli
from sekd_sfm.cli import match as match_cli
from sekd_sfm.cli.main import sekd
from sekd_sfm.cli.reconstruct import reconstruct
from sekd_sfm.confs import (
    CONFS,
    DEFAULT_CONF,
    build_configs,
    describe_confs,
    get_conf,
    output_names,
)
from sekd_sfm.errors import SekdError

# The settings each preset documents (`sekd confs`): feature, keypoints, resize, precision, mode, ratio.
DOCUMENTED = {
    "sekd-n2000-r1600": ("sekd", 2000, 1600, "auto", "both", 0.9),
    "sekd-n4000-r1600": ("sekd", 4000, 1600, "auto", "both", 0.9),
    "sekd-fast": ("sekd", 2000, 1024, "auto", "both", 0.9),
    "sift-n8000": ("sift", 8000, 1600, "auto", "both", 0.85),
    "disk-n2000": ("disk", 2000, 1600, "auto", "both", 1.0),
    "aliked-n2000": ("aliked", 2000, 1024, "auto", "both", 0.95),
}


@pytest.mark.parametrize("name", sorted(DOCUMENTED))
def test_preset_resolves_to_documented_settings(name):
    features, matching, _ = build_configs(conf=name)
    feature, keypoints, resize, precision, mode, ratio = DOCUMENTED[name]
    assert (features.feature, features.max_keypoints, features.resize_max) == (feature, keypoints, resize)
    assert features.sekd.precision == precision
    assert (matching.mode, matching.ratio) == (mode, ratio)
    line = next(row for row in describe_confs().splitlines() if row.startswith(name + " "))
    assert line.split()[1:6] == [feature, str(keypoints), str(resize), precision, mode]


def test_every_preset_is_documented():
    assert set(CONFS) == set(DOCUMENTED)


def test_default_preset_is_what_reconstruct_runs_without_options():
    defaults = {p.name: p.default for p in reconstruct.params}
    features, matching, _ = build_configs(defaults)
    features.resize_max = features.resize_max or 1600  # reconstruct's own default
    preset_features, preset_matching, _ = build_configs(defaults, conf=DEFAULT_CONF)
    assert features == preset_features
    # Without a preset the ratio is resolved later from the feature type: the same number.
    from sekd_sfm.stages.match import describe_config

    assert describe_config(matching, "sekd", False) == describe_config(preset_matching, "sekd", False)


def test_explicit_options_override_the_preset():
    options = {"feature": "sekd", "max_keypoints": 3000, "resize_max": None, "match_mode": "both", "ratio": None}
    features, matching, _ = build_configs(options, explicit={"max_keypoints"}, conf="sekd-fast")
    assert (features.max_keypoints, features.resize_max, matching.ratio) == (3000, 1024, 0.9)


def test_another_feature_or_mode_gets_its_own_default_ratio():
    options = {"feature": "orb", "match_mode": "ratio", "ratio": None}
    features, matching, _ = build_configs(options, explicit={"feature"}, conf="sekd-n2000-r1600")
    assert features.feature == "orb" and matching.ratio is None  # resolved later: orb's measured ratio
    _, matching, _ = build_configs(options, explicit={"match_mode"}, conf="sift-n8000")
    assert matching.mode == "ratio" and matching.ratio is None
    _, matching, _ = build_configs({**options, "ratio": 0.7}, explicit={"match_mode", "ratio"}, conf="sift-n8000")
    assert matching.ratio == 0.7


def test_max_pixels_zero_means_no_cap():
    assert build_configs({"max_pixels": 0})[0].max_pixels is None


def test_unknown_preset():
    with pytest.raises(SekdError, match="unknown preset 'nope'; choose from sekd-n2000-r1600"):
        get_conf("nope")
    result = CliRunner().invoke(sekd, ["extract", "photos", "--conf", "nope"])
    assert result.exit_code == 2 and "unknown preset 'nope'" in result.output


def test_output_names():
    assert output_names("sift-n8000", "out/pairs-retrieval.txt") == ("feats-sift-n8000.h5",
                                                                      "matches-sift-n8000_pairs-retrieval.h5")


@pytest.fixture
def captured(monkeypatch):
    """Replace the work of extract and match by recording what the command passes on."""
    calls = {}

    def fake(name):
        def run(_input, *args, **kwargs):
            calls[name] = args
            return args[-2] if name == "match" else args[0]
        return run

    monkeypatch.setattr(extract_cli, "extract_features", fake("extract"))
    monkeypatch.setattr(match_cli, "match_features", fake("match"))
    return calls


def test_cli_extract_conf_with_override(captured, tmp_path):
    result = CliRunner().invoke(sekd, ["extract", str(tmp_path / "photos"), "--conf", "sift-n8000",
                                       "--max-keypoints", "500"])
    assert result.exit_code == 0, result.output
    output, config = captured["extract"]
    assert output == tmp_path / "feats-sift-n8000.h5"
    assert (config.feature, config.max_keypoints, config.resize_max) == ("sift", 500, 1600)


def test_cli_extract_without_conf_keeps_its_defaults(captured, tmp_path):
    result = CliRunner().invoke(sekd, ["extract", str(tmp_path / "photos"), "--feature", "orb"])
    assert result.exit_code == 0, result.output
    output, config = captured["extract"]
    assert output == tmp_path / "features-orb.h5" and (config.max_keypoints, config.resize_max) == (2000, None)


def test_cli_match_conf_names_the_output(captured, tmp_path):
    result = CliRunner().invoke(sekd, ["match", str(tmp_path / "f.h5"), str(tmp_path / "pairs-a.txt"),
                                       "--conf", "sift-n8000", "--match-mode", "mnn"])
    assert result.exit_code == 0, result.output
    _, output, config = captured["match"]
    assert Path(output) == tmp_path / "matches-sift-n8000_pairs-a.h5"
    assert (config.mode, config.ratio) == ("mnn", None)


def test_cli_reconstruct_conf_sets_configs_and_file_names(monkeypatch, tmp_path):
    import sekd_sfm.pipelines.reconstruct as sfm_reconstruct

    seen = {}
    monkeypatch.setattr(sfm_reconstruct, "reconstruct", lambda images, out, config, **kw: seen.update(c=config))
    result = CliRunner().invoke(sekd, ["reconstruct", str(tmp_path), "-o", str(tmp_path / "out"),
                                       "--conf", "sekd-fast", "--ratio", "0.8"])
    assert result.exit_code == 0, result.output
    config = seen["c"]
    assert (config.features.feature, config.features.max_keypoints, config.features.resize_max) == ("sekd", 2000, 1024)
    assert config.matching.ratio == 0.8 and config.file_names == ("feats-sekd-fast.h5", "matches-sekd-fast_pairs.h5")
    CliRunner().invoke(sekd, ["reconstruct", str(tmp_path), "-o", str(tmp_path / "out")])
    assert seen["c"].file_names == ("features.h5", "matches.h5") and seen["c"].features.resize_max == 1600


def test_given_fields_are_the_options_that_change_a_field():
    """build_configs reports the fields the user's choices decide: explicit options that change a field, the preset."""
    assert build_configs().given == frozenset()
    assert build_configs({"max_keypoints": 3000}, explicit={"max_keypoints"}).given == {
        "features.max_keypoints", "features.sekd.max_keypoints"}
    assert build_configs({"max_keypoints": 2000}, explicit={"max_keypoints"}).given == frozenset()  # the default
    assert build_configs({"device": "cpu"}, explicit={"device"}).given == {"features.sekd.device", "matching.device"}
    # Under a preset: what the preset changes, and explicit options where they differ from the preset.
    assert build_configs(conf="sekd-fast", defaults={"resize_max": 1600}).given == {"features.resize_max",
                                                                                   "matching.ratio"}
    assert build_configs({"max_keypoints": 4000}, {"max_keypoints"}, "sekd-n4000-r1600").given == {
        "features.resize_max", "matching.ratio"}  # 1600 px against the dataclass's full size
    assert "features.max_keypoints" in build_configs({"max_keypoints": 2000}, {"max_keypoints"}, "sekd-n4000-r1600").given


# The fields `reconstruct --extend` checks against the model's record, for a few command lines.
EXTEND_GIVEN = [
    ([], {}),
    (["--max-keypoints", "3000"], {"features.max_keypoints": 3000, "features.sekd.max_keypoints": 3000}),
    (["--max-keypoints", "2000"], {}),
    (["--conf", "sekd-fast"], {"features.resize_max": 1024, "matching.ratio": 0.9,
                               "file_names": ["feats-sekd-fast.h5", "matches-sekd-fast_pairs.h5"]}),
    (["--conf", "sekd-fast", "--resize-max", "1600"], {"features.resize_max": 1600, "matching.ratio": 0.9,
                                                       "file_names": ["feats-sekd-fast.h5", "matches-sekd-fast_pairs.h5"]}),
    (["--resize-max", "1600"], {}),
    (["--conf", "sift-n8000", "--feature", "sekd"], {
        "features.feature": "sekd", "features.max_keypoints": 8000, "features.sekd.max_keypoints": 8000,
        "matching.ratio": None, "file_names": ["feats-sift-n8000.h5", "matches-sift-n8000_pairs.h5"]}),
    (["--ratio", "0.9"], {"matching.ratio": 0.9}),
    (["--camera-model", "PINHOLE"], {"camera.model": "PINHOLE"}),
    (["--no-refine"], {"refine.enabled": False}),
    (["--mapper-type", "global"], {"mapper_type": "global"}),
    (["--max-pixels", "0", "--seed", "3", "--gps", "off"], {"features.max_pixels": None, "seed": 3}),
    (["--pairs", "sequential", "--window", "5", "--loop-every", "0"], {"pairs.mode": "sequential", "pairs.window": 5}),
    (["--pairs", "retrieval", "--pairs-file", "f.txt"], {"pairs.mode": "from-file", "pairs.file": "f.txt",
                                                         "pairs.num_neighbors": 20}),
    (["--mapper", "mapper.x=1", "--verification", "a=b"], {"mapper": ["mapper.x=1"], "verification": ["a=b"]}),
    (["--weights", "w.pth", "--adapt"], {"features.weights": "w.pth"}),
]


@pytest.mark.parametrize(("options", "given"), EXTEND_GIVEN, ids=lambda v: " ".join(v) if isinstance(v, list) else "")
def test_cli_extend_checks_the_fields_the_options_set(monkeypatch, tmp_path, options, given):
    import sekd_sfm.pipelines.reconstruct as sfm_reconstruct
    from sekd_sfm.cli import adapt as adapt_cli

    seen = {}
    monkeypatch.setattr(sfm_reconstruct, "reconstruct", lambda images, out, config, **kw: seen.update(kw))
    monkeypatch.setattr(adapt_cli, "adapt_or_reuse", lambda *args, **kwargs: tmp_path / "adapted.pth")
    result = CliRunner().invoke(sekd, ["reconstruct", str(tmp_path), "-o", str(tmp_path / "out"), "--extend", *options])
    assert result.exit_code == 0, result.output
    assert seen["extend"].given == given
