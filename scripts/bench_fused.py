"""The fused CPU forward (sekd_sfm.model.fused) against the eager network: extraction images/s, same run.

For each model (full SEKD, SEKD-Lite) and precision (fp32, and bf16 where the CPU has native
bf16), builds the fast extractor twice, fused and eager (``SEKD_FUSED=0``), and times
``extract`` on the same 480x640 images, alternating the two ROUNDS times so that machine noise
hits both alike. Also prints how many keypoints land on the same pixel (2000 keypoints, integer
positions) and the descriptor cosine there, fused against eager; then the same for one
labelling step of ``sekd evolve`` (fp32).

Usage: python scripts/bench_fused.py [--count 8] [--rounds 3] [--num-threads N] [-o result.json]
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from sekd_sfm.bench.speed import agreement, load_bench_images
from sekd_sfm.model import fused
from sekd_sfm.model.inference import SEKDConfig, SEKDExtractor
from sekd_sfm.model.weights import EMBEDDED_MODELS, load_model
from sekd_sfm.runtime import (
    cpu_description,
    cpu_has_fast_bf16,
    set_num_threads,
    shared_dir,
)


def extractor(net, precision: str, use_fused: bool) -> SEKDExtractor:
    os.environ[fused.ENV_SWITCH] = "1" if use_fused else "0"
    try:
        ex = SEKDExtractor(net, SEKDConfig(max_keypoints=2000, device="cpu", subpixel=False, precision=precision))
    finally:
        os.environ.pop(fused.ENV_SWITCH, None)
    assert (ex.model.fused is not None) == use_fused
    return ex


def rate(ex: SEKDExtractor, images: list[np.ndarray]) -> tuple[float, list[dict]]:
    ex.extract(images[0])  # warm-up: oneDNN builds its kernels for this shape
    start = time.perf_counter()
    out = [ex.extract(image) for image in images]
    return len(images) / (time.perf_counter() - start), out


def bench_labels(rounds: int, images: list[np.ndarray]) -> dict:
    """``sekd evolve``'s labelling step (c) (fp32; target view + 4 warps per photo) with the fused and the eager forward."""
    import torch

    from sekd_sfm.model.fused import fp32_eval_forward
    from sekd_sfm.model.network import use_fast_deconv
    from sekd_sfm.train.config import TrainConfig
    from sekd_sfm.train.labels import label_one

    net = use_fast_deconv(load_model(EMBEDDED_MODELS["authors"])[0]).eval()
    forwards = {"fused": fp32_eval_forward(net, torch.device("cpu")), "eager": net.forward_train}
    cfg, photos = TrainConfig(), [np.repeat(image[:, :, None], 3, axis=2) for image in images[:4]]
    rates: dict[str, list[float]] = {"fused": [], "eager": []}
    for _ in range(rounds):
        for name, forward in forwards.items():
            start = time.perf_counter()
            for i, rgb in enumerate(photos):
                label_one(forward, rgb, np.random.default_rng(i), "c", cfg, torch.device("cpu"))
            rates[name].append(len(photos) / (time.perf_counter() - start))
    ratio = float(np.median(rates["fused"]) / np.median(rates["eager"]))
    print(f"labels (c), fp32, 480x640 + {cfg.num_warps} warps: eager {np.median(rates['eager']):.2f} photos/s, "
          f"fused {np.median(rates['fused']):.2f} -> {ratio:.2f}x")
    return {"model": "authors", "precision": "fp32", "step": "labels (c)", "photos_per_s": rates, "fused_vs_eager": ratio}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--num-threads", type=int, default=None)
    parser.add_argument("--images", type=Path, default=None)
    parser.add_argument("-o", "--output", type=Path, default=None)
    args = parser.parse_args()
    threads = set_num_threads(args.num_threads)
    images = load_bench_images(args.images or shared_dir() / "data/train/coco", args.count, 480, 640)
    precisions = ["fp32"] + (["bf16"] if cpu_has_fast_bf16() else [])
    print(f"{args.count} images at 480x640, {threads} threads, {args.rounds} alternating rounds; "
          f"cpu: {cpu_description()}")
    results = []
    for model in ("authors", "lite"):
        net = load_model(EMBEDDED_MODELS[model])[0]
        for precision in precisions:
            pair = {"fused": extractor(net, precision, True), "eager": extractor(net, precision, False)}
            rates: dict[str, list[float]] = {"fused": [], "eager": []}
            outputs = {}
            for _ in range(args.rounds):
                for name, ex in pair.items():
                    value, outputs[name] = rate(ex, images)
                    rates[name].append(value)
            same = agreement(outputs["eager"], outputs["fused"])
            row = {"model": model, "precision": precision, "images_per_s": rates,
                   "fused_vs_eager": float(np.median(rates["fused"]) / np.median(rates["eager"])), "agreement": same}
            results.append(row)
            print(f"{model:8s} {precision}: eager {np.median(rates['eager']):6.2f} images/s, fused "
                  f"{np.median(rates['fused']):6.2f} (median of {args.rounds}) -> {row['fused_vs_eager']:.2f}x; "
                  f"fused vs eager: {100 * same['same_pixel']:.1f}% same pixel, cosine median "
                  f"{same['cosine_median']:.5f}")
    results.append(bench_labels(args.rounds, images))
    if args.output:
        args.output.write_text(json.dumps({"threads": threads, "count": args.count, "rounds": args.rounds,
                                           "cpu": cpu_description(), "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
