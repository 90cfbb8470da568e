"""The run's report (``sekd_sfm.pipelines.report``): why a photo is in no model, and the summary lines."""
from __future__ import annotations

from sekd_sfm.pipelines.report import format_summary, unregistered_report


def _stats() -> dict:
    """Photos a0-a3 in model 0; b0-b1 linked to each other only; c0-c2 linked to each other only; d0 linked to a0
    but not registered; e0 with a pair under 15 inliers; f0 with no pair at all."""
    pairs = [("a0", "a1", 300, 200), ("a1", "a2", 300, 180), ("a2", "a3", 250, 150), ("b0", "b1", 120, 60),
             ("c0", "c1", 90, 40), ("c1", "c2", 90, 35), ("a0", "d0", 80, 30), ("e0", "a3", 40, 12)]
    names = ["a0", "a1", "a2", "a3", "b0", "b1", "c0", "c1", "c2", "d0", "e0", "f0"]
    images = {name: {"keypoints": 1000, "verified_pairs": 0, "best_inliers": 0} for name in names}
    for a, b, _, inliers in pairs:
        for name in (a, b):
            images[name]["best_inliers"] = max(images[name]["best_inliers"], inliers)
            images[name]["verified_pairs"] += inliers >= 15
    return {"min_inliers": 15, "pairs": sorted(pairs, key=lambda p: -p[3]), "images": images}


def test_every_unregistered_photo_gets_its_reason():
    stats = _stats()
    where = dict.fromkeys(["a0", "a1", "a2", "a3"], 0)
    report = {item["name"]: item for item in unregistered_report(
        ["b0", "b1", "c0", "c1", "c2", "d0", "e0", "f0"], stats, where)}
    reasons = {name: item["reason"] for name, item in report.items()}
    assert reasons["b0"] == reasons["b1"] == ("verified pairs only with 1 other photo(s) in no model: a model needs "
                                              "3 photos")
    assert reasons["c1"].startswith("one of 3 photos linked only to each other, which the mapper could not start")
    assert reasons["d0"].startswith("verified pairs with photos of model 0, but the mapper could not register it")
    assert reasons["e0"] == "no verified pair: its best pair has 12 inliers, a pair needs 15"
    assert reasons["f0"] == "no verified pair: its best pair has 0 inliers, a pair needs 15"
    assert report["d0"]["best_pairs"] == [{"with": "a0", "matches": 80, "inliers": 30}]


def test_the_summary_gives_model_sizes_reasons_and_the_chance_check():
    stats = {"status": "ok", "failure": None,
             "model": {"registered_images": 8, "points3D": 900, "mean_track_length": 3.5,
                       "mean_reprojection_error_px": 0.4},
             "models": [{"registered_images": 8}, {"registered_images": 3}],
             "matches": {"images": 12, "pairs_with_matches": 66, "median_matches": 40, "verified_pairs": 30,
                         "median_inliers": 50},
             "chance": {"verified": 34, "tested": 12, "dropped": 4, "config": {"margin": 1.25}},
             "unregistered": [{"name": "x.jpg", "reason": "no verified pair: its best pair has 9 inliers, a pair "
                                                         "needs 15"}]}
    text = format_summary(stats)
    assert "  models             2: 8, 3 photos (the others in models/)" in text
    assert "  chance check       4 of 34 verified pairs dropped" in text
    assert "  not registered     x.jpg: no verified pair: its best pair has 9 inliers" in text
