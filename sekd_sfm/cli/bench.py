"""``sekd bench``: speed, the paper's evaluations (homography, pose, SfM), summaries and plots."""
from __future__ import annotations

import json
from pathlib import Path

import click

from sekd_sfm.bench.methods import with_weights
from sekd_sfm.bench.speed import benchmark_speed
from sekd_sfm.model.weights import load_model
from sekd_sfm.runtime import PRECISIONS, shared_dir

from .options import num_threads_option, weights_option


@click.group()
def bench() -> None:
    """Benchmarks: every figure quoted in the README comes from one of these commands."""


@bench.command()
@click.option("--images", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Folder of images (default: $SEKD_SHARED/data/train/coco).")
@click.option("--count", type=click.IntRange(min=1), default=8, show_default=True, help="Images per method.")
@click.option("--repeats", type=click.IntRange(min=1), default=2, show_default=True, help="Timed passes over them.")
@click.option("--height", type=click.IntRange(min=16), default=480, show_default=True)
@click.option("--width", type=click.IntRange(min=16), default=640, show_default=True)
@click.option("--max-keypoints", type=click.IntRange(min=1), default=2000, show_default=True)
@num_threads_option
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also write the results as JSON.")
@weights_option
def speed(images, count, repeats, height, width, max_keypoints, num_threads, output, weights) -> None:
    """Images/s at 480x640 for plain fp32 SEKD, the fast path, int8 (with the int8 extra) and OpenCV SIFT, in one run.

    \b
    Example:
      sekd bench speed --weights ../shared/weights/sekd/sekd.pth
    """
    net, _ = load_model(weights)
    result = benchmark_speed(net, images or shared_dir() / "data/train/coco", count, height, width, repeats,
                             max_keypoints, num_threads)
    click.echo(f"{result['images']} images at {height}x{width}, {result['threads']} threads, "
               f"{result['gflop_per_image']:.1f} GFLOP per SEKD image, auto precision = {result['precision_auto']}, "
               f"{result['fast_forward']} forward")
    cpu = result["cpu"]
    have = [name for name, present in cpu["features"].items() if present]
    missing = [name for name, present in cpu["features"].items() if not present]
    click.echo(f"cpu: {cpu['model']}, {cpu['cores']} cores; has {' '.join(have) or 'none of'}"
               + (f"; lacks {' '.join(missing)}" if missing else "") + f"; torch kernels {cpu['torch_kernels']}")
    for name, rate in result["images_per_s"].items():
        gflops = result["gflop_per_s"].get(name)
        click.echo(f"  {name:<18}{rate:7.2f} images/s" + (f"  {gflops:6.1f} GFLOP/s" if gflops else ""))
    for name, error in result["failed"].items():
        click.echo(f"  {name:<18} failed, not timed: {error}")
    click.echo(f"  fast/plain {result['fast_vs_plain']:.2f}x   fast/SIFT {result['fast_vs_sift']:.2f}x")
    if "int8_vs_fast_fp32" in result:
        click.echo(f"  int8/fast fp32 {result['int8_vs_fast_fp32']:.2f}x   int8/SIFT {result['int8_vs_sift']:.2f}x")
    if "lite_vs_sift" in result:  # SEKD-Lite rows (docs/model_card_lite.md); agreement is against Lite fp32
        click.echo(f"  lite auto ({result['precision_lite_auto']})/SIFT {result['lite_vs_sift']:.2f}x   "
                   f"lite fp32/SIFT {result['lite_fp32_vs_sift']:.2f}x   {result['lite_gflop_per_image']:.1f} GFLOP per Lite image")
    if "lite_int8_vs_lite_fp32" in result:
        click.echo(f"  lite int8/lite fp32 {result['lite_int8_vs_lite_fp32']:.2f}x")
    for key in ("agreement_fast_fp32", "agreement_fast_auto", "agreement_int8", "agreement_lite_auto",
                "agreement_lite_int8"):
        if key not in result:  # int8: only with the optional extra installed
            continue
        a = result[key]
        click.echo(f"  {key}: {100 * a['same_pixel']:.1f}% same pixel, descriptor cosine median {a['cosine_median']:.5f} min {a['cosine_min']:.4f}")
    if output:
        output.write_text(json.dumps(result, indent=2))


@bench.command()
@click.argument("roots", nargs=-1, type=click.Path(file_okay=False, path_type=Path))
@click.option("-m", "--method", "methods", multiple=True,
              help="[LABEL=]FEATURE[:WEIGHTS], repeatable: sift, orb, akaze, brisk, kaze, disk, aliked, xfeat, "
                   "sekd (the --model / --weights model, else the default), sekd:own, sekd:authors, sekd:lite, sekd:PATH. "
                   "Default: every classic and peer, plus sekd:--weights if given.")
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("bench-homography"),
              show_default=True, help="Folder for results.json, results.md, plots and the prediction cache.")
@click.option("--resize-max", type=click.IntRange(min=0), default=640, show_default=True, help="Long side limit in px; 0 = full resolution.")
@click.option("--max-keypoints", type=click.IntRange(min=1), default=500, show_default=True)
@click.option("--precision", type=click.Choice(PRECISIONS), default="fp32", show_default=True,
              help="SEKD network precision (fp32: the model's own numbers; auto: the fast path of `extract`; "
                   "int8: quantized, needs the int8 extra).")
@click.option("--ransac-runs", type=click.IntRange(min=1), default=50, show_default=True,
              help="RANSAC runs per pair: the first on the matches in order (the paper's Avg.HA), the others on "
                   "shuffled orders; the table adds their mean ± sd, which ranks methods closer than one run can.")
@num_threads_option
@weights_option
def homography(roots, methods, output, resize_max, max_keypoints, precision, ransac_runs, num_threads, weights) -> None:
    """Homography estimation (the paper's Table 2 / Fig. 4) on HPatches-layout sequences.

    \b
    ROOTS are sequence folders (1.*..N.*, H_1_k) or folders of them; default: the shared
    hpatches and oxford sequences. Prints the table; writes JSON, Markdown and PNG plots.
    Example:
      sekd bench homography -m sift -m sekd:../shared/weights/sekd/sekd.pth -o out/hom
    """
    from sekd_sfm.bench.homography import HomographyConfig, run_homography_benchmark
    from sekd_sfm.bench.methods import parse_method

    roots = list(roots) or [shared_dir() / "data/homography/hpatches", shared_dir() / "data/homography/oxford"]
    specs = method_specs(methods, weights)
    config = HomographyConfig(resize_max=resize_max or None, max_keypoints=max_keypoints, precision=precision,
                              ransac_runs=ransac_runs, num_threads=num_threads)
    path = run_homography_benchmark(roots, [parse_method(m) for m in specs], output, config)
    click.echo((path.parent / "results.md").read_text())
    click.echo(f"results: {path}")


DEFAULT_METHODS = ["sift", "orb", "akaze", "brisk", "kaze", "disk", "aliked", "xfeat"]


def method_specs(methods: tuple[str, ...], weights: str | None) -> list[str]:
    """The ``-m`` list to run: every classic and peer plus ``sekd:WEIGHTS`` when none is given."""
    if not methods:
        return DEFAULT_METHODS + ([f"sekd:{weights}"] if weights else [])
    return with_weights(methods, weights)


@bench.command()
@click.argument("scenes", nargs=-1, type=click.Path(file_okay=False, path_type=Path))
@click.option("-m", "--method", "methods", multiple=True, help="As for `bench homography`. Default: every classic and peer.")
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("bench-pose"),
              show_default=True, help="Folder for results.json, results.md, pose_accuracy.png and the feature cache.")
@click.option("--max-keypoints", type=click.IntRange(min=1), default=2000, show_default=True)
@click.option("--resize-max", type=click.IntRange(min=0), default=1600, show_default=True, help="Extraction size limit; 0 = full.")
@click.option("--precision", type=click.Choice(["auto", "fp32", "bf16"]), default="fp32", show_default=True,
              help="SEKD network precision (fp32: the model's own numbers; auto: the fast path of `extract`).")
@click.option("--ransac-runs", type=click.IntRange(min=1), default=10, show_default=True,
              help="RANSAC runs per pair: the first on the matches in order (the mAA / AUC columns), the others on "
                   "shuffled orders; the table adds their mean ± sd.")
@num_threads_option
@weights_option
def pose(scenes, methods, output, max_keypoints, resize_max, precision, ransac_runs, num_threads, weights) -> None:
    """Relative pose on every image pair of scenes with ground-truth cameras (mAA, AUC).

    \b
    SCENES: Strecha layout (images + gt_dense_cameras/*.camera) or images/ + a COLMAP
    model as ground truth in sparse/ or sparse/0/. Default: the shared fountain-P11.
    Example:
      sekd bench pose -m sift -m sekd:../shared/weights/sekd/sekd.pth -o out/pose
    """
    from sekd_sfm.bench.methods import parse_method
    from sekd_sfm.bench.pose import PoseConfig, run_pose_benchmark

    scenes = list(scenes) or [shared_dir() / "data/sfm/fountain-P11"]
    specs = method_specs(methods, weights)
    config = PoseConfig(max_keypoints=max_keypoints, resize_max=resize_max or None, precision=precision,
                        ransac_runs=ransac_runs, num_threads=num_threads)
    path = run_pose_benchmark(scenes, [parse_method(m) for m in specs], output, config)
    click.echo((path.parent / "results.md").read_text())
    click.echo(f"results: {path}")


@bench.command()
@click.option("-m", "--method", "methods", multiple=True,
              help="As for `bench homography`. Default: sift and sekd (the default embedded model).")
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("bench-localization"),
              show_default=True, help="Folder for the warped photos, each method's files, results.json and results.md.")
@click.option("--num-images", type=click.IntRange(min=1), default=20, show_default=True,
              help="Shared COCO photos to warp (the first N).")
@click.option("--max-keypoints", type=click.IntRange(min=1), default=2000, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the random homographies.")
@num_threads_option
def localization(methods, output, num_images, max_keypoints, seed, num_threads) -> None:
    """How closely matched keypoints follow the surface: photos warped by known homographies.

    \b
    Per method: the distance (px) between each correct mutual-NN match's keypoint and its
    partner's true position, as detected and after the keypoint refinement `sekd reconstruct`
    applies (median, RMS, share under 0.5 px). The pixel error of keypoints is what bundle
    adjustment accumulates into drift on long walks.
    Example:
      sekd bench localization -m sift -m sekd -m sekd:authors -o out/loc
    """
    from sekd_sfm.bench.localization import (
        LocalizationConfig,
        run_localization_benchmark,
    )
    from sekd_sfm.bench.methods import parse_method

    config = LocalizationConfig(num_images=num_images, max_keypoints=max_keypoints, seed=seed, num_threads=num_threads)
    path = run_localization_benchmark(output, [parse_method(m) for m in (methods or ("sift", "sekd"))], config)
    click.echo((path.parent / "results.md").read_text())
    click.echo(f"results: {path}")


_RESULTS = click.Path(dir_okay=False, exists=True, path_type=Path)


@bench.command()
@click.option("--homography", "homography_results", type=_RESULTS, multiple=True,
              help="results.json of `bench homography` (repeatable: a later run's rows replace earlier ones).")
@click.option("--pose", "pose_results", type=_RESULTS, multiple=True, help="results.json of `bench pose` (repeatable).")
@click.option("--sfm", "sfm_results", type=_RESULTS, multiple=True, help="results.json of `bench sfm` (repeatable).")
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("bench-summary"),
              show_default=True, help="Folder for summary.md and summary.png.")
@click.option("--highlight", multiple=True, help="Method label drawn in a different colour (repeatable).")
def summary(homography_results, pose_results, sfm_results, output, highlight) -> None:
    """One table and one plot joining the homography, pose and SfM results by method label.

    \b
    Example:
      sekd bench summary --homography out/hom/results.json --pose out/pose/results.json \\
          --sfm out/sfm/results.json -o out/summary --highlight sekd_ours
    """
    from sekd_sfm.bench.summary import write_summary

    if not (homography_results or pose_results or sfm_results):
        raise click.UsageError("give at least one of --homography, --pose, --sfm")
    path = write_summary(output, list(homography_results), list(pose_results), list(sfm_results), tuple(highlight))
    click.echo(path.read_text())
    click.echo(f"summary: {path} and {path.with_suffix('.png')}")


@bench.command()
@click.argument("results_dir", type=click.Path(file_okay=False, exists=True, path_type=Path))
def plots(results_dir) -> None:
    """Redraw every benchmark plot under RESULTS_DIR from the results.json files there.

    Figures that combine several runs (a later run's rows replace earlier ones of the same
    method) are listed in RESULTS_DIR/figures.json; see docs/benchmarks.md.

    \b
    Example:
      sekd bench plots docs/results
    """
    from sekd_sfm.bench.report import regenerate_plots

    for path in regenerate_plots(results_dir):
        click.echo(path)


from . import bench_sfm

bench.add_command(bench_sfm.sfm)
bench.add_command(bench_sfm.ratios)

from . import bench_scale

bench.add_command(bench_scale.scale)

from . import bench_maps

bench.add_command(bench_maps.maps)

from . import bench_pairs

bench.add_command(bench_pairs.pairs)

from . import bench_captures

bench.add_command(bench_captures.captures)
