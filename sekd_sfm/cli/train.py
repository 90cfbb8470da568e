"""``sekd evolve`` (the whole self-evolving loop) and ``sekd train`` (one step of it)."""
from __future__ import annotations

from pathlib import Path

import click

from sekd_sfm.errors import SekdError
from sekd_sfm.runtime import DEVICES
from sekd_sfm.train.config import RUNTIME_FIELDS, SCHEDULES, parse_set, resolve_config
from sekd_sfm.train.evolve import KEYPOINT_SOURCES, STEPS, RunResult, train_one_step
from sekd_sfm.train.evolve import evolve as run_evolve
from sekd_sfm.train.fork import fork_run


def run_options(f):
    """Options shared by both commands: data, config layers, hardware, resume."""
    options = [
        click.option("--images", type=click.Path(file_okay=False, path_type=Path), default=None,
                     help="Folder of training images (searched recursively)."),
        click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True,
                     help="Run folder: config, logs, labels, checkpoints, metrics, best.pth and last.pth."),
        click.option("--schedule", type=click.Choice(SCHEDULES), default=None,
                     help="Named base configuration (default: the config file's `schedule`, else cpu)."),
        click.option("--config", "config_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
                     help="YAML file of config fields applied on top of the schedule."),
        click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
                     help="Override one config field (repeatable), e.g. --set lr=1e-4 --set no_affine=true."),
        click.option("--seed", type=click.IntRange(min=0), default=None, help="Random seed (init, data, shuffling)."),
        click.option("--device", type=click.Choice(DEVICES), default=None, help="auto uses a CUDA GPU when present."),
        click.option("--num-threads", type=click.IntRange(min=0), default=None,
                     help="CPU threads per process (0: the cores divided by the processes)."),
        click.option("--no-progress", is_flag=True, help="No progress bars."),
        click.option("--resume", is_flag=True,
                     help="Continue the run in --out after a crash or Ctrl-C (its saved config is used)."),
    ]
    for option in reversed(options):
        f = option(f)
    return f


def _overrides(images, settings, seed, device, num_threads, no_progress, **extra) -> dict:
    values = parse_set(settings)
    given = {"images": str(images.resolve()) if images else None, "seed": seed, "device": device,
             "num_threads": num_threads, "progress": False if no_progress else None, **extra}
    values.update({k: v for k, v in given.items() if v is not None})
    return values


def _launch(fn, out: Path, resume: bool, schedule, config_file, overrides: dict, command: str, **kw) -> RunResult:
    if resume and (schedule or config_file):
        raise SekdError("--resume uses the run's saved config; drop --schedule/--config")
    config = None if resume else resolve_config(schedule, config_file, overrides)
    try:
        return fn(out, config, resume=resume, runtime=overrides if resume else None, **kw)
    except KeyboardInterrupt:
        raise SekdError(f"interrupted; continue with: sekd {command} --resume --out {out}") from None


def _report(result: RunResult) -> None:
    click.echo(f"best model: {result.best}")
    click.echo(f"last model: {result.last}")
    click.echo(f"metrics:    {result.folder / 'metrics.csv'}  curves: {result.folder / 'curves.png'}")


@click.command()
@run_options
@click.option("--rounds", type=click.IntRange(min=1), default=None, help="Self-evolving rounds (schedule: cpu 5).")
@click.option("--fork", "fork_from", type=click.Path(file_okay=False, exists=True, path_type=Path), default=None,
              help="Start --out as a copy of this run up to its first step (b), then continue with the --set "
                   "step-(b) settings or --rounds changed (nothing before is recomputed).")
def evolve(images, out, schedule, config_file, settings, seed, device, num_threads, no_progress, resume, rounds,
           fork_from) -> None:
    """Train SEKD from unlabeled images with the paper's self-evolving loop.

    \b
    Each round: (a) keypoints from the detector with affine adaptation, (b) descriptor
    update, (c) keypoints from descriptor reliability, (d) detector update; round 0
    runs (c), (d) only unless round0_random is set. After each update, (b) or (d), the
    model is validated on homography sequences; best.pth (the best of these) and last.pth
    load in `sekd extract --weights`.
    Settings are checked before anything runs (types, ranges, one step's memory against this
    machine's RAM); a run folder is used by one process at a time, and --resume refuses an
    image folder that changed since the run started.
    Multi-process: torchrun --nproc_per_node N -m sekd_sfm.cli.main evolve ...

    \b
    Examples:
      sekd evolve --images ../shared/data/train/coco --out runs/cpu
      sekd evolve --images photos --out runs/t --schedule tiny --set no_affine=true
      sekd evolve --resume --out runs/cpu
      sekd evolve --fork runs/cpu --out runs/spread --set spread_weight=1
    """
    overrides = _overrides(images, settings, seed, device, num_threads, no_progress, rounds=rounds)
    if fork_from is not None:
        if resume or schedule or config_file or images:
            raise SekdError("--fork takes the source run's config: drop --resume/--schedule/--config/--images")
        fork_run(fork_from, out, overrides)
        click.echo(f"forked {fork_from} into {out}; continuing it")
        resume, overrides = True, {k: v for k, v in overrides.items() if k in RUNTIME_FIELDS}
    _report(_launch(run_evolve, out, resume, schedule, config_file, overrides, "evolve"))


@click.command()
@run_options
@click.option("--weights", type=click.Path(dir_okay=False), default=None,
              help="Start checkpoint (default: a random network seeded by --seed).")
@click.option("--step", type=click.Choice(sorted(STEPS)), default="det", show_default=True,
              help="desc = step (b) descriptor update; det = step (d) detector update.")
@click.option("--keypoints", type=click.Choice(sorted(KEYPOINT_SOURCES)), default="reliability", show_default=True,
              help="Labels: detector = step (a), reliability = step (c), random = step (a0).")
@click.option("--round", "round_index", type=click.IntRange(min=0), default=0, show_default=True,
              help="Round index: picks the image subset and the random streams.")
def train(images, out, schedule, config_file, settings, seed, device, num_threads, no_progress, resume,
          weights, step, keypoints, round_index) -> None:
    """Run one step of the self-evolving loop from a checkpoint.

    \b
    Labels the round's images (--keypoints), then trains the descriptor or the detector
    (--step) with the losses of the paper; the building block `sekd evolve` repeats.
    Example: sekd train --images photos --weights runs/a/last.pth --step desc --keypoints detector --out runs/b
    """
    overrides = _overrides(images, settings, seed, device, num_threads, no_progress,
                           init_weights=str(Path(weights).resolve()) if weights else None)
    _report(_launch(train_one_step, out, resume, schedule, config_file, overrides, "train",
                    step=step, keypoints=keypoints, round_index=round_index))
