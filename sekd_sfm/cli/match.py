"""``sekd pairs`` (features.h5 -> pairs.txt) and ``sekd match`` (features.h5 + pairs.txt -> matches.h5)."""
from __future__ import annotations

from pathlib import Path

import click

from sekd_sfm.confs import output_names
from sekd_sfm.execution import open_executor
from sekd_sfm.stages.match import MATCH_MODES, match_features
from sekd_sfm.stages.pairs import DEFAULT_NEIGHBORS, PAIR_MODES, PairsConfig, make_pairs

from .options import (
    OptionValues,
    device_option,
    executor_options,
    num_threads_option,
    option_group,
)
from .presets import conf_option, feature_and_match_configs


def pairs_options(f):
    """--pairs, --pairs-file, --window, --loop-every, --num-neighbors."""
    options = [
        click.option("--pairs", "pairs_mode", type=click.Choice(PAIR_MODES), default=None,
                     help="auto (default): exhaustive up to 2K+1 images (41 at K=20), retrieval above; "
                          "exhaustive: all pairs; sequential: video frames in name order; retrieval: each image "
                          "with its K most similar images; from-file: the pairs in --pairs-file."),
        click.option("--pairs-file", type=click.Path(dir_okay=False, path_type=Path), default=None,
                     help="Pairs to match, one per line: NAME0 NAME1 (COLMAP/hloc format; tab-separated also read). "
                          "Implies --pairs from-file; with --pairs retrieval or --num-neighbors, retrieval pairs are added."),
        click.option("--window", type=click.IntRange(min=1), default=10, show_default=True,
                     help="sequential: pair each frame with the next N frames."),
        click.option("--loop-every", type=click.IntRange(min=0), default=0, show_default=True,
                     help="sequential: also pair every K-th frame with all other K-th frames (loop closure); 0 = off."),
        click.option("--num-neighbors", type=click.IntRange(min=1), default=None,
                     help=f"retrieval/auto: pair each image with its K most similar images [default: {DEFAULT_NEIGHBORS}]; "
                          "with sequential or from-file: add these retrieval pairs (loop closure)."),
    ]
    for option in reversed(options):
        f = option(f)
    return f


def pairs_config(pairs_mode, pairs_file, window, loop_every, num_neighbors=None) -> PairsConfig:
    """PairsConfig from the options of pairs_options (``pairs_config(**pairing.values)`` for the group ``pairing``)."""
    mode = pairs_mode or ("from-file" if pairs_file else "auto")
    if mode == "retrieval" and pairs_file is not None:  # the file's pairs plus retrieval: union
        mode, num_neighbors = "from-file", num_neighbors or DEFAULT_NEIGHBORS
    if mode == "from-file" and pairs_file is None:
        raise click.UsageError("--pairs from-file needs --pairs-file PATH")
    if pairs_file is not None and mode != "from-file":
        raise click.UsageError(f"--pairs-file is read with --pairs from-file or retrieval, not {mode}")
    if mode == "exhaustive" and num_neighbors:
        raise click.UsageError("--num-neighbors has no effect with --pairs exhaustive; use --pairs retrieval")
    return PairsConfig(mode=mode, window=window, loop_every=loop_every, file=str(pairs_file) if pairs_file else None,
                       num_neighbors=num_neighbors)


def match_options(f):
    """--match-mode, --ratio, --rootsift/--no-rootsift."""
    options = [
        click.option("--match-mode", type=click.Choice(MATCH_MODES), default="both", show_default=True,
                     help="mnn: mutual nearest neighbours; ratio: Lowe's ratio test; both: the two together."),
        click.option("--ratio", type=click.FloatRange(0, 1, min_open=True), default=None,
                     help="Ratio-test threshold d1/d2 (default: measured per feature type, see docs/matching.md)."),
        click.option("--rootsift/--no-rootsift", default=None,
                     help="Match float descriptors as RootSIFT (Hellinger distance). Default: on for SIFT only."),
    ]
    for option in reversed(options):
        f = option(f)
    return f


#: The groups of `pairs`, `match` and `reconstruct`: each passed to the command as one OptionValues.
pairing_options = option_group("pairing", pairs_options)
matching_options = option_group("matching", match_options)


@click.command()
@click.argument("features", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Pairs file to write. Default: pairs-MODE.txt beside FEATURES.")
@pairing_options
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@executor_options
def pairs(features: Path, output: Path | None, pairing: OptionValues, no_progress: bool, executor: str,
          ray_options) -> None:
    """Choose the image pairs to match among the images of a feature file.

    \b
    The file holds one pair per line, NAME0 NAME1 separated by one space: COLMAP
    (pycolmap.verify_matches, colmap matches_importer) and hloc read it unchanged.
    Images whose names contain whitespace (or start with '#') are left out with one
    warning: rename them. Duplicates and reversed duplicates collapse to one pair.

    \b
    Retrieval describes each image by one global descriptor (VLAD over its own local
    descriptors, vocabulary learned on the collection; any feature type), stored in
    FEATURES.global.h5 beside FEATURES and reused by later runs; then pairs each image
    with its K most similar images (cosine). N images give at most N*K pairs instead of
    N(N-1)/2. See docs/pairs.md.

    \b
    Examples:
      sekd pairs out/features.h5 -o out/pairs.txt                  # auto: exhaustive or retrieval by size
      sekd pairs out/features.h5 --pairs exhaustive                # all N(N-1)/2 pairs
      sekd pairs out/features.h5 --pairs retrieval --num-neighbors 30
      sekd pairs out/features.h5 --pairs sequential --window 5 --loop-every 20
      sekd pairs out/features.h5 --pairs sequential --window 5 --num-neighbors 10   # video + retrieval loop closure
      sekd pairs out/features.h5 --pairs-file mine.txt             # exactly the pairs in mine.txt
      sekd pairs out/features.h5 --pairs-file mine.txt --num-neighbors 10           # mine.txt plus retrieval
      sekd pairs /shared/out/features.h5 --pairs retrieval --executor ray          # global descriptors on Ray
    """
    config = pairs_config(**pairing.values)
    output = output or features.with_name(f"pairs-{config.mode}.txt")
    with open_executor(executor, ray_options) as runner:
        click.echo(str(make_pairs(features, output, config, progress=not no_progress, executor=runner)))


@click.command()
@click.argument("features", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("pairs_file", metavar="PAIRS", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Match file to write. Default: matches.h5 beside FEATURES (matches-CONF_PAIRS.h5 with --conf).")
@conf_option
@option_group("matching", match_options, device_option)
@num_threads_option
@click.option("--overwrite", is_flag=True, help="Replace an existing output file instead of resuming it.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@executor_options
def match(features: Path, pairs_file: Path, output: Path | None, conf: str | None, matching: OptionValues,
          num_threads: int | None, overwrite: bool, no_progress: bool, executor: str, ray_options) -> None:
    """Match the descriptors of the image pairs in PAIRS (nearest neighbours, batched torch).

    \b
    L2 distance for float descriptors, Hamming for binary ones (ORB, AKAZE, BRISK).
    The output is hloc-compatible: NAME0/NAME1/matches0 (int32, -1 = unmatched) and
    matching_scores0 (float32), nested by image name; a pair whose names contain '/' is
    also linked under hloc's key (a-x.jpg/b-y.jpg for a/x.jpg, b/y.jpg), so hloc's
    get_matches reads every pair (docs/matching.md). FEATURES may also be a feature file
    written by hloc (float16 accepted; matched as float descriptors, L2 distance).
    An interrupted run resumes where it stopped.

    \b
    Examples:
      sekd match out/features.h5 out/pairs.txt -o out/matches.h5 --ratio 0.8
      sekd match out/feats-sift-n8000.h5 out/pairs.txt --conf sift-n8000   # -> matches-sift-n8000_pairs.h5
    """
    config = feature_and_match_configs(matching, conf=conf).matching
    output = output or features.with_name(output_names(conf, pairs_file)[1] if conf else "matches.h5")
    path = match_features(features, pairs_file, output, config,
                          overwrite=overwrite, num_threads=num_threads, progress=not no_progress,
                          executor=executor, ray_options=ray_options)
    click.echo(str(path))
