"""``sekd reconstruct PHOTOS -o OUT --extend``: add the photos OUT's model lacks, without moving what it has.

The photos of PHOTOS that OUT's database does not hold yet are extracted, paired, matched,
refined, imported and registered into OUT's model with the settings OUT was built with
(stats.json ``config``):

* pairs: the pairs OUT's pairing mode would choose among all its photos plus the new ones
  (exhaustive while that is small, retrieval with the same vocabulary above), those with
  at least one new photo; matched into OUT's match file (only the missing pairs are matched);
* keypoints: the new photos' keypoints are refined with the earlier photos' refined keypoints
  held fixed (``refine_keypoints(anchor=...)``), so the earlier ones stay what the model has;
* database: the new photos are added to a copy of OUT's database (image and camera ids of
  the earlier photos unchanged; a new photo of an existing camera joins it) and only the new
  pairs are verified;
* mapping: pycolmap's incremental mapper continues from OUT's model with the existing frames
  and cameras fixed in every bundle adjustment (``--extend-refine`` lets everything move),
  and triangulates new points. Earlier poses are then checked to be bitwise unchanged.

Crash safety: everything is staged in ``OUT/extend/`` (database copy, refined keypoints,
model, pairs, stats.json); a journal (``OUT/extend/commit.json``) is written when the staged
files are complete, then the model folder is exchanged with ``model/`` atomically (Linux
``renameat2(RENAME_EXCHANGE)``; elsewhere two renames, ``model.backup`` then holds the old
one) and the other files replace theirs. A later run finishes an interrupted commit first
(roll forward) and otherwise discards an incomplete stage, so kill -9 at any moment, then
the same command again, gives the result of an uninterrupted run, and ``model/`` is always a
complete model (the earlier one until the exchange, the new one from then on).
"""
from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import json
import logging
import os
import shutil
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .. import execution
from ..errors import SekdError
from ..stages.extract import extract_features
from ..features import FeatureConfig
from ..files import features as ff
from ..files.images import list_images
from ..files.locking import exclusive_lock
from ..stages.match import MatchConfig, match_features
from ..stages.pairs import (
    PairsConfig,
    generate_pairs,
    read_pairs,
    resolve_mode,
    split_writable,
    unique_pairs,
    warn_skipped,
    write_pairs,
)
from ..stages.retrieval import compute_global_descriptors, nearest_neighbors
from ..runtime import package_versions
from ..stages.colmap import (
    clean_logs,
    colmap_log,
    log_prefix,
    open_database,
    require_pycolmap,
    set_options,
)
from ..stages.database import CameraConfig, add_to_database, two_view_options, verify_matches
from ..stages.mapping import (
    MAIN_MODEL,
    clean_scratch,
    default_options,
    model_stats,
    registered_names,
    run_mapper,
)
from ..stages.refine import RefineConfig, refine_keypoints, refine_summary
from .report import (
    StageTimer,
    match_statistics,
    summarize_matches,
    unregistered_report,
)
from ..files.atomic import write_json

logger = logging.getLogger("sekd")
#: The staging folder of an extension inside OUT, and the commit journal in it.
STAGE = "extend"
JOURNAL = "commit.json"
BACKUP = "model.backup"
#: Config fields that never conflict: the network's path is not recorded (the feature file checks the network).
UNCHECKED = ("features.weights",)


@dataclass(frozen=True)
class ExtendOptions:
    """``--extend`` settings. ``refine``: let the earlier cameras' poses and intrinsics move (``--extend-refine``).
    ``given``: configuration fields (dotted, as in stats.json ``config``) the user set explicitly, with
    their values: each must agree with OUT's record."""

    refine: bool = False
    given: dict = field(default_factory=dict)


@dataclass
class _Recorded:
    """The stage settings of OUT's record (stats.json ``config``)."""

    features: FeatureConfig
    pairs: PairsConfig
    matching: MatchConfig
    camera: CameraConfig
    refine: RefineConfig
    mapper: list[str]
    verification: list[str]
    seed: int
    file_names: tuple[str, str]
    masks: str | None
    #: Models built before the final filter existed record none: their extensions are not filtered either.
    final_filter: bool = False


def _typed(cls, data: dict):
    """The dataclass ``cls`` from a dict of asdict(); unknown keys (newer or older records) are ignored."""
    values = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default) and isinstance(value, dict):
            value = _typed(type(default), value)
        elif isinstance(default, tuple) and isinstance(value, list):
            value = tuple(value)
        values[f.name] = value
    return cls(**values)


def _recorded(config: dict, weights: str | None) -> _Recorded:
    features = _typed(FeatureConfig, config.get("features", {}))
    features.weights = weights
    return _Recorded(features=features, pairs=_typed(PairsConfig, config.get("pairs", {})),
                     matching=_typed(MatchConfig, config.get("matching", {})),
                     camera=_typed(CameraConfig, config.get("camera", {})),
                     refine=_typed(RefineConfig, config.get("refine", {})), mapper=list(config.get("mapper", [])),
                     verification=list(config.get("verification", [])), seed=int(config.get("seed", 0)),
                     file_names=tuple(config.get("file_names", ("features.h5", "matches.h5"))),
                     masks=config.get("masks"), final_filter=bool(config.get("final_filter", False)))


def flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (tuples as lists, as JSON has them)."""
    if isinstance(data, dict):
        out: dict[str, Any] = {}
        for key, value in data.items():
            out.update(flatten(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: list(data) if isinstance(data, tuple) else data}


def check_given(given: dict, config: dict, out: Path) -> None:
    """SekdError when an explicitly given setting differs from the one OUT's model was built with."""
    recorded = flatten(config)
    wrong = {k: v for k, v in flatten(given).items() if k not in UNCHECKED and k in recorded and recorded[k] != v}
    if wrong:
        listed = ", ".join(f"{k} = {v!r} (built with {recorded[k]!r})" for k, v in sorted(wrong.items()))
        raise SekdError(f"{out / 'stats.json'}: --extend adds photos with the settings the model was built with, "
                        f"but these options differ: {listed}; leave them out")


def refined_path(out: Path, features_name: str) -> Path:
    """OUT's refined keypoints: features.h5 -> features-refined.h5 (as ``reconstruct`` names them)."""
    path = Path(features_name)
    return out / f"{path.stem}-refined{path.suffix or '.h5'}"


def extend_model(image_dir: str | Path, output_dir: str | Path, options: ExtendOptions, settings: Any,
                 weights: str | None = None) -> Path:
    """Add the photos below ``image_dir`` that ``output_dir``'s model lacks; returns the model's folder.

    ``settings``: the run's RunSettings (``sekd_sfm.pipelines.reconstruct``: threads, progress, executor);
    ``weights``: the feature network's file when not the packaged one (not recorded in stats.json).
    Photos already in OUT's database (registered or not) are not new: with none new, nothing is
    done ("nothing to add"). SekdError when OUT holds no finished model or its settings conflict.
    """
    require_pycolmap()
    image_dir, out = Path(image_dir), Path(output_dir)
    if not image_dir.is_dir():
        raise SekdError(f"{image_dir}: not a folder of images; give the folder holding the photos")
    if not out.is_dir():
        raise SekdError(f"{out}: no such folder, so no model to extend; build one first: "
                        f"sekd reconstruct {image_dir} -o {out}")
    with exclusive_lock(out, what="reconstruction folder"):
        clean_scratch(out)
        clean_logs(out / "colmap-extend.log")
        if (out / STAGE / JOURNAL).is_file():  # a commit was interrupted: finish it, then see what is left
            logger.warning("%s: finishing the extension an earlier run was interrupted in", out)
            commit(out)
        shutil.rmtree(out / STAGE, ignore_errors=True)  # an unfinished stage is made again from the start
        return _extend(image_dir, out, options, settings, weights)


def _read_stats(out: Path) -> dict:
    path = out / "stats.json"
    try:
        stats = json.loads(path.read_text())
    except (OSError, ValueError):
        stats = None
    model = out / MAIN_MODEL
    if not stats or stats.get("status") != "ok" or not (model / "images.bin").is_file():
        raise SekdError(f"{out}: holds no finished model (model/ and stats.json of a successful "
                        "`sekd reconstruct`) to extend; run sekd reconstruct without --extend first")
    inputs = stats.get("inputs") or {}
    if inputs.get("features") or inputs.get("matches"):
        raise SekdError(f"{out}: was built from given files (--features/--matches), which --extend cannot add "
                        "photos to; rebuild it from the photos")
    return stats


def _extend(image_dir: Path, out: Path, options: ExtendOptions, settings: Any, weights: str | None) -> Path:
    stats = _read_stats(out)
    check_given(options.given, stats.get("config", {}), out)
    config = _recorded(stats["config"], weights)
    database = out / "database.db"
    known = database_names(database)
    on_disk = list_images(image_dir)
    missing = sorted(known - set(on_disk))
    if missing:
        raise SekdError(f"{image_dir}: lacks {len(missing)} photo(s) of {out}'s model, e.g. {missing[0]}; give "
                        "the folder the model was built from, with the new photos added")
    new = [name for name in on_disk if name not in known]
    if not new:
        logger.warning("%s: nothing to add: every photo of %s is already in the model's database", out, image_dir)
        return out / MAIN_MODEL
    timer, stage = StageTimer(), out / STAGE
    stage.mkdir()
    record = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "images_dir": str(image_dir),
              "refine_existing": options.refine, "versions": package_versions(),
              "config": stats["config"]}  # the settings used: the model's own
    staged = _stage(image_dir, out, stage, config, options, settings, sorted(known), new, timer, record)
    record["timings_s"] = {**timer.seconds, "total": round(sum(timer.seconds.values()), 3)}
    stats.setdefault("extensions", []).append(record)
    _stage_stats(stats, staged, stage)
    _write_journal(stage, out)
    commit(out)
    logger.info("%s: %d of %d new photo(s) registered in %.1f s (%s); the summary below is the model's, the "
                "extension's record is stats.json extensions[-1]", out, len(record["registered"]), len(record["added"]),
                record["timings_s"]["total"], ", ".join(f"{k} {v:.1f}s" for k, v in record["timings_s"].items()
                                                         if k != "total"))
    return out / MAIN_MODEL


def _stage(image_dir: Path, out: Path, stage: Path, config: _Recorded, options: ExtendOptions, settings: Any,
           known: list[str], new: list[str], timer: StageTimer, record: dict) -> dict:
    """Every staged file of the extension in ``stage``; returns what the stats need."""
    features, matches = out / config.file_names[0], out / config.file_names[1]
    with execution.using(settings.executor, settings.ray_options) as executor:
        with timer("extract"):
            extract_features(image_dir, features, config.features, num_threads=settings.num_threads,
                             progress=settings.progress, executor=executor,
                             masks=Path(config.masks) if config.masks else None)
        extracted = set(ff.list_keys(features))
        added = [name for name in new if name in extracted]  # unreadable photos are skipped with a warning
        record["added"] = added
        if not added:
            raise SekdError(f"{image_dir}: none of the {len(new)} new photo(s) could be read (e.g. {new[0]}); "
                            "nothing was added")
        _check_features(features, out / "database.db", known)
        with timer("pairs"):
            pairs = new_pairs(features, known, added, config.pairs, settings.progress)
            pairs_file = write_pairs(pairs, stage / "pairs-new.txt")
        with timer("match"):
            match_features(features, pairs_file, matches, config.matching, num_threads=settings.num_threads,
                           progress=settings.progress, executor=executor)
    record["pairs"] = len(pairs)
    keypoints = features
    if config.refine.enabled:
        with timer("refine"):
            keypoints = refine_keypoints(features, matches, pairs, image_dir, stage / "refined.h5", config.refine,
                                         progress=settings.progress, anchor=refined_path(out, config.file_names[0]))
        record["refine"] = refine_summary(keypoints)
    database = stage / "database.db"
    with colmap_log(out / "colmap-extend.log") as log:
        with timer("database"):
            copy_database(out / "database.db", database)
            add_to_database(database, image_dir, keypoints, matches, pairs, added, config.camera)
        with timer("verification"):
            verify_new_pairs(database, pairs, two_view_options(config.verification, config.seed),
                             settings.num_threads or -1)
        mapper = extension_options(config, options.refine, database, known)
        match_stats = match_statistics(database, int(mapper.min_num_matches))
        with timer("mapping"):
            filtered: list = []
            models = run_mapper(database, image_dir, mapper, settings.progress, log_prefix=log_prefix(log),
                                input_model=out / MAIN_MODEL, final_filter=config.final_filter, records=filtered)
            record["final_filter"] = filtered[0] if filtered else None
    settle_database(database)
    model = _checked_model(models, out, options.refine)
    (stage / "model.tmp").mkdir()
    model.write_binary(str(stage / "model.tmp"))
    _fsync_tree(stage / "model.tmp")
    os.rename(stage / "model.tmp", stage / MAIN_MODEL)
    names = set(registered_names(model))
    record["registered"] = [n for n in added if n in names]
    record["unregistered"] = unregistered_report([n for n in added if n not in names], match_stats)
    record["mapper"] = {"type": "incremental, continuing from model/", "fix_existing_frames":
                        bool(mapper.fix_existing_frames), "constant_cameras": sorted(mapper.constant_cameras),
                        "ba_refine_principal_point": bool(mapper.ba_refine_principal_point)}
    return {"model": model, "match_stats": match_stats, "pairs": pairs,
            "refined": config.refine.enabled, "features_name": config.file_names[0]}


def verify_new_pairs(database: Path, pairs: list, options, num_threads: int) -> None:
    """Geometric verification of ``pairs`` only, their results written into ``database``.

    COLMAP's verification of a database goes over every matched pair again, those it verified
    before included: on the generated 250-photo walk that is ~3,200 pairs (many of them retrieval
    pairs that do not verify, which run every RANSAC trial) for 680 new ones. So the new pairs are
    verified in a copy that holds only their matches, and the two-view geometries copied back.
    """
    pycolmap = require_pycolmap()
    with contextlib.closing(sqlite3.connect(database)) as db:
        ids = dict(db.execute("SELECT name, image_id FROM images"))
    wanted = [(pycolmap.image_pair_to_pair_id(ids[a], ids[b]),) for a, b in pairs if a in ids and b in ids]
    scratch = database.with_name("verify.db")
    copy_database(database, scratch)
    with contextlib.closing(sqlite3.connect(scratch)) as db:
        db.execute("CREATE TEMP TABLE wanted (pair_id INTEGER PRIMARY KEY)")
        db.executemany("INSERT OR IGNORE INTO wanted VALUES (?)", wanted)
        db.execute("DELETE FROM matches WHERE pair_id NOT IN (SELECT pair_id FROM wanted)")
        db.execute("DELETE FROM two_view_geometries")
        db.commit()
    verify_matches(scratch, options, num_threads)
    with contextlib.closing(sqlite3.connect(database)) as db:
        db.execute("ATTACH DATABASE ? AS fresh", (str(scratch),))
        db.execute("INSERT OR REPLACE INTO two_view_geometries SELECT * FROM fresh.two_view_geometries")
        db.commit()
        db.execute("DETACH DATABASE fresh")
    for suffix in ("", "-wal", "-shm"):
        scratch.with_name(scratch.name + suffix).unlink(missing_ok=True)


def database_names(path: Path) -> set[str]:
    """The image names of a COLMAP database, read without writing to it (COLMAP's own open may)."""
    if not path.is_file():
        raise SekdError(f"{path}: missing, so the model cannot be extended; rebuild it without --extend")
    with contextlib.closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as db:
        return {name for (name,) in db.execute("SELECT name FROM images")}


def copy_database(source: Path, target: Path) -> None:
    """A copy of the SQLite database ``source`` (with whatever its write-ahead log still holds) at ``target``."""
    with contextlib.closing(sqlite3.connect(f"file:{source}?mode=ro", uri=True)) as src, \
            contextlib.closing(sqlite3.connect(target)) as dst:
        src.backup(dst)


def settle_database(path: Path) -> None:
    """Fold the write-ahead log COLMAP leaves into the database file itself, so the file alone can be moved."""
    with contextlib.closing(sqlite3.connect(path)) as db:
        db.execute("PRAGMA journal_mode=DELETE")
    for suffix in ("-wal", "-shm"):
        if path.with_name(path.name + suffix).exists():
            raise SekdError(f"{path}: still has its {suffix} file; another process has it open")


def _check_features(features: Path, database: Path, known: list[str]) -> None:
    """SekdError unless the feature file still has, for each photo of the database, its keypoint count there
    (a re-extraction would renumber the keypoints the model's observations refer to)."""
    with contextlib.closing(sqlite3.connect(f"file:{database}?mode=ro", uri=True)) as db:
        counts = dict(db.execute("SELECT images.name, keypoints.rows FROM images "
                                 "JOIN keypoints ON images.image_id = keypoints.image_id"))
    with h5py.File(features, "r") as f:
        stored = {name: f[name]["keypoints"].shape[0] for name in known if name in f}
    for name in known:
        n = stored.get(name, -1)
        if n != counts.get(name, 0):
            raise SekdError(f"{features}: {name} has {n} keypoints, the model's database {counts[name]}: the features "
                            "were extracted again since the model was built; rebuild the model instead")


def new_pairs(features: Path, known: list[str], new: list[str], config: PairsConfig, progress: bool = True) -> list:
    """The pairs of the ``new`` photos with OUT's pairing ``config``, over ``known`` + ``new`` photos.

    ``auto`` decides on the whole collection as a rebuild would: exhaustive up to 2K + 1 photos (every
    pair with a new photo), retrieval above: each new photo with its K most similar photos, earlier
    or new (the earlier photos' own neighbour lists are not revisited: a rebuild would add the pairs
    of earlier photos that list a new one among their K, which on the generated 250-photo walk
    doubles the pairs to match, 2070 instead of 1000). Other modes: the pairs a rebuild would
    choose that have a new photo.
    """
    names, bad = split_writable(sorted(set(known) | set(new)))
    warn_skipped(bad)
    fresh = [n for n in new if n not in bad]
    mode, k = resolve_mode(config, len(names))
    if mode == "retrieval":
        global_file = compute_global_descriptors(features, config.retrieval, progress=progress)
        neighbours = nearest_neighbors(global_file, names, k)
        return unique_pairs((a, b) for a in fresh for b in neighbours[a])
    chosen = set(fresh)
    return unique_pairs(p for p in generate_pairs(names, config, features, progress) if p[0] in chosen or p[1] in chosen)


def extension_options(config: _Recorded, refine: bool, database: Path, known: list[str]):
    """The incremental mapper's options of the extension: the record's mapper options that it has, existing
    frames and cameras fixed (unless ``refine``), one model (new photos register into OUT's or not at all)."""
    options = default_options("incremental", config.seed)
    for assignment in config.mapper:  # a hierarchical record's incremental_options.X are the incremental X
        own = assignment.removeprefix("incremental_options.")
        try:
            options = set_options(options, [own], "--mapper")
        except SekdError:
            logger.info("--extend: mapper option %s is not the incremental mapper's; not used", assignment)
    options.ba_refine_principal_point = config.camera.principal_point == "refine"
    options.multiple_models = False
    if not refine:
        options.fix_existing_frames = True
        with open_database(database) as db:
            cameras = {image.camera_id for image in db.read_all_images() if image.name in set(known)}
        options.constant_cameras = cameras
    return options


def _checked_model(models: list, out: Path, refine: bool):
    """The extended model; SekdError (nothing committed) if it lost an earlier photo or moved one while fixed."""
    pycolmap = require_pycolmap()
    before = pycolmap.Reconstruction(str(out / MAIN_MODEL))
    if not models:
        raise SekdError(f"{out}: the mapper returned no model from the existing one; nothing was changed")
    model = models[0]
    lost = [before.image(i).name for i in before.reg_image_ids() if not model.exists_image(i)
            or not model.image(i).has_pose]
    if lost:
        raise SekdError(f"{out}: the extended model lost {len(lost)} earlier photo(s) (e.g. {lost[0]}); "
                        "nothing was changed")
    if refine:
        keep_frame(before, model)
    else:
        restore_fixed(before, model, out)
    return model


def keep_frame(before, model) -> None:
    """Move ``model`` back into ``before``'s coordinate frame (``--extend-refine``).

    COLMAP renormalises a model whose cameras are free: it shifts and scales it (2.5 units on
    fountain-P11), never rotates it. The scale and shift that map the earlier cameras' centres back
    onto their former positions (least squares) undo that, so what remains is the refinement itself.
    """
    pycolmap = require_pycolmap()
    ids = list(before.reg_image_ids())
    old = np.array([before.image(i).projection_center() for i in ids])
    new = np.array([model.image(i).projection_center() for i in ids])
    old_c, new_c = old - old.mean(0), new - new.mean(0)
    if len(ids) < 2 or not (new_c ** 2).sum() > 0:
        return
    scale = float((old_c * new_c).sum() / (new_c ** 2).sum())
    shift = old.mean(0) - scale * new.mean(0)
    model.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(), shift))


#: How far (in the pose's own units: quaternion components, model units) a fixed frame may come back from
#: the mapper. Held constant, they still come back a few 1e-16 off: COLMAP renormalises every rotation
#: and rounds the poses through its bundle adjuster's parameter blocks; anything larger is a real move.
FIXED_TOLERANCE = 1e-9


def restore_fixed(before, model, out: Path) -> None:
    """Put the earlier frames' poses and cameras' parameters back bitwise into ``model`` (they were fixed, so only
    rounding separates them: see FIXED_TOLERANCE); SekdError if one really moved."""
    moved = []
    for frame_id in before.reg_frame_ids():
        old, new = before.frame(frame_id).rig_from_world, model.frame(frame_id).rig_from_world
        gap = max(np.abs(old.rotation.quat - new.rotation.quat).max(), np.abs(old.translation - new.translation).max())
        if gap > FIXED_TOLERANCE * max(1.0, np.abs(old.translation).max()):
            moved.append(f"frame {frame_id} by {gap:.2g}")
        model.frame(frame_id).rig_from_world = old
    for camera_id in before.cameras:
        if not np.allclose(before.camera(camera_id).params, model.camera(camera_id).params, rtol=FIXED_TOLERANCE):
            moved.append(f"camera {camera_id}")
        model.camera(camera_id).params = before.camera(camera_id).params
    bad = [before.image(i).name for i in before.reg_image_ids() if not same_pose(before.image(i), model.image(i))]
    if moved or bad:
        raise SekdError(f"{out}: the mapper moved {', '.join((moved + bad)[:3])} although they were fixed; "
                        "nothing was changed")


def same_pose(a, b) -> bool:
    """Whether two images' world-to-camera poses are bitwise equal."""
    return np.array_equal(pose_matrix(a), pose_matrix(b)) and a.name == b.name


def pose_matrix(image) -> np.ndarray:
    """An image's cam_from_world as a 3 x 4 float64 matrix (pycolmap 4: a method; 3.x: a property)."""
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    return np.asarray(pose.matrix(), dtype=np.float64)


def _stage_stats(stats: dict, staged: dict, stage: Path) -> None:
    """stats.json, pairs.txt of the extended OUT, staged in ``stage``."""
    model, match_stats = staged["model"], staged["match_stats"]
    names = set(registered_names(model))
    stats["model"], stats["output"] = model_stats(model), str(stage.parent / MAIN_MODEL)
    stats["matches"] = summarize_matches(match_stats)
    if stats.get("models"):
        stats["models"][0] = {**stats["models"][0], **model_stats(model), "images": sorted(names)}
    in_a_model = names | {n for m in stats.get("models", [])[1:] for n in m.get("images", [])}
    stats["unregistered"] = unregistered_report(sorted(set(match_stats["images"]) - in_a_model), match_stats)
    write_json(stats, stage / "stats.json")


def _write_journal(stage: Path, out: Path) -> None:
    """The commit's plan, written once every staged file is complete: after it, the extension only rolls forward."""
    pairs = read_pairs(out / "pairs.txt") if (out / "pairs.txt").is_file() else []
    write_pairs(unique_pairs([*pairs, *read_pairs(stage / "pairs-new.txt")]), stage / "pairs.txt")
    stats = json.loads((stage / "stats.json").read_text())
    refined = (stage / "refined.h5").is_file()
    moves = [["database.db", "database.db"], ["pairs.txt", "pairs.txt"], ["stats.json", "stats.json"]]
    if refined:
        moves.append(["refined.h5", refined_path(out, stats["config"]["file_names"][0]).name])
    journal = {"model_inode": (stage / MAIN_MODEL).stat().st_ino, "moves": moves}
    for name in ("database.db", "refined.h5", "pairs.txt", "stats.json"):
        if (stage / name).is_file():
            _fsync(stage / name)
    write_json(journal, stage / JOURNAL)
    _fsync(stage / JOURNAL)
    _fsync(stage)


def commit(out: Path) -> None:
    """Carry out (or finish) the journal's commit; every step can be repeated after a kill."""
    stage = out / STAGE
    journal = json.loads((stage / JOURNAL).read_text())
    model, staged = out / MAIN_MODEL, stage / MAIN_MODEL
    new_in_place = model.is_dir() and model.stat().st_ino == journal["model_inode"]
    if not new_in_place and not (model.is_dir() and staged.is_dir() and _exchange(staged, model)):
        _swap_by_renames(model, staged, out / BACKUP)
    if staged.is_dir():  # the earlier model, after the exchange
        shutil.rmtree(out / BACKUP, ignore_errors=True)
        os.rename(staged, out / BACKUP)
    for source, target in journal["moves"]:
        if (stage / source).is_file():
            _drop_sqlite_sidecars(out / target)  # the earlier file's (read-only opens leave them)
            os.replace(stage / source, out / target)
    _drop_sqlite_sidecars(out / "database.db")
    _fsync(out)
    shutil.rmtree(out / BACKUP, ignore_errors=True)  # the new model is complete: the backup can go
    (stage / JOURNAL).unlink()
    shutil.rmtree(stage, ignore_errors=True)


def _drop_sqlite_sidecars(path: Path) -> None:
    """Remove ``path``'s SQLite -wal/-shm files: once the staged database (settled, no log of its own) replaces
    ``path`` they belong to the earlier file, which nothing uses any more, and must not be applied to the new one."""
    if path.name.endswith(".db"):
        for suffix in ("-wal", "-shm"):
            path.with_name(path.name + suffix).unlink(missing_ok=True)


def _swap_by_renames(model: Path, staged: Path, backup: Path) -> None:
    """Where directories cannot be exchanged atomically: model -> backup, staged -> model (a kill in between
    leaves the earlier model in ``backup`` and the new one staged; the next run finishes the swap)."""
    if model.is_dir():
        shutil.rmtree(backup, ignore_errors=True)
        os.rename(model, backup)
    os.rename(staged, model)


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap two directories in one step (Linux renameat2 RENAME_EXCHANGE); False where unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    logger.info("renameat2 exchange unavailable (errno %d): two renames instead", ctypes.get_errno())
    return False


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_tree(folder: Path) -> None:
    for path in folder.iterdir():
        _fsync(path)
    _fsync(folder)
