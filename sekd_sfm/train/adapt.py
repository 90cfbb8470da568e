"""``sekd adapt``: fine-tune a SEKD model on the user's own unlabeled photos (self-evolving rounds).

SEKD learns from nothing but images, so the loop that trained the model can continue on
the photos a user wants to reconstruct: each round labels the photos with the model's
own detections under affine adaptation (a), updates the descriptor on them (b), labels
them by descriptor reliability (c) and updates the detector (d): the tasks of
``sekd evolve`` rounds 1.., run by its machinery (``evolve.run_tasks``), every photo every
round, starting from the given model's weights.

The run folder sits beside the output (``model.pth.run/``): it records every finished
task and each epoch, so an adaptation that was killed continues with ``resume=True``.
The result is an ordinary checkpoint (``sekd extract --weights model.pth``).
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import torch

from ..errors import SekdError
from ..files.atomic import atomic_output
from ..files.images import list_images
from ..model.weights import (
    DEFAULT_MODEL,
    EMBEDDED_MODELS,
    embedded_model_path,
    file_sha256,
    resolve_weights_path,
)
from .config import TrainConfig, apply, schedule_config
from .evolve import RunFolder, Task, run_tasks
from .report import write_atomic

logger = logging.getLogger("sekd.train")
SCHEDULES = ("auto", "tiny")
#: Training views per step of the ``auto`` schedule: epochs = views / photos, clipped to
#: [1, MAX_EPOCHS_*]. About 320 crops for the descriptor and 160 for the detector keep a
#: round at a few minutes on a 2-core CPU for 20-200 photos while every photo is seen.
DESC_VIEWS, DET_VIEWS = 320, 160
MAX_EPOCHS_DESC, MAX_EPOCHS_DET = 8, 4
#: Fine-tuning starts from a trained model: a tenth of the learning rate that trains one from scratch.
ADAPT_LR = 1.0e-4
RECORD = "adapt.json"


@dataclass(frozen=True)
class AdaptConfig:
    """What to adapt from, for how long. ``start``: ``own``, ``authors`` or a checkpoint path."""

    start: str = DEFAULT_MODEL
    rounds: int = 1
    schedule: str = "auto"       # auto: sized to the photo count; tiny: seconds (tests, smoke runs)
    seed: int = 0
    num_threads: int = 0         # 0: all cores
    progress: bool = True


def run_folder(output: Path) -> Path:
    """The run folder of the adaptation that writes ``output``: ``output`` + ``.run``."""
    return Path(output).with_name(Path(output).name + ".run")


def start_weights(start: str) -> Path:
    """The checkpoint ``start`` names: an embedded model (``own``, ``authors``) or a file."""
    full = [name for name in EMBEDDED_MODELS if name != "lite"]  # self-evolving training builds the full network
    if start in EMBEDDED_MODELS:
        if start not in full:
            raise SekdError(f"--from {start}: adaptation trains the full SEKD network; start from "
                            f"{' or '.join(full)}, or a full-network checkpoint")
        return embedded_model_path(start)
    if not Path(start).expanduser().is_file():
        raise SekdError(f"{start}: neither {' nor '.join(full)} nor an existing checkpoint file; "
                        "pass --from own, --from authors or --from PATH to a .pth")
    return resolve_weights_path(start).resolve()


def adapt_tasks(rounds: int) -> list[Task]:
    """Rounds 1..``rounds`` of ``sekd evolve``: (a), (b), (c), (d); each update exports ``last.pth``."""
    tasks = []
    for k in range(1, rounds + 1):
        tasks += [Task(k, "a"), Task(k, "b", labels=f"r{k}_a", validate=True),
                  Task(k, "c"), Task(k, "d", labels=f"r{k}_c", validate=True)]
    return tasks


def train_config(photos: Path, count: int, config: AdaptConfig) -> TrainConfig:
    """The ``TrainConfig`` of an adaptation of ``count`` photos (no validation: users have no ground truth)."""
    common = {"images": str(Path(photos).resolve()), "init_weights": str(start_weights(config.start)),
              "rounds": config.rounds, "subset_factor": 1, "round0_random": False, "validate": False,
              "validate_start": False, "keep_epoch_checkpoints": False, "seed": config.seed,
              "num_threads": config.num_threads, "progress": config.progress, "num_workers": 0}
    if config.schedule == "tiny":
        base = schedule_config("tiny")
        sized = {"epochs_desc": 1, "epochs_det": 1, "num_warps": 1, "batch_size": 2, "lr": ADAPT_LR}
    elif config.schedule == "auto":
        base = schedule_config("cpu")
        sized = {"epochs_desc": _epochs(DESC_VIEWS, count, MAX_EPOCHS_DESC),
                 "epochs_det": _epochs(DET_VIEWS, count, MAX_EPOCHS_DET), "lr": ADAPT_LR}
    else:
        raise SekdError(f"unknown adapt schedule {config.schedule!r}; choose one of {', '.join(SCHEDULES)}")
    cfg = apply(base, {**sized, **common}, "adapt")
    cfg.schedule = f"adapt-{config.schedule}"
    return cfg


def _epochs(views: int, count: int, most: int) -> int:
    return max(1, min(most, math.ceil(views / max(count, 1))))


def adapt(photos: Path, output: Path, config: AdaptConfig = AdaptConfig(), resume: bool = False) -> Path:
    """Fine-tune ``config.start`` on the photos below ``photos``; write the model to ``output``; return it.

    ``resume``: continue the run folder of an interrupted adaptation (its recorded settings
    are used; ``config`` must not contradict them). An existing ``output`` is never replaced.
    """
    photos, output = Path(photos), Path(output)
    folder = run_folder(output)
    if output.exists():
        raise SekdError(f"{output}: already exists; choose another -o or delete it (the adaptation never replaces it)")
    if resume:
        config = _resumed_config(folder, photos, config)
        # Killed before the first task was recorded: nothing to continue, start the recorded run afresh.
        resume = RunFolder(folder).state_path.exists()
    elif RunFolder(folder).state_path.exists():
        raise SekdError(f"{folder}: an adaptation to {output.name} was started here; continue it with --resume, "
                        "or delete the folder to start again")
    count = _count_photos(photos)
    cfg = train_config(photos, count, config)
    start = Path(cfg.init_weights)
    if not resume:
        folder.mkdir(parents=True, exist_ok=True)
        record = {"photos": cfg.images, "count": count, **dataclasses.asdict(config), "start_path": str(start),
                  "start_sha256": file_sha256(start, 64)}
        write_atomic(folder / RECORD, json.dumps(record, indent=1))
    logger.info("adapting %s (%d photos, %d round(s), schedule %s: %d + %d epochs per round) into %s",
                start.name, count, config.rounds, config.schedule, cfg.epochs_desc, cfg.epochs_det, output)
    runtime = {"num_threads": config.num_threads, "progress": config.progress}
    try:
        result = run_tasks(folder, None if resume else cfg, None if resume else adapt_tasks(config.rounds),
                           resume=resume, runtime=runtime if resume else None)
    except KeyboardInterrupt:
        raise SekdError(f"interrupted; continue with: sekd adapt {photos} -o {output} --resume") from None
    return _write_output(result.last, output, json.loads((folder / RECORD).read_text()))


def _count_photos(photos: Path) -> int:
    if not photos.is_dir():
        raise SekdError(f"{photos}: photo folder not found; pass the folder of the photos to adapt to")
    count = len(list_images(photos))
    if count == 0:
        raise SekdError(f"{photos}: no images found (jpg, jpeg, png, ppm, pgm, tif, bmp); nothing to adapt to")
    return count


def _resumed_config(folder: Path, photos: Path, given: AdaptConfig) -> AdaptConfig:
    """The recorded settings of the run in ``folder``; SekdError if ``given`` asks for other ones."""
    path = folder / RECORD
    if not path.is_file():
        raise SekdError(f"{folder}: no adaptation to resume ({RECORD} not found); start one without --resume")
    record = json.loads(path.read_text())
    if Path(record["photos"]) != photos.resolve():
        raise SekdError(f"{folder}: this adaptation is of the photos in {record['photos']}, not {photos}; "
                        "pass that folder, or another -o for a new adaptation")
    saved = AdaptConfig(**{f.name: record[f.name] for f in dataclasses.fields(AdaptConfig)})
    changed = [name for name in ("start", "rounds", "schedule", "seed")
               if getattr(given, name) != getattr(AdaptConfig(), name) and getattr(given, name) != getattr(saved, name)]
    if changed:
        raise SekdError(f"{folder}: --resume continues the recorded adaptation ({', '.join(f'{n}={getattr(saved, n)}' for n in changed)}); "
                        "drop the options that differ, or delete the folder to start again")
    return dataclasses.replace(saved, num_threads=given.num_threads, progress=given.progress)


def _write_output(last: Path, output: Path, record: dict) -> Path:
    """``last`` with the adaptation's facts added to its metadata, written atomically to ``output``."""
    checkpoint = torch.load(last, map_location="cpu", weights_only=True)
    meta = dict(checkpoint.get("sekd_sfm", {}))
    meta["adapted"] = {k: record[k] for k in ("photos", "count", "rounds", "schedule", "seed", "start",
                                              "start_path", "start_sha256")}
    with atomic_output(output) as tmp:
        torch.save({"state_dict": checkpoint["state_dict"], "sekd_sfm": meta}, tmp)
    logger.info("adapted model: %s (run folder %s)", output, run_folder(output))
    return output


def adapt_or_reuse(photos: Path, output: Path, config: AdaptConfig) -> Path:
    """``output`` if it is already made; else continue its run folder if there is one, else adapt from scratch.

    What ``sekd reconstruct --adapt`` calls: a rerun of the command reuses (or finishes) the adaptation.
    """
    if Path(output).is_file():
        record = run_folder(output) / RECORD
        if record.is_file() and json.loads(record.read_text()).get("start_sha256") != file_sha256(
                start_weights(config.start), 64):
            raise SekdError(f"{output}: adapted from another model than the one asked for; delete it and "
                            f"{run_folder(output)} to adapt again")
        logger.info("reusing the adapted model %s", output)
        return Path(output)
    return adapt(photos, output, config, resume=(run_folder(output) / RECORD).is_file())
