"""Homography benchmark: metrics on hand-made cases, the dataset reader, and the harness check."""
import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import GRAFFITI, SEKD_WEIGHTS

from sekd_sfm.bench.homography import (
    HomographyConfig,
    evaluate_pair,
    run_homography_benchmark,
    summarise,
)
from sekd_sfm.bench.methods import Method, parse_method
from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.evaluation import metrics
from sekd_sfm.evaluation.datasets import find_sequences


def test_identity_homography_has_zero_corner_error():
    assert metrics.corner_error(np.eye(3), np.eye(3), 640, 480) == 0.0
    assert metrics.corner_error(None, np.eye(3), 640, 480) == float("inf")


def test_known_shift_gives_expected_accuracy():
    shift = np.array([[1, 0, 2.5], [0, 1, 0], [0, 0, 1.0]])
    error = metrics.corner_error(shift, np.eye(3), 100, 100)
    assert error == pytest.approx(2.5)
    curve = metrics.accuracy_curve([error, 0.5, float("inf")])
    assert curve.tolist() == pytest.approx([1 / 3, 1 / 3] + [2 / 3] * 8)


def test_match_accuracy_and_repeatability_by_hand():
    kp0 = np.array([[10.0, 10.0], [20.0, 20.0], [30.0, 30.0]])
    h = np.array([[1, 0, 5], [0, 1, 0], [0, 0, 1.0]])
    kp1 = kp0 + [5, 0] + [[0, 0], [2, 0], [0, 50]]   # errors 0, 2, 50 px
    mma = metrics.match_accuracy(kp0, kp1, np.array([[0, 0], [1, 1], [2, 2]]), h)
    assert mma[0] == pytest.approx(1 / 3) and mma[1] == pytest.approx(2 / 3) and mma[9] == pytest.approx(2 / 3)
    assert metrics.match_accuracy(kp0, kp1, np.zeros((0, 2), int), h).tolist() == [0.0] * 10
    # Visible in both: all three of image 0, and kp1[2] = (35, 80) maps back inside image 0 too.
    assert metrics.repeatability(kp0, kp1, h, (100, 100), (100, 100)) == pytest.approx(4 / 6)


def test_pose_metrics_by_hand():
    angle = np.radians(3.0)
    r = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    assert metrics.rotation_error_deg(r, np.eye(3)) == pytest.approx(3.0)
    assert metrics.translation_error_deg(np.array([1.0, 0, 0]), np.array([1.0, 1.0, 0])) == pytest.approx(45.0)
    assert metrics.mean_average_accuracy([0.5, 5.5, 20.0]) == pytest.approx((10 + 5) / 3 / 10)
    # Errors 0 and 10 deg: recall 0.5 from 0 to 10 deg, so AUC@10 = 0.5 (area of the step) ... up to the jump.
    assert metrics.pose_auc([0.0, 10.0], 10) == pytest.approx(0.5)
    assert metrics.pose_auc([0.0, 0.0], 5) == pytest.approx(1.0)


def test_ransac_orders_are_the_matcher_order_then_seeded_permutations():
    assert metrics.ransac_order(5, 0).tolist() == [0, 1, 2, 3, 4]
    first, again, other = (metrics.ransac_order(50, run) for run in (1, 1, 2))
    assert sorted(first.tolist()) == list(range(50)) and first.tolist() == again.tolist()
    assert first.tolist() != other.tolist() and first.tolist() != list(range(50))
    assert metrics.ransac_order(0, 3).size == 0
    assert metrics.mean_and_sd([0.5, 0.7]) == pytest.approx((0.6, 0.1))
    assert metrics.mean_and_sd([0.4]) == (0.4, 0.0)


def test_summary_of_ransac_runs_by_hand():
    # Two pairs, two runs: run 0 solves both within 1 px; run 1 solves pair 1 at 4 px and fails pair 2.
    pairs = [{"subset": "i", "corner_error": 0.5, "corner_error_runs": [0.5, 4.0], "mma": [0] * 10,
              "repeatability": 0.5, "matches": 10},
             {"subset": "v", "corner_error": 0.5, "corner_error_runs": [0.5, float("inf")], "mma": [0] * 10,
              "repeatability": 0.5, "matches": 10}]
    s = summarise(pairs)
    # Avg.HA@1:10 per run: run 0 = 1.0; run 1 = (7/10 for pair 1 + 0 for pair 2) / 2 = 0.35.
    assert s["ransac_runs"] == 2 and s["avg_ha_all"] == 1.0
    assert (s["avg_ha_all_mean"], s["avg_ha_all_sd"]) == pytest.approx((0.675, 0.325))
    assert (s["avg_ha_i_mean"], s["avg_ha_v_mean"]) == pytest.approx((0.85, 0.5))


def test_first_ransac_run_is_the_papers_single_run():
    rng = np.random.default_rng(0)
    kp0 = rng.uniform(0, 300, (60, 2))
    kp1 = kp0 + [3.0, -2.0]
    kp1[:20] = rng.uniform(0, 300, (20, 2))   # a third of the matches are wrong
    f0 = {"keypoints": kp0.astype(np.float32), "descriptors": np.eye(60, 64, dtype=np.float32), "image_size": [300, 300]}
    f1 = {"keypoints": kp1.astype(np.float32), "descriptors": np.eye(60, 64, dtype=np.float32), "image_size": [300, 300]}
    truth = np.array([[1, 0, 3.0], [0, 1, -2.0], [0, 0, 1]])
    single, runs = evaluate_pair(f0, f1, truth, False), evaluate_pair(f0, f1, truth, False, ransac_runs=5)
    assert single["corner_error_runs"] == [single["corner_error"]]
    assert runs["corner_error"] == single["corner_error"] and len(runs["corner_error_runs"]) == 5
    assert max(runs["corner_error_runs"]) < 0.1    # every order finds the shift from the 40 right matches


def make_sequence(folder, name, shift=(7.0, 3.0), sizes=((120, 160), (100, 150))):
    rng = np.random.default_rng(1)
    base = cv2.GaussianBlur((rng.random((200, 260, 3)) * 255).astype(np.uint8), (5, 5), 2)
    seq = folder / name
    seq.mkdir(parents=True)
    h, w = sizes[0]
    cv2.imwrite(str(seq / "1.png"), base[:h, :w])
    h2, w2 = sizes[1]
    cv2.imwrite(str(seq / "2.jpg"), base[int(shift[1]):int(shift[1]) + h2, int(shift[0]):int(shift[0]) + w2], [cv2.IMWRITE_JPEG_QUALITY, 98])
    np.savetxt(seq / "H_1_2", [[1, 0, -shift[0]], [0, 1, -shift[1]], [0, 0, 1]])
    return seq


def test_dataset_reader_layouts(tmp_path):
    make_sequence(tmp_path / "root", "i_a")
    single = make_sequence(tmp_path, "v_b")
    seqs = find_sequences([tmp_path / "root", single])
    assert [(s.name, s.subset, sorted(s.images), sorted(s.homographies)) for s in seqs] == [
        ("i_a", "i", [1, 2], [2]), ("v_b", "v", [1, 2], [2])]
    (tmp_path / "empty").mkdir()
    with pytest.raises(SekdError, match="no homography sequences"):
        find_sequences([tmp_path / "empty"])
    with pytest.raises(SekdError, match="folder not found"):
        find_sequences([tmp_path / "missing"])


def test_parse_method():
    assert parse_method("sift") == Method("sift", "sift", None)
    assert parse_method("sekd:/w/sekd_wo_affine.pth") == Method("sekd_wo_affine", "sekd", "/w/sekd_wo_affine.pth")
    assert parse_method("ours=sekd:/w/x.pth") == Method("ours", "sekd", "/w/x.pth")
    with pytest.raises(SekdError, match="unknown method"):
        parse_method("surf")


def test_a_bare_sekd_method_takes_the_model_of_model_or_weights():
    from sekd_sfm.bench.methods import with_weights
    from sekd_sfm.cli.bench import method_specs

    assert with_weights(("sift", "sekd", "mine=sekd", "sekd:own", "sekd:/w/x.pth"), "/m/sekd_lite.pth") == [
        "sift", "sekd:/m/sekd_lite.pth", "mine=sekd:/m/sekd_lite.pth", "sekd:own", "sekd:/w/x.pth"]
    assert with_weights(("sekd",), None) == ["sekd"]  # no --model / --weights: the default model
    assert parse_method(with_weights(["sekd"], "/m/sekd_lite.pth")[0]) == Method("sekd_lite", "sekd", "/m/sekd_lite.pth")
    assert method_specs((), None)[-1] == "xfeat" and method_specs((), "/m/a.pth")[-1] == "sekd:/m/a.pth"
    assert parse_method("sekd:lite").weights.endswith("sekd_lite.pth")  # the embedded Lite by name


def test_tiny_end_to_end_with_a_pure_translation(tmp_path):
    make_sequence(tmp_path / "data", "v_shift")
    out = run_homography_benchmark([tmp_path / "data"], [parse_method("sift"), parse_method("orb")], tmp_path / "out",
                                   HomographyConfig(resize_max=None, crop_multiple=4))
    results = json.loads(out.read_text())
    sift = results["methods"]["sift"]["summary"]
    assert sift["ha_all"][2] == 1.0  # a 2-image sequence with a known shift is solved within 3 px
    assert sift["ransac_runs"] == 50 and sift["avg_ha_all_sd"] >= 0
    assert "mean ± sd (50 runs)" in (tmp_path / "out/results.md").read_text()
    single = run_homography_benchmark([tmp_path / "data"], [parse_method("sift")], tmp_path / "one",
                                      HomographyConfig(resize_max=None, crop_multiple=4, ransac_runs=1))
    table = (single.parent / "results.md").read_text()
    assert "mean ± sd" not in table and table.count("| sift |") == 1
    assert len(table.splitlines()[2].split("|")) == len(table.splitlines()[4].split("|"))  # header and row agree
    assert (tmp_path / "out/homography_accuracy.png").is_file() and "| orb |" in (tmp_path / "out/results.md").read_text()


def test_harness_reproduces_the_authors_mma_on_v_graffiti(tmp_path, shared):
    """The authors' code gives MMA@3 0.83 / 0.70 / 0.44 / 0.12 / 0.02 for pairs 1-2 .. 1-6 at full resolution."""
    out = run_homography_benchmark([GRAFFITI], [parse_method(f"sekd:{SEKD_WEIGHTS}")], tmp_path,
                                   HomographyConfig(resize_max=None, precision="fp32"))
    pairs = json.loads(out.read_text())["methods"]["sekd"]["pairs"]
    assert [p["pair"] for p in pairs] == ["1-2", "1-3", "1-4", "1-5", "1-6"]
    assert np.abs(np.array([p["mma"][2] for p in pairs]) - [0.83, 0.70, 0.44, 0.12, 0.02]).max() <= 0.03


def test_cli_skips_absent_peer_weights(tmp_path, monkeypatch, caplog):
    make_sequence(tmp_path / "data", "v_shift")
    monkeypatch.setenv("SEKD_SHARED", str(tmp_path / "nothing"))
    result = CliRunner().invoke(sekd, ["bench", "homography", str(tmp_path / "data"), "-m", "disk", "-m", "sift",
                                       "-o", str(tmp_path / "out"), "--resize-max", "0"])
    assert result.exit_code == 0, result.output
    assert "skipping disk" in caplog.text and "| sift |" in result.output and "| disk |" not in result.output


def test_cli_num_threads_is_used_and_recorded(tmp_path):
    import torch

    import sekd_sfm

    make_sequence(tmp_path / "data", "v_shift")
    before = torch.get_num_threads()
    try:
        result = CliRunner().invoke(sekd, ["bench", "homography", str(tmp_path / "data"), "-m", "sift", "--num-threads", "1",
                                           "-o", str(tmp_path / "out"), "--resize-max", "0", "--ransac-runs", "1"])
        assert result.exit_code == 0, result.output
        results = json.loads((tmp_path / "out/results.json").read_text())
        assert results["config"]["num_threads"] == 1 == results["timing"]["threads"] == torch.get_num_threads()
        assert results["timing"]["cpu"]["cores"] >= 1
        record = results["record"]  # every result names its version, source commit, machine and command
        assert record["sekd_sfm"] == sekd_sfm.__version__ and record["cpu"]["model"]
        assert set(record) == {"sekd_sfm", "commit", "cpu", "command", "date"}
    finally:
        torch.set_num_threads(before)
    refused = CliRunner().invoke(sekd, ["bench", "pose", "--num-threads", "0"])
    assert refused.exit_code == 2 and "--num-threads" in refused.output


def test_an_interrupt_stops_the_whole_benchmark(tmp_path, monkeypatch):
    """Ctrl-C / SIGTERM during one method's extraction must not be reported as that method failing."""
    from sekd_sfm.bench import homography
    from sekd_sfm.errors import Interrupted

    make_sequence(tmp_path / "data", "v_shift")

    def interrupted(*args, **kwargs):
        raise Interrupted("interrupted: 0 more images saved; run the same command again to resume")

    monkeypatch.setattr(homography, "cached_features", interrupted)
    with pytest.raises(Interrupted):
        run_homography_benchmark([tmp_path / "data"], [parse_method("sift"), parse_method("orb")], tmp_path / "out",
                                 HomographyConfig(resize_max=None))
    assert not (tmp_path / "out/results.json").exists()


def test_feature_cache_follows_the_model_file_content(tmp_path, shared):
    """A new model at the same path (e.g. a newly shipped embedded model) must not reuse cached features."""
    import shutil

    import torch

    from sekd_sfm.bench.methods import cache_file
    from sekd_sfm.model.weights import load_model, save_checkpoint

    weights = tmp_path / "model.pth"
    shutil.copy(SEKD_WEIGHTS, weights)
    method = parse_method(f"mine=sekd:{weights}")
    config = method.feature_config(500)
    before = cache_file(method, config, tmp_path, tmp_path)
    assert cache_file(method, config, tmp_path, tmp_path) == before
    net = load_model(weights)[0]
    with torch.no_grad():
        next(net.parameters()).add_(1.0)
    save_checkpoint(net, weights)
    assert cache_file(method, config, tmp_path, tmp_path) != before
    sift = parse_method("sift")
    assert cache_file(sift, sift.feature_config(500), tmp_path, tmp_path).name.startswith("sift-")


def test_feature_cache_of_prepared_images_moves_with_the_output_folder(tmp_path):
    """Images prepared inside the cache name it by their place there: a copied output folder reuses it."""
    from sekd_sfm.bench.methods import cache_file

    sift = parse_method("sift")
    config = sift.feature_config(500)
    a, b = tmp_path / "a" / "cache", tmp_path / "b" / "cache"
    assert cache_file(sift, config, a / "images", a).name == cache_file(sift, config, b / "images", b).name
    assert cache_file(sift, config, a / "images", a).name != cache_file(sift, config, a / "other", a).name
    # Images outside the cache (a pose scene's photos) still count by their own folder.
    assert cache_file(sift, config, tmp_path / "scene1", a).name != cache_file(sift, config, tmp_path / "scene2", a).name
    assert cache_file(sift, config, tmp_path / "scene1", a).name == cache_file(sift, config, tmp_path / "scene1", b).name


def test_results_json_keeps_number_lists_on_one_line_and_rounds_only_the_runs():
    from sekd_sfm.bench.report import results_json

    results = {"config": {"ransac_runs": 3}, "methods": {
        "a": {"summary": {"mma": [0.25, 0.5]}, "pairs": [{"corner_error": 1.23456, "corner_error_runs": [1.23456, float("inf"), 7.0]}]},
        "b": {"error": "weights not found"}}}
    text = results_json(results)
    assert '"corner_error_runs": [1.23, Infinity, 7.0]' in text and '"mma": [0.25, 0.5]' in text
    back = json.loads(text)
    assert back["methods"]["a"]["pairs"][0]["corner_error"] == 1.23456 and back["methods"]["b"] == {"error": "weights not found"}
    assert results["methods"]["a"]["pairs"][0]["corner_error_runs"][0] == 1.23456   # the caller's dict is untouched
