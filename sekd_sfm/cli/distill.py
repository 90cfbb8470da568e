"""``sekd distill``: train SEKD-Lite by distillation from a full SEKD model."""
from __future__ import annotations

from pathlib import Path

import click

from sekd_sfm.errors import SekdError
from sekd_sfm.model.weights import DEFAULT_MODEL
from sekd_sfm.train.distill import TRAIN_PRECISIONS, DistillConfig
from sekd_sfm.train.distill import distill as run_distill


@click.command()
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Run folder: config.json, state.pt, last.pth, metrics.jsonl and the final student.pth.")
@click.option("--teacher", default=None, metavar="own|authors|PATH",
              help=f"Full SEKD model to distil: an embedded one or a checkpoint file. Default: {DEFAULT_MODEL}.")
@click.option("--photos", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Folder of training photos. Default: the shared COCO photos ($SEKD_SHARED/data/train/coco).")
@click.option("--steps", type=click.IntRange(min=1), default=None, help="Training steps (default 3000).")
@click.option("--batch-size", type=click.IntRange(min=1), default=None, help="Crops per step (default 8).")
@click.option("--crop", type=(int, int), default=None, metavar="H W",
              help="Crop size in pixels, multiples of 4 (default 192 256).")
@click.option("--lr", type=click.FloatRange(min=0, min_open=True), default=None, help="Peak learning rate (default 3e-3).")
@click.option("--channels", type=(int, int, int), default=None, metavar="C0 C1 C2",
              help="Student channels at full, 1/2 and 1/4 resolution, multiples of 8 (default 8 24 48).")
@click.option("--blocks", type=(int, int, int), default=None, metavar="B0 B1 B2",
              help="Student residual blocks at full, 1/2 and 1/4 resolution (full resolution may have 0; "
                   "default 0 1 1).")
@click.option("--context-dilations", default=None, metavar="D,...",
              help="One more dilated residual block at 1/4 resolution per entry, comma-separated "
                   "dilations (default 2,4: a descriptor sees ~60 px).")
@click.option("--init", default=None, metavar="lite|PATH",
              help="Start from this SEKD-Lite (the embedded one, or a checkpoint) instead of a random student; "
                   "its architecture is kept. Default: random initialisation.")
@click.option("--train-precision", type=click.Choice(TRAIN_PRECISIONS), default=None,
              help="Student training precision: bf16 = mixed precision, faster on CPUs with native bf16 "
                   "(auto: bf16 there only). Default: fp32.")
@click.option("--pair-weight", type=click.FloatRange(min=0), default=None,
              help="Weight of the cross-view matching term: the batch becomes pairs of views of one photo related "
                   "by a known homography, and the student's descriptors are trained to tell the teacher's "
                   "keypoints apart across them (evolve's triplet loss). The shipped Lite: 3, in a second "
                   "run from a plain one (--init). Default: 0 (plain distillation).")
@click.option("--val-every", type=click.IntRange(min=1), default=None, help="Steps between validations (default 250).")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Random seed (default 0).")
@click.option("--num-threads", type=click.IntRange(min=0), default=1, show_default=True,
              help="CPU threads (0: all cores).")
@click.option("--resume", is_flag=True, help="Continue the interrupted run in OUTPUT with its recorded settings.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def distill(output, teacher, photos, steps, batch_size, crop, lr, channels, blocks, context_dilations, init, train_precision, pair_weight,
            val_every, seed, num_threads, resume, no_progress) -> None:
    """Train a SEKD-Lite network to reproduce a full SEKD model's outputs.

    \b
    Teacher and student see the same augmented crops (random perspective warps, scale,
    rotation, brightness/contrast/gamma, blur, noise) of the training photos; the student
    learns the teacher's keypoint logits (peak-weighted squared error) and its
    descriptors (1 - cosine at every 1/4 cell). The last 16 photos are held out: every
    --val-every steps the log shows the share of the teacher's keypoints the student finds
    within 2 px, the median descriptor cosine at them, and how often the student's and the
    teacher's descriptors find the right partner across a pair of views. The state is saved every 3 minutes;
    an interrupted run continues with --resume. The result (OUTPUT/student.pth) loads
    wherever --weights does; the architecture is recorded in the checkpoint.

    \b
    Examples:
      sekd distill -o runs/lite                                   # shared COCO photos, 3000 steps
      sekd distill -o runs/lite --steps 6000 --num-threads 2
      sekd distill -o runs/lite --resume                          # after Ctrl-C or a crash
      sekd distill -o runs/lite2 --init runs/lite/student.pth --lr 1e-3 --steps 3000 \
          --pair-weight 3 --train-precision auto    # stage 2 of the shipped Lite: learn to match
      sekd extract photos/ -o features.h5 --weights runs/lite/student.pth
    """
    given = {"teacher": teacher, "photos": str(photos) if photos else None, "steps": steps, "batch_size": batch_size,
             "crop": list(crop) if crop else None, "lr": lr, "val_every": val_every, "seed": seed, "init": init,
             "train_precision": train_precision, "pair_weight": pair_weight,
             "student": _student_config(channels, blocks, context_dilations)}
    given = {k: v for k, v in given.items() if v is not None}
    if resume and given:
        raise SekdError(f"--resume continues {output} with its recorded settings; drop "
                        + ", ".join("--" + k.replace("_", "-") for k in given))
    if init and given.get("student"):
        raise SekdError("--init keeps the checkpoint's architecture; drop --channels, --blocks and --context-dilations")
    config = None
    if not resume:
        config = DistillConfig()
        for key, value in given.items():
            setattr(config, key, {**config.student, **value} if key == "student" else value)
    click.echo(str(run_distill(output, config, resume=resume, num_threads=num_threads, progress=not no_progress)))


def _student_config(channels, blocks, context_dilations: str | None) -> dict | None:
    """The student architecture settings given on the command line (None: none given)."""
    config = {}
    if channels:
        config["channels"] = list(channels)
    if blocks:
        config["blocks"] = list(blocks)
    if context_dilations is not None:
        try:
            config["context_dilations"] = [int(d) for d in context_dilations.split(",") if d.strip()]
        except ValueError:
            raise SekdError(f"--context-dilations takes comma-separated integers such as 2,4; got {context_dilations!r}") from None
    return config or None
