"""Ordered captures (a walk, a turntable, a video's keyframes): the capture order against look-alikes.

On repeated or symmetric structure a folded model is more consistent with the verified pairs than the
right one: look-alike pairs outnumber the few right pairs across the fold, so no count of agreeing pairs
can choose the right model (docs/experiments.md, section 32). A capture taken in order says more: photos
next to each other in it show the same place, look-alikes are far apart in it. So when the photos' names give
an order in which nearly every photo is verified with the next, they are mapped in capture order:

1. only the pairs of photos at most ``window`` apart in the order: a chain that look-alikes cannot fold
   (it may drift a little over a long loop);
2. every farther pair checked against the chain's poses, as the model check does: a pair whose inliers
   do not fit them (under ``min_agreement`` within ``max_error_px``) is dropped;
3. ``order_first`` (the default): the chain's poses held, every point triangulated again from the pairs kept
   and the whole model adjusted (loop closures and right far pairs tie the chain, its drift goes), as the
   hierarchical mapper's clusters are merged; no mapping of all the pairs at all, so no first model that
   look-alikes fold and no mapper trying initial pair after initial pair on wrong pairs. A chain that leaves
   photos out falls back to mapping all pairs; a result the model check suspects gives way to the chain alone.
   Only up to ``order_first_max_photos`` photos: over a longer chain the drift makes true loop closures fail
   step 2. Without ``order_first``, and above that size: all pairs are mapped first, and only a folded
   (``modelcheck``) or split model is mapped again in two passes, the chain and then all photos with the pairs
   kept.

The pipeline keeps a model only when it is better (not folded, else more photos). Measured:
docs/experiments.md, sections 35 and 38.
"""
from __future__ import annotations

import re
import shutil
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .colmap import delete_verified_pairs, open_database, require_pycolmap
from .modelcheck import matched_points, pair_agreement


@dataclass
class SequenceConfig:
    """Settings of the capture-order remapping (module doc)."""

    enabled: bool = True
    #: An ordered capture is mapped in capture order from the start (module doc, step 3), not only after all
    #: pairs gave a folded or split model.
    order_first: bool = True
    #: ... up to this many photos (those with a verified pair). Over a longer chain the drift makes the true pairs
    #: that close a loop look unfit, and they would be dropped: a generated 1,000-photo walk mapped in order lost
    #: its 29 strongest loop-closing pairs (up to 900 inliers) and bent, pose AUC@5 0.783 where all pairs at once
    #: gave 0.968 (docs/experiments.md, section 39). Above it all pairs are mapped first and a folded or split model
    #: is mapped again in capture order afterwards, as with ``order_first`` off.
    order_first_max_photos: int = 250
    #: Photos at most this far apart in the capture order are mapped first (the chain).
    window: int = 3
    #: The photos count as an ordered capture when at least this share of consecutive photos (those with a
    #: verified pair) are a verified pair.
    min_linked: float = 0.8
    #: ... and when photos next to each other in that order share no less than photos far apart: the median inliers
    #: of consecutive pairs over those of pairs more than ``window`` apart must reach this. Photos named by something
    #: else than their order (sacre_coeur's Flickr ids) link their neighbours as well, when nearly every pair of a
    #: few photos of one facade verifies (89 % of consecutive ones), but with fewer inliers than pairs far apart
    #: (median 54 against 170); mapped in that order their model folded (11 strong pairs contradicting it). Walks,
    #: turntables and fountain-P11: 2.6 to 8 with SEKD, a 24-photo temple with SIFT 1.3, a generated arc whose every
    #: view sees every point 1.0 (docs/experiments.md, section 48).
    min_order_contrast: float = 1.0
    #: A split model is mapped again when its largest model leaves out more than this share of the photos.
    max_left_out: float = 0.05
    #: Distance (px, Sampson) within which a far pair's inlier fits the chain's poses: twice the verification's,
    #: as the chain drifts over long loops.
    max_error_px: float = 8.0
    #: A far pair with a smaller share of its inliers fitting the chain is dropped.
    min_agreement: float = 0.5
    #: Dropped pairs listed in the record (most inliers first).
    listed: int = 20


@dataclass(frozen=True)
class VerifiedPair:
    """A verified pair of the database: ids, names, inliers and how far apart the photos are in the capture order."""

    image1: int
    image2: int
    name1: str
    name2: str
    inliers: int
    gap: int


def natural_key(name: str) -> list:
    """Sort key of a photo name with its numbers compared as numbers (``img2`` before ``img10``)."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def capture_order(names: Iterable[str]) -> list[str]:
    """The names in capture order: sorted, numbers compared as numbers."""
    return sorted(names, key=natural_key)


def verified_pairs(database: str | Path, min_inliers: int) -> list[VerifiedPair]:
    """The pairs of ``database`` with ``min_inliers`` or more verified inliers; ``gap`` counts only the photos that
    have such a pair (a distractor between two photos of the walk does not break their link)."""
    pycolmap = require_pycolmap()
    with open_database(database) as db:
        names = {image.image_id: image.name for image in db.read_all_images()}
        counts = dict(zip(*db.read_two_view_geometry_num_inliers()))
    found = [(pycolmap.pair_id_to_image_pair(pair_id), int(n)) for pair_id, n in counts.items() if n >= min_inliers]
    linked = {name for (a, b), _ in found for name in (names[a], names[b])}
    index = {name: k for k, name in enumerate(capture_order(linked))}
    return [VerifiedPair(a, b, names[a], names[b], n, abs(index[names[a]] - index[names[b]])) for (a, b), n in found]


def linked_share(pairs: list[VerifiedPair]) -> float:
    """The share of consecutive photos in the capture order that are a verified pair (0 for under 3 photos)."""
    photos = {name for pair in pairs for name in (pair.name1, pair.name2)}
    if len(photos) < 3:
        return 0.0
    return sum(pair.gap == 1 for pair in pairs) / (len(photos) - 1)


def order_contrast(pairs: list[VerifiedPair], window: int) -> float:
    """The median inliers of consecutive photos' pairs over those of pairs more than ``window`` apart in the capture
    order: under 1 when the order contradicts which photos overlap (inf without far pairs, 0 without consecutive
    ones; 1 where every pair shares as much, as in a generated scene every view sees whole)."""
    consecutive = [pair.inliers for pair in pairs if pair.gap == 1]
    far = [pair.inliers for pair in far_pairs(pairs, window)]
    if not consecutive:
        return 0.0
    return float(np.median(consecutive) / np.median(far)) if far else float("inf")


def is_ordered(linked: float, contrast: float, config: SequenceConfig) -> bool:
    """Whether photos with ``linked_share`` and ``order_contrast`` are an ordered capture by ``config``."""
    return linked >= config.min_linked and contrast >= config.min_order_contrast


def far_pairs(pairs: list[VerifiedPair], window: int) -> list[VerifiedPair]:
    """The pairs of photos more than ``window`` apart in the capture order."""
    return [pair for pair in pairs if pair.gap > window]


def drop_pairs(database: str | Path, pairs: Iterable[VerifiedPair]) -> None:
    """Delete the verified inliers of ``pairs`` from ``database`` (their raw matches stay)."""
    delete_verified_pairs(database, [(pair.image1, pair.image2) for pair in pairs])


def chain_database(database: str | Path, target: str | Path, window: int) -> list[VerifiedPair]:
    """A copy of ``database`` at ``target`` keeping only the verified pairs at most ``window`` apart in the capture
    order; returns the pairs left out (``far_pairs``)."""
    shutil.copyfile(database, target)
    far = far_pairs(verified_pairs(database, 1), window)
    drop_pairs(target, far)
    return far


def disagreeing_pairs(models: list, database: str | Path, pairs: list[VerifiedPair],
                      config: SequenceConfig) -> list[tuple[VerifiedPair, float]]:
    """The ``pairs`` whose inliers fit the poses of the model among ``models`` that holds both photos less than
    ``config.min_agreement`` (``modelcheck.pair_agreement``), each with its share. A pair no model holds whole is
    not judged (kept): if it folds the model again, the model check says so and the chain is kept instead."""
    posed = [{image.name: image_id for image_id, image in model.images.items() if image.has_pose} for model in models]
    found = []
    with open_database(database) as db:
        keypoints: dict[int, np.ndarray] = {}
        for pair in pairs:
            holder = next((k for k, names in enumerate(posed) if pair.name1 in names and pair.name2 in names), None)
            if holder is None:
                continue
            matches = np.asarray(db.read_two_view_geometry(pair.image1, pair.image2).inlier_matches).reshape(-1, 2)
            share = pair_agreement(models[holder], posed[holder][pair.name1], posed[holder][pair.name2],
                                   *matched_points(db, keypoints, pair.image1, pair.image2, matches),
                                   config.max_error_px)
            if share < config.min_agreement:
                found.append((pair, share))
    return found


def remap_reason(models: list, suspect: bool, photos: int, config: SequenceConfig) -> str | None:
    """Why the mapped ``models`` (largest first) should be mapped again in capture order, or None: ``folded`` (the
    model check suspects the largest), ``split`` (several models, or the largest leaves out more than
    ``config.max_left_out`` of the ``photos`` with a verified pair)."""
    if suspect:
        return "folded"
    if len(models) > 1 or registered(models) < (1 - config.max_left_out) * photos:
        return "split"
    return None


def registered(models: list) -> int:
    """Photos registered in the largest of ``models`` (largest first; 0 without one)."""
    return models[0].num_reg_images() if models else 0


def rank(score: tuple[bool, int]) -> tuple[bool, int]:
    """Sort key of a model's ``score`` = (suspect, photos registered): not folded first, then more photos."""
    return not score[0], score[1]


def better(new: tuple[bool, int], old: tuple[bool, int]) -> bool:
    """Whether a model scoring ``new`` beats one scoring ``old`` (``rank``)."""
    return rank(new) > rank(old)


def sequence_record(reason: str, linked: float, config: SequenceConfig, **figures) -> dict:
    """The record of ``stats.json`` ``sequence``."""
    return {"reason": reason, "linked": round(linked, 4), **figures, "config": asdict(config)}


def listed_pairs(dropped: list[tuple[VerifiedPair, float]], count: int) -> list[dict]:
    """The ``count`` dropped pairs with most inliers, for the record."""
    strongest = sorted(dropped, key=lambda d: -d[0].inliers)[:count]
    return [{"pair": [p.name1, p.name2], "inliers": p.inliers, "apart": p.gap, "agreement": round(share, 3)}
            for p, share in strongest]
