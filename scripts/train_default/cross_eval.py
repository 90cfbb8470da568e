"""Which half of a trained model is weak: its detector or its descriptor?

Scores every (detector, descriptor) combination of two checkpoints with the training
validation (the shared homography sequences at 320 px, top 500 keypoints, mutual NN):
keypoints from one network's probability map, descriptors sampled from the other's map.

    python scripts/train_default/cross_eval.py sekd_sfm/model/checkpoints/sekd_own.pth ../shared/weights/sekd/sekd.pth

Prints a Markdown table of MMA@3 (overall / i / v) and Avg.HA@1:10 per combination.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from sekd_sfm.model.inference import nms_keypoints, sample_descriptors
from sekd_sfm.model.weights import load_model
from sekd_sfm.train.validate import (
    find_sequences,
    load_sequence,
    mutual_matches,
    pair_scores,
    summarise,
)

SETS = ["data/homography/hpatches/*", "data/homography/oxford/*"]


@torch.inference_mode()
def maps(net, image) -> tuple[torch.Tensor, torch.Tensor]:
    """(probability H x W, raw descriptors 128 x H/4 x W/4) of one uint8 grayscale image."""
    prob, raw = net(torch.from_numpy(image).float()[None, None] / 255.0)
    return prob[0, 0], raw[0]


def cross_scores(detector, descriptor, folders: list[Path], long_side: int = 320, max_keypoints: int = 500) -> dict:
    rows = []
    for folder in folders:
        seq = load_sequence(folder, long_side)
        feats = []
        for image in seq.images:
            prob, _ = maps(detector, image)
            _, raw = maps(descriptor, image)
            xy, _ = nms_keypoints(prob, 4, 0.0, max_keypoints)
            desc = sample_descriptors(raw, xy.float(), *prob.shape)
            feats.append((xy.numpy(), desc.numpy()))
        for k, h_gt in enumerate(seq.homographies, start=1):
            matches = mutual_matches(feats[0][1], feats[k][1])
            mma, corner = pair_scores(feats[0][0], feats[k][0], matches, h_gt, seq.images[0].shape)
            rows.append((seq.name, mma, corner, len(matches), len(feats[0][0])))
    return summarise(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ours", type=Path)
    parser.add_argument("reference", type=Path)
    args = parser.parse_args()
    torch.manual_seed(0)
    nets = {args.ours.stem: load_model(args.ours)[0], args.reference.stem: load_model(args.reference)[0]}
    folders = find_sequences(SETS)
    print("| detector | descriptor | MMA@3 | MMA@3 i | MMA@3 v | Avg.HA@1:10 |\n|---|---|---|---|---|---|")
    for det_name, det in nets.items():
        for desc_name, desc in nets.items():
            s = cross_scores(det, desc, folders)
            print(f"| {det_name} | {desc_name} | {s['mma3']:.3f} | {s['mma3_i']:.3f} | {s['mma3_v']:.3f} | "
                  f"{s['ha_avg']:.3f} |")


if __name__ == "__main__":
    main()
