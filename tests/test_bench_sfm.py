"""`sekd bench sfm`: a small end-to-end run on fountain-P11 with ground truth."""
import json

from click.testing import CliRunner

from sekd_sfm.cli.main import sekd
from sekd_sfm.evaluation.metrics import mean_average_accuracy


def test_sfm_benchmark_two_methods_with_pose_maa(tmp_path, shared):
    result = CliRunner().invoke(sekd, ["bench", "sfm", str(shared / "data/sfm/fountain-P11"), "-o", str(tmp_path),
                                       "-m", "sift", "-m", "orb", "--resize-max", "480", "--max-keypoints", "1500",
                                       "--no-baseline", "--num-threads", "2"])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "results.json").read_text())
    sift, orb = report["results"]
    assert sift["method"] == "sift" and orb["method"] == "orb"
    assert sift["registered_images"] >= 9
    # Pose mAA counts pairs with an unregistered image as failures: at most (registered pairs) / 55.
    n = sift["registered_images"]
    assert 0.3 < sift["maa"] <= n * (n - 1) / 2 / 55
    assert sift["mean_track_length"] > 2
    assert 0 <= sift["auc1"] <= sift["auc5"] <= 1 and "pose AUC@1" in result.output
    # One camera for the 11 photos: `auto` lets bundle adjustment refine its principal point.
    assert json.loads((tmp_path / "sift" / "stats.json").read_text())["principal_point"] == "refined"
    assert "| sift |" in result.output and "pose mAA" in result.output


def test_maa_counts_failures():
    assert mean_average_accuracy([0.5] * 5 + [float("inf")] * 5) == 0.5
