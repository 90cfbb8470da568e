"""``sekd adapt`` (fine-tune a model on your own photos) and ``reconstruct --adapt``'s in-line call."""
from __future__ import annotations

from pathlib import Path

import click

from sekd_sfm.errors import SekdError
from sekd_sfm.model.weights import DEFAULT_MODEL, EMBEDDED_MODELS
from sekd_sfm.train.adapt import SCHEDULES, AdaptConfig, adapt_or_reuse
from sekd_sfm.train.adapt import adapt as run_adapt

#: The adapted model of ``reconstruct --adapt``, inside its output folder (run folder beside it).
ADAPTED_NAME = "adapted.pth"


@click.command()
@click.argument("photos", type=click.Path(file_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Adapted model to write (.pth); its run folder OUTPUT.run/ is kept beside it.")
@click.option("--from", "start", default=None, metavar="own|authors|PATH",
              help=f"Model to start from: an embedded one ({', '.join(EMBEDDED_MODELS)}) or a checkpoint file. "
                   f"Default: {DEFAULT_MODEL} (the default of `extract`).")
@click.option("--rounds", type=click.IntRange(1, 2), default=None, help="Self-evolving rounds (default 1).")
@click.option("--schedule", type=click.Choice(SCHEDULES), default=None,
              help="auto (default): epochs sized to the number of photos; tiny: a few seconds, for trying it out.")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Random seed (default 0).")
@click.option("--num-threads", type=click.IntRange(min=0), default=0, show_default=True,
              help="CPU threads (0: all cores).")
@click.option("--resume", is_flag=True, help="Continue an interrupted adaptation to OUTPUT (its recorded settings).")
@click.option("--no-progress", is_flag=True, help="No progress bars.")
def adapt(photos, output, start, rounds, schedule, seed, num_threads, resume, no_progress) -> None:
    """Fine-tune a SEKD model on the photos below PHOTOS, without any labels.

    \b
    SEKD trains itself: each round labels the photos with the model's own detections
    (affine adaptation), updates the descriptor on them, relabels by descriptor reliability
    and updates the detector, as `sekd evolve` does, starting from the --from model. The
    photos are used at 320 px; one round on 11 photos took 1.7 min of CPU time (one thread).
    Training costs the same from 40 photos on (epochs are sized to the collection), the
    labelling grows with the photo count. An interrupted run continues with --resume; the
    result loads wherever --weights does.

    \b
    Examples:
      sekd adapt photos/ -o photos-sekd.pth
      sekd extract photos/ -o features.h5 --weights photos-sekd.pth
      sekd adapt photos/ -o m.pth --from own --rounds 2
      sekd adapt photos/ -o m.pth --resume                 # after Ctrl-C or a crash
      sekd reconstruct photos/ -o out/ --adapt             # adapt, then reconstruct with it
    """
    defaults = AdaptConfig()
    config = AdaptConfig(start=start or defaults.start, rounds=rounds or defaults.rounds,
                         schedule=schedule or defaults.schedule, seed=defaults.seed if seed is None else seed,
                         num_threads=num_threads, progress=not no_progress)
    click.echo(str(run_adapt(photos, output, config, resume=resume)))


adapt_option = click.option(
    "--adapt", is_flag=True,
    help=f"First fine-tune the SEKD model (--model/--weights) on these photos (`sekd adapt`, 1 round), "
         f"then extract with it; kept as OUTPUT/{ADAPTED_NAME} and reused by later runs.")


def adapt_in_line(images: Path, output: Path, features, num_threads: int | None, progress: bool) -> None:
    """``reconstruct --adapt``: adapt the chosen model to ``images`` and make ``features`` use the result."""
    if features.feature != "sekd":
        raise SekdError(f"--adapt fine-tunes a SEKD model; --feature {features.feature} has none to adapt")
    config = AdaptConfig(start=str(features.weights) if features.weights else DEFAULT_MODEL,
                         num_threads=num_threads or 0, progress=progress)
    features.weights = str(adapt_or_reuse(images, Path(output) / ADAPTED_NAME, config))
