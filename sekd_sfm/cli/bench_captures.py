"""``sekd bench captures``: reconstruct on a generated video, camera rig or set of panoramas, against the truth."""
from __future__ import annotations

from pathlib import Path

import click

from .options import num_threads_option


@click.command()
@click.argument("kind", type=click.Choice(["video", "rig", "panorama"]))
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("bench-captures"),
              show_default=True, help="Folder; everything goes to OUTPUT/KIND/.")
@click.option("--count", type=click.IntRange(min=2), default=None,
              help="Video frames / rig instants / panoramas [default: 600 / 50 / 30].")
@click.option("--image-size", type=click.IntRange(min=64), default=None,
              help="Long side of the video frames and rig photos (px) [default: 640]; panoramas: their width "
                   "[default: 2048].")
@click.option("--spacing", type=click.FloatRange(min=0.1), default=None,
              help="Panoramas: metres between them along the walk [default: 2.5].")
@click.option("--seed", type=int, default=0, show_default=True, help="Scene, cameras, blur and mapper seed.")
@click.option("--no-baseline", is_flag=True, help="Skip the baseline run (video, rig).")
@num_threads_option
def captures(kind, output, count, image_size, spacing, seed, no_baseline, num_threads) -> None:
    """`sekd reconstruct` on a generated capture of the city block of `bench scale`, with known cameras.

    \b
    KIND, what is generated (OUTPUT/KIND/scene) and measured against the true poses:
      video     a walk.avi (MJPG, 30 fps, 0.25 m per frame, 15% of the frames motion blurred);
                keyframes chosen, blurred among them, registered, seconds of video without a
                registered keyframe (gaps > 1 s), models, pose AUC@5/10/20 over keyframe pairs.
                Baseline: every 5th frame as photos.
      rig       two cameras on a rig (camera 1: 0.3 m right, turned 40 deg) at --count instants;
                reconstructed with rig.json (relative pose unknown; rig_known.json has it).
                Registered photos, AUC over all pairs, the model rig's error (rotation,
                translation direction) and per instant the deviation of the two cameras' relative
                rotation (median, max). Baseline: the same photos without the rig.
      panorama  equirectangular 2:1 panoramas --spacing m apart (true world-to-panorama poses); posed
                panoramas (OUT/panoramas.txt), AUC over pairs, median rotation error.
    Pairs with an unregistered image count as failures. Results: OUTPUT/KIND/results.json
    (version, commit, machine, command, settings, figures) and results.md. A rerun reuses
    the generated capture and the finished runs.

    \b
    Examples:
      sekd bench captures rig -o out/captures
      sekd bench captures video --count 300 --no-baseline -o out/captures
      sekd bench captures panorama --image-size 1024 -o out/captures
    """
    from sekd_sfm.bench.captures import CapturesConfig, run_captures_benchmark

    config = CapturesConfig(kind, count, image_size, seed, not no_baseline, num_threads, spacing=spacing)
    path = run_captures_benchmark(output, config)
    click.echo((path.parent / "results.md").read_text())
    click.echo(f"results: {path}")
