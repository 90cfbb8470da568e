"""``sekd bench pairs``: how many verified pairs are wrong, against the true cameras."""
from __future__ import annotations

from pathlib import Path

import click

from .options import num_threads_option, weights_option


def _methods(ctx, param, value: str) -> tuple[str, ...]:
    from sekd_sfm.bench.pairs import METHODS

    methods = tuple(dict.fromkeys(v.strip() for v in value.split(",") if v.strip()))
    wrong = [m for m in methods if m not in METHODS]
    if not methods or wrong:
        raise click.BadParameter(f"{value!r}: give one or more of {', '.join(METHODS)}, separated by commas")
    return methods


@click.command()
@click.argument("scene")
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("bench-pairs"),
              show_default=True, help="Folder for each method's work folder, results.json and results.md.")
@click.option("--methods", default="sekd,sift", show_default=True, callback=_methods,
              help="sekd: our pipeline up to its verification step; sift: pycolmap's SIFT extraction, matching "
                   "and verification on the same pairs (every pair without sekd).")
@click.option("--resize-max", type=click.IntRange(min=0), default=1600, show_default=True,
              help="Long side (px) of the photos for extraction, both methods; 0 = full size.")
@click.option("--max-keypoints", type=click.IntRange(min=1), default=None,
              help="sekd's keypoints per photo (default: `sekd reconstruct`'s).")
@click.option("--max-error", "max_error_deg", type=click.FloatRange(min=0, min_open=True), default=10.0,
              show_default=True, help="A pair's pose is off when its rotation or translation direction is off by more "
                                      "(deg).")
@click.option("--min-truth-support", type=click.FloatRange(min=0, max=1), default=0.8, show_default=True,
              help="A pair whose pose is off is still right (ambiguous) when the true pose keeps at least this share "
                   "of the inliers the estimated pose keeps: true matches on a plane or through a long lens fit "
                   "several poses.")
@click.option("--min-inliers", type=click.IntRange(min=5), default=15, show_default=True,
              help="Pairs with fewer inlier matches are not verified (COLMAP's and the mapper's default).")
@click.option("--near", type=click.IntRange(min=1), default=2, show_default=True,
              help="Near pairs: photos at most this far apart in the sequence (cyclic on a ring), or by "
                   "nearest-centre rank / 2 when the photos form no sequence.")
@click.option("--seed", type=int, default=0, show_default=True,
              help="RANSAC seed of sekd's verification and of the scoring.")
@click.option("--score-only", is_flag=True,
              help="Score the databases an earlier run left in OUTPUT again (other thresholds), running nothing.")
@num_threads_option
@weights_option
def pairs(scene, output, methods, resize_max, max_keypoints, max_error_deg, min_truth_support, min_inliers, near, seed,
          score_only, num_threads, weights) -> None:
    """Verified pairs that are wrong: each pair's own inliers against the true cameras.

    \b
    SCENE: a folder with images/ and gt_dense_cameras/ (Strecha .camera files: fountain-P11, or a
    scene of `sekd bench scale`, whose covisibility.txt and distractors are used too), or a name
    under $SEKD_SHARED/data/sfm. Per method: the pairs verification accepts (COLMAP's database,
    at least --min-inliers inliers); per pair, the relative pose its inlier matches give with the
    TRUE intrinsics (essential matrix, 5-point RANSAC) against the true one: off beyond
    --max-error deg; wrong when off and the true pose explains fewer than --min-truth-support of
    the inliers the estimated one explains. Reports wrong pairs overall and among near and far
    pairs, median inliers of right and wrong pairs and a histogram of the wrong pairs' inliers;
    writes results.json, results.md and OUT/<method>/pair_scores.json (one row per pair).

    \b
    Examples:
      sekd bench pairs fountain-P11 -o out/pairs --resize-max 1024
      sekd bench pairs fountain-P11 -o out/pairs --score-only --max-error 5
      sekd bench pairs out/scale/n47/scene -o out/pairs-ring --methods sekd,sift --model lite
    """
    from sekd_sfm.bench.pairs import PairsBenchConfig, run_pairs_benchmark

    config = PairsBenchConfig(methods=methods, resize_max=resize_max or None, weights=weights,
                              max_keypoints=max_keypoints, max_error_deg=max_error_deg,
                              min_truth_support=min_truth_support, min_inliers=min_inliers, near=near,
                              num_threads=num_threads, seed=seed, score_only=score_only)
    path = run_pairs_benchmark(scene, output, config)
    click.echo((path.parent / "results.md").read_text())
    click.echo(f"results: {path}")
