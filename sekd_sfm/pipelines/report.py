"""Match statistics from the database, failure explanations, the run's record and the summary screen."""
from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..stages.colmap import open_database, require_pycolmap
from .record import STATS


class ReconstructionError(SekdError):
    """The reconstruction failed or is incomplete; the message's first line says what, the rest why."""


class StageTimer:
    """Wall time of each named stage: ``with timer("extract"): ...`` sets ``timer.seconds["extract"]`` (s, 3 decimals)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] = round(time.perf_counter() - start, 3)


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
    """Counts and medians of the match statistics (what the run's record keeps)."""
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
    """The mapper made no model: for the incremental mappers, the initial-pair requirements; the best pairs."""
    from ..stages.mapping import initial_pair_options, mapper_type_of

    kind, init = mapper_type_of(options), initial_pair_options(options)
    if init is not None:
        first = "no initial pair: the mapper found no image pair to start from"
        why = (f"  an initial pair needs >= {init.init_min_num_inliers} inliers, a triangulation angle >= "
               f"{init.init_min_tri_angle} deg and forward motion <= {init.init_max_forward_motion}\n")
        prefix = "incremental_options." if kind == "hierarchical" else ""
        fix = (f"  try --mapper {prefix}mapper.init_min_num_inliers=50 --mapper {prefix}mapper.init_min_tri_angle=8, "
               "or images with a wider baseline")
        if kind == "hierarchical":  # its clusters also drop models smaller than min_model_size
            size = options.incremental_options.min_model_size
            why += f"  and the hierarchical mapper keeps only models of >= {size} images\n"
            fix += "; for small collections use --mapper-type incremental"
    else:
        first = "no model: the global mapper could not place enough cameras"
        why = (f"  a model needs >= {options.min_model_size} images linked by pairs with >= {options.min_num_matches} "
               "verified inliers and consistent relative rotations\n")
        fix = "  try --mapper-type incremental, more keypoints, or images with more overlap"
    return ReconstructionError(
        first + "\n" + why + _counts_line(stats) + "\n  best pairs:\n" + (_pair_lines(stats["pairs"]) or "    (none)")
        + f"\n  database kept: {database}\n" + fix
    )


def explain_models(groups: list[list[str]], stats: dict, paths: list[Path]) -> str:
    """Several models: where each was written, its images, and the strongest verified links between them."""
    where = {name: k for k, names in enumerate(groups) for name in names}
    links = [p for p in stats["pairs"] if p[0] in where and p[1] in where and where[p[0]] != where[p[1]]]
    lines = [f"    {path}: {len(names)} images: {', '.join(names[:8])}{' ...' if len(names) > 8 else ''}"
             for path, names in zip(paths, groups)]
    return (
        f"{len(groups)} models: the images split into groups the mapper could not join; each is written, "
        "the largest to model/\n" + "\n".join(lines) + "\n"
        f"  strongest links between different models (needs >= {stats['min_inliers']} inliers and enough 3D points):\n"
        + (_pair_lines(links) or "    (no verified pair links them)") + "\n"
        "  to join them: pairs linking the groups (--pairs exhaustive), more keypoints, or photos between the groups"
    )


def unregistered_report(names: list[str], stats: dict, where: dict[str, int] | None = None,
                        min_model_size: int | None = None) -> list[dict]:
    """For images in no model: keypoints, verified pairs, best inlier count, raw matches of their best pairs, and
    ``reason``, why the image is in no model (``unregistered_reason``). ``where``: image name -> index of the model
    holding it (the images of no model left out); ``min_model_size``: the mapper's (default: ``MIN_MODEL_SIZE``)."""
    if min_model_size is None:
        from ..stages.mapping import MIN_MODEL_SIZE as min_model_size
    where = where or {}
    groups = unmapped_groups(names, stats)
    report = []
    for name in names:
        best = [(b if a == name else a, raw, inl) for a, b, raw, inl in stats["pairs"] if name in (a, b)][:3]
        item = {"name": name, **stats["images"].get(name, {}),
                "best_pairs": [{"with": other, "matches": raw, "inliers": inl} for other, raw, inl in best]}
        item["reason"] = unregistered_reason(name, stats, where, groups[name], min_model_size)
        report.append(item)
    return report


def unmapped_groups(names: list[str], stats: dict) -> dict[str, list[str]]:
    """Each of ``names`` (images in no model) -> the images in no model it is linked to by verified pairs,
    itself included (connected components of the verified pairs among ``names``)."""
    parent = {name: name for name in names}

    def root(name: str) -> str:
        while parent[name] != name:
            parent[name] = parent[parent[name]]
            name = parent[name]
        return name

    for a, b, _, inliers in stats["pairs"]:
        if inliers >= stats["min_inliers"] and a in parent and b in parent:
            parent[root(a)] = root(b)
    members: dict[str, list[str]] = {}
    for name in names:
        members.setdefault(root(name), []).append(name)
    return {name: members[root(name)] for name in names}


def unregistered_reason(name: str, stats: dict, where: dict[str, int], group: list[str], min_model_size: int) -> str:
    """Why ``name`` is in no model, in one line: no verified pair; pairs with a model's photos that the mapper could
    not register it from; or a group of photos in no model (fewer than ``min_model_size``, or no initial pair)."""
    image = stats["images"].get(name, {})
    if not image.get("verified_pairs"):
        return (f"no verified pair: its best pair has {image.get('best_inliers', 0)} inliers, a pair needs "
                f"{stats['min_inliers']}")
    linked = sorted({where[b if a == name else a] for a, b, _, inl in stats["pairs"]
                     if name in (a, b) and inl >= stats["min_inliers"] and (b if a == name else a) in where})
    if linked:
        return (f"verified pairs with photos of model {linked[0]}, but the mapper could not register it (too few of "
                "its matches reach the model's 3D points, or its pose did not verify)")
    if len(group) < min_model_size:
        return (f"verified pairs only with {len(group) - 1} other photo(s) in no model: a model needs "
                f"{min_model_size} photos")
    return (f"one of {len(group)} photos linked only to each other, which the mapper could not start a model from "
            "(no initial pair: too few inliers or too little parallax)")


def folded_warning(check: dict) -> str:
    """One line: a model (``check``: its ``model_check`` record) that verified pairs contradict may be folded."""
    strongest = check["strongest"][0]
    return (f"{check['path']} may be folded or twisted (look-alike structure joined): {check['strong_contradicting']}"
            f" strong verified pairs contradict its poses, the strongest {strongest['pair'][0]} - "
            f"{strongest['pair'][1]} with {strongest['inliers']} inliers, {strongest['agreement']:.0%} of them "
            "fitting the model; check it against photos or known cameras before use")


def sequence_line(record: dict) -> str:
    """One line: what mapping in capture order (``stats.json`` ``sequence``) did and which model was kept."""
    if record["reason"] == "ordered":
        return _ordered_line(record)
    why = "folded" if record["reason"] == "folded" else "split"
    if not record.get("remapped"):
        if record["linked"] >= record["config"]["min_linked"]:  # linked, but the order says nothing of overlap
            return (f"the model is {why}; the names are no capture order ({record['linked']:.0%} of consecutive "
                    "photos verified, but they share fewer inliers than photos far apart: "
                    f"{record.get('contrast') or 0:.2f} times theirs), so it stays")
        return (f"the model is {why}; the photos are no ordered capture ({record['linked']:.0%} of consecutive "
                f"photos verified, {record['config']['min_linked']:.0%} needed), so it stays")
    models = record["models"]
    before, after = models["before"], models[record["kept"]] if record["kept"] != "before" else None
    done = (f"the model was {why} ({before['registered']} photos); mapped again in capture order, "
            f"{record['dropped']} of {record['far_pairs']} pairs over {record['config']['window']} photos apart "
            "dropped (their inliers do not fit the order's poses)")
    if after is None:
        return done + "; no better model came of it, the first stays"
    return done + f"; kept: {after['registered']} photos" + (", still folded" if after["suspect"] else ", not folded")


def _ordered_line(record: dict) -> str:
    """``sequence_line`` of an ordered capture mapped in capture order from the start."""
    window = record["config"]["window"]
    if not record.get("remapped"):
        return (f"the chain of photos at most {window} apart in the order holds {record['chain_registered']} of "
                f"{record['photos']} photos: all pairs mapped at once instead")
    done = (f"photos at most {window} apart mapped first; {record['dropped']} of {record['far_pairs']} farther pairs "
            "dropped (their inliers do not fit that chain's poses)")
    kept = record["models"][record["kept"]]
    if record["kept"] == "closed":
        return done + f", the rest triangulated onto its poses: {kept['registered']} photos" + (
            ", folded" if kept["suspect"] else "")
    return done + f"; with the rest it folds, so the chain alone is kept: {kept['registered']} photos"


def _capture_lines(stats: dict) -> list[str]:
    """The summary's lines on rigs and panoramas: each rig's cameras and instants, each estimated pose's support."""
    lines = []
    panoramas = stats.get("panoramas")
    if panoramas and "posed" in panoramas:
        lines.append(f"  panoramas          {panoramas['posed']} of {panoramas['panoramas']} posed (each as "
                     f"{len(panoramas['yaws_deg'])} views), poses in panoramas.txt")
    rig = stats.get("rig") or {}
    for entry in [] if panoramas else rig.get("model", []):
        lines.append(f"  rig                {len(entry['cameras'])} cameras ({', '.join(rig['photos_per_camera'])}), "
                     f"{entry['instants_registered']} instants registered")
    for prefix, support in (rig.get("estimated") or {}).items():
        lines.append(f"  rig pose           {prefix} estimated where {support['agreeing']} of {support['instants']} "
                     "instants agree (rig.json)")
    return lines


def stage_lines(stats: dict) -> list[str]:
    """The summary's table of stages: seconds and where each computed (``Run.stage_table``), a stage's timed parts
    indented under it, then the total; one ``time`` line for a record that has only the seconds (older runs)."""
    stages, timings = stats.get("stages"), stats.get("timings_s", {})
    if not stages:
        return ["  time               " + ", ".join(f"{k} {v:.1f}s" for k, v in timings.items())] if timings else []
    width = max(15, *(len(stage["stage"]) for stage in stages),
                *(len(part) + 2 for stage in stages for part in stage.get("parts", {})))
    lines = [f"  {'stages':<{width + 2}}  {'seconds':>8}  ran on"]
    for stage in stages:
        lines.append(f"    {stage['stage']:<{width}}  {stage['seconds']:8.1f}  {stage['ran_on']}")
        lines += [f"      {part:<{width - 2}}  {seconds:8.1f}" for part, seconds in stage.get("parts", {}).items()]
    lines.append(f"    {'total':<{width}}  {sum(stage['seconds'] for stage in stages):8.1f}")
    return lines


def format_summary(stats: dict) -> str:
    """The one-screen summary of a run's record (``record.STATS``, as a dictionary)."""
    lines = [f"reconstruction: {stats['status']}" + (f" ({stats['failure']})" if stats.get("failure") else "")]
    model = stats.get("model")
    if model:
        lines.append(f"  registered images  {model['registered_images']} / {stats['matches']['images']}")
        lines.append(f"  3D points          {model['points3D']}")
        lines.append(f"  mean track length  {model['mean_track_length']:.2f}")
        lines.append(f"  mean reproj. error {model['mean_reprojection_error_px']:.3f} px")
        sizes = ", ".join(str(m["registered_images"]) for m in stats["models"])
        lines.append(f"  models             {len(stats['models'])}" + (f": {sizes} photos (the others in models/)"
                                                                      if len(stats["models"]) > 1 else ""))
    lines += _capture_lines(stats)
    m = stats.get("matches") or {}
    if m:
        lines.append(f"  matches            {m['pairs_with_matches']} pairs, median {m['median_matches']:.0f} matches, "
                     f"{m['verified_pairs']} verified (median {m['median_inliers']:.0f} inliers)")
    refine = stats.get("refine")
    if refine:
        lines.append(f"  refined keypoints  {refine['aligned']} of {refine['matches']} matches aligned, "
                     f"median shift {refine['median_shift_px']:.2f} px")
    chance = stats.get("chance")
    if chance and chance.get("dropped"):
        lines.append(f"  chance check       {chance['dropped']} of {chance['verified']} verified pairs dropped: their "
                     f"inliers no more than {chance['config']['margin']:.2f} x what their matches reach shuffled")
    graph = stats.get("view_graph")
    if graph and graph.get("skipped"):
        lines.append(f"  view graph         not checked: {graph['skipped']} (--camera-params makes it checkable)")
    elif graph and graph.get("pairs"):
        lines.append(f"  view graph         {graph['dropped']} of {graph['pairs']} verified pairs dropped: their rotation "
                     f"disagrees with the others' by more than {graph['threshold_deg']:.1f} deg")
    if stats.get("sequence"):
        lines.append(f"  capture order      {sequence_line(stats['sequence'])}")
    for check in stats.get("model_check") or []:
        if check.get("suspect"):
            lines.append(f"  model check        {folded_warning(check)}")
    filtered = stats.get("final_filter")
    if filtered and "threshold_px" in filtered:
        lines.append(f"  final filter       {filtered['removed_observations']} of {filtered['observations']} observations "
                     f"beyond {filtered['threshold_px']:.2f} px dropped, mean error "
                     f"{filtered['mean_error_before_px']:.3f} -> {filtered['mean_error_after_px']:.3f} px")
    unregistered = stats.get("unregistered", [])
    for item in unregistered[:5]:
        lines.append(f"  not registered     {item['name']}: " + (item.get("reason") or
                     f"{item.get('keypoints', 0)} keypoints, {item.get('verified_pairs', 0)} verified pairs, "
                     f"best {item.get('best_inliers', 0)} inliers"))
    if len(unregistered) > 5:
        lines.append(f"  not registered     ... and {len(unregistered) - 5} more (listed in {STATS})")
    lines += stage_lines(stats)
    if stats.get("output"):
        lines.append(f"  output             {stats['output']}")
    return "\n".join(lines)
