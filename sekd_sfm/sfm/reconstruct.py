"""The whole pipeline (``sekd reconstruct``): images -> features -> pairs -> matches -> database -> model -> report.

Files in the output folder::

    features.h5, pairs.txt, matches.h5   the earlier stages (reused when made with the same configuration;
                                         features/matches given by the caller are read in place instead)
    features-refined.h5                  the keypoints moved to where their matches agree (``refine``;
                                         hloc layout, keypoints only), what the database gets
    database.db                          COLMAP database (kept on failure, for inspection)
    colmap.log                           COLMAP's log
    model/, models/<k>/                  COLMAP binary models (the largest in model/, the others largest first)
    stats.json                           counts, accuracy figures, images in no model, timings, configuration
    .lock                                held for the run: a second run on the same folder is refused

The run holds the folder's lock from start to end, so whatever a killed run left behind
(the mapper's ``mapping-*`` scratch folders, ``colmap.log.*`` pieces) is removed at the start.
"""
from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from .. import execution
from ..errors import SekdError
from ..execution import RayOptions
from ..extract import changed_masks, extract_features
from ..features import FeatureConfig
from ..files import features as ff
from ..files import matches as mf
from ..files.images import list_images
from ..files.locking import exclusive_lock
from ..match import MatchConfig, match_features
from ..pairs import GpsNeighbors, PairsConfig, make_pairs, read_pairs, write_pairs
from ..runtime import package_versions
from .colmap import clean_logs, colmap_log, log_prefix, require_pycolmap
from .database import (
    CameraConfig,
    check_principal_point_mode,
    create_database,
    parse_camera_params,
    two_view_options,
    verify_matches,
)
from .extend import ExtendOptions, extend_model
from .georef import GpsConfig, georeference, photo_names, plan_gps, write_georef
from .mapping import (
    clean_scratch,
    mapper_options,
    min_num_matches,
    model_stats,
    registered_names,
    resolve_mapper_type,
    run_mapper,
    write_models,
)
from .principal_point import PrincipalPointPlan, plan_principal_point
from .refine import RefineConfig, refine_keypoints, refine_summary
from .report import (
    ReconstructionError,
    StageTimer,
    check_enough_matches,
    explain_models,
    explain_no_model,
    match_statistics,
    summarize_matches,
    unregistered_report,
    write_json,
)

logger = logging.getLogger("sekd")


#: Long side (px) images are reduced to for reconstruction, as hloc does: SEKD's cost grows with
#: the pixels, and a 24 MP photo at full size costs ~40 s of CPU to extract.
DEFAULT_RESIZE_MAX = 1600
#: The mapper used unless told otherwise: ``auto`` = incremental up to 250 photos, hierarchical
#: above (docs/reconstruction.md has the measurements).
DEFAULT_MAPPER = "auto"


@dataclass
class ReconstructConfig:
    """Every stage's settings; ``mapper`` / ``verification`` are ``key=value`` pycolmap option overrides.

    ``mapper_type`` is one of MAPPER_CHOICES; ``mapper`` options are those of its option class
    (for ``auto``: of the mapper it picks for the collection's size).
    """

    features: FeatureConfig = field(default_factory=lambda: FeatureConfig(resize_max=DEFAULT_RESIZE_MAX))
    pairs: PairsConfig = field(default_factory=PairsConfig)
    matching: MatchConfig = field(default_factory=MatchConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    mapper_type: str = DEFAULT_MAPPER
    mapper: list[str] = field(default_factory=list)
    verification: list[str] = field(default_factory=list)
    #: Keypoint refinement between matching and the database (``refine.py``): on the generated
    #: 250-photo block pose AUC@5 0.971 -> 0.980, reprojection error 0.39 -> 0.22 px.
    refine: RefineConfig = field(default_factory=RefineConfig)
    #: After mapping, drop each model's outlying observations (beyond max(0.5 px, 3 robust sigma)) and adjust it
    #: again (``mapper_worker.final_filter``): pose AUC@5 on the generated 250-photo block 0.972 -> 0.993.
    final_filter: bool = True
    seed: int = 0
    #: Names of the feature and match files made in the output folder (``--conf`` names them
    #: hloc-style, feats-<conf>.h5 and matches-<conf>_pairs.h5, so several presets' files coexist).
    file_names: tuple[str, str] = ("features.h5", "matches.h5")
    #: Folder of masks (``--masks``; photo NAME's is ``masks/NAME.png``, zero = ignore; docs/masks.md), or None.
    #: Recorded in stats.json as ``config.masks``, where later commands (``sekd export``) find it.
    masks: str | None = None
    #: EXIF GPS (``--gps``, georef.py): ``mode`` auto = GPS neighbour pairs + the model aligned to GPS in a
    #: local ENU frame in metres, when at least 3 photos carry GPS.
    gps: GpsConfig = field(default_factory=GpsConfig)


@dataclass(frozen=True)
class RunSettings:
    """How a reconstruction runs, as opposed to what it computes (ReconstructConfig, recorded in stats.json)."""

    #: Recompute features and matches instead of reusing the files an earlier run left in the output folder.
    overwrite: bool = False
    #: CPU threads of extraction, matching and geometric verification (None: every core the process may use).
    num_threads: int | None = None
    progress: bool = True
    #: Where extraction and matching run: ``local`` (this machine) or ``ray`` (the cluster of ``ray_options``).
    executor: str = "local"
    ray_options: RayOptions | None = None

    def keywords(self) -> dict[str, Any]:
        """These settings as keyword arguments of ``reconstruct``: ``reconstruct(..., **settings.keywords())``."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


def _config_dict(config: ReconstructConfig) -> dict:
    data = asdict(config)
    data["features"].pop("weights", None)  # a local path; the model's hash is in features.h5
    return data


def reconstruct(image_dir: str | Path, output_dir: str | Path, config: ReconstructConfig | None = None, *,
                overwrite: bool = False, num_threads: int | None = None, progress: bool = True,
                features: str | Path | None = None, matches: str | Path | None = None, executor: str = "local",
                ray_options: RayOptions | None = None, extend: ExtendOptions | None = None) -> Path:
    """Reconstruct the images below ``image_dir`` into ``output_dir``; returns the main model's folder.

    Runs the missing stages (extract, pairs, match) and reuses existing outputs made with
    the same configuration. ``features`` (a feature file of sekd or hloc) replaces extraction;
    ``matches`` (a match file, needs ``features``) replaces pairs and matching: its pairs are
    those of ``config.pairs.file`` when set, else all the pairs it holds. Both are read in
    place, never modified. When the images split into several models each is written
    (``model/`` the largest, ``models/1``, ...) and the split is logged as a warning.
    ``executor`` / ``ray_options``: where extraction and matching run (``sekd_sfm.execution``);
    the keyword arguments from ``overwrite`` on are the fields of RunSettings.
    Raises ReconstructionError, after writing stats.json and keeping the database, when no
    model comes out; SekdError when another process is using ``output_dir``.
    ``extend``: add the photos ``output_dir``'s model lacks to it instead, with its recorded settings (extend.py).
    """
    require_pycolmap()
    config = config or ReconstructConfig()
    settings = RunSettings(overwrite=overwrite, num_threads=num_threads, progress=progress, executor=executor,
                           ray_options=ray_options)
    image_dir, out = Path(image_dir), Path(output_dir)
    _check_inputs(image_dir, features, matches)
    if extend is not None:
        if features is not None or overwrite:
            raise SekdError("--extend adds photos to OUTPUT's own files: leave out --features, --matches, --overwrite")
        return extend_model(image_dir, out, extend, settings, weights=config.features.weights)
    out.mkdir(parents=True, exist_ok=True)
    with exclusive_lock(out, what="reconstruction folder"):
        clean_scratch(out)  # left by a killed run: nobody else can be using them while we hold the lock
        clean_logs(out / "colmap.log")
        return _locked(image_dir, out, config, settings, features, matches)


def _check_inputs(image_dir: Path, features: str | Path | None, matches: str | Path | None) -> None:
    if not image_dir.is_dir():
        raise SekdError(f"{image_dir}: not a folder of images; give the folder holding the photos")
    if matches is not None and features is None:
        raise SekdError(f"--matches {matches}: also give the feature file these matches index (--features)")
    for what, path in (("--features", features), ("--matches", matches)):
        if path is not None and not Path(path).is_file():
            raise SekdError(f"{what} {path}: no such file; give an existing HDF5 file or leave {what} out")


def _locked(image_dir: Path, out: Path, config: ReconstructConfig, settings: RunSettings,
            features: str | Path | None, matches: str | Path | None) -> Path:
    """The run, inside the folder's lock; stats.json records how it ended, success or a failure to explain."""
    timer, stats = StageTimer(), {"status": "running", "failure": None, "config": _config_dict(config),
                              "versions": package_versions(), "images_dir": str(image_dir),
                              "inputs": {"features": str(features) if features else None,
                                         "matches": str(matches) if matches else None}}
    try:
        model = _run(image_dir, out, config, settings, timer, stats, features, matches)
        stats["status"] = "ok"
        return model
    except ReconstructionError as exc:
        stats["status"], stats["failure"] = "failed", str(exc).splitlines()[0]
        stats["failure_details"] = str(exc)
        raise
    finally:
        stats["timings_s"] = {**timer.seconds, "total": round(sum(timer.seconds.values()), 3)}
        if stats["status"] != "running":
            write_json(stats, out / "stats.json")


def _run(image_dir: Path, out: Path, config: ReconstructConfig, settings: RunSettings, timer: StageTimer, stats: dict,
         features: str | Path | None, matches: str | Path | None) -> Path:
    # Options are checked first, so a typo fails in a second, not after extraction and matching.
    options, two_view = _checked_options(image_dir, config, features, stats)
    gps = plan_gps(image_dir, photo_names(image_dir, features), config.gps)
    features, pairs_file, matches = _inputs(image_dir, out, config, settings, timer, features, matches,
                                            gps.neighbors(config.gps))
    stats["matching"] = _matching_config(matches)
    pairs, keypoints = read_pairs(pairs_file), features
    if config.refine.enabled:
        with timer("refine"):
            keypoints = refine_keypoints(features, matches, pairs, image_dir, out / refined_name(config.file_names[0]),
                                         config.refine, progress=settings.progress)
        stats["refine"] = refine_summary(keypoints)
    database = out / "database.db"
    with colmap_log(out / "colmap.log") as log:
        with timer("database"):
            create_database(image_dir, keypoints, matches, pairs, database, config.camera)
        principal_point = _principal_point(config, database, options)
        stats["principal_point"], stats["principal_point_decision"] = principal_point.outcome, principal_point.details()
        with timer("verification"):
            verify_matches(database, two_view, settings.num_threads or -1)
        match_stats = match_statistics(database, min_num_matches(options))
        stats["matches"] = summarize_matches(match_stats)
        check_enough_matches(match_stats, database)
        with timer("mapping"):
            filtered: list = []
            models = run_mapper(database, image_dir, options, settings.progress, log_prefix=log_prefix(log),
                                final_filter=config.final_filter, records=filtered)
            stats["final_filter"] = filtered[0] if filtered else None
            models = principal_point.settle(models, out, options, settings.progress, log_prefix(log))
        stats["principal_point"], stats["principal_point_decision"] = principal_point.outcome, principal_point.details()
    georef = georeference(models, gps, config.gps, config.seed)  # models[0] moved into the ENU frame
    stats["georeference"] = {k: v for k, v in georef.items() if k != "per_image"}
    model = _finish(models, match_stats, options, out, stats, database)
    write_georef(out, georef)
    return model


def _checked_options(image_dir: Path, config: ReconstructConfig, features: str | Path | None,
                     stats: dict) -> tuple[Any, Any]:
    """pycolmap's mapper and two-view geometry options of ``config``, after checking every option of the run
    (the mapper type resolved for the collection's size, recorded in ``stats``)."""
    count = _num_photos(image_dir, features) if config.mapper_type == "auto" else 0  # only auto looks at the size
    mapper_type = resolve_mapper_type(config.mapper_type, count)
    stats["mapper_type"] = mapper_type
    options = mapper_options(config.mapper, config.seed, mapper_type)
    two_view = two_view_options(config.verification, config.seed)
    parse_camera_params(config.camera.model, config.camera.params)
    check_principal_point_mode(config.camera.principal_point)
    return options, two_view


def _principal_point(config: ReconstructConfig, database: Path, options) -> PrincipalPointPlan:
    """The principal-point plan of ``config.camera`` on the database's cameras (``principal_point.py``: ``auto``
    maps with it fixed, then ``settle`` keeps a refined model only where the photos determine it); sets the
    mapper's refinement in ``options``. An explicit ``--mapper ...refine_principal_point=...`` wins."""
    return plan_principal_point(config.camera, config.mapper, database, options)


def _num_photos(image_dir: Path, features: str | Path | None) -> int:
    """The photos to map: the feature file's images when given, else those below ``image_dir`` (0 if none:
    extraction then says so, after the options are checked)."""
    try:
        return len(ff.list_keys(Path(features))) if features is not None else len(list_images(image_dir))
    except (SekdError, OSError):
        return 0


def refined_name(features_name: str) -> str:
    """The refined keypoints' file name beside the features': features.h5 -> features-refined.h5."""
    path = Path(features_name)
    return f"{path.stem}-refined{path.suffix or '.h5'}"


def _inputs(image_dir: Path, out: Path, config: ReconstructConfig, settings: RunSettings, timer: StageTimer,
            features: str | Path | None, matches: str | Path | None,
            gps: GpsNeighbors | None = None) -> tuple[Path, Path, Path]:
    """Features, pairs file and matches: the caller's files where given, else made (or reused) in ``out``
    (``gps``: GPS neighbour pairs added to the pairs made).

    Extraction and matching run where ``settings.executor`` says, in one session: a Ray cluster is
    connected to (or a local one started) once for both stages, not once per stage.
    """
    masks = Path(config.masks) if config.masks else None
    rematch = False
    with execution.session(settings.executor, settings.ray_options):
        with timer("extract"):
            if features is None:
                # Photos extracted again because their mask changed: the reused matches of their pairs are stale.
                rematch = bool(changed_masks(out / config.file_names[0], masks))
                if rematch and not settings.overwrite:
                    logger.info("matching every pair again: photos are extracted again (their masks changed)")
                features = extract_features(image_dir, out / config.file_names[0], config.features,
                                            overwrite=settings.overwrite, num_threads=settings.num_threads,
                                            progress=settings.progress, executor=settings.executor,
                                            ray_options=settings.ray_options, masks=masks)
            else:
                ff.read_attrs(Path(features))  # sekd or hloc, else one clear error
                if masks is not None:
                    logger.warning("warning: --masks %s: not applied to --features %s, which is used as it is",
                                   masks, features)
        with timer("pairs"):
            pairs_file = _pairs_file(out, config.pairs, features, matches, settings.progress, gps)
        with timer("match"):
            if matches is None:
                matches = match_features(features, pairs_file, out / config.file_names[1], config.matching,
                                         overwrite=settings.overwrite or rematch, num_threads=settings.num_threads,
                                         progress=settings.progress, executor=settings.executor,
                                         ray_options=settings.ray_options)
    return Path(features), pairs_file, Path(matches)


def _pairs_file(out: Path, config: PairsConfig, features: str | Path, matches: str | Path | None,
                progress: bool, gps: GpsNeighbors | None = None) -> Path:
    """``out``/pairs.txt: the pairs chosen among the features' images (plus ``gps`` neighbours), or those of
    the caller's matches."""
    if matches is None:
        return make_pairs(features, out / "pairs.txt", config, progress=progress, gps=gps)
    pairs = read_pairs(config.file) if config.file else _stored_pairs(Path(matches))
    return write_pairs(pairs, out / "pairs.txt")  # the record of what was imported


def _stored_pairs(matches: Path) -> list:
    try:
        return mf.list_pairs(matches)
    except (OSError, KeyError) as exc:
        raise SekdError(f"{matches}: cannot list its pairs ({exc}); give them with --pairs-file") from None


def _matching_config(matches: Path) -> dict:
    """The match file's configuration (defaults resolved, e.g. the ratio); a placeholder for foreign files."""
    try:
        return json.loads(ff.read_attrs(matches, mf.FORMAT)["config"])
    except (SekdError, KeyError, ValueError):
        return {"source": str(matches)}


def distinct_models(models: list) -> tuple[list, int]:
    """Drop sub-models whose images all lie in a larger one (the mapper's failed early starts).

    ``models`` is largest first. Returns the kept models and how many were dropped.
    """
    kept, seen = [], []
    for model in models:
        names = set(registered_names(model))
        if not any(names <= other for other in seen):
            kept.append(model)
            seen.append(names)
    return kept, len(models) - len(kept)


def _finish(models: list, match_stats: dict, options, out: Path, stats: dict, database: Path) -> Path:
    if not models:
        raise explain_no_model(match_stats, options, database)
    models, stats["dropped_submodels"] = distinct_models(models)
    paths = write_models(models, out)
    groups = [registered_names(m) for m in models]
    stats["model"] = model_stats(models[0])
    stats["models"] = [{"path": str(p), **model_stats(m), "images": names} for p, m, names in zip(paths, models, groups)]
    in_a_model = {name for names in groups for name in names}
    stats["unregistered"] = unregistered_report(sorted(set(match_stats["images"]) - in_a_model), match_stats)
    stats["output"] = str(paths[0])
    if len(models) > 1:
        message = explain_models(groups, match_stats, paths)
        stats["split"] = message.splitlines()[0]
        logger.warning("%s", message)
    return paths[0]
