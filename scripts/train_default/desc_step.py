"""Quick step-(b) experiments: one descriptor step on a run's saved labels, validated after every epoch.

Starts from a run's step model (e.g. ``r0_d``) and trains step (b) on the labels the run
saved for it (e.g. ``r1_a``), with the run's config plus KEY=VALUE overrides, so variants
of (b) are compared on exactly the same model, labels and pairs without relabelling.
After every epoch: the run's validation (MMA@3, Avg.HA, ``desc_cos``) printed as one JSON
line and the model saved as ``OUT/e<N>.pth`` (for ``sekd bench homography -m x=sekd:OUT/e3.pth``).

    python scripts/train_default/desc_step.py runs/floor r0_d r1_a /tmp/spread \\
        --epochs 3 spread_weight=1
"""
from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from sekd_sfm.model.weights import load_model, save_checkpoint
from sekd_sfm.train.config import apply, load_run_config, parse_set
from sekd_sfm.train.data import TrainImages
from sekd_sfm.train.distributed import setup
from sekd_sfm.train.labels import Labels
from sekd_sfm.train.model import plain_copy
from sekd_sfm.train.steps import train_step
from sekd_sfm.train.validate import evaluate, find_sequences

SHOWN = ("total", "desc", "spread", "pres", "mma3", "mma3_i", "mma3_v", "ha_avg", "desc_cos")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("model", help="step model of the run to start from, e.g. r0_d")
    parser.add_argument("labels", help="labels of the run to train on, e.g. r1_a")
    parser.add_argument("out", type=Path)
    parser.add_argument("settings", nargs="*", metavar="KEY=VALUE")
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    cfg = apply(load_run_config(args.run / "config.yaml"), parse_set(args.settings), "settings")
    cfg = dataclasses.replace(cfg, epochs_desc=args.epochs, progress=False)
    ctx = setup("cpu", args.threads)
    labels = Labels.load(args.run / "labels" / f"{args.labels}.npz")
    net = load_model(args.run / "models" / f"{args.model}.pth")[0]
    sequences = find_sequences(cfg.val_sets)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []

    def after_epoch(epoch: int, state: dict) -> None:
        # evaluate() scores a plain copy, so the training network stays in train mode
        metrics = evaluate(net, sequences, cfg.val_long_side, cfg.val_max_keypoints, cfg.val_threshold,
                           cfg.val_nms_radius, ctx.device)
        row = {"epoch": epoch + 1, **{k: v for k, v in {**state["history"][-1], **metrics}.items() if k in SHOWN}}
        rows.append(row)
        print(json.dumps(row), flush=True)
        (args.out / "results.json").write_text(json.dumps({"settings": args.settings, "rows": rows}, indent=1))
        save_checkpoint(plain_copy(net), args.out / f"e{epoch + 1}.pth", {"settings": args.settings})

    train_step(net, "b", labels, TrainImages(cfg.images, cfg.long_side, cfg.size_multiple), cfg, ctx,
               labels.round_index, None, after_epoch, alpha=cfg.alpha)


if __name__ == "__main__":
    main()
