"""Retrieval recall on a mixed collection of the shared scenes (numbers in docs/pairs.md).

The collection: the 5 homography sequences (6 images each), fountain-P11 (11), sacre_coeur
(10) and COCO photos as distractors (256 by default, each its own scene). The true
neighbours of an image are the other images of its scene; distractors have none.

    python scripts/retrieval_recall.py --work /tmp/recall --feature sekd --resize-max 640

Extraction is resumable (rerun to add feature types); prints recall@K and pair recall.
``--cost`` also measures, in CPU seconds of this process (robust on a shared machine), the
matching cost of one pair against the global-descriptor cost of one image (the `auto` rule).
"""
from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

import torch

from sekd_sfm.features import FeatureConfig
from sekd_sfm.files import features as ff
from sekd_sfm.stages.extract import extract_features
from sekd_sfm.stages.match import MatchConfig, match_features
from sekd_sfm.stages.pairs import exhaustive_pairs, unique_pairs, write_pairs
from sekd_sfm.stages.retrieval import (
    RetrievalConfig,
    compute_global_descriptors,
    learn_vocabulary,
    nearest_neighbors,
    neighbour_recall,
    pair_recall,
    vlad,
)


def build_collection(shared: Path, folder: Path, distractors: int) -> None:
    """Symlinks ``folder/<scene>/<image>`` to the shared images (nothing is copied)."""
    data = shared / "data"
    scenes = {p.name: sorted(p.glob("[0-9].p*")) for p in sorted((data / "homography").glob("*/*")) if p.is_dir()}
    scenes["fountain-P11"] = sorted((data / "sfm/fountain-P11/images").glob("*.jpg"))
    scenes["sacre_coeur"] = sorted((data / "sfm/sacre_coeur/images").glob("*.jpg"))
    scenes["coco"] = sorted((data / "train/coco").glob("*.jpg"))[:distractors]
    for scene, files in scenes.items():
        (folder / scene).mkdir(parents=True, exist_ok=True)
        for file in files:
            link = folder / scene / file.name
            if not link.exists():
                link.symlink_to(file.resolve())


def scene_truth(names: list[str], distractor_scene: str = "coco") -> dict[str, set[str]]:
    """True neighbours: the other images of the same top-level folder; none for distractors."""
    scene = {n: n.split("/")[0] for n in names}
    groups: dict[str, set[str]] = {}
    for n in names:
        groups.setdefault(scene[n], set()).add(n)
    return {n: set() if scene[n] == distractor_scene else groups[scene[n]] - {n} for n in names}


def measure_cost(features: Path, names: list[str], config: RetrievalConfig, work: Path) -> None:
    """CPU time: matching one pair (105 pairs of 15 images), vocabulary, one global descriptor, the search."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    pairs = write_pairs(exhaustive_pairs(names[:15]), work / "pairs.txt")
    started = time.process_time()
    match_features(features, pairs, work / "matches.h5", MatchConfig(), num_threads=1, progress=False)
    per_pair = (time.process_time() - started) / 105
    started = time.process_time()
    vocab = learn_vocabulary(features, names, config)
    vocabulary = time.process_time() - started
    started = time.process_time()
    for name in names:
        vlad(ff.read_features(features, name)["descriptors"], vocab)
    per_image = (time.process_time() - started) / len(names)
    out = compute_global_descriptors(features, config, work / "g.global.h5", progress=False)
    started = time.process_time()
    nearest_neighbors(out, names, 20)
    search = time.process_time() - started
    print(f"  CPU time: match {1000 * per_pair:.1f} ms/pair; vocabulary {vocabulary:.2f} s; global descriptor "
          f"{1000 * per_image:.1f} ms/image (= {per_image / per_pair:.3f} pairs); search K=20 {1000 * search:.0f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shared", type=Path, default=Path(os.environ.get("SEKD_SHARED", "../shared")))
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--feature", default="sekd")
    parser.add_argument("--resize-max", type=int, default=640)
    parser.add_argument("--max-keypoints", type=int, default=2000)
    parser.add_argument("--distractors", type=int, default=256)
    parser.add_argument("--vocabulary-size", type=int, default=RetrievalConfig.vocabulary_size)
    parser.add_argument("--pca-dim", type=int, default=RetrievalConfig.pca_dim)
    parser.add_argument("--features", type=Path, default=None,
                        help="use this feature file of WORK/images instead of extracting one")
    parser.add_argument("--cost", action="store_true", help="also measure matching vs global-descriptor CPU cost")
    args = parser.parse_args()
    torch.set_num_threads(1)
    build_collection(args.shared, args.work / "images", args.distractors)
    features = args.features or extract_features(args.work / "images", args.work / f"{args.feature}-{args.resize_max}.h5",
                                FeatureConfig(feature=args.feature, resize_max=args.resize_max,
                                              max_keypoints=args.max_keypoints), progress=False)
    names = ff.list_keys(features)
    truth = scene_truth(names)
    config = RetrievalConfig(vocabulary_size=args.vocabulary_size, pca_dim=args.pca_dim)
    out = features.with_name(f"{features.stem}-k{config.vocabulary_size}-d{config.pca_dim}.global.h5")
    out.unlink(missing_ok=True)
    started = time.perf_counter()
    compute_global_descriptors(features, config, out, progress=False)
    described = time.perf_counter() - started
    started = time.perf_counter()
    neighbours = nearest_neighbors(out, names, 20)
    searched = time.perf_counter() - started
    print(f"{features.name}: {len(names)} images, global descriptors {described:.1f} s "
          f"({1000 * described / len(names):.0f} ms/image incl. vocabulary), neighbour search {searched * 1000:.0f} ms")
    for k in (1, 5, 10, 20):
        pairs = unique_pairs((a, b) for a in names for b in neighbours[a][:k])
        print(f"  K={k:2d}: recall@K {neighbour_recall(neighbours, truth, k):.3f}  "
              f"pair recall {pair_recall(pairs, truth):.3f}  pairs {len(pairs)}")
    scenes = sorted({n.split("/")[0] for n in names if truth[n]})
    print("  recall@20 per scene: " + ", ".join(
        f"{s} {neighbour_recall(neighbours, {n: t for n, t in truth.items() if n.startswith(s + '/')}, 20):.2f}"
        for s in scenes))
    if args.cost:
        measure_cost(features, names, config, args.work / "cost")


if __name__ == "__main__":
    main()
