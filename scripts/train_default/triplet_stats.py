"""What step (b)'s triplet loss sees: positive and hardest-negative distances of models on training pairs.

Builds the step-(b) training pairs of one round of a run (its labels, its config, epoch 0,
so every model sees exactly the same pairs) and reports, per model, averaged over the
pairs: keypoints per pair, mean positive distance, mean hardest-negative distance, mean
distance to a random other keypoint, the share of keypoints whose positive is nearer than
their hardest negative, the ratio-form loss, and the mean pairwise cosine of the
descriptors (near 1: collapsed).

    python scripts/train_default/triplet_stats.py runs/floor r1_a \\
        ../shared/weights/sekd/sekd.pth runs/floor/models/r0_d.pth

A descriptor the loss can train has positives nearer than hardest negatives for many
keypoints; when almost none are, the ratio (and margin) loss is lowest for descriptors that
shrink every distance alike: they collapse (docs/experiments.md, finding 3).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from sekd_sfm.model.weights import load_model
from sekd_sfm.train.config import load_run_config
from sekd_sfm.train.data import PairDataset, TrainImages
from sekd_sfm.train.labels import Labels
from sekd_sfm.train.losses import hardest_negatives, pairwise_distances, triplet_loss
from sekd_sfm.train.steps import matched_keypoints, sample_upsampled
from sekd_sfm.train.validate import mean_pairwise_cosine

COLUMNS = ("keypoints", "pos", "hardest neg", "random neg", "pos < neg", "ratio loss", "cosine")


@torch.inference_mode()
def pair_stats(net, pair: dict, rng: np.random.Generator) -> list[float]:
    """The statistics of one training pair (eval-mode network), in the order of COLUMNS."""
    (_, d0, _), (_, d1, _) = (net.forward_train(pair[k][None]) for k in ("image0", "image1"))
    h, w = pair["label0"].shape
    p, q = matched_keypoints(pair["label0"], pair["corr"])
    a, b = (sample_upsampled(d[0], x[:, 0], x[:, 1], h, w) for d, x in ((d0, p), (d1, q)))
    d = pairwise_distances(a, b)
    pos, neg = d.diagonal(), hardest_negatives(d)
    other = (np.arange(len(d)) + rng.integers(1, len(d), len(d))) % len(d)  # never the keypoint itself
    return [len(p), pos.mean().item(), neg.mean().item(), d[np.arange(len(d)), other].mean().item(),
            (pos < neg).float().mean().item(), triplet_loss(a, b).item(), mean_pairwise_cosine(a.numpy())]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="run folder (config.yaml, labels/)")
    parser.add_argument("labels", help="labelling task whose keypoints step (b) learns from, e.g. r1_a")
    parser.add_argument("weights", nargs="+", type=Path)
    parser.add_argument("--pairs", type=int, default=16, help="training pairs (the first images of the round)")
    args = parser.parse_args()
    torch.manual_seed(0)
    cfg = load_run_config(args.run / "config.yaml")
    labels = Labels.load(args.run / "labels" / f"{args.labels}.npz")
    indices = sorted(labels.keypoints)[:args.pairs]
    pairs = PairDataset(TrainImages(cfg.images, cfg.long_side, cfg.size_multiple), indices, labels.keypoints,
                        cfg, labels.round_index, "b", 0)
    print("| model | " + " | ".join(COLUMNS) + " |")
    print("|---" * (len(COLUMNS) + 1) + "|")
    for path in args.weights:
        net = load_model(path)[0].eval()
        rng = np.random.default_rng(0)
        stats = np.mean([pair_stats(net, pairs[j], rng) for j in range(len(pairs))], axis=0)
        print(f"| {path} | {stats[0]:.0f} | " + " | ".join(f"{v:.3f}" for v in stats[1:]) + " |")


if __name__ == "__main__":
    main()
