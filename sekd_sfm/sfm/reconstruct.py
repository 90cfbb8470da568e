"""The whole pipeline (``sekd reconstruct``): images -> features -> pairs -> matches -> database -> model -> report.

Files in the output folder::

    features.h5, pairs.txt, matches.h5   the earlier stages (reused when made with the same configuration)
    database.db                          COLMAP database (kept on failure, for inspection)
    colmap.log                           COLMAP's log
    model/, submodels/<k>/               COLMAP binary models (largest first)
    stats.json                           counts, accuracy figures, timings, configuration
"""
from __future__ import annotations

import json
import logging
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .. import featurefile as ff
from .. import matchfile as mf
from ..extract import extract_features
from ..features import FeatureConfig
from ..match import MatchConfig, match_features
from ..pairs import PairsConfig, make_pairs, read_pairs
from ..runtime import package_versions
from .colmap import colmap_log, require_pycolmap
from .database import (
    CameraConfig,
    create_database,
    parse_camera_params,
    two_view_options,
    verify_matches,
)
from .mapping import (
    mapper_options,
    model_stats,
    registered_names,
    run_mapper,
    write_models,
)
from .report import (
    ReconstructionError,
    check_enough_matches,
    explain_no_model,
    explain_submodels,
    match_statistics,
    summarize_matches,
    unregistered_report,
    write_json,
)

logger = logging.getLogger("sekd")


@dataclass
class ReconstructConfig:
    """Every stage's settings; ``mapper`` / ``verification`` are ``key=value`` pycolmap option overrides."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    pairs: PairsConfig = field(default_factory=PairsConfig)
    matching: MatchConfig = field(default_factory=MatchConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    mapper: list[str] = field(default_factory=list)
    verification: list[str] = field(default_factory=list)
    seed: int = 0


class _Timer:
    def __init__(self):
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] = round(time.perf_counter() - start, 3)


def _config_dict(config: ReconstructConfig) -> dict:
    data = asdict(config)
    data["features"].pop("weights", None)  # a local path; the model's hash is in features.h5
    return data


def reconstruct(image_dir: str | Path, output_dir: str | Path, config: ReconstructConfig | None = None, *,
                overwrite: bool = False, num_threads: int | None = None, progress: bool = True) -> Path:
    """Reconstruct the images below ``image_dir`` into ``output_dir``; returns the main model's folder.

    Runs the missing stages (extract, pairs, match) and reuses existing outputs made with
    the same configuration. Raises ReconstructionError, after writing stats.json and keeping
    the database, when no model or several sub-models come out. COLMAP's log goes to
    ``output_dir/colmap.log``.
    """
    require_pycolmap()
    config = config or ReconstructConfig()
    image_dir, out = Path(image_dir), Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    timer, stats = _Timer(), {"status": "running", "failure": None, "config": _config_dict(config),
                              "versions": package_versions(), "images_dir": str(image_dir)}
    try:
        model = _run(image_dir, out, config, timer, stats, overwrite, num_threads, progress)
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


def _run(image_dir, out, config, timer, stats, overwrite, num_threads, progress) -> Path:
    # Options are checked first, so a typo fails in a second, not after extraction and matching.
    options = mapper_options(config.mapper, config.seed)
    two_view = two_view_options(config.verification, config.seed)
    parse_camera_params(config.camera.model, config.camera.params)
    with timer("extract"):
        features = extract_features(image_dir, out / "features.h5", config.features, overwrite=overwrite,
                                    num_threads=num_threads, progress=progress)
    with timer("pairs"):
        pairs_file = make_pairs(features, out / "pairs.txt", config.pairs)
    with timer("match"):
        matches = match_features(features, pairs_file, out / "matches.h5", config.matching, overwrite=overwrite,
                                 num_threads=num_threads, progress=progress)
    stats["matching"] = json.loads(ff.read_attrs(matches, mf.FORMAT)["config"])  # defaults resolved (ratio)
    database = out / "database.db"
    with colmap_log(out / "colmap.log"):
        with timer("database"):
            create_database(image_dir, features, matches, read_pairs(pairs_file), database, config.camera)
        with timer("verification"):
            verify_matches(database, two_view, num_threads or -1)
        match_stats = match_statistics(database, options.min_num_matches)
        stats["matches"] = summarize_matches(match_stats)
        check_enough_matches(match_stats, database)
        with timer("mapping"):
            models = run_mapper(database, image_dir, options, progress)
    return _finish(models, match_stats, options, out, stats, database)


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
    stats["models"] = [{"path": str(p), **model_stats(m)} for p, m in zip(paths, models)]
    stats["unregistered"] = unregistered_report(sorted(set(match_stats["images"]) - set(groups[0])), match_stats)
    stats["output"] = str(paths[0])
    if len(models) > 1:
        raise explain_submodels(groups, match_stats, database)
    return paths[0]
