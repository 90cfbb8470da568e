"""SEKD-Lite checkpoints against each other and OpenCV SIFT: extraction images/s, same run.

Times ``SEKDExtractor`` (fast path, fp32 and ``auto``) for each checkpoint and SIFT on the same
480x640 shared COCO images, alternating them ROUNDS times so that machine noise hits all alike,
and reports each rate and its ratio to SIFT's rate in the same round. For comparing Lite
networks of different shapes, e.g. the embedded version 3 against version 2 from the history:

    git show 9e1b26c:sekd_sfm/model/checkpoints/sekd_lite.pth > /tmp/lite_v2.pth
    python scripts/bench_lite_versions.py v2=/tmp/lite_v2.pth v3=lite [--num-threads 2] [-o out.json]

``lite`` names the embedded model. On a CPU with native bf16, hold torch and oneDNN to AVX2
(``ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2``) to stand in for one without
(docs/experiments.md, section 8).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from sekd_sfm.bench.speed import SiftExtractor, load_bench_images, time_method
from sekd_sfm.model.inference import SEKDConfig, SEKDExtractor
from sekd_sfm.model.weights import EMBEDDED_MODELS, load_model
from sekd_sfm.runtime import cpu_description, set_num_threads, shared_dir


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("models", nargs="+", metavar="LABEL=PATH|lite", help="SEKD-Lite checkpoints to time")
    parser.add_argument("--count", type=int, default=8, help="images per pass")
    parser.add_argument("--rounds", type=int, default=3, help="alternations of all methods")
    parser.add_argument("--num-threads", type=int, default=None, help="torch threads (default: all cores)")
    parser.add_argument("-o", "--output", type=Path, default=None, help="also write the results as JSON")
    args = parser.parse_args()
    threads = set_num_threads(args.num_threads)
    images = load_bench_images(shared_dir() / "data" / "train" / "coco", args.count, 480, 640)
    nets = {}
    for spec in args.models:
        label, _, path = spec.partition("=")
        nets[label] = load_model(EMBEDDED_MODELS["lite"] if path in ("", "lite") else Path(path))[0]
    rates: dict[str, list[float]] = {"opencv sift": []}
    for _ in range(args.rounds):
        rates["opencv sift"].append(time_method(SiftExtractor(2000), images, 2)[0])
        for label, net in nets.items():
            for precision in ("fp32", "auto"):
                extractor = SEKDExtractor(net, SEKDConfig(max_keypoints=2000, device="cpu", precision=precision))
                rates.setdefault(f"{label} {precision}", []).append(time_method(extractor, images, 2)[0])
    sift = rates["opencv sift"]
    result = {"threads": threads, "cpu": cpu_description(), "images": args.count,
              "images_per_s": {k: [round(r, 2) for r in v] for k, v in rates.items()},
              "vs_sift": {k: [round(r / s, 3) for r, s in zip(v, sift)] for k, v in rates.items()}}
    for name, ratios in result["vs_sift"].items():
        print(f"{name:20s} images/s {result['images_per_s'][name]}  vs SIFT {ratios}")
    if args.output:
        args.output.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
