"""``sekd pairs`` (features.h5 -> pairs.txt) and ``sekd match`` (features.h5 + pairs.txt -> matches.h5)."""
from __future__ import annotations

from pathlib import Path

import click

from sekd_sfm.match import MATCH_MODES, MatchConfig, match_features
from sekd_sfm.pairs import PAIR_MODES, PairsConfig, make_pairs
from sekd_sfm.runtime import DEVICES


def pairs_options(f):
    """--pairs, --pairs-file, --window, --loop-every."""
    options = [
        click.option("--pairs", "pairs_mode", type=click.Choice(PAIR_MODES), default=None,
                     help="exhaustive: all pairs (default); sequential: video frames in name order; "
                          "from-file: the pairs in --pairs-file."),
        click.option("--pairs-file", type=click.Path(dir_okay=False, path_type=Path), default=None,
                     help="Pairs to match, one per line: NAME0<TAB>NAME1 (or whitespace-separated names). "
                          "Implies --pairs from-file."),
        click.option("--window", type=click.IntRange(min=1), default=10, show_default=True,
                     help="sequential: pair each frame with the next N frames."),
        click.option("--loop-every", type=click.IntRange(min=0), default=0, show_default=True,
                     help="sequential: also pair every K-th frame with all other K-th frames (loop closure); 0 = off."),
    ]
    for option in reversed(options):
        f = option(f)
    return f


def pairs_config(pairs_mode, pairs_file, window, loop_every) -> PairsConfig:
    mode = pairs_mode or ("from-file" if pairs_file else "exhaustive")
    if mode == "from-file" and pairs_file is None:
        raise click.UsageError("--pairs from-file needs --pairs-file PATH")
    return PairsConfig(mode=mode, window=window, loop_every=loop_every, file=str(pairs_file) if pairs_file else None)


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


def match_config(match_mode, ratio, rootsift, device="auto") -> MatchConfig:
    return MatchConfig(mode=match_mode, ratio=ratio, rootsift=rootsift, device=device)


@click.command()
@click.argument("features", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Pairs file to write. Default: pairs-MODE.txt beside FEATURES.")
@pairs_options
def pairs(features: Path, output: Path | None, pairs_mode, pairs_file, window, loop_every) -> None:
    """Choose the image pairs to match among the images of a feature file.

    \b
    Duplicates and reversed duplicates collapse to one pair. The file is written with one
    pair per line, NAME0<TAB>NAME1, so names with spaces survive.

    \b
    Examples:
      sekd pairs out/features.h5 -o out/pairs.txt
      sekd pairs out/features.h5 --pairs sequential --window 5 --loop-every 20
    """
    config = pairs_config(pairs_mode, pairs_file, window, loop_every)
    output = output or features.with_name(f"pairs-{config.mode}.txt")
    click.echo(str(make_pairs(features, output, config)))


@click.command()
@click.argument("features", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("pairs_file", metavar="PAIRS", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Match file to write. Default: matches.h5 beside FEATURES.")
@match_options
@click.option("--device", type=click.Choice(DEVICES), default="auto", show_default=True,
              help="auto uses a CUDA GPU when one is present.")
@click.option("--num-threads", type=int, default=None, help="CPU threads (default: all available cores).")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file instead of resuming it.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def match(features: Path, pairs_file: Path, output: Path | None, match_mode, ratio, rootsift, device, num_threads,
          overwrite, no_progress) -> None:
    """Match the descriptors of the image pairs in PAIRS (nearest neighbours, batched torch).

    \b
    L2 distance for float descriptors, Hamming for binary ones (ORB, AKAZE, BRISK).
    The output is hloc-compatible: NAME0/NAME1/matches0 (int32, -1 = unmatched) and
    matching_scores0 (float32), nested by image name without renaming (docs/matching.md).
    An interrupted run resumes where it stopped.

    \b
    Example:
      sekd match out/features.h5 out/pairs.txt -o out/matches.h5 --ratio 0.8
    """
    output = output or features.with_name("matches.h5")
    path = match_features(features, pairs_file, output, match_config(match_mode, ratio, rootsift, device),
                          overwrite=overwrite, num_threads=num_threads, progress=not no_progress)
    click.echo(str(path))
