"""The mapper's child process: ``python -m sekd_sfm.stages.mapper_worker`` (started by ``mapping.run_mapper``).

Why a child process: pycolmap's mappers run in C++ with the GIL released; the incremental
mapper looks for Ctrl-C only between its steps (a bundle adjustment runs to its end: up to
3 s on ten photos, far longer on large scenes), the global and hierarchical mappers never
(they run to the end). A child can be killed at once, and its death frees every thread and
every byte the mapper held.

Protocol: the parent writes one pickled request (a dict, see ``main``) to stdin and closes
it. The child writes one line per progress event to stdout (``pair``: an initial pair was
found; ``image``: an image was registered), writes each reconstruction found to
``<output>/<k>`` (largest first, COLMAP binary) and, with ``final_filter`` in the request, the record
of each one's final filtered adjustment to ``<output>/<k>.json``, and exits 0; on an exception it prints
the traceback to stderr and exits 1. Only pycolmap, numpy, the standard library and the merge of the
hierarchical mapper's clusters (``cluster_merge``: NumPy and pycolmap) are imported here, so the child starts in well
under a second (no torch).
"""
from __future__ import annotations

import ctypes
import json
import os
import pickle
import signal
import sys
import time
from pathlib import Path

import numpy as np

from .cluster_merge import SEAM_MAX_ERROR_PX, assemble, merge_pieces, pieces_of, triangulate_held

_PR_SET_PDEATHSIG = 1  # prctl(2)


def _die_with_parent(parent_pid: int) -> None:
    """Ask Linux to SIGKILL this process when the parent dies (even by kill -9); no-op elsewhere."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)


def quiet_colmap_log(prefix: str | None, pycolmap) -> None:
    """COLMAP's log (glog) into files named ``<prefix><date>-<time>.<pid>``, nothing on the console."""
    log = pycolmap.logging
    log.alsologtostderr, log.logtostderr, log.stderrthreshold, log.minloglevel = False, False, 3, 0
    for level in (log.WARNING, log.ERROR):
        log.set_log_destination(level, "")
    log.set_log_destination(log.INFO, prefix or "")


def _event(text: str) -> None:
    os.write(1, (text + "\n").encode())  # unbuffered: the parent's progress bar moves at once


#: Ceres stops when an iteration lowers the cost by less than this share of it (Ceres' own default). COLMAP sets
#: 0, so each adjustment ran to its 100 iterations, the last ones moving nothing: on a generated 1,000-photo walk's
#: merged model, the merge's adjustment and final filter took 161 + 135 s at 0 and 101 + 56 s at 1e-6, pose AUC@5
#: 0.9934 and 0.9933 (docs/experiments.md, section 42).
ADJUSTMENT_FUNCTION_TOLERANCE = 1e-6


def adjustment_options(reconstruction, num_threads: int, pycolmap, refine: dict | None = None):
    """pycolmap BundleAdjustmentOptions for one global adjustment of ``reconstruction``: quiet, on ``num_threads``,
    Ceres' sparse direct solver at any size; ``refine`` (focal_length, principal_point, extra_params) sets which
    intrinsics move (None: pycolmap's defaults)."""
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.ceres.solver_options.num_threads = num_threads
    # Above 1,000 images Ceres would switch to its iterative Schur solver, which took more than 13 minutes on
    # the merged 2,000-photo block; the sparse direct one stays cheap while the camera graph is sparse, as
    # retrieval pairs make it (each photo shares points with a few dozen others).
    options.ceres.max_num_images_direct_sparse_cpu_solver = max(1000, reconstruction.num_reg_images())
    options.ceres.solver_options.function_tolerance = ADJUSTMENT_FUNCTION_TOLERANCE
    if refine is not None:
        options.refine_focal_length = refine["focal_length"]
        options.refine_principal_point = refine["principal_point"]
        options.refine_extra_params = refine["extra_params"]
        options.refine_sensor_from_rig = refine.get("sensor_from_rig", True)
    return options


def refined_intrinsics(options) -> tuple[dict[str, bool], int]:
    """Which intrinsics the mapper ``options`` refines (focal_length, principal_point, extra_params) and on how
    many threads; None: COLMAP's defaults (the principal point fixed), one thread."""
    if options is None:
        return {"focal_length": True, "principal_point": False, "extra_params": True}, 1
    inner = getattr(options, "incremental_options", options)
    if hasattr(inner, "ba_refine_focal_length"):  # incremental, or the clusters of hierarchical
        return ({"focal_length": bool(inner.ba_refine_focal_length),
                 "principal_point": bool(inner.ba_refine_principal_point),
                 "extra_params": bool(inner.ba_refine_extra_params),
                 "sensor_from_rig": bool(inner.ba_refine_sensor_from_rig)}, int(inner.num_threads))
    ba = options.mapper.bundle_adjustment  # global
    return ({"focal_length": bool(ba.refine_focal_length), "principal_point": bool(ba.refine_principal_point),
             "extra_params": bool(ba.refine_extra_params),
             "sensor_from_rig": bool(options.mapper.refine_sensor_from_rig)}, int(options.num_threads))


#: The scale (px) of the merged model's robust loss (``bundle_adjust_merged``): an observation beyond it counts
#: less than under a squared loss. The refined keypoints' errors are a tenth of it.
MERGE_LOSS_SCALE_PX = 1.0
#: The merged model's adjustment (``bundle_adjust_merged``) with Ceres' inner iterations: after each step every 3D
#: point is re-solved on its own with the cameras held. Plain Levenberg-Marquardt took 49 steps (and 21 rejected)
#: to close the 100-photo walk's chain over every pair, each a little; with inner iterations each step is dearer
#: and goes further, so the stop at a relative decrease of 1e-6 comes too early, and at 1e-7 it lands where the
#: plain adjustment does. That closing on one thread: plain 9.3 s; inner iterations at 1e-6: 12 steps, 4.3 s, pose
#: AUC@5 after the final filter 0.99343 -> 0.99300 (median pose error 0.0280 -> 0.0298 deg); at 1e-7: 4.5 s,
#: 0.99341 (0.0280 deg). The 1,000-photo walk's three merge passes (12 clusters, two threads) take as long either
#: way (460.8 / 470.1 s, AUC@5 0.99436 / 0.99428) (docs/experiments.md, section 50). The final filter's
#: adjustments start at the optimum and gain nothing from them.
MERGE_INNER_ITERATIONS = True
MERGE_FUNCTION_TOLERANCE = 1e-7


def bundle_adjust_merged(reconstruction, num_threads: int, pycolmap, filters=None) -> None:
    """One global bundle adjustment of a model the hierarchical mapper merged from clusters, robust to the
    wrong observations its seams' tracks may hold; then COLMAP's own filter as the mapper's options set it
    (``filters``: their IncrementalMapperOptions, ``filter_max_reproj_error`` and ``filter_min_tri_angle``;
    None: COLMAP's defaults, 4 px and 1.5 deg).

    COLMAP merges its clusters by similarity transforms and stops there, so each cluster
    keeps its own drift and the seams stay where the merge put them: on the generated
    250-photo block (clusters of 125 photos) pose AUC@5 0.939 as merged, 0.981 after this
    adjustment (the incremental mapper: 0.980). The merge's tracks cross the seams only with a tolerance of
    several pixels (``cluster_merge.SEAM_MAX_ERROR_PX``), so the loss is Cauchy's at MERGE_LOSS_SCALE_PX: a
    seam's right observations pull it shut, a wrong match with an error of many pixels weighs little; Ceres'
    inner iterations (MERGE_INNER_ITERATIONS) halve the capture order's closing at 100 photos.
    """
    if reconstruction.num_reg_images() < 2:
        return
    options = adjustment_options(reconstruction, num_threads, pycolmap)
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = MERGE_LOSS_SCALE_PX
    options.ceres.solver_options.use_inner_iterations = MERGE_INNER_ITERATIONS
    options.ceres.solver_options.function_tolerance = MERGE_FUNCTION_TOLERANCE
    pycolmap.bundle_adjustment(reconstruction, options)
    filters = filters or pycolmap.IncrementalMapperOptions()
    pycolmap.ObservationManager(reconstruction).filter_all_points3D(filters.filter_max_reproj_error,
                                                                     filters.filter_min_tri_angle)


#: The final filtered adjustment (``final_filter``): an observation is an outlier when its reprojection error
#: exceeds FINAL_FILTER_SIGMAS robust standard deviations of the model's errors, and never below
#: FINAL_FILTER_MIN_PX (half a photo pixel): 3 sigma leaves about 1 % of Gaussian errors out. The floor was
#: 1 px at first; 0.5 px measured better on every scene tried (docs/experiments.md, section 30).
FINAL_FILTER_SIGMAS = 3.0
FINAL_FILTER_MIN_PX = 0.5
#: Filter-and-adjust rounds at most. A round after the first that finds under FINAL_FILTER_STOP of the
#: observations ends it without adjusting again: on the generated 1,000- and 2,000-photo walks the second round
#: found 105 and 184 of ~1.4 and ~2.9 million, and its adjustment (26 % and 13 % of the filter's time) changed
#: pose AUC@5 by less than 0.0001 (docs/experiments.md, section 43).
FINAL_FILTER_ROUNDS = 3
FINAL_FILTER_STOP = 0.001
#: Points whose rays meet at a smaller angle (deg) go too, as COLMAP's own filter (``filter_min_tri_angle``).
FINAL_FILTER_MIN_TRI_ANGLE = 1.5
#: The median of the norm of a 2D Gaussian error is this many standard deviations (sqrt(2 ln 2)).
_CHI2_MEDIAN = 1.1774


def reprojection_errors(reconstruction) -> np.ndarray:
    """The reprojection error (px) of every observation of ``reconstruction``'s 3D points, image by image."""
    errors = []
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.image(image_id)
        observed = [p for p in image.points2D if p.has_point3D()]
        if not observed:
            continue
        xyz = np.array([reconstruction.point3D(p.point3D_id).xyz for p in observed])
        xy = np.array([p.xy for p in observed])
        cam_points = xyz @ image.cam_from_world().rotation.matrix().T + image.cam_from_world().translation
        projected = reconstruction.camera(image.camera_id).img_from_cam(cam_points, check_cheirality=False)
        errors.append(np.linalg.norm(projected - xy, axis=1))
    return np.concatenate(errors) if errors else np.zeros(0)


def mean_observation_error(reconstruction) -> tuple[float, int]:
    """The mean reprojection error (px) over every observation of ``reconstruction``'s points, and their number:
    ``reprojection_errors``' mean from the points' errors, which COLMAP computes (one Python object per point, not
    per observation). Updates the points' errors."""
    reconstruction.update_point_3d_errors()
    points = reconstruction.points3D.values()
    errors = np.array([(point.error, point.track.length()) for point in points]).reshape(-1, 2)
    observations = int(errors[:, 1].sum())
    return (float(errors[:, 0] @ errors[:, 1]) / observations if observations else 0.0), observations


def final_filter(reconstruction, refine: dict, num_threads: int, pycolmap, fixed_frames=(), fixed_cameras=()) -> dict:
    """Drop the outlying observations of a mapped model and adjust it again, until few are left (in place).

    COLMAP keeps every observation within 4 px (``filter_max_reproj_error``) in its final bundle
    adjustment, with a squared loss. Refined keypoints are good to a fraction of a pixel (median
    reprojection error 0.07 px on the generated 250-photo block), so a 2-4 px observation is a wrong
    match that still bends the model. Each round removes the observations beyond max(FINAL_FILTER_MIN_PX,
    FINAL_FILTER_SIGMAS robust sigma) (sigma from the median error) and adjusts everything once more (a later
    round that removes almost nothing, under FINAL_FILTER_STOP, only removes), the intrinsics as the mapper refined
    them (``refine``: focal_length, principal_point, extra_params);
    ``fixed_frames`` / ``fixed_cameras`` (ids) stay constant, as an extension's earlier ones.
    Pose AUC@5 against the true cameras: generated 250-photo block 0.972 -> 0.993; 47-photo turntable
    ring under a long lens 0.985 -> 0.993 at 640 px (SIFT 0.991), 0.991 -> 0.997 at 1280 px (SIFT 0.998);
    fountain-P11 0.970 -> 0.988 (AUC@1 0.852 -> 0.938: its principal point, tested afterwards, is no
    longer pulled by the outliers) (docs/experiments.md, section 30).
    Returns its entry in the run's record (threshold, removed observations, error before/after, seconds).
    """
    start = time.perf_counter()
    errors = reprojection_errors(reconstruction)
    record = {"observations": int(errors.size), "mean_error_before_px": float(errors.mean()) if errors.size else 0.0,
              "rounds": 0, "removed_observations": 0}
    if reconstruction.num_reg_images() < 2 or errors.size == 0:
        return record
    sigma = float(np.median(errors)) / _CHI2_MEDIAN
    threshold = max(FINAL_FILTER_MIN_PX, FINAL_FILTER_SIGMAS * sigma)
    record.update(sigma_px=round(sigma, 4), threshold_px=round(threshold, 4))
    options = adjustment_options(reconstruction, num_threads, pycolmap, refine)
    for _ in range(FINAL_FILTER_ROUNDS):
        before = reconstruction.compute_num_observations()
        pycolmap.ObservationManager(reconstruction).filter_all_points3D(threshold, FINAL_FILTER_MIN_TRI_ANGLE)
        removed = before - reconstruction.compute_num_observations()
        record["removed_observations"] += int(removed)
        if removed == 0 or (record["rounds"] and removed < FINAL_FILTER_STOP * before):
            break  # what is left moves the model too little to pay for another adjustment
        _adjust(reconstruction, options, fixed_frames, fixed_cameras, pycolmap)
        record["rounds"] += 1
        if removed < FINAL_FILTER_STOP * before:
            break
    mean, observations = mean_observation_error(reconstruction)
    record.update(mean_error_after_px=mean, observations_after=observations,
                  seconds=round(time.perf_counter() - start, 3))
    return record


def _adjust(reconstruction, options, fixed_frames, fixed_cameras, pycolmap) -> None:
    """One bundle adjustment of everything, the given frames' poses and cameras' intrinsics held constant."""
    if not fixed_frames and not fixed_cameras:
        pycolmap.bundle_adjustment(reconstruction, options)
        return
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.reg_image_ids():
        config.add_image(image_id)
    for frame_id in fixed_frames:
        config.set_constant_rig_from_world_pose(frame_id)
    for camera_id in set(fixed_cameras) & {reconstruction.images[i].camera_id for i in reconstruction.reg_image_ids()}:
        config.set_constant_cam_intrinsics(camera_id)
    if not fixed_frames:
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_ceres_bundle_adjuster(options, config, reconstruction).solve()


#: The triangulate-and-adjust passes of the merge (``merge_clusters``), each its seam tolerance (px). The first
#: pass's tracks cross a seam only where the clusters disagree by less than ``cluster_merge.SEAM_MAX_ERROR_PX``;
#: its adjustment pulls the seam in, so the second pass's triangulation finds the tracks the first could not; a
#: seam still off by more (one of a 2,000-photo walk) keeps a few tracks at twice the tolerance, which the third
#: pass's adjustment closes. Widening the second pass instead let in more than it closed. Generated walks, pose
#: AUC@5 after one pass, two and three: 1,000 photos 0.958, 0.994, 0.994; 2,000 photos 0.913, 0.923, 0.978
#: (docs/experiments.md, sections 41 to 44).
MERGE_PASS_TOLERANCES_PX = (SEAM_MAX_ERROR_PX, SEAM_MAX_ERROR_PX, 2 * SEAM_MAX_ERROR_PX)
MERGE_PASSES = len(MERGE_PASS_TOLERANCES_PX)


def merged_model(piece, database: str, image_dir: str, options, scratch: Path, pycolmap, passes: int = MERGE_PASSES,
                 seconds: dict | None = None):
    """The Reconstruction of one merged ``piece`` (``cluster_merge.Piece``): its points triangulated from
    ``database`` with the poses held (``cluster_merge.assemble``), adjusted (``bundle_adjust_merged``), then
    ``passes`` - 1 (at most MERGE_PASSES - 1) times triangulated again from the adjusted poses at that pass's
    tolerance (MERGE_PASS_TOLERANCES_PX) and adjusted again; ``passes`` = 0: the merged poses only, no point (a
    chain the capture order closes afterwards: its check reads the poses, and the closing clears every point and
    triangulates again; 1.2-1.7 s of a 100-photo walk's serial time). ``options``: the
    IncrementalPipelineOptions; ``seconds`` (``triangulate_s``, ``bundle_adjustment_s``) adds up the time."""
    seconds = seconds if seconds is not None else {"triangulate_s": 0.0, "bundle_adjustment_s": 0.0}
    clock = time.perf_counter()
    model = assemble(piece, database, image_dir, options, scratch, pycolmap, triangulate=passes > 0)
    seconds["triangulate_s"] += time.perf_counter() - clock
    for k in range(passes):
        clock = time.perf_counter()
        if k:
            model = triangulate_held(model, database, image_dir, options, scratch, pycolmap,
                                     MERGE_PASS_TOLERANCES_PX[k])
        adjusting = time.perf_counter()
        bundle_adjust_merged(model, options.num_threads, pycolmap, options.mapper)
        seconds["triangulate_s"] += adjusting - clock
        seconds["bundle_adjustment_s"] += time.perf_counter() - adjusting
    return model


def merge_clusters(request: dict, options, pycolmap) -> dict:
    """The models of the clusters mapped on the executor (``request["clusters"]``: their ``model_arrays``),
    merged, triangulated again from the database and adjusted as a whole (``merged_model``), and kept when they
    hold ``min_model_size`` photos. ``request["merge_passes"]``: ``merged_model``'s passes (default MERGE_PASSES);
    ``request["merge"]`` gets the record: pieces, models, passes, seconds of each step. ``options``: the
    hierarchical mapper's, or the incremental mapper's (one model's poses closed over the database: the capture
    order's chain, ``run_mapper(poses_from=...)``)."""
    inner = getattr(options, "incremental_options", options)
    start = time.perf_counter()
    pieces = [piece for arrays in request["clusters"] for piece in pieces_of(arrays)]
    merged = [piece for piece in merge_pieces(pieces) if len(piece.poses) >= int(inner.min_model_size)]
    seconds = {"align_s": time.perf_counter() - start, "triangulate_s": 0.0, "bundle_adjustment_s": 0.0}
    passes = int(request.get("merge_passes", MERGE_PASSES))
    found = {k: merged_model(piece, request["database"], request["image_dir"], inner,
                             Path(request["scratch"]) / f"merge-{k}", pycolmap, passes, seconds)
             for k, piece in enumerate(merged)}
    request["merge"] = {"pieces": len(pieces), "models": [len(piece.poses) for piece in merged], "passes": passes,
                        **{key: round(value, 3) for key, value in seconds.items()}}
    return found


def run(request: dict) -> list:
    """Run the requested mapper; the reconstructions found, largest first."""
    import pycolmap

    quiet_colmap_log(request.get("log_prefix"), pycolmap)
    options, kind = request["options"], request["mapper_type"]
    pycolmap.set_random_seed(max(0, int(request.get("seed", 0))))
    args = (str(request["database"]), str(request["image_dir"]), str(request["scratch"]), options)
    if request.get("clusters") is not None:  # poses mapped elsewhere: clusters, or a chain to close
        found = merge_clusters(request, options, pycolmap)
    elif kind == "incremental":
        found = pycolmap.incremental_mapping(*args, input_path=request.get("input_path") or "",
                                             initial_image_pair_callback=lambda: _event("pair"),
                                             next_image_callback=lambda: _event("image"))
    elif kind == "global":
        found = pycolmap.global_mapping(*args)
    elif kind == "hierarchical":
        found = pycolmap.hierarchical_mapping(*args)
        for reconstruction in found.values():
            bundle_adjust_merged(reconstruction, options.incremental_options.num_threads, pycolmap,
                                 options.incremental_options.mapper)
    else:
        raise ValueError(f"unknown mapper type {kind!r}")
    models = sorted(found.values(), key=lambda r: (-r.num_reg_images(), -r.num_points3D()))
    if request.get("final_filter"):
        refine, threads = refined_intrinsics(options)  # the final filter refines what the mapper refined
        fixed_frames = ()
        fixed_cameras = list(getattr(getattr(options, "incremental_options", options), "constant_cameras", ()))
        if request.get("input_path") and getattr(options, "fix_existing_frames", False):  # --extend: earlier ones
            fixed_frames = list(pycolmap.Reconstruction(request["input_path"]).reg_frame_ids())
        request["records"] = [final_filter(r, refine, threads, pycolmap, fixed_frames, fixed_cameras) for r in models]
    if request.get("log_prefix"):
        pycolmap.logging.set_log_destination(pycolmap.logging.INFO, "")  # flush and close the log
    return models


def main() -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides: on Ctrl-C it kills this process
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})  # inherited blocked from the parent's start
    request = pickle.load(sys.stdin.buffer)
    _die_with_parent(int(request["parent_pid"]))
    models = run(request)
    result = Path(request["result"])
    result.mkdir(parents=True, exist_ok=True)
    for k, reconstruction in enumerate(models):
        (result / str(k)).mkdir(parents=True, exist_ok=True)
        reconstruction.write_binary(str(result / str(k)))
        if request.get("records"):
            (result / f"{k}.json").write_text(json.dumps(request["records"][k]))
    if request.get("merge"):
        (result / "merge.json").write_text(json.dumps(request["merge"]))
    _event(f"done {len(models)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
