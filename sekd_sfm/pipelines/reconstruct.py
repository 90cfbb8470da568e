"""The whole pipeline (``sekd reconstruct``): images -> features -> pairs -> matches -> database -> model -> report.

``RECONSTRUCT`` lists its steps in order; each is ``step(run, state) -> state`` over a ``Reconstruction``
(``run.py``). The files it writes in the output folder are named in ``record.py``. Features and
matches made with the same configuration are reused; features/matches given by the caller are
read in place instead. The run holds the folder's lock from start to end, so whatever a killed
run left behind (the mapper's ``mapping-*`` scratch folders, ``colmap.log.*`` pieces) is removed
at the start.
"""
from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from ..errors import SekdError
from ..execution import RayOptions
from ..files import features as ff
from ..files import matches as mf
from ..files.images import list_images
from ..files.signature import input_signature
from ..files.video import is_video, list_videos
from ..runtime import package_versions
from ..stages.chance import check_chance
from ..stages.colmap import clean_logs, colmap_log, log_prefix, require_pycolmap
from ..stages.database import (
    check_principal_point_mode,
    create_database,
    images_per_camera,
    parse_camera_params,
    two_view_options,
    verify_matches,
)
from ..stages.extract import changed_masks, extract_features
from ..stages.georef import GpsPlan, georeference, photo_names, plan_gps, write_georef
from ..stages.keyframes import link_photos, prepare_captures
from ..stages.mapping import (
    clean_scratch,
    mapper_options,
    min_model_size,
    min_num_matches,
    model_stats,
    registered_names,
    resolve_mapper_type,
    run_mapper,
    write_models,
)
from ..stages.match import match_features
from ..stages.modelcheck import check_model
from ..stages.pairs import make_pairs, read_pairs, write_pairs
from ..stages.panoramas import (
    find_panoramas,
    panorama_rig,
    render_views,
    same_panorama,
    write_panorama_poses,
)
from ..stages.principal_point import PrincipalPointPlan, plan_principal_point
from ..stages.refine import refine_keypoints, refine_summary
from ..stages.rig import (
    apply_rigs,
    calibration_photos,
    check_photos,
    estimate_cam_from_rig,
    poses_known,
    read_rigs,
    rig_record,
    write_rigs,
)
from ..stages.verification import verify_pairs
from ..stages.viewgraph import check_view_graph
from . import record
from .config import DEFAULT_MAPPER, DEFAULT_RESIZE_MAX, ReconstructConfig, config_dict
from .extend import ExtendOptions, extend_model
from .ordered import map_in_capture_order, order_first, record_principal_point, sequence
from .report import (
    ReconstructionError,
    check_enough_matches,
    explain_models,
    explain_no_model,
    folded_warning,
    match_statistics,
    summarize_matches,
    unregistered_report,
)
from .run import Run, RunOptions, Step, run_steps

logger = logging.getLogger("sekd")

__all__ = ["DEFAULT_MAPPER", "DEFAULT_RESIZE_MAX", "RECONSTRUCT", "ReconstructConfig", "Reconstruction", "RunOptions",
           "distinct_models", "reconstruct"]


@dataclass
class Reconstruction:
    """What the steps of ``RECONSTRUCT`` have made so far, and the record they fill (``stats``).

    ``features`` / ``matches``: the caller's files, else those the steps make in OUT; ``keypoints``:
    what the database gets (the refined keypoints, or the features); ``options`` / ``two_view``: pycolmap's
    mapper and verification options; ``log``: COLMAP's log, open from the database step to the run's end.
    """

    image_dir: Path
    config: ReconstructConfig
    stats: dict
    features: Path | None = None
    matches: Path | None = None
    pairs: Path | None = None
    pair_list: list = field(default_factory=list)
    keypoints: Path | None = None
    database: Path | None = None
    log: Path | None = None
    options: Any = None
    two_view: Any = None
    gps: GpsPlan | None = None
    principal_point: PrincipalPointPlan | None = None
    match_stats: dict = field(default_factory=dict)
    models: list = field(default_factory=list)
    model: Path | None = None
    #: Photos were extracted again because their mask changed: the reused matches of their pairs are stale.
    rematch: bool = False
    #: The input as given when it holds videos (a video, or a folder of videos and photos), else None.
    captures: Path | None = None
    #: The camera rigs (``stages.rig``: ``--rig-config``, and the panoramas' views), else None.
    rigs: list | None = None
    #: The input's 360-degree panoramas (``stages.panoramas``), mapped as rigs of views.
    panoramas: list[str] = field(default_factory=list)


def reconstruct(image_dir: str | Path, output_dir: str | Path, config: ReconstructConfig | None = None, *,
                overwrite: bool = False, num_threads: int | None = None, progress: bool = True,
                features: str | Path | None = None, matches: str | Path | None = None, executor: str = "local",
                ray_options: RayOptions | None = None, extend: ExtendOptions | None = None,
                options: RunOptions | None = None, steps: Sequence[Step] | None = None) -> Path:
    """Reconstruct the images below ``image_dir`` into ``output_dir``; returns the main model's folder.

    Runs the missing stages (extract, pairs, match) and reuses existing outputs made with
    the same configuration. ``features`` (a feature file of sekd or hloc) replaces extraction;
    ``matches`` (a match file, needs ``features``) replaces pairs and matching: its pairs are
    those of ``config.pairs.file`` when set, else all the pairs it holds. Both are read in
    place, never modified. When the images split into several models each is written
    (``model/`` the largest, ``models/1``, ...) and the split is logged as a warning.
    How the run runs: ``options`` (a RunOptions), or its fields ``overwrite``, ``num_threads``, ``progress``,
    ``executor`` and ``ray_options`` as keywords (where extraction and matching run: ``sekd_sfm.execution``).
    Raises ReconstructionError, after writing the record and keeping the database, when no
    model comes out; SekdError when another process is using ``output_dir``.
    ``extend``: add the photos ``output_dir``'s model lacks to it instead, with its recorded settings (extend.py).
    ``steps``: the pipeline to run instead of ``RECONSTRUCT`` (e.g. with a step of your own inserted,
    docs/architecture.md); each is ``step(run, state: Reconstruction) -> Reconstruction``.
    """
    require_pycolmap()
    config = config or ReconstructConfig()
    options = options or RunOptions(overwrite=overwrite, num_threads=num_threads, progress=progress,
                                    executor=executor, ray_options=ray_options)
    image_dir, out = Path(image_dir), Path(output_dir)
    videos = bool(list_videos(image_dir))
    _check_inputs(image_dir, features, matches, videos)
    if extend is not None:
        if videos:
            raise SekdError(f"{image_dir}: --extend takes photos; videos are mapped by a run of their own")
        if features is not None or options.overwrite:
            raise SekdError("--extend adds photos to OUTPUT's own files: leave out --features, --matches, --overwrite")
        return extend_model(image_dir, out, extend, options, weights=config.features.weights)
    state = Reconstruction(image_dir, config, _new_record(image_dir, config, features, matches),
                           features=Path(features) if features else None, matches=Path(matches) if matches else None,
                           captures=image_dir if videos else None)
    with Run(out, options, lock="reconstruction folder") as run:
        clean_scratch(out)  # left by a killed run: nobody else can be using them while we hold the lock
        clean_logs(out / record.COLMAP_LOG)
        return _recorded(run, state, RECONSTRUCT if steps is None else steps)


def _check_inputs(image_dir: Path, features: str | Path | None, matches: str | Path | None, videos: bool) -> None:
    if not image_dir.is_dir() and not is_video(image_dir):
        raise SekdError(f"{image_dir}: not a folder of images or a video; give the folder holding the photos")
    if videos and features is not None:
        raise SekdError(f"{image_dir}: holds videos, whose keyframes are chosen by this run: leave out --features")
    if matches is not None and features is None:
        raise SekdError(f"--matches {matches}: also give the feature file these matches index (--features)")
    for what, path in (("--features", features), ("--matches", matches)):
        if path is not None and not Path(path).is_file():
            raise SekdError(f"{what} {path}: no such file; give an existing HDF5 file or leave {what} out")


def _new_record(image_dir: Path, config: ReconstructConfig, features, matches) -> dict:
    return {"status": "running", "failure": None, "config": config_dict(config), "versions": package_versions(),
            "images_dir": str(image_dir), "inputs": {"features": str(features) if features else None,
                                                     "matches": str(matches) if matches else None}}


def _recorded(run: Run, state: Reconstruction, steps: Sequence[Step]) -> Path:
    """``steps`` over ``state``; the record says how it ended, success or a failure to explain."""
    stats = state.stats
    try:
        state = run_steps(run, steps, state)
        stats["status"] = "ok"
        return state.model
    except ReconstructionError as exc:
        stats["status"], stats["failure"] = "failed", str(exc).splitlines()[0]
        stats["failure_details"] = str(exc)
        raise
    finally:
        stats["timings_s"], stats["stages"] = run.timings(), run.stage_table()
        if stats["status"] != "running":
            record.write_record(stats, run.out)


# ----------------------------------------------------------------------------- the steps, in order

def keyframes(run: Run, s: Reconstruction) -> Reconstruction:
    """The keyframes of the input's videos written to OUT/images (``stages.keyframes``), its photos linked there:
    OUT/images is the run's photo folder. Pairs for video at ``auto``: sequential, with retrieval pairs for loop
    closure."""
    s.image_dir = run.out / record.IMAGES
    made = prepare_captures(s.captures, s.image_dir, s.config.keyframes, run.progress)
    s.stats["images_dir"] = str(s.image_dir)
    s.stats["keyframes"] = {name: {k: v for k, v in entry.items() if k != "keyframes"} | {
        "keyframes": len(entry["keyframes"])} for name, entry in made["videos"].items()}
    if s.config.pairs.mode == "auto":
        pairs = replace(s.config.pairs, mode="sequential",
                        num_neighbors=s.config.pairs.num_neighbors or VIDEO_LOOP_NEIGHBORS)
        s.config = replace(s.config, pairs=pairs)
        s.stats["config"]["pairs"] = config_dict(s.config)["pairs"]
    return s


#: Retrieval neighbours per keyframe added to a video's sequential pairs: the loops a walk closes.
VIDEO_LOOP_NEIGHBORS = 10


def check_options(run: Run, s: Reconstruction) -> Reconstruction:
    """pycolmap's mapper and two-view options of the configuration, every option checked first (a typo fails in a
    second, not after extraction and matching); the mapper type resolved for the collection's size; the GPS plan."""
    config = s.config
    count = _num_photos(s.image_dir, s.features) if config.mapper_type == "auto" else 0  # only auto looks at the size
    mapper_type = resolve_mapper_type(config.mapper_type, count)
    s.stats["mapper_type"] = mapper_type
    s.options = mapper_options(config.mapper, config.seed, mapper_type)
    s.two_view = two_view_options(config.verification, config.seed)
    parse_camera_params(config.camera.model, config.camera.params)
    check_principal_point_mode(config.camera.principal_point)
    names = photo_names(s.image_dir, s.features)
    s.gps = plan_gps(s.image_dir, names, config.gps)
    s.rigs = read_rigs(config.rig) if config.rig else None
    if s.rigs:  # a prefix that names no photo fails now, not after extraction
        check_photos(s.rigs, names, config.rig)
    if s.features is None:
        s.panoramas = find_panoramas(s.image_dir, names, config.camera.model == "EQUIRECTANGULAR")
    if s.panoramas and (config.rig or config.masks):
        raise SekdError(f"{s.image_dir}: holds 360-degree panoramas, mapped as rigs of views: leave out "
                        f"{'--rig-config' if config.rig else '--masks'}")
    return s


def panoramas(run: Run, s: Reconstruction) -> Reconstruction:
    """Each panorama's perspective views and masks written to OUT/views (``stages.panoramas``), the input's other
    photos linked there: OUT/views is the run's photo folder, the views one rig of known poses and intrinsics."""
    views, masks = run.out / record.VIEWS, run.out / record.VIEW_MASKS
    made = render_views(s.image_dir, s.panoramas, views, masks, run.progress)
    link_photos(s.image_dir, views, exclude=set(s.panoramas))
    s.image_dir, s.rigs = views, [panorama_rig(made["width"])]
    camera = replace(s.config.camera, principal_point="fixed",  # the views' intrinsics are exact
                     model="PINHOLE" if s.config.camera.model == "EQUIRECTANGULAR" else s.config.camera.model)
    s.config = replace(s.config, masks=str(masks), camera=camera)
    s.stats["images_dir"] = str(views)  # the view masks stay out of the record: exports would take them for masks
    s.stats["panoramas"] = {"panoramas": len(made["panoramas"]), **made["views"]}
    logger.info("%d photos are 360-degree panoramas: each mapped as %d views", len(made["panoramas"]),
                len(made["views"]["yaws_deg"]))
    return s


def extract(run: Run, s: Reconstruction) -> Reconstruction:
    """OUT's feature file (made or resumed), or a check of the caller's."""
    masks = Path(s.config.masks) if s.config.masks else None
    if s.features is not None:
        ff.read_attrs(s.features)  # sekd or hloc, else one clear error
        if masks is not None:
            logger.warning("warning: --masks %s: not applied to --features %s, which is used as it is", masks,
                           s.features)
        return s
    output = run.out / s.config.file_names[0]
    s.rematch = bool(changed_masks(output, masks))
    if s.rematch and not run.options.overwrite:
        logger.info("matching every pair again: photos are extracted again (their masks changed)")
    s.features = extract_features(s.image_dir, output, s.config.features, overwrite=run.options.overwrite,
                                  num_threads=run.num_threads, progress=run.progress, executor=run.executor,
                                  masks=masks)
    return s


def pairs(run: Run, s: Reconstruction) -> Reconstruction:
    """OUT's pairs file: the pairs chosen among the features' images (plus GPS neighbours), or those of the
    caller's matches."""
    path = run.out / record.PAIRS
    if s.matches is None:
        s.pairs = make_pairs(s.features, path, s.config.pairs, progress=run.progress,
                             gps=s.gps.neighbors(s.config.gps), executor=run.executor)
        if s.panoramas:  # views of one panorama share no pixel
            s.pairs = write_pairs([p for p in read_pairs(s.pairs) if not same_panorama(*p)], path)
    else:
        listed = read_pairs(s.config.pairs.file) if s.config.pairs.file else _stored_pairs(s.matches)
        s.pairs = write_pairs(listed, path)  # the record of what was imported
    return s


def match(run: Run, s: Reconstruction) -> Reconstruction:
    """OUT's match file (made or resumed), unless the caller gave one."""
    if s.matches is None:
        s.matches = match_features(s.features, s.pairs, run.out / s.config.file_names[1], s.config.matching,
                                   overwrite=run.options.overwrite or s.rematch, num_threads=run.num_threads,
                                   progress=run.progress, executor=run.executor)
    s.stats["matching"] = _matching_config(s.matches)
    s.pair_list = read_pairs(s.pairs)  # what refinement and the database take, read once
    return s


def refine(run: Run, s: Reconstruction) -> Reconstruction:
    """The keypoints moved to where their matches agree (``stages.refine``)."""
    s.keypoints = refine_keypoints(s.features, s.matches, s.pair_list, s.image_dir,
                                   run.out / record.refined_name(s.config.file_names[0]), s.config.refine,
                                   progress=run.progress, executor=run.executor)
    s.stats["refine"] = refine_summary(s.keypoints)
    return s


def database(run: Run, s: Reconstruction) -> Reconstruction:
    """COLMAP's database of the keypoints (refined, or as extracted) and matches; COLMAP's log goes to OUT from here
    to the run's end."""
    s.log = run.hold(colmap_log(run.out / record.COLMAP_LOG))
    s.database = run.out / record.DATABASE
    s.keypoints = s.keypoints or s.features
    prefixes = tuple(camera.prefix for rig in s.rigs or [] for camera in rig)
    create_database(s.image_dir, s.keypoints, s.matches, s.pair_list, s.database, s.config.camera, prefixes)
    return s


def rig(run: Run, s: Reconstruction) -> Reconstruction:
    """The rigs checked against the photos and, where every camera's pose in its rig is given, written into the
    database and kept by the mapper (``stages.rig``); otherwise the step ``rig calibration`` estimates them."""
    names = list(ff.list_keys(s.keypoints))
    s.stats["rig"] = {"photos_per_camera": check_photos(s.rigs, names, s.config.rig or record.VIEWS)}
    if s.config.camera.principal_point == "auto":  # its test's covariances take one photo per instant, not a rig
        s.config = replace(s.config, camera=replace(s.config.camera, principal_point="fixed"))
    if poses_known(s.rigs):
        _keep_rigs(s, apply_rigs(s.database, s.rigs))
    return s


def rig_calibration(run: Run, s: Reconstruction) -> Reconstruction:
    """The photos of the first ``RIG_CALIBRATION_INSTANTS`` instants (all of them if those do not do) mapped as free
    photos, each rig camera's pose estimated where most instants agree, and the rigs written into the database for
    mapping (their poses refined there); OUT/rig.json records them."""
    names = list(ff.list_keys(s.keypoints))
    for subset in (calibration_photos(s.rigs, names, RIG_CALIBRATION_INSTANTS), []):
        options = mapper_options([], s.config.seed, "incremental")
        options.image_names = subset  # [] = every photo
        free = run_mapper(s.database, s.image_dir, options, run.progress, log_prefix=log_prefix(s.log))
        if not free and not subset:
            raise explain_no_model(s.match_stats, options, s.database)
        try:
            s.rigs, s.stats["rig"]["estimated"] = estimate_cam_from_rig(s.rigs, free[0] if free else None)
            break
        except SekdError:
            if not subset or len(subset) == len(names):
                raise
    apply_rigs(s.database, s.rigs)
    write_rigs(s.rigs, run.out / record.RIG)
    s.stats["rig"]["free_model_photos"] = free[0].num_reg_images()
    return s


#: Instants whose photos are mapped freely to estimate the poses in a rig: enough to outvote a few wrong ones, and
#: a fraction of a long capture's mapping time.
RIG_CALIBRATION_INSTANTS = 20


def principal_point(run: Run, s: Reconstruction) -> Reconstruction:
    """The principal-point plan of the cameras (``stages.principal_point``: ``auto`` maps with it fixed, then
    tests it); sets the mapper's refinement in the options. An explicit ``--mapper ...refine_principal_point=...``
    wins."""
    s.principal_point = plan_principal_point(s.config.camera, s.config.mapper, s.database, s.options)
    record_principal_point(s)
    return s


def verification(run: Run, s: Reconstruction) -> Reconstruction:
    """Geometric verification of every pair: COLMAP's, per pair on the run's executor (``stages.verification``);
    photos in rigs by pycolmap over the database, which knows the rigs' frames."""
    if s.rigs:
        verify_matches(s.database, s.two_view, run.num_threads or -1)
        return s
    inputs = input_signature((s.keypoints, s.matches), s.pair_list, asdict(s.config.camera))
    verify_pairs(s.database, s.two_view, run.executor, signature=inputs, progress=run.progress)
    return s


def chance(run: Run, s: Reconstruction) -> Reconstruction:
    """The verified pairs whose inliers chance alone would give dropped (``stages.chance``)."""
    s.stats["chance"] = check_chance(s.database, min_num_matches(s.options), s.config.chance, s.config.seed,
                                     run.executor, run.progress)
    return s


def match_report(run: Run, s: Reconstruction) -> Reconstruction:
    """The verified matches' statistics; ReconstructionError when too few to map."""
    s.match_stats = match_statistics(s.database, min_num_matches(s.options))
    s.stats["matches"] = summarize_matches(s.match_stats)
    check_enough_matches(s.match_stats, s.database)
    return s


def view_graph(run: Run, s: Reconstruction) -> Reconstruction:
    """The verified pairs whose rotation disagrees with the rest of the view graph dropped (``stages.viewgraph``)."""
    s.stats["view_graph"] = check_view_graph(s.database, min_num_matches(s.options), s.config.view_graph)
    return s


def mapping(run: Run, s: Reconstruction) -> Reconstruction:
    """The models (largest first), filtered after mapping, the principal point settled. An ordered capture is
    mapped in capture order (``stages.sequence``); other photos, or a chain that leaves photos out, all pairs at
    once."""
    filtered: list = []
    hierarchical: dict = {}
    models = map_in_capture_order(run, s, filtered, hierarchical) if order_first(s) else None
    if models is None:
        with run.part("all pairs"):
            models = run_mapper(s.database, s.image_dir, s.options, run.progress, log_prefix=log_prefix(s.log),
                                final_filter=s.config.final_filter, records=filtered, executor=run.executor,
                                details=hierarchical)
    s.models = models
    s.stats["hierarchical"] = hierarchical or None
    if not s.models and (s.stats.get("rig") or {}).get("estimated"):
        raise ReconstructionError(
            f"no model with the rig: the photos mapped as free photos ({s.stats['rig']['free_model_photos']} of them "
            f"in one model) gave each camera's pose in the rig ({record.RIG}), and with those poses the mapper found "
            "no initial pair: the free model is likely wrong (too few or too similar photos); measure the poses and "
            "give them in the rig file (cam_from_rig_rotation, cam_from_rig_translation)")
    s.stats["final_filter"] = filtered[0] if filtered else None
    with run.part("principal point test") if s.principal_point.test else nullcontext():
        s.models = s.principal_point.settle(s.models, run.out, s.options, run.progress, log_prefix(s.log))
    record_principal_point(s)
    return s


def georeferencing(run: Run, s: Reconstruction) -> Reconstruction:
    """The main model moved into a local east-north-up frame from the photos' GPS, where the plan says so."""
    georef = georeference(s.models, s.gps, s.config.gps, s.config.seed)  # models[0] moved into the ENU frame
    s.stats["georeference"] = {k: v for k, v in georef.items() if k != "per_image"}
    s.model, s.models = _finish(s.models, s.match_stats, s.options, run.out, s.stats, s.database)
    write_georef(run.out, georef)
    if s.rigs:
        s.stats["rig"]["model"] = rig_record(s.models[0])
    if s.panoramas:
        s.stats["panoramas"]["posed"] = write_panorama_poses(s.models[0], run.out / record.PANORAMA_POSES)
    return s


def model_check(run: Run, s: Reconstruction) -> Reconstruction:
    """Each written model checked against the verified pairs it should explain (``stages.modelcheck``); a model
    that may be folded is said so (a warning, the summary, ``stats.json`` ``model_check``)."""
    records = []
    for model, entry in zip(s.models, s.stats["models"]):  # the models as written (``_finish``)
        checked = check_model(model, s.database, s.config.model_check)
        records.append({"path": entry["path"], **checked})
        if checked["suspect"]:
            logger.warning("warning: %s", folded_warning(records[-1]))
    s.stats["model_check"] = records
    return s


#: ``sekd reconstruct``, step by step (untimed steps are checks and bookkeeping, not stages of the record's timings).
RECONSTRUCT: tuple[Step, ...] = (
    Step("keyframes", keyframes, when=lambda s: s.captures is not None),
    Step("options", check_options, timed=False),
    Step("panoramas", panoramas, when=lambda s: bool(s.panoramas)),
    Step("extract", extract),
    Step("pairs", pairs),
    Step("match", match),
    Step("refine", refine, when=lambda s: s.config.refine.enabled),
    Step("database", database),
    Step("rig", rig, timed=False, when=lambda s: bool(s.rigs)),
    Step("principal point", principal_point, timed=False),
    Step("verification", verification),
    Step("chance check", chance, when=lambda s: s.config.chance.enabled),
    Step("match report", match_report, timed=False),
    Step("view graph", view_graph, when=lambda s: s.config.view_graph.enabled),
    Step("rig calibration", rig_calibration, when=lambda s: bool(s.rigs) and not poses_known(s.rigs)),
    Step("mapping", mapping),
    Step("capture order", sequence, timed=False,  # timed by itself, only when it maps again
         when=lambda s: s.config.sequence.enabled and not s.rigs and not s.panoramas and not s.stats.get("sequence")),
    Step("georeference", georeferencing, timed=False),
    Step("model check", model_check, when=lambda s: s.config.model_check.enabled),
)


def _keep_rigs(s: Reconstruction, given_cameras: dict[str, int]) -> None:
    """The mapper keeps the rigs' given poses and the cameras' given intrinsics (a rig file's, the panoramas')."""
    options = getattr(s.options, "incremental_options", s.options)
    if hasattr(options, "ba_refine_sensor_from_rig"):
        options.ba_refine_sensor_from_rig = False
        options.constant_cameras = set(given_cameras.values())
    else:  # global: no constant cameras; its adjustment keeps all intrinsics when the rigs give them all
        options.mapper.refine_sensor_from_rig = False
        if given_cameras and len(given_cameras) == len(images_per_camera(s.database)):
            ba = options.mapper.bundle_adjustment
            ba.refine_focal_length = ba.refine_principal_point = ba.refine_extra_params = False


def _num_photos(image_dir: Path, features: str | Path | None) -> int:
    """The photos to map: the feature file's images when given, else those below ``image_dir`` (0 if none:
    extraction then says so, after the options are checked)."""
    try:
        return len(ff.list_keys(Path(features))) if features is not None else len(list_images(image_dir))
    except (SekdError, OSError):
        return 0


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


def _finish(models: list, match_stats: dict, options, out: Path, stats: dict, database: Path) -> tuple[Path, list]:
    """The models written (sub-models dropped: ``distinct_models``) and recorded; the main model's folder and the
    models kept, in the order of ``stats["models"]``."""
    if not models:
        raise explain_no_model(match_stats, options, database)
    models, stats["dropped_submodels"] = distinct_models(models)
    paths = write_models(models, out)
    groups = [registered_names(m) for m in models]
    stats["model"] = model_stats(models[0])
    stats["models"] = [{"path": str(p), **model_stats(m), "images": names} for p, m, names in zip(paths, models, groups)]
    where = {name: k for k, names in enumerate(groups) for name in names}
    stats["unregistered"] = unregistered_report(sorted(set(match_stats["images"]) - set(where)), match_stats, where,
                                                min_model_size(options))
    stats["output"] = str(paths[0])
    if len(models) > 1:
        message = explain_models(groups, match_stats, paths)
        stats["split"] = message.splitlines()[0]
        logger.warning("%s", message)
    return paths[0], models
