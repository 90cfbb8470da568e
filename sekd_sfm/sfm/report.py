"""Match statistics from the database, failure explanations, stats.json and the summary screen."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import SekdError
from .colmap import open_database, require_pycolmap


class ReconstructionError(SekdError):
    """The reconstruction failed or is incomplete; the message's first line says what, the rest why."""


def match_statistics(database: str | Path, min_inliers: int) -> dict:
    """Per image and per pair counts from a verified database.

    ``pairs``: ``(name0, name1, raw matches, verified inliers)`` sorted by inliers, decreasing;
    ``images``: name -> keypoints, pairs with >= ``min_inliers`` inliers, best inlier count.
    """
    pycolmap = require_pycolmap()
    with open_database(database) as db:
        names = {image.image_id: image.name for image in db.read_all_images()}
        keypoints = {names[i]: int(db.num_keypoints_for_image(i)) for i in names}
        raw = dict(zip(*db.read_num_matches()))
        inliers = dict(zip(*db.read_two_view_geometry_num_inliers()))
    pairs = []
    for pair_id in sorted(set(raw) | set(inliers)):
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        pairs.append((names[a], names[b], int(raw.get(pair_id, 0)), int(inliers.get(pair_id, 0))))
    pairs.sort(key=lambda p: (-p[3], -p[2], p[0], p[1]))
    return {"min_inliers": min_inliers, "pairs": pairs, "images": _per_image(keypoints, pairs, min_inliers)}


def _per_image(keypoints: dict[str, int], pairs: list, min_inliers: int) -> dict:
    images = {name: {"keypoints": n, "verified_pairs": 0, "best_inliers": 0} for name, n in keypoints.items()}
    for a, b, _, inl in pairs:
        for name in (a, b):
            images[name]["best_inliers"] = max(images[name]["best_inliers"], inl)
            images[name]["verified_pairs"] += inl >= min_inliers
    return images


def summarize_matches(stats: dict) -> dict:
    """Counts and medians of the match statistics (what stats.json records)."""
    raw = [p[2] for p in stats["pairs"]]
    inl = [p[3] for p in stats["pairs"]]
    keypoints = [v["keypoints"] for v in stats["images"].values()]
    med = (lambda v: float(np.median(v)) if v else 0.0)
    return {
        "images": len(stats["images"]),
        "median_keypoints": med(keypoints),
        "pairs_with_matches": sum(r > 0 for r in raw),
        "verified_pairs": sum(i >= stats["min_inliers"] for i in inl),
        "median_matches": med(raw),
        "median_inliers": med(inl),
        "max_inliers": max(inl, default=0),
    }


def _pair_lines(pairs: list, limit: int = 5) -> str:
    return "\n".join(f"    {a} - {b}: {raw} matches, {inl} verified inliers" for a, b, raw, inl in pairs[:limit])


def _counts_line(stats: dict) -> str:
    s = summarize_matches(stats)
    return (f"  {s['images']} images, median {s['median_keypoints']:.0f} keypoints; {s['pairs_with_matches']} pairs with "
            f"matches (median {s['median_matches']:.0f}); {s['verified_pairs']} pairs with >= {stats['min_inliers']} "
            f"verified inliers (median {s['median_inliers']:.0f}, max {s['max_inliers']})")


def check_enough_matches(stats: dict, database: Path) -> None:
    """ReconstructionError when no pair has enough verified inliers for the mapper to start."""
    if summarize_matches(stats)["verified_pairs"] > 0:
        return
    raise ReconstructionError(
        f"too few matches: no image pair has the {stats['min_inliers']} geometrically verified matches the mapper needs\n"
        + _counts_line(stats) + "\n  best pairs:\n" + (_pair_lines(stats["pairs"]) or "    (none)") + "\n"
        f"  database kept: {database}\n"
        "  try more keypoints (--max-keypoints), a looser --ratio, other pairs, or images with more overlap"
    )


def explain_no_model(stats: dict, options, database: Path) -> ReconstructionError:
    """The mapper found no initial pair: the requirements it checks and the best candidate pairs."""
    mapper = options.mapper
    return ReconstructionError(
        "no initial pair: the mapper found no image pair to start from\n"
        f"  an initial pair needs >= {mapper.init_min_num_inliers} inliers, a triangulation angle >= "
        f"{mapper.init_min_tri_angle} deg and forward motion <= {mapper.init_max_forward_motion}\n"
        + _counts_line(stats) + "\n  best pairs:\n" + (_pair_lines(stats["pairs"]) or "    (none)") + "\n"
        f"  database kept: {database}\n"
        "  try --mapper mapper.init_min_num_inliers=50 --mapper mapper.init_min_tri_angle=8, or images with a wider baseline"
    )


def explain_submodels(groups: list[list[str]], stats: dict, database: Path) -> ReconstructionError:
    """Several sub-models: their images and the strongest verified links between them."""
    where = {name: k for k, names in enumerate(groups) for name in names}
    links = [p for p in stats["pairs"] if p[0] in where and p[1] in where and where[p[0]] != where[p[1]]]
    lines = [f"    model {k}: {len(names)} images: {', '.join(names[:8])}{' ...' if len(names) > 8 else ''}"
             for k, names in enumerate(groups)]
    return ReconstructionError(
        f"{len(groups)} sub-models: the images split into groups the mapper could not join; the largest is the main model\n"
        + "\n".join(lines) + "\n" + _counts_line(stats) + "\n"
        f"  strongest links between different sub-models (needs >= {stats['min_inliers']} inliers and enough 3D points):\n"
        + (_pair_lines(links) or "    (no verified pair links them)") + "\n"
        f"  database kept: {database}\n"
        "  try pairs linking the groups (exhaustive), more keypoints, or --mapper min_model_size / multiple_models=false"
    )


def unregistered_report(names: list[str], stats: dict) -> list[dict]:
    """For images not in the main model: keypoints, verified pairs and best inlier count."""
    return [{"name": n, **stats["images"].get(n, {})} for n in names]


def write_json(data: dict, path: Path) -> Path:
    """Write JSON atomically (temporary file + rename)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=False))
    os.replace(tmp, path)
    return path


def format_summary(stats: dict) -> str:
    """The one-screen summary of a stats.json dictionary."""
    lines = [f"reconstruction: {stats['status']}" + (f" ({stats['failure']})" if stats.get("failure") else "")]
    model = stats.get("model")
    if model:
        lines.append(f"  registered images  {model['registered_images']} / {stats['matches']['images']}")
        lines.append(f"  3D points          {model['points3D']}")
        lines.append(f"  mean track length  {model['mean_track_length']:.2f}")
        lines.append(f"  mean reproj. error {model['mean_reprojection_error_px']:.3f} px")
        lines.append(f"  sub-models         {len(stats['models'])}")
    m = stats.get("matches") or {}
    if m:
        lines.append(f"  matches            {m['pairs_with_matches']} pairs, median {m['median_matches']:.0f} matches, "
                     f"{m['verified_pairs']} verified (median {m['median_inliers']:.0f} inliers)")
    for item in stats.get("unregistered", [])[:5]:
        lines.append(f"  not registered     {item['name']}: {item.get('keypoints', 0)} keypoints, "
                     f"{item.get('verified_pairs', 0)} verified pairs, best {item.get('best_inliers', 0)} inliers")
    timings = stats.get("timings_s", {})
    lines.append("  time               " + ", ".join(f"{k} {v:.1f}s" for k, v in timings.items()))
    if stats.get("output"):
        lines.append(f"  output             {stats['output']}")
    return "\n".join(lines)
