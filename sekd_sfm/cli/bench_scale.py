"""``sekd bench scale``: every stage's cost against the number of photos, on generated scenes."""
from __future__ import annotations

from pathlib import Path

import click

from .options import num_threads_option, weights_option
from .reconstruct import mapper_option, mapper_type_option, refine_option


def _sizes(ctx, param, value: str) -> tuple[int, ...]:
    try:
        sizes = tuple(sorted({int(v) for v in value.split(",") if v.strip()}))
    except ValueError:
        raise click.BadParameter(f"{value!r}: give photo counts separated by commas, e.g. 250,500,1000") from None
    if not sizes or min(sizes) < 8:
        raise click.BadParameter(f"{value!r}: give at least one size, each of at least 8 photos")
    return sizes


@click.command()
@click.option("--sizes", default="250,500,1000", show_default=True, callback=_sizes,
              help="Photos per scene (distractors included), comma-separated.")
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("bench-scale"),
              show_default=True, help="Folder for the scenes, work files, results.json, results.md and scale.png.")
@click.option("--image-size", type=click.IntRange(min=64), default=640, show_default=True,
              help="Long side of the generated photos (px).")
@click.option("--spacing", type=click.FloatRange(min=0.1), default=1.5, show_default=True,
              help="Metres walked between two consecutive photos (block).")
@click.option("--layout", type=click.Choice(["block", "ring"]), default="block", show_default=True,
              help="block: a walk around a city block; ring: a turntable series, the photos taken from a circle "
                   "around an object (no distractors).")
@click.option("--hfov", "hfov_deg", type=click.FloatRange(min=10, max=120), default=60.0, show_default=True,
              help="Horizontal field of view of the generated photos (deg); 24 at 640 px is a focal length of "
                   "1,500 px (a long lens).")
@click.option("--repeats", type=click.IntRange(min=1, max=8), default=1, show_default=True,
              help="Faces per texture (photo region, colour gain and grain): with N > 1 the block's buildings "
                   "repeat N times around the street (the walk passes the same facades N times, on different "
                   "sides: N = 2 makes the opposite sides alike, the views from them differing mostly in the "
                   "pavement), and the ring becomes a round temple of N like columns around a core (photos "
                   "360/N deg apart alike). Look-alikes that pass geometric verification while being wrong; the "
                   "ground truth (cameras, co-visibility) stays geometric.")
@click.option("--symmetric", is_flag=True,
              help="Mirror the layout: the block's opposite long sides carry the same facades in mirror order "
                   "(the short sides mirrored about their middle); the ring's boxes mirrored across a vertical "
                   "plane (with --repeats, every column mirror-symmetric too).")
@click.option("--seed", type=int, default=0, show_default=True, help="Scene layout, cameras and mapper seed.")
@click.option("--textures", type=click.Path(file_okay=False, exists=True), default=None,
              help="Folder of photos for the facades and distractors (default: $SEKD_SHARED/data/train/coco).")
@click.option("--no-baseline", is_flag=True, help="Skip pycolmap's SIFT pipeline.")
@click.option("--baseline-map-max", type=click.IntRange(min=0), default=1000, show_default=True,
              help="Largest scene pycolmap's incremental mapper runs on; above it the baseline stops after "
                   "verification (its mapping time grows as N^1.6: about 2.5 hours at 2,000 photos on 2 cores). "
                   "0: no limit.")
@num_threads_option
@click.option("--generate-only", is_flag=True, help="Only generate the scenes (OUT/n<N>/scene) and report the time.")
@click.option("--baseline-from", type=click.Path(file_okay=False, exists=True), default=None,
              help="An earlier `bench scale` folder: its scenes and pycolmap runs are reused where scene settings, "
                   "pairs and pycolmap version are the same, so a variant of our pipeline costs only its own run.")
@weights_option
@click.option("--max-keypoints", type=click.IntRange(min=1), default=None,
              help="Our pipeline's keypoints per photo (default: `sekd reconstruct`'s).")
@mapper_type_option
@mapper_option
@refine_option
def scale(sizes, output, image_size, spacing, layout, hfov_deg, repeats, symmetric, seed, textures, no_baseline,
          baseline_map_max, num_threads, generate_only, baseline_from, weights, max_keypoints, mapper_type, mapper,
          refine) -> None:
    """Our pipeline and pycolmap's SIFT pipeline on generated scenes of growing size.

    \b
    Each scene is a city block of textured box buildings photographed by a camera walking
    around it (one photo every --spacing m), with known cameras, ground-truth co-visibility,
    lighting changes and ~3% unrelated distractor photos; with --layout ring, a few textured
    boxes photographed from N cameras on a circle around them (a turntable series; --hfov 24
    is a long lens). --repeats and --symmetric give the scenes repeated or mirrored structure
    (look-alike facades far apart). Per size and stage (extract, pairs, match, refine, import, verify, map):
    wall time, peak RSS and bytes written; per pipeline: registered photos, registered
    distractors, models, pose AUC@5 and median errors against the true cameras; then the
    growth exponent of each stage and, once two sizes ran on one machine and commit, each
    stage's time projected to 10,000 and 100,000 photos (a plan, not a measurement). Our pipeline runs with `sekd reconstruct`'s defaults unless
    --weights, --max-keypoints, --mapper-type, --mapper or --no-refine say otherwise.
    Finished sizes are skipped when the command is run again on the same folder with the
    same settings; with other settings of our pipeline, only ours reruns (pycolmap's run is
    kept when its scene and pairs are unchanged).

    \b
    Examples:
      sekd bench scale --sizes 50,100 -o out/scale
      sekd bench scale --sizes 250,500,1000 -o out/scale      # adds the larger sizes
      sekd bench scale --sizes 2000 -o out/scale              # pycolmap: features and verification only
      sekd bench scale --sizes 1000 --generate-only -o out/scale
      sekd bench scale --sizes 250,500 -o out/hier --baseline-from out/scale --mapper-type hierarchical
      sekd bench scale --layout ring --hfov 24 --sizes 47 -o out/ring  # a long lens around an object
      sekd bench scale --layout ring --hfov 24 --sizes 24 --repeats 4 -o out/temple  # 4 like columns
      sekd bench scale --sizes 100 --repeats 2 -o out/alike     # opposite sides of the block alike
      sekd bench scale --sizes 100 --symmetric -o out/mirror    # opposite sides in mirror order
    """
    import json

    from sekd_sfm.bench.scale.run import ScaleConfig, run_scale_benchmark
    from sekd_sfm.bench.scale.scene import SceneConfig, generate_scene

    if generate_only:
        for size in sizes:
            path = generate_scene(output / f"n{size}" / "scene", SceneConfig(
                num_images=size, image_size=image_size, spacing=spacing, seed=seed, textures=textures, layout=layout,
                hfov_deg=hfov_deg, repeats=repeats, symmetric=symmetric))
            seconds = json.loads(path.read_text())["generation_s"]
            click.echo(f"n={size}: {path.parent} ({seconds:.1f} s, {size / max(seconds, 1e-9):.1f} images/s)")
        return
    from sekd_sfm.pipelines.reconstruct import ReconstructConfig
    from sekd_sfm.stages.mapping import mapper_options

    if mapper_type != "auto":  # a wrong option fails now, not after the first scene (auto: per size, before its run)
        mapper_options(list(mapper), seed, mapper_type)
    reconstruct_config = ReconstructConfig(mapper_type=mapper_type, mapper=list(mapper), seed=seed)
    reconstruct_config.refine.enabled = refine
    if weights:
        reconstruct_config.features.weights = weights
    if max_keypoints:
        reconstruct_config.features.max_keypoints = max_keypoints
    config = ScaleConfig(sizes=sizes, image_size=image_size, spacing=spacing, layout=layout, hfov_deg=hfov_deg,
                         repeats=repeats, symmetric=symmetric, seed=seed, baseline=not no_baseline,
                         num_threads=num_threads, textures=textures,
                         baseline_from=str(baseline_from) if baseline_from else None,
                         baseline_map_max=baseline_map_max or None)
    path = run_scale_benchmark(output, config, reconstruct_config)
    click.echo((path.parent / "results.md").read_text())
    click.echo(f"results: {path}")
