"""`bench summary`: the three benchmarks joined by method label, on hand-made results."""
import json

from click.testing import CliRunner

from sekd_sfm.bench.summary import summary_markdown, summary_rows, write_summary
from sekd_sfm.cli.main import sekd

HOMOGRAPHY = {"methods": {
    "sift": {"summary": {"avg_ha_all": 0.784, "avg_ha_i": 0.98, "avg_ha_v": 0.6533, "mma": [0.1, 0.4, 0.5929]}},
    "broken": {"error": "weights not found"}}}
POSE = {"methods": {"sift": {"summary": {"maa": 0.8621}},
                    "ours": {"summary": {"maa": 0.5, "ransac_runs": 10, "maa_mean": 0.4812, "maa_sd": 0.0234}}}}
SFM = {"images": 11, "results": [
    {"method": "sift", "registered_images": 11, "maa": 1.0, "auc1": 0.8841, "median_rotation_deg": 0.2146,
     "wall_time_s": 21.9},
    {"method": "pycolmap SIFT pipeline", "registered_images": 10, "maa": None, "median_rotation_deg": None,
     "wall_time_s": 67.0}]}


def test_rows_join_by_label_in_first_seen_order():
    rows = summary_rows(HOMOGRAPHY, POSE, SFM)
    assert list(rows) == ["sift", "ours", "pycolmap SIFT pipeline"]   # failed methods have no row
    assert rows["sift"] == {"avg_ha_all": 0.784, "avg_ha_i": 0.98, "avg_ha_v": 0.6533, "mma3": 0.5929,
                            "pose_maa": 0.8621, "sfm_registered": "11/11", "sfm_maa": 1.0, "sfm_auc1": 0.8841,
                            "sfm_rot_deg": 0.2146, "sfm_time_s": 21.9}
    assert rows["ours"] == {"pose_maa": 0.5, "pose_maa_runs": (0.4812, 0.0234)}


def test_summary_files_and_table_cells(tmp_path):
    paths = {}
    for name, data in (("h", HOMOGRAPHY), ("p", POSE), ("s", SFM)):
        paths[name] = tmp_path / f"{name}.json"
        paths[name].write_text(json.dumps(data))
    md = write_summary(tmp_path / "out", paths["h"], paths["p"], paths["s"], highlight=("ours",))
    lines = md.read_text().splitlines()
    assert lines[2] == "| sift | 78.4 | 98.0 | 65.3 |  | 59.3 | 0.862 |  | 11/11 | 1.000 | 0.884 | 0.215 | 22 |"
    assert lines[3] == "| ours |  |  |  |  |  | 0.500 | 0.481 ± 0.023 |  |  |  |  |  |"
    assert lines[4] == "| pycolmap SIFT pipeline |  |  |  |  |  |  |  | 10/11 |  |  |  | 67 |"
    assert (tmp_path / "out/summary.png").stat().st_size > 10_000


def test_cli_needs_at_least_one_results_file(tmp_path):
    result = CliRunner().invoke(sekd, ["bench", "summary", "-o", str(tmp_path)])
    assert result.exit_code == 2 and "give at least one of --homography" in result.output


def test_a_later_run_replaces_the_rows_of_its_methods():
    rerun = {"images": 11, "results": [{"method": "sift", "registered_images": 9, "maa": 0.5,
                                        "median_rotation_deg": 1.0, "wall_time_s": 30.0}]}
    rows = summary_rows(HOMOGRAPHY, None, [SFM, rerun])
    assert rows["sift"]["sfm_registered"] == "9/11" and rows["sift"]["sfm_maa"] == 0.5
    assert rows["sift"]["avg_ha_all"] == 0.784 and rows["pycolmap SIFT pipeline"]["sfm_registered"] == "10/11"


def test_homography_mean_over_ransac_runs_is_a_column():
    results = {"methods": {"a": {"summary": {"avg_ha_all": 0.74, "avg_ha_i": 0.88, "avg_ha_v": 0.6467,
                                             "mma": [0, 0, 0.5987], "ransac_runs": 40, "avg_ha_all_mean": 0.735,
                                             "avg_ha_all_sd": 0.0172}}}}
    rows = summary_rows(results, None, None)
    assert rows["a"]["avg_ha_runs"] == (0.735, 0.0172)
    assert summary_markdown(rows, {}).splitlines()[2] == "| a | 74.0 | 88.0 | 64.7 | 73.5 ± 1.7 | 59.9 |  |  |  |  |  |  |  |"
