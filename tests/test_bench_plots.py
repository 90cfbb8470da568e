"""`sekd bench plots`: every plot of a results tree redrawn from hand-made results."""
import json

import matplotlib.image
import pytest
from click.testing import CliRunner

from sekd_sfm.bench.report import PALETTE, line_style, merge_results, regenerate_plots
from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError


def _homography(methods: dict[str, float]) -> dict:
    """A bench-homography results dict: each method's curves are flat at ``value``."""
    def summary(value):
        curve = [value] * 10
        return {"pairs_all": 2, "pairs_i": 1, "pairs_v": 1, "ha_all": curve, "ha_i": curve, "ha_v": curve,
                "avg_ha_all": value, "avg_ha_i": value, "avg_ha_v": value, "mma": curve}
    return {"sequences": ["i_x", "v_y"], "config": {}, "methods": {m: {"summary": summary(v)} for m, v in methods.items()}}


def _pose(methods: dict[str, float]) -> dict:
    return {"scenes": ["s"], "config": {}, "methods": {m: {"summary": {"accuracy": [v] * 10, "maa": v}}
                                                       for m, v in methods.items()}}


def _write(path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def test_merge_keeps_order_and_lets_later_runs_replace_rows():
    old = _homography({"sift": 0.78, "ours": 0.27, "authors": 0.74})
    new = _homography({"ours": 0.71, "ours_prev": 0.70})
    merged = merge_results([old, new])
    assert list(merged["methods"]) == ["sift", "ours", "authors", "ours_prev"]
    assert merged["methods"]["ours"]["summary"]["avg_ha_all"] == 0.71
    assert list(old["methods"]) == ["sift", "ours", "authors"]  # inputs untouched


def test_styles_are_distinct_for_32_methods():
    styles = {(s["color"], s["linestyle"], s["marker"]) for s in map(line_style, range(32))}
    assert len(styles) == 32
    assert {line_style(i)["color"] for i in range(8)} == set(PALETTE)


def test_every_results_folder_and_every_listed_figure_is_drawn(tmp_path):
    _write(tmp_path / "hom/results.json", _homography({"sift": 0.78, "ours": 0.27}))
    _write(tmp_path / "later/hom/results.json", _homography({"ours": 0.71}))
    _write(tmp_path / "pose/results.json", _pose({"sift": 0.86}))
    _write(tmp_path / "sfm/results.json", {"images": 2, "results": []})  # SfM: no curves
    (tmp_path / "figures.json").write_text(json.dumps({
        "hom": {"homography": ["hom/results.json", "later/hom/results.json"]},
        "summary": {"summary": {"homography": ["hom/results.json", "later/hom/results.json"],
                                "pose": ["pose/results.json"], "highlight": ["ours"]}}}))
    written = regenerate_plots(tmp_path)
    assert sorted(p.relative_to(tmp_path).as_posix() for p in written) == [
        "hom/homography_accuracy.png", "hom/mma.png", "later/hom/homography_accuracy.png", "later/hom/mma.png",
        "pose/pose_accuracy.png", "summary/summary.png"]
    for path in written:
        height, width = matplotlib.image.imread(path).shape[:2]
        assert width > 300 and height > 200
    # The merged figure's table says the later run's number for "ours".
    assert "| ours | 71.0 |" in (tmp_path / "summary/summary.md").read_text()


def test_homography_legend_sits_below_the_axes(tmp_path):
    _write(tmp_path / "hom/results.json", _homography({f"m{i}": i / 20 for i in range(16)}))
    (png,) = [p for p in regenerate_plots(tmp_path) if p.name == "homography_accuracy.png"]
    height, _width = matplotlib.image.imread(png).shape[:2]
    assert height > 4 * 110  # the 4-inch axes plus the legend rows under them


@pytest.mark.parametrize("manifest, message", [
    ("{not json", "not valid JSON"),
    ('{"x": {"homography": ["missing/results.json"]}}', "missing results file"),
    ('{"x": {"bars": []}}', "unknown figure kind 'bars'"),
])
def test_bad_figures_file_is_one_clear_error(tmp_path, manifest, message):
    (tmp_path / "figures.json").write_text(manifest)
    with pytest.raises(SekdError, match=message):
        regenerate_plots(tmp_path)


def test_cli_plots_and_errors(tmp_path):
    _write(tmp_path / "pose/results.json", _pose({"sift": 0.86, "ours": 0.83}))
    result = CliRunner().invoke(sekd, ["bench", "plots", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert result.output.strip() == str(tmp_path / "pose/pose_accuracy.png")
    _write(tmp_path / "bad/results.json", {})
    (tmp_path / "bad/results.json").write_text("{")
    result = CliRunner().invoke(sekd, ["bench", "plots", str(tmp_path)])
    assert result.exit_code == 1 and "cannot read benchmark results" in result.output
    assert CliRunner().invoke(sekd, ["bench", "plots", str(tmp_path / "none")]).exit_code == 2
