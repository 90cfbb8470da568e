"""The capture order's steps of ``sekd reconstruct`` (``stages.sequence``): an ordered capture mapped in capture
order from the start (``map_in_capture_order``, called by the mapping step), or, when the photos were mapped all
at once, a folded or split model mapped again in capture order afterwards (``sequence``, the step "capture
order")."""
from __future__ import annotations

import logging
import math
import os
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

from ..stages.colmap import log_prefix
from ..stages.hierarchical import model_arrays
from ..stages.mapping import SCRATCH_PREFIX, mapper_type_of, min_num_matches, run_mapper
from ..stages.modelcheck import check_model
from ..stages.sequence import (
    better,
    chain_database,
    disagreeing_pairs,
    drop_pairs,
    is_ordered,
    linked_share,
    listed_pairs,
    order_contrast,
    rank,
    registered,
    remap_reason,
    sequence_record,
    verified_pairs,
)
from .report import sequence_line
from .run import Run

#: The state of ``sekd reconstruct``'s steps (``reconstruct.Reconstruction``; not imported: it imports this module).
Reconstruction = Any

logger = logging.getLogger("sekd")

#: The closing's triangulate-and-adjust passes (``mapper_worker.merged_model``): the chain holds at most
#: ``order_first_max_photos`` photos, whose clusters' own adjustments leave seams one pass at 16 px closes (the
#: second and third passes are for the seams of walks of thousands of photos). One pass against two, pose AUC@5:
#: generated 100-photo walk 0.99612 / 0.99616, 250-photo walk with every building twice 0.99601 / 0.99594, temples
#: of 24 and 31 photos 0.99375 / 0.99377 and 0.99626 / 0.99627; the second pass cost 7-8 s at 97 photos
#: (docs/experiments.md, sections 44 and 45).
CLOSE_PASSES = 1


def order_first(s: Reconstruction) -> bool:
    """Whether the photos are mapped in capture order from the start (``SequenceConfig.order_first``): free photos
    (no rigs, no panoramas), a mapper that triangulates incrementally (not the global one), and at most
    ``order_first_max_photos`` photos with a verified pair (a longer chain drifts beyond the far-pair check)."""
    config = s.config.sequence
    if not (config.enabled and config.order_first and not s.rigs and not s.panoramas
            and mapper_type_of(s.options) != "global"):
        return False
    photos = _photos_with_pairs(s)
    if photos > config.order_first_max_photos:
        logger.info("capture order: %d photos, more than %d: all pairs mapped first (the order only for a model that "
                    "folds or splits)", photos, config.order_first_max_photos)
        return False
    return True


def map_in_capture_order(run: Run, s: Reconstruction, filtered: list, details: dict) -> list | None:
    """``stages.sequence`` from the start: the chain of photos near each other in the order mapped, the farther
    pairs that do not fit its poses dropped, the rest triangulated onto its poses and the whole adjusted; the
    models (largest first), ``s.database`` replaced by the pairs they were made from. None when the photos are no
    ordered capture or the chain leaves photos out: then all pairs are mapped at once."""
    config = s.config.sequence
    linked, contrast = _order_evidence(s)
    if not is_ordered(linked, contrast, config):
        if linked >= config.min_linked:  # said: names that look like an order (numbers) but are not one
            logger.info("capture order: %.0f%% of consecutive photos verified, but they share less than photos "
                        "far apart (median inliers %.2f times theirs): the names are no capture order, all pairs "
                        "mapped at once", 100 * linked, contrast)
        return None
    photos = _photos_with_pairs(s)
    scratch = Path(tempfile.mkdtemp(prefix=SCRATCH_PREFIX, dir=run.out))
    try:
        chain_db, closed_db = scratch / "chain.db", scratch / "closed.db"
        far = chain_database(s.database, chain_db, config.window)
        # The chain's poses only, its clusters merged but not adjusted (hierarchical): closing it triangulates and
        # adjusts the whole again (``_close``), which undoes a final filter and makes adjusting the chain first
        # moot (generated walks in clusters of 60: pose AUC@5 the same to 0.0001, mapping 77 -> 59 s at 100 photos,
        # 267 -> 164 s at 250; docs/experiments.md, section 44).
        with run.part("chain"):
            chain = run_mapper(chain_db, s.image_dir, s.options, run.progress, log_prefix=log_prefix(s.log),
                               executor=run.executor, details=details, merge_passes=0)
        if registered(chain) < (1 - config.max_left_out) * photos:
            s.stats["sequence"] = sequence_record("ordered", linked, config, remapped=False,
                                                  chain_registered=registered(chain), photos=photos)
            return None
        with run.part("far pairs"):
            dropped = _without_unfit_pairs(s, chain, far, closed_db)
        closings: dict[str, dict] = {"closed": {}, "chain": {}}  # each closing's record, the kept one's recorded
        with run.part("closing"):
            closed, records = _close(run, s, closed_db, chain, closings["closed"])
        with run.part("fold check"):
            scores, kept = {"closed": _verdict(s, closed, closed_db)}, "closed"
        if scores["closed"][0] or registered(closed) < registered(chain):
            # The far pairs kept fold it (or cost photos): the chain alone, adjusted and filtered over its own
            # pairs, when that is better.
            with run.part("closing"):
                alone, alone_records = _close(run, s, chain_db, chain, closings["chain"])
            with run.part("fold check"):
                scores["chain"] = _verdict(s, alone, chain_db)
            if rank(scores["chain"]) > rank(scores["closed"]):
                kept, closed, records = "chain", alone, alone_records
        os.replace(closed_db if kept == "closed" else chain_db, s.database)  # the pairs the kept model was made from
        filtered.extend(records)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    _record_remap(s, "ordered", linked, far, dropped, kept, scores, closing=closings[kept].get("merge"))
    return closed


def _close(run: Run, s: Reconstruction, database: Path, chain: list, details: dict | None = None
           ) -> tuple[list, list]:
    """The chain's largest model with its poses held, its points triangulated again from ``database``'s pairs, the
    whole adjusted and filtered (``run_mapper(poses_from=...)``): the models and the final filter's records.
    ``details`` gets the record of the closing (``merge``: its passes and the seconds of each step)."""
    records: list = []
    models = run_mapper(database, s.image_dir, s.options, run.progress, log_prefix=log_prefix(s.log),
                        final_filter=s.config.final_filter, records=records, poses_from=[model_arrays(chain[:1])],
                        merge_passes=CLOSE_PASSES, details=details)
    return models, records


def sequence(run: Run, s: Reconstruction) -> Reconstruction:
    """A folded or split model of an ordered capture mapped again in capture order (``stages.sequence``): the
    photos near each other in the order first, then the farther pairs that fit that chain. The new model and its
    database replace the old ones only when the new model is better (not folded, else more photos)."""
    config = s.config.sequence
    check = check_model(s.models[0], s.database, s.config.model_check) if s.models else {"suspect": False}
    photos = _photos_with_pairs(s)
    reason = remap_reason(s.models, check["suspect"], photos, config)
    if reason is None:
        return s
    linked, contrast = _order_evidence(s)
    if not is_ordered(linked, contrast, config):
        s.stats["sequence"] = sequence_record(reason, linked, config, remapped=False,
                                              contrast=round(contrast, 3) if math.isfinite(contrast) else None)
        return s
    # Said now, not only with the outcome: the remap maps the collection twice more (at 2,000 photos, most of a run).
    logger.info("capture order: the model looks %s (its largest of %d holds %d of the %d photos with a verified "
                "pair); mapping again in capture order", reason, len(s.models), registered(s.models), photos)
    with run.timed("capture order"):
        return _remap_in_order(run, s, reason, linked, check["suspect"])


def _remap_in_order(run: Run, s: Reconstruction, reason: str, linked: float, suspect: bool) -> Reconstruction:
    """``sequence``'s two passes, the better model kept and the record written."""
    scratch = Path(tempfile.mkdtemp(prefix=SCRATCH_PREFIX, dir=run.out))
    try:
        far, dropped, candidates = _map_in_order(run, s, scratch)
        scores = {"before": (suspect, registered(s.models))}
        scores.update({name: _verdict(s, models, db) for name, (models, db) in candidates.items()})
        kept = max(("remapped", "chain", "before"), key=lambda k: rank(scores[k]))
        kept = kept if better(scores[kept], scores["before"]) else "before"
        if kept != "before":
            models, db = candidates[kept]
            s.models = s.principal_point.settle(models, run.out, s.options, run.progress, log_prefix(s.log))
            os.replace(db, s.database)  # the pairs the kept model was mapped from
            record_principal_point(s)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    _record_remap(s, reason, linked, far, dropped, kept, scores)
    return s


def _map_in_order(run: Run, s: Reconstruction, scratch: Path) -> tuple[list, list, dict]:
    """The two passes of ``stages.sequence`` on copies of the database in ``scratch``: the far pairs, those dropped
    (with their agreement) and the candidates ``{"chain": (models, database), "remapped": (models, database)}``."""
    config = s.config.sequence
    chain_db, final_db = scratch / "chain.db", scratch / "final.db"
    far = chain_database(s.database, chain_db, config.window)
    chain = _map_raw(run, s, chain_db)
    dropped = _without_unfit_pairs(s, chain, far, final_db)
    final = _map_raw(run, s, final_db) if chain else []
    return far, dropped, {"chain": (chain, chain_db), "remapped": (final, final_db)}


def _map_raw(run: Run, s: Reconstruction, database: Path) -> list:
    """The models of ``database`` (largest first) by the run's mapper and final filter, the principal point as
    mapped."""
    return run_mapper(database, s.image_dir, s.options, run.progress, log_prefix=log_prefix(s.log),
                      final_filter=s.config.final_filter, executor=run.executor)


def _order_evidence(s: Reconstruction) -> tuple[float, float]:
    """``linked_share`` and ``order_contrast`` of the verified pairs of ``s.database``."""
    pairs = verified_pairs(s.database, min_num_matches(s.options))
    return linked_share(pairs), order_contrast(pairs, s.config.sequence.window)


def _photos_with_pairs(s: Reconstruction) -> int:
    """The photos with at least one verified pair (those a model can hold)."""
    return sum(1 for image in s.match_stats["images"].values() if image["verified_pairs"])


def _without_unfit_pairs(s: Reconstruction, chain: list, far: list, target: Path) -> list:
    """A copy of ``s.database`` at ``target`` without the ``far`` pairs the ``chain``'s poses do not fit; those
    pairs, each with its agreement (``stages.sequence.disagreeing_pairs``)."""
    dropped = disagreeing_pairs(chain, s.database, far, s.config.sequence)
    shutil.copyfile(s.database, target)
    drop_pairs(target, [pair for pair, _ in dropped])
    return dropped


def _verdict(s: Reconstruction, models: list, database: Path) -> tuple[bool, int]:
    """``(suspect, photos registered)`` of the largest of ``models`` (``(True, 0)`` without one), checked against
    the pairs it was made from at the far pairs' tolerance: the chain drifts a little over long loops, a fold is
    off by far more."""
    if not models:
        return True, 0
    tolerant = replace(s.config.model_check, max_error_px=s.config.sequence.max_error_px)
    return check_model(models[0], database, tolerant)["suspect"], registered(models)


def _record_remap(s: Reconstruction, reason: str, linked: float, far: list, dropped: list, kept: str,
                  scores: dict, **figures) -> None:
    """``stats.json`` ``sequence`` of a run that mapped in capture order (and ``figures``), and its log line."""
    config = s.config.sequence
    s.stats["sequence"] = sequence_record(
        reason, linked, config, remapped=True, far_pairs=len(far), dropped=len(dropped),
        dropped_pairs=listed_pairs(dropped, config.listed), kept=kept,
        models={k: {"suspect": v[0], "registered": v[1]} for k, v in scores.items()}, **figures)
    logger.info("capture order: %s", sequence_line(s.stats["sequence"]))


def record_principal_point(s: Reconstruction) -> None:
    """The principal point's outcome and decision into the record, after the models it settled."""
    s.stats["principal_point"], s.stats["principal_point_decision"] = (s.principal_point.outcome,
                                                                       s.principal_point.details())
