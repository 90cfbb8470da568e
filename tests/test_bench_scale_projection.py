"""bench/scale/projection.py: stage times carried to larger collections by their growth exponents."""
import pytest

from sekd_sfm.bench.scale.projection import project, projection_markdown, same_run_sizes
from sekd_sfm.bench.scale.run import scale_markdown

STAGES = ("extract", "match", "map")
XEON = {"model": "Intel Xeon", "torch_kernels": "AVX512", "cores": 2}
EPYC = {"model": "AMD EPYC", "torch_kernels": "AVX2", "cores": 2}


def _size(n: int, extract: float, match: float, map_s: float, cpu=XEON, commit="abc", **ours) -> dict:
    stages = {"extract": {"time_s": extract}, "match": {"time_s": match}, "map": {"time_s": map_s}}
    return {"size": n, "run": {"cpu": cpu, "commit": commit}, "ours": {"stages": stages, **ours}}


def test_each_stage_grows_by_its_own_exponent_and_the_stages_are_summed():
    # extract linear (100 -> 200), match as N^1.5 (10 -> 10 * 2^1.5), map quadratic (5 -> 20)
    results = [_size(1000, 100.0, 10.0, 5.0), _size(2000, 200.0, 10.0 * 2 ** 1.5, 20.0)]
    p = project(results, STAGES, sizes=(10_000,))
    assert p["from_sizes"] == [1000, 2000]
    assert p["exponents"] == pytest.approx({"extract": 1.0, "match": 1.5, "map": 2.0})
    row = p["projected"][10_000]
    assert row["extract"] == pytest.approx(1000.0)            # 200 * 5
    assert row["match"] == pytest.approx(10.0 * 10 ** 1.5)     # grows from 1000 as N^1.5
    assert row["map"] == pytest.approx(500.0)                   # 20 * 5^2
    assert row["total"] == pytest.approx(1000.0 + 10.0 * 10 ** 1.5 + 500.0)


def test_only_the_largest_sizes_machine_and_commit_enter_the_fit():
    results = [_size(250, 1.0, 1.0, 1.0, cpu=EPYC), _size(500, 50.0, 50.0, 50.0),
               _size(1000, 100.0, 100.0, 100.0), _size(2000, 1.0, 1.0, 1.0, commit="old"),
               _size(4000, 1.0, 1.0, 1.0, skipped=["map"])]  # stopped before mapping: not a whole run
    assert [r["size"] for r in same_run_sizes(results)] == [2000]
    assert project(results, STAGES) is None                    # one size of that run: no slope
    kept = results[:3]
    assert [r["size"] for r in same_run_sizes(kept)] == [500, 1000]
    assert project(kept, STAGES)["exponents"] == pytest.approx({"extract": 1.0, "match": 1.0, "map": 1.0})


def test_a_stage_of_one_size_is_carried_linearly_and_named():
    first, second = _size(1000, 100.0, 10.0, 5.0), _size(2000, 200.0, 20.0, 10.0)
    second["ours"]["stages"]["refine"] = {"time_s": 30.0}      # a stage the smaller run did not have
    p = project([first, second], ("extract", "refine"), sizes=(4000,))
    assert list(p["exponents"]) == ["extract", "refine", "match", "map"]  # the stages outside the order follow
    assert p["linear"] == ["refine"] and p["projected"][4000]["refine"] == pytest.approx(60.0)
    text = "\n".join(projection_markdown(p))
    assert "Carried linearly (one size only): refine." in text
    assert "| 4,000 | 400 | 60 | 40 | 20 | 520 | 0.1 |" in text


def test_the_scale_report_ends_with_the_projection():
    results = [_size(1000, 100.0, 10.0, 5.0), _size(2000, 200.0, 20.0, 20.0)]
    for r in results:
        r["ours"].update(registered=1, scene_images=1, registered_distractors=[], auc5=1.0, auc5_covisible=1.0,
                         median_pose_error_deg=0.1, wall_s=1.0, peak_rss_mb=1.0, written_mb=1.0)
        r.update(pairs={"pairs": 1, "recall": 1.0}, distractors=[])
    report = {"results": results, "exponents": {}, "cpu_exponents": {},
              "projection": project(results, ("extract", "match", "map"))}
    text = scale_markdown(report)
    assert "fitted over N = 1000, 2000 (one machine and commit)" in text
    # 10,000 photos: extract 200 * 5, match 20 * 5, map 20 * 5^2
    assert text.rstrip().endswith("| 100,000 | 10000 | 1000 | 50000 | 61000 | 16.9 |")
    assert "| 10,000 | 1000 | 100 | 500 | 1600 | 0.4 |" in text
