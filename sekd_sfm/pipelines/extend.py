"""``sekd reconstruct PHOTOS -o OUT --extend``: add the photos OUT's model lacks, without moving what it has.

The photos of PHOTOS that OUT's database does not hold yet are extracted, paired, matched,
refined, imported and registered into OUT's model with the settings OUT was built with (the
``config`` of its record, ``record.STATS``). ``EXTEND`` lists the steps, each
``step(run, state) -> state`` over an ``Extension`` (``run.py``):

* extract: the new photos' features, added to OUT's feature file;
* pairs: the pairs OUT's pairing mode would choose among all its photos plus the new ones
  (exhaustive while that is small, retrieval with the same vocabulary above), those with
  at least one new photo; match: into OUT's match file (only the missing pairs are matched);
* refine: the new photos' keypoints are refined with the earlier photos' refined keypoints
  held fixed (``refine_keypoints(anchor=...)``), so the earlier ones stay what the model has;
* database: the new photos are added to a copy of OUT's database (image and camera ids of
  the earlier photos unchanged; a new photo of an existing camera joins it); verification:
  only the new pairs are verified;
* mapping: pycolmap's incremental mapper continues from OUT's model with the existing frames
  and cameras fixed in every bundle adjustment (``--extend-refine`` lets everything move),
  and triangulates new points. Earlier poses are then checked to be bitwise unchanged;
* record, commit: OUT's record gets the extension's entry (``extensions[-1]``), and the staged
  files replace OUT's.

Crash safety (``extend_commit.py``): everything is staged in ``OUT/extend/`` and committed
through a journal, so kill -9 at any moment, then the same command again, gives the result
of an uninterrupted run, and ``model/`` is always a complete model.
"""
from __future__ import annotations

import contextlib
import logging
import sqlite3
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from ..errors import SekdError
from ..files import features as ff
from ..files.images import list_images
from ..runtime import package_versions
from ..stages.chance import check_chance
from ..stages.colmap import (
    clean_logs,
    colmap_log,
    log_prefix,
    open_database,
    read_only_database,
    require_pycolmap,
    set_options,
)
from ..stages.database import add_to_database, two_view_options, verify_matches
from ..stages.extract import extract_features
from ..stages.mapping import (
    clean_scratch,
    default_options,
    min_model_size,
    model_stats,
    registered_names,
    run_mapper,
)
from ..stages.match import match_features
from ..stages.modelcheck import check_model as check_folded
from ..stages.pairs import (
    PairsConfig,
    generate_pairs,
    resolve_mode,
    split_writable,
    unique_pairs,
    warn_skipped,
    write_pairs,
)
from ..stages.refine import refine_keypoints, refine_summary
from ..stages.retrieval import compute_global_descriptors, nearest_neighbors
from . import record
from .config import ReconstructConfig
from .extend_commit import (
    NEW_PAIRS,
    REFINED,
    STAGE,
    commit,
    recover,
    stage_model,
    write_journal,
)
from .report import (
    folded_warning,
    match_statistics,
    summarize_matches,
    unregistered_report,
)
from .run import Run, RunOptions, Step, run_steps

if TYPE_CHECKING:
    import pycolmap

logger = logging.getLogger("sekd")

__all__ = ["EXTEND", "UNCHECKED", "ExtendOptions", "Extension", "check_given", "commit", "copy_database",
           "database_names", "extend_model", "extension_options", "flatten", "keep_frame", "new_pairs", "pose_matrix",
           "restore_fixed", "same_pose", "settle_database", "verify_new_pairs"]

#: COLMAP's log of the extension in OUT (the build's own, ``record.COLMAP_LOG``, is left as it was).
LOG = "colmap-extend.log"
#: Config fields that never conflict: the network's path is not recorded (the feature file checks the network).
UNCHECKED = ("features.weights",)


@dataclass(frozen=True)
class ExtendOptions:
    """``--extend`` settings. ``refine``: let the earlier cameras' poses and intrinsics move (``--extend-refine``).
    ``given``: configuration fields (dotted, as in the record's ``config``) the user set explicitly, with
    their values: each must agree with OUT's record."""

    refine: bool = False
    given: dict = field(default_factory=dict)


@dataclass
class Extension:
    """What the steps of ``EXTEND`` have made so far, and the records they fill.

    ``earlier``: OUT's record, which becomes the extended OUT's (``entry``, the extension's own, appended to its
    ``extensions``); ``config``: its settings, typed; ``known``: the photos of OUT's database; ``new``: those below
    PHOTOS it lacks; ``added``: the new ones extracted (unreadable photos are skipped); ``stage``: where every file
    of the extension is made before the commit; ``keypoints``: what the database gets (refined, or the features);
    ``log``: COLMAP's log, open from the database step to the model check (``log_context``).
    """

    image_dir: Path
    options: ExtendOptions
    earlier: record.Record
    config: ReconstructConfig
    known: list[str]
    new: list[str]
    stage: Path
    features: Path
    matches: Path
    entry: dict = field(default_factory=dict)
    added: list[str] = field(default_factory=list)
    pairs: list = field(default_factory=list)
    pairs_file: Path | None = None
    keypoints: Path | None = None
    database: Path | None = None
    log: Path | None = None
    log_context: ExitStack | None = None
    mapper: pycolmap.IncrementalPipelineOptions | None = None
    match_stats: dict = field(default_factory=dict)
    models: list[pycolmap.Reconstruction] = field(default_factory=list)
    model: pycolmap.Reconstruction | None = None


def flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (tuples as lists, as JSON has them)."""
    if isinstance(data, dict):
        out: dict[str, Any] = {}
        for key, value in data.items():
            out.update(flatten(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: list(data) if isinstance(data, tuple) else data}


def check_given(given: dict, config: dict, out: Path) -> None:
    """SekdError when an explicitly given setting differs from the one OUT's model was built with (``config``: the
    record's, as recorded)."""
    recorded = flatten(config)
    wrong = {k: v for k, v in flatten(given).items() if k not in UNCHECKED and k in recorded and recorded[k] != v}
    if wrong:
        listed = ", ".join(f"{k} = {v!r} (built with {recorded[k]!r})" for k, v in sorted(wrong.items()))
        raise SekdError(f"{record.record_path(out)}: --extend adds photos with the settings the model was built with, "
                        f"but these options differ: {listed}; leave them out")


def extend_model(image_dir: str | Path, output_dir: str | Path, options: ExtendOptions, run_options: RunOptions,
                 weights: str | None = None) -> Path:
    """Add the photos below ``image_dir`` that ``output_dir``'s model lacks; returns the model's folder.

    ``run_options``: how the run runs (threads, progress, executor); ``weights``: the feature network's file when
    not the packaged one (records leave it out). Photos already in OUT's database (registered or not) are not new:
    with none new, nothing is done ("nothing to add"). SekdError when OUT holds no finished model or its settings
    conflict.
    """
    require_pycolmap()
    image_dir, out = Path(image_dir), Path(output_dir)
    if not image_dir.is_dir():
        raise SekdError(f"{image_dir}: not a folder of images; give the folder holding the photos")
    if not out.is_dir():
        raise SekdError(f"{out}: no such folder, so no model to extend; build one first: "
                        f"sekd reconstruct {image_dir} -o {out}")
    with Run(out, run_options, lock="reconstruction folder") as run:
        clean_scratch(out)  # left by a killed run: nobody else can be using them while we hold the lock
        clean_logs(out / LOG)
        recover(out)  # an interrupted commit finished, an unfinished stage dropped
        state = _extension(image_dir, out, options, weights)
        if state is not None:
            run_steps(run, EXTEND, state)
        return out / record.MODEL


def _finished_record(out: Path) -> record.Record:
    """OUT's record; SekdError unless it is that of a successful ``sekd reconstruct`` of photos."""
    try:
        earlier = record.Record.from_record(out, needs="")
    except SekdError:  # no readable record: no model to extend, said as for an unfinished one
        earlier = None
    if earlier is None or not earlier.finished:
        raise SekdError(f"{out}: holds no finished model (model/ and {record.STATS} of a successful "
                        "`sekd reconstruct`) to extend; run sekd reconstruct without --extend first")
    if earlier.inputs.get("features") or earlier.inputs.get("matches"):
        raise SekdError(f"{out}: was built from given files (--features/--matches), which --extend cannot add "
                        "photos to; rebuild it from the photos")
    if earlier.config_data.get("rig") or (out / record.VIEWS).is_dir():
        raise SekdError(f"{out}: was built from a camera rig or 360-degree panoramas, which --extend cannot add to; "
                        "run sekd reconstruct on all the photos into a new folder")
    return earlier


def _extension(image_dir: Path, out: Path, options: ExtendOptions, weights: str | None) -> Extension | None:
    """The extension to make, its settings checked against OUT's record; None (a warning) when no photo is new."""
    earlier = _finished_record(out)
    check_given(options.given, earlier.config_data, out)
    config = earlier.config(weights)
    known = database_names(out / record.DATABASE)
    on_disk = list_images(image_dir)
    missing = sorted(known - set(on_disk))
    if missing:
        raise SekdError(f"{image_dir}: lacks {len(missing)} photo(s) of {out}'s model, e.g. {missing[0]}; give "
                        "the folder the model was built from, with the new photos added")
    new = [name for name in on_disk if name not in known]
    if not new:
        logger.warning("%s: nothing to add: every photo of %s is already in the model's database", out, image_dir)
        return None
    return Extension(image_dir, options, earlier, config, sorted(known), new, out / STAGE,
                     features=out / config.file_names[0], matches=out / config.file_names[1])


# ----------------------------------------------------------------------------- the steps, in order

def open_stage(run: Run, s: Extension) -> Extension:
    """The staging folder, and the extension's entry: when, from where, with which settings (the model's own)."""
    s.stage.mkdir()
    s.entry = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "images_dir": str(s.image_dir),
               "refine_existing": s.options.refine, "versions": package_versions(),
               "config": s.earlier.config_data}
    return s


def extract(run: Run, s: Extension) -> Extension:
    """The new photos' features, added to OUT's feature file."""
    extract_features(s.image_dir, s.features, s.config.features, num_threads=run.num_threads, progress=run.progress,
                     executor=run.executor, masks=Path(s.config.masks) if s.config.masks else None)
    return s


def check_added(run: Run, s: Extension) -> Extension:
    """The new photos extraction could read; SekdError when none, or when the earlier photos' keypoints changed."""
    extracted = set(ff.list_keys(s.features))
    s.added = [name for name in s.new if name in extracted]  # unreadable photos are skipped with a warning
    s.entry["added"] = s.added
    if not s.added:
        raise SekdError(f"{s.image_dir}: none of the {len(s.new)} new photo(s) could be read (e.g. {s.new[0]}); "
                        "nothing was added")
    _check_features(s.features, run.out / record.DATABASE, s.known)
    return s


def pairs(run: Run, s: Extension) -> Extension:
    """The new photos' pairs (``new_pairs``), staged as ``NEW_PAIRS``."""
    s.pairs = new_pairs(s.features, s.known, s.added, s.config.pairs, run.progress)
    s.pairs_file = write_pairs(s.pairs, s.stage / NEW_PAIRS)
    s.entry["pairs"] = len(s.pairs)
    return s


def match(run: Run, s: Extension) -> Extension:
    """The new pairs matched into OUT's match file."""
    match_features(s.features, s.pairs_file, s.matches, s.config.matching, num_threads=run.num_threads,
                   progress=run.progress, executor=run.executor)
    return s


def refine(run: Run, s: Extension) -> Extension:
    """The refined keypoints, staged: the earlier photos' as OUT's refined file has them, the new ones refined."""
    s.keypoints = refine_keypoints(s.features, s.matches, s.pairs, s.image_dir, s.stage / REFINED, s.config.refine,
                                   progress=run.progress, anchor=s.earlier.refined, executor=run.executor)
    s.entry["refine"] = refine_summary(s.keypoints)
    return s


def database(run: Run, s: Extension) -> Extension:
    """A staged copy of OUT's database with the new photos and their pairs' matches; COLMAP's log goes to ``LOG``
    from here to the model check."""
    s.log_context = run.hold(ExitStack())  # closed by the model check, or by the run when a step fails before
    s.log = s.log_context.enter_context(colmap_log(run.out / LOG))
    s.database = s.stage / record.DATABASE
    s.keypoints = s.keypoints or s.features
    copy_database(run.out / record.DATABASE, s.database)
    add_to_database(s.database, s.image_dir, s.keypoints, s.matches, s.pairs, s.added, s.config.camera)
    return s


def verification(run: Run, s: Extension) -> Extension:
    """Geometric verification of the new pairs only (``verify_new_pairs``)."""
    verify_new_pairs(s.database, s.pairs, two_view_options(s.config.verification, s.config.seed),
                     run.num_threads or -1)
    return s


def chance(run: Run, s: Extension) -> Extension:
    """The verified pairs no better than chance dropped (``stages.chance``), as the run that made the model did:
    its decisions on the pairs already there repeat (seeded per pair), so only new pairs can be dropped."""
    floor = two_view_options(s.config.verification, s.config.seed).min_num_inliers  # what verification accepts
    s.entry["chance"] = check_chance(s.database, floor, s.config.chance, s.config.seed, run.executor, run.progress)
    return s


def match_report(run: Run, s: Extension) -> Extension:
    """The mapper's options (``extension_options``) and the verified matches' statistics."""
    s.mapper = extension_options(s.config, s.options.refine, s.database, s.known)
    s.match_stats = match_statistics(s.database, int(s.mapper.min_num_matches))
    return s


def mapping(run: Run, s: Extension) -> Extension:
    """The incremental mapper, continuing from OUT's model (filtered after mapping when the model was)."""
    filtered: list = []
    s.models = run_mapper(s.database, s.image_dir, s.mapper, run.progress, log_prefix=log_prefix(s.log),
                          input_model=run.out / record.MODEL, final_filter=s.config.final_filter, records=filtered)
    s.entry["final_filter"] = filtered[0] if filtered else None
    return s


def check_model(run: Run, s: Extension) -> Extension:
    """The extended model checked (``_checked_model``) and staged with the database; which new photos registered."""
    s.log_context.close()  # COLMAP's log is complete: the database can settle
    settle_database(s.database)
    s.model = _checked_model(s.models, run.out, s.options.refine)
    stage_model(s.model, s.stage)
    names = set(registered_names(s.model))
    s.entry["registered"] = [n for n in s.added if n in names]
    s.entry["unregistered"] = unregistered_report([n for n in s.added if n not in names], s.match_stats,
                                                  dict.fromkeys(names, 0), min_model_size(s.mapper))
    if s.config.model_check.enabled:  # a new photo placed on a look-alike can fold the model too
        s.entry["model_check"] = {"path": str(run.out / record.MODEL),
                                  **check_folded(s.model, s.database, s.config.model_check)}
        if s.entry["model_check"]["suspect"]:
            logger.warning("warning: %s", folded_warning(s.entry["model_check"]))
    s.entry["mapper"] = {"type": "incremental, continuing from model/", "fix_existing_frames":
                         bool(s.mapper.fix_existing_frames), "constant_cameras": sorted(s.mapper.constant_cameras),
                         "ba_refine_principal_point": bool(s.mapper.ba_refine_principal_point)}
    return s


def stage_record(run: Run, s: Extension) -> Extension:
    """OUT's record of the extended model, staged: the extension's entry (with the timed steps' seconds) appended,
    the model's counts, matches and unregistered photos updated."""
    s.entry["timings_s"], s.entry["stages"] = run.timings(), run.stage_table()
    stats = s.earlier.data
    stats.setdefault("extensions", []).append(s.entry)
    names = set(registered_names(s.model))
    stats["model"], stats["output"] = model_stats(s.model), str(run.out / record.MODEL)
    stats["matches"] = summarize_matches(s.match_stats)
    if stats.get("models"):
        stats["models"][0] = {**stats["models"][0], **model_stats(s.model), "images": sorted(names)}
    where = {**{n: k for k, m in enumerate(stats.get("models", [])) for n in m.get("images", [])}, **dict.fromkeys(names, 0)}
    stats["unregistered"] = unregistered_report(sorted(set(s.match_stats["images"]) - set(where)), s.match_stats, where,
                                                min_model_size(s.mapper))
    record.write_record(stats, s.stage)
    return s


def commit_stage(run: Run, s: Extension) -> Extension:
    """The staged files made OUT's (``extend_commit``: journal, then commit)."""
    write_journal(s.stage, run.out, s.config.file_names[0])
    commit(run.out)
    timings = s.entry["timings_s"]
    logger.info("%s: %d of %d new photo(s) registered in %.1f s (%s); the summary below is the model's, the "
                "extension's record is %s extensions[-1]", run.out, len(s.entry["registered"]), len(s.added),
                timings["total"], ", ".join(f"{k} {v:.1f}s" for k, v in timings.items() if k != "total"), record.STATS)
    return s


#: ``sekd reconstruct --extend``, step by step (untimed steps are checks and bookkeeping, not stages of the entry's
#: timings).
EXTEND: tuple[Step, ...] = (
    Step("stage", open_stage, timed=False),
    Step("extract", extract),
    Step("new photos", check_added, timed=False),
    Step("pairs", pairs),
    Step("match", match),
    Step("refine", refine, when=lambda s: s.config.refine.enabled),
    Step("database", database),
    Step("verification", verification),
    Step("chance check", chance, when=lambda s: s.config.chance.enabled),
    Step("match report", match_report, timed=False),
    Step("mapping", mapping),
    Step("model check", check_model, timed=False),
    Step("record", stage_record, timed=False),
    Step("commit", commit_stage, timed=False),
)


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
    """The image names of a COLMAP database, read without writing to it (``colmap.read_only_database``)."""
    if not path.is_file():
        raise SekdError(f"{path}: missing, so the model cannot be extended; rebuild it without --extend")
    with read_only_database(path) as db:
        return {name for (name,) in db.execute("SELECT name FROM images")}


def copy_database(source: Path, target: Path) -> None:
    """A copy of the SQLite database ``source`` (with whatever its write-ahead log still holds) at ``target``."""
    with read_only_database(source) as src, contextlib.closing(sqlite3.connect(target)) as dst:
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
    with read_only_database(database) as db:
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


def extension_options(config: ReconstructConfig, refine: bool, database: Path,
                      known: list[str]) -> pycolmap.IncrementalPipelineOptions:
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
    before = pycolmap.Reconstruction(str(out / record.MODEL))
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
