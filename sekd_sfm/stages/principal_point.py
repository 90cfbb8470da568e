"""The principal point in bundle adjustment (``--principal-point``): refined only where the photos determine it.

COLMAP keeps every camera's principal point at the image centre. A real lens's centre is off it
(fountain-P11: 15-17 px at 3072 px) and many photos of one camera can measure it: refined,
fountain-P11's pose errors halve. It is not always observable, though: moving it by d px turns
every view by about d / f rad, and under a long lens, photos that all look at one object (a
turntable ring) cannot tell the two apart. Refined from the start of mapping it then wanders
with the rotations: on a generated 30-photo ring at 320 x 240 px (focal length 750 px, field of
view 24 deg) it moved 76 px and the median pose error went from 0.43 to 8.6 deg (docs/experiments.md).

``auto`` (the default) therefore decides on the finished model, never at its price:

1. known intrinsics (``--camera-params``) or a camera with fewer than PRINCIPAL_POINT_MIN_IMAGES
   photos: fixed, no test (``plan_principal_point``);
2. otherwise the mapper maps with the principal point **fixed**, then each model goes through one
   more bundle adjustment with the principal points free (``try_refinement``, in a child process
   like the mapper: Ctrl-C kills it at once);
3. the refined model replaces the mapped one only when the photos determine the new principal
   points and need them: for every camera the shift from the image centre is at least
   MIN_SIGNIFICANCE times the principal point's largest standard deviation (the major axis of
   the 2 x 2 covariance of (cx, cy) from the adjustment, scaled by the residual variance) and
   the point stays inside the image; the mean reprojection error drops by at least
   MIN_REPROJECTION_GAIN (a shift that the rotations absorb explains nothing); no photo is
   lost. Otherwise the model keeps its centred principal points.

``refine`` lets the mapper refine it throughout (the former ``auto`` on 8+ photos), ``fixed``
never; ``--mapper ...refine_principal_point=...`` still wins. The run's record keeps the outcome
(``principal_point``: refined / fixed / set by --mapper) and why (``principal_point_decision``).

This module is also the test's child process (``python -m sekd_sfm.stages.principal_point``, the
protocol of ``mapper_worker``); it imports only pycolmap, numpy and the standard library at the top.
"""
from __future__ import annotations

import json
import logging
import math
import pickle
import shutil
import signal
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .mapper_worker import adjustment_options, refined_intrinsics

logger = logging.getLogger("sekd")

#: How far the refined principal point must move from the image centre, in its largest standard deviation
#: (the major axis of its covariance ellipse: a coordinate the photos leave free must not ride on a
#: well-determined one), to be kept. Measured (docs/experiments.md, section 27): fountain-P11 31.9 (SEKD,
#: 1600 px; pose AUC@1 0.676 -> 0.852), 7.5 (SIFT, 480 px), 13.9 (its first 8 photos); generated
#: turntable rings under a 24 deg lens 0.9-3.3 (refined, they lose 0.06-0.51 of pose AUC@5); the
#: generated city block 2.7 (its principal point is the image centre).
MIN_SIGNIFICANCE = 4.0
#: Smallest relative drop of the mean reprojection error for the refined principal point to be kept: the
#: refinement must explain the observations better, not only move (a shift the rotations absorb leaves the
#: error where it was, and the covariance is overconfident along such a weak direction). Measured:
#: fountain-P11 9.6 % (SEKD, 1600 px), 1.4 % (SIFT, 480 px), 4.8 % (its first 8 photos); the rings and
#: the city block -0.0 to 0.1 %.
MIN_REPROJECTION_GAIN = 0.005
#: Photos of a model above which the test is measured on an evenly spaced sample of this many (the
#: covariance's cost grows with the cube of the photos: 2 s at 242 photos, minutes at 1,000).
MAX_COVARIANCE_IMAGES = 300
#: For the wording of a rejection only: a principal point whose largest standard deviation exceeds this
#: fraction of the focal length (0.06 deg), or that moved 4 times as far, is "not observable"; a tighter
#: one that stayed closer to the centre says "the image centre fits".
LOOSE_SD = 1e-3
#: The command of the test's child process.
COMMAND = [sys.executable, "-m", "sekd_sfm.stages.principal_point"]


@dataclass
class PrincipalPointPlan:
    """What ``--principal-point`` does on a database (``plan_principal_point``), then what it did (``settle``).

    ``outcome``: ``refined``, ``fixed`` or ``set by --mapper``; ``reason`` says why; ``test``:
    whether the mapped models go through the final test; ``models``: its record per model.
    """

    setting: str
    outcome: str
    reason: str
    test: bool = False
    min_significance: float = MIN_SIGNIFICANCE
    min_reprojection_gain: float = MIN_REPROJECTION_GAIN
    models: list[dict] = field(default_factory=list)

    def details(self) -> dict:
        """The run's record's ``principal_point_decision``: the outcome, why, and the test's measurements."""
        record = {"setting": self.setting, "outcome": self.outcome, "reason": self.reason}
        if self.test:
            record["thresholds"] = {"min_significance": self.min_significance,
                                    "min_reprojection_gain": self.min_reprojection_gain}
            record["models"] = self.models
        return record

    def settle(self, models: list, scratch_dir: str | Path, options=None, progress: bool = True,
               log_prefix: str | Path | None = None) -> list:
        """The models to keep: each tested model replaced by its refined version where the test keeps it.

        Without a pending test, ``models`` as they are. ``scratch_dir``: the folder for the
        child's scratch files (the output folder: ``mapping.clean_scratch`` removes leftovers);
        ``options``: the mapper's (the adjustment refines what it refined, on its threads).
        Sets ``outcome``, ``reason`` and ``models`` from the main (first) model's test.
        """
        if not self.test:
            return models
        if not models:
            self.reason = "fixed: no model to refine the principal point in"
            return models
        from ..errors import Interrupted, SekdError

        refine, threads = refined_intrinsics(options)
        refine_focal, refine_extra = refine["focal_length"], refine["extra_params"]
        request = {"min_significance": self.min_significance, "min_reprojection_gain": self.min_reprojection_gain,
                   "refine_focal_length": refine_focal, "refine_extra_params": refine_extra, "num_threads": threads,
                   "max_covariance_images": MAX_COVARIANCE_IMAGES}
        try:
            models, self.models = run_test(models, request, scratch_dir, progress, log_prefix)
        except Interrupted:
            raise
        except SekdError as exc:  # never at the price of the model: the mapped one stays
            self.reason = f"fixed: the final adjustment failed ({str(exc).splitlines()[0]}); the mapped model is kept"
            logger.warning("principal point %s", self.reason)
            return models
        main = self.models[0]
        self.outcome = "refined" if main["kept"] else "fixed"
        self.reason = main["reason"]
        logger.info("principal point %s", self.reason)
        return models


def plan_principal_point(camera, mapper_assignments: list[str], database: str | Path, options) -> PrincipalPointPlan:
    """Set the mapper's principal-point refinement in ``options`` from ``camera`` (a CameraConfig) and the
    database's cameras; returns the plan (``auto``: the mapper keeps it fixed, ``settle`` tests the models).

    An explicit ``--mapper ...refine_principal_point=...`` (in ``mapper_assignments``) wins and is left alone.
    """
    from .database import (
        PRINCIPAL_POINT_MIN_IMAGES,
        check_principal_point_mode,
        images_per_camera,
        refines_principal_point,
        tries_principal_point,
    )
    from .mapping import set_principal_point_refinement

    setting = camera.principal_point
    check_principal_point_mode(setting)
    if any("refine_principal_point" in assignment for assignment in mapper_assignments):
        return PrincipalPointPlan(setting, "set by --mapper", "set by --mapper")
    per_camera = images_per_camera(database)
    fewest = min(per_camera, default=0)
    if refines_principal_point(camera, per_camera):
        plan = PrincipalPointPlan(setting, "refined", "refined: --principal-point refine")
    elif tries_principal_point(camera, per_camera):
        plan = PrincipalPointPlan(setting, "fixed", "fixed while mapping; refined in a final adjustment if the "
                                  "photos determine it", test=True)
    elif setting == "fixed":
        plan = PrincipalPointPlan(setting, "fixed", "fixed: --principal-point fixed")
    elif camera.params:
        plan = PrincipalPointPlan(setting, "fixed", "fixed: known intrinsics (--camera-params)")
    else:
        plan = PrincipalPointPlan(setting, "fixed", f"fixed: a camera has {fewest} photo(s), fewer than the "
                                  f"{PRINCIPAL_POINT_MIN_IMAGES} from which it is tested")
    set_principal_point_refinement(options, plan.outcome == "refined")
    logger.info("principal point %s (%s; %d camera(s), fewest photos per camera %d)", plan.reason, setting,
                len(per_camera), fewest)
    return plan


def run_test(models: list, request: dict, scratch_dir: str | Path, progress: bool = True,
             log_prefix: str | Path | None = None) -> tuple[list, list[dict]]:
    """``try_refinement`` of every model in a child process; the models to keep and the record of each."""
    from .colmap import require_pycolmap
    from .mapping import SCRATCH_PREFIX, run_child

    pycolmap = require_pycolmap()
    scratch = Path(tempfile.mkdtemp(prefix=SCRATCH_PREFIX, dir=scratch_dir))
    try:
        folders = []
        for k, model in enumerate(models):
            folder = scratch / "models" / str(k)
            folder.mkdir(parents=True)
            model.write_binary(str(folder))
            folders.append(str(folder))
        request = {**request, "models": folders, "result": str(scratch / "result.json"),
                   "log_prefix": str(log_prefix) if log_prefix else None}
        run_child(COMMAND, request, scratch, "principal point test", progress)
        records = json.loads((scratch / "result.json").read_text())
        kept = [pycolmap.Reconstruction(folder) if record["kept"] else model
                for model, folder, record in zip(models, folders, records)]
        return kept, records
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


# ----------------------------------------------------------------------------- the test (in the child process)

def field_of_view_deg(camera) -> tuple[float, float]:
    """Horizontal and vertical field of view (deg) of a pycolmap camera, from its mean focal length."""
    f = float(camera.mean_focal_length())
    return (math.degrees(2 * math.atan(camera.width / (2 * f))), math.degrees(2 * math.atan(camera.height / (2 * f))))


def _adjust(reconstruction, refine_focal: bool, refine_extra: bool, num_threads: int, pycolmap,
            refine_principal_point: bool = True):
    """One bundle adjustment of ``reconstruction`` (in place), the principal points free; ``(adjuster, summary)``."""
    refine = {"focal_length": refine_focal, "principal_point": refine_principal_point, "extra_params": refine_extra}
    options = adjustment_options(reconstruction, num_threads, pycolmap, refine)
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, reconstruction)
    summary = adjuster.solve()
    return adjuster, summary


def _principal_point_covariance(covariance, camera, refine_focal: bool, refine_extra: bool) -> np.ndarray | None:
    """The 2 x 2 covariance of (cx, cy) in the tangent covariance of the camera's parameter block (rows of
    constant parameters omitted: focal length or extra parameters when not refined)."""
    if covariance is None:
        return None
    block = covariance.get_other_params_cov(camera.params)
    if block is None:
        return None
    variable = sorted([*camera.principal_point_idxs(), *(camera.focal_length_idxs() if refine_focal else []),
                       *(camera.extra_params_idxs() if refine_extra else [])])
    if block.shape != (len(variable), len(variable)):
        return None
    rows = [variable.index(i) for i in camera.principal_point_idxs()]
    return np.asarray(block)[np.ix_(rows, rows)]


def try_refinement(reconstruction, min_significance: float = MIN_SIGNIFICANCE,
                    min_reprojection_gain: float = MIN_REPROJECTION_GAIN, refine_focal_length: bool = True,
                    refine_extra_params: bool = True, num_threads: int = 1,
                    max_covariance_images: int = MAX_COVARIANCE_IMAGES) -> tuple[object | None, dict]:
    """Refine the principal points of ``reconstruction`` (on a copy) in one bundle adjustment and judge the result.

    Returns ``(the refined copy, or None when rejected; record)``. The record: ``kept``, ``reason``,
    the registered photos and mean reprojection error (px) ``before`` and ``after``, the relative
    ``reprojection_gain`` (the drop over the error before), and per camera its size, field of
    view, refined principal point, shift and standard deviations (px: per coordinate, and the
    largest in any direction) and significance (the shift over that largest standard deviation).

    A model of more than ``max_covariance_images`` photos is judged on an evenly spaced sample of
    that many (the covariance's cost grows with the cube of the photos; fewer photos only widen
    the standard deviations); the whole model is refined only if the sample keeps its refinement,
    and must lower its own reprojection error as much (``record["sample"]``: the sample's photos).
    """
    import pycolmap

    registered = reconstruction.num_reg_images()
    if registered <= max_covariance_images:
        return _judge(reconstruction, min_significance, min_reprojection_gain, refine_focal_length,
                      refine_extra_params, num_threads)
    sample = _evenly_spaced(reconstruction, max_covariance_images)
    # The sample's own optimum with the principal points where they are: what its refinement is compared with.
    _adjust(sample, refine_focal_length, refine_extra_params, num_threads, pycolmap, refine_principal_point=False)
    _, record = _judge(sample, min_significance, min_reprojection_gain, refine_focal_length, refine_extra_params,
                       num_threads)
    record["sample"] = {"photos": int(sample.num_reg_images()), "of": int(registered)}
    if not record["kept"]:
        record["reason"] += f" (measured on {sample.num_reg_images()} of the {registered} photos)"
        return None, record
    reconstruction.update_point_3d_errors()
    refined = pycolmap.Reconstruction(reconstruction)
    _, summary = _adjust(refined, refine_focal_length, refine_extra_params, num_threads, pycolmap)
    refined.update_point_3d_errors()
    before, after = _state(reconstruction), _state(refined)
    gain = 1 - after["reprojection_error_px"] / max(before["reprojection_error_px"], 1e-12)
    whole = {"before": before, "after": after, "reprojection_gain": round(gain, 5),
             "principal_point_px": [[round(float(c.principal_point_x), 2), round(float(c.principal_point_y), 2)]
                                    for _, c in sorted(refined.cameras.items())]}
    record["whole"] = whole
    problems = [text for bad, text in ((not summary.is_solution_usable(), "the adjustment failed"),
                                       (after["registered"] < before["registered"], "fewer registered photos"),
                                       (gain < min_reprojection_gain, "no better fit")) if bad]
    record["kept"] = not problems
    scope = f"measured on {sample.num_reg_images()} of the {registered} photos; the whole model: reprojection error " \
            f"{before['reprojection_error_px']:.3f} -> {after['reprojection_error_px']:.3f} px ({-100 * gain:+.1f} %)"
    record["reason"] = (record["reason"][:-1] + f"; {scope})" if record["kept"] else
                        f"fixed: the whole model's refinement was rejected: {', '.join(problems)} ({scope})")
    return (refined if record["kept"] else None), record


def _state(reconstruction) -> dict:
    """Registered photos and mean reprojection error (px; point errors must be up to date)."""
    return {"registered": int(reconstruction.num_reg_images()),
            "reprojection_error_px": float(reconstruction.compute_mean_reprojection_error())}


def _evenly_spaced(reconstruction, count: int):
    """A copy of ``reconstruction`` with ``count`` of its registered photos, evenly spaced in image-id order
    (the others' frames removed, with their observations and the points left in fewer than two photos)."""
    import pycolmap

    sample = pycolmap.Reconstruction(reconstruction)
    ids = sorted(sample.reg_image_ids())
    keep = {sample.image(ids[round(k * (len(ids) - 1) / max(count - 1, 1))]).frame_id for k in range(count)}
    for frame_id in {sample.image(i).frame_id for i in ids} - keep:
        sample.deregister_frame(frame_id)
    sample.tear_down()  # drops the unregistered frames and images (the covariance reads every frame's pose)
    # A merged track may hold two observations in one photo; left with only those, its point has no depth and the
    # adjustment runs away with it (a 1,000-photo walk: one such point at 1e154 px, the test rejected for "no
    # covariance").
    for point_id in [i for i, p in sample.points3D.items() if len({e.image_id for e in p.track.elements}) < 2]:
        sample.delete_point3D(point_id)
    return sample


def _judge(reconstruction, min_significance: float, min_reprojection_gain: float, refine_focal_length: bool,
           refine_extra_params: bool, num_threads: int) -> tuple[object | None, dict]:
    """``try_refinement`` on the whole of ``reconstruction``."""
    import pycolmap

    reconstruction.update_point_3d_errors()
    before = _state(reconstruction)
    record = {"kept": False, "before": before, "cameras": []}
    if before["registered"] < 2:
        return None, {**record, "reason": "fixed: fewer than 2 registered photos"}
    refined = pycolmap.Reconstruction(reconstruction)
    adjuster, summary = _adjust(refined, refine_focal_length, refine_extra_params, num_threads, pycolmap)
    refined.update_point_3d_errors()
    after = _state(refined)
    gain = 1 - after["reprojection_error_px"] / max(before["reprojection_error_px"], 1e-12)
    record.update(after=after, reprojection_gain=round(gain, 5))
    # Per-coordinate residual standard deviation: the mean error norm of a 2-D Gaussian is sigma sqrt(pi / 2).
    sigma = after["reprojection_error_px"] / math.sqrt(math.pi / 2)
    covariance = pycolmap.estimate_ba_covariance(pycolmap.BACovarianceOptions(), refined, adjuster)
    problems, centred = [], True
    for camera_id in sorted(refined.cameras):
        camera, original = refined.camera(camera_id), reconstruction.camera(camera_id)
        entry = _camera_record(camera, original, covariance, sigma, refine_focal_length, refine_extra_params)
        record["cameras"].append(entry)
        if entry["significance"] is None:
            problems.append(f"camera {camera_id}: no covariance")
            continue
        if entry["significance"] < min_significance:
            problems.append("not determined")
        elif not (0 <= camera.principal_point_x <= camera.width and 0 <= camera.principal_point_y <= camera.height):
            problems.append(f"camera {camera_id}: outside the image")
        # For the wording: tightly determined and barely moved, or left free by the photos.
        loose = LOOSE_SD * camera.mean_focal_length()
        centred &= entry["sd_major_px"] <= loose and math.hypot(*entry["shift_px"]) <= 4 * loose
    if gain < min_reprojection_gain:
        problems.append("no better fit")
    record["centred"] = centred
    if not summary.is_solution_usable():
        problems.append("the adjustment failed")
    if after["registered"] < before["registered"]:
        problems.append("fewer registered photos")
    record["kept"] = not problems
    record["reason"] = _reason(record, sorted(set(problems)), min_significance, min_reprojection_gain)
    return (refined if record["kept"] else None), record


def _camera_record(camera, original, covariance, sigma: float, refine_focal: bool, refine_extra: bool) -> dict:
    """One camera's part of the test's record (``try_refinement``)."""
    shift = np.array([camera.principal_point_x - original.principal_point_x,
                      camera.principal_point_y - original.principal_point_y])
    fov = field_of_view_deg(camera)
    entry = {"camera_id": int(camera.camera_id), "size": [int(camera.width), int(camera.height)],
             "field_of_view_deg": [round(fov[0], 1), round(fov[1], 1)],
             "principal_point_px": [round(float(camera.principal_point_x), 2),
                                    round(float(camera.principal_point_y), 2)],
             "shift_px": [round(float(v), 2) for v in shift], "sd_px": None, "significance": None}
    c = _principal_point_covariance(covariance, camera, refine_focal, refine_extra)
    if c is not None and np.all(np.isfinite(c)) and np.linalg.det(c) > 0:
        scaled = c * sigma**2
        entry["sd_px"] = [round(float(v), 2) for v in np.sqrt(np.diag(scaled))]
        # The largest standard deviation in any direction (the major axis of the covariance ellipse): a
        # coordinate the photos leave free must not ride on a well-determined one.
        largest = math.sqrt(float(np.linalg.eigvalsh(scaled)[-1]))
        entry["sd_major_px"] = round(largest, 2)
        entry["significance"] = round(float(np.linalg.norm(shift)) / largest, 2)
    return entry


def _reason(record: dict, problems: list[str], min_significance: float, min_gain: float) -> str:
    """One line for the run's record and the log: the outcome and the measurements behind it."""
    def px(value: float) -> str:
        return f"{value:.2f}" if abs(value) < 1 else f"{value:.1f}"

    def camera(entry: dict) -> str:
        dx, dy = entry["shift_px"]
        text = f"moved ({dx:+.1f}, {dy:+.1f}) px"
        if entry["significance"] is not None:
            sx, sy = entry["sd_px"]
            text += f", {entry['significance']:.1f} times its largest standard deviation (sd {px(sx)}, {px(sy)} px)"
        return text

    cameras = "; ".join(camera(entry) for entry in record["cameras"][:3])
    if len(record["cameras"]) > 3:
        cameras += f"; ... ({len(record['cameras'])} cameras)"
    before, after = record["before"]["reprojection_error_px"], record["after"]["reprojection_error_px"]
    change = -100 * record["reprojection_gain"]
    measured = f"{cameras}; reprojection error {before:.3f} -> {after:.3f} px ({change:+.1f} %)"
    fov = "/".join(f"{entry['field_of_view_deg'][0]:.0f}" for entry in record["cameras"][:3])
    if record["kept"]:
        return f"refined in the final adjustment: kept ({measured}; field of view {fov} deg)"
    if set(problems) <= {"not determined", "no better fit"}:
        label = "the image centre fits" if record["centred"] else "not observable"
        return (f"fixed: {label} (field of view {fov} deg); refined in the final adjustment it {measured}: "
                f"rejected (it must move at least {min_significance:g} standard deviations in every direction "
                f"and lower the reprojection error by {100 * min_gain:g} %)")
    return f"fixed: the refinement in the final adjustment was rejected: {', '.join(problems)} ({measured})"


def main() -> int:
    """The child process: test every model of the request, write the kept ones over the originals, report."""
    from .mapper_worker import _die_with_parent, _event, quiet_colmap_log

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides: on Ctrl-C it kills this process
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})  # inherited blocked from the parent's start
    request = pickle.load(sys.stdin.buffer)
    _die_with_parent(int(request["parent_pid"]))
    import pycolmap

    quiet_colmap_log(request.get("log_prefix"), pycolmap)
    records = []
    for folder in request["models"]:
        refined, record = try_refinement(pycolmap.Reconstruction(folder), request["min_significance"],
                                         request["min_reprojection_gain"], request["refine_focal_length"],
                                         request["refine_extra_params"], request["num_threads"],
                                         request["max_covariance_images"])
        if refined is not None:
            refined.write_binary(folder)
        records.append(record)
        _event("model")
    if request.get("log_prefix"):
        pycolmap.logging.set_log_destination(pycolmap.logging.INFO, "")  # flush and close the log
    Path(request["result"]).write_text(json.dumps(records))
    _event("done")
    return 0


if __name__ == "__main__":
    sys.exit(main())
