"""``sekd bench scale``: our pipeline and pycolmap's SIFT pipeline on generated scenes of growing size.

For each size N, in ``OUT/n<N>/``:

1. ``scene/``: a generated scene of N photos (``scene.SceneConfig``; about 3% distractors): the
   city block, or with ``layout="ring"`` a turntable ring around an object (no distractors).
2. ``ours/``: ``sfm.reconstruct.reconstruct`` with its defaults (whatever pair selection,
   mapper and camera sharing they choose), run in its own process; its stages (extract,
   pairs, match, database, verification, mapping) are cut out of one sampled timeline.
3. ``pycolmap/``: pycolmap's own pipeline on the same photos: SIFT extraction, SIFT matching
   of the *same pairs* our pipeline chose (exhaustive when it chose all pairs), geometric
   verification and incremental mapping; each stage in its own process. All photos come
   from one camera, so this pipeline is told so (``CameraMode.SINGLE``).

Per stage: wall time, peak RSS, bytes written (``measure``). Per pipeline: registered
scene photos, registered distractors, models, pose AUC@5/10/20 deg over all pairs of scene photos
(relative rotation and translation direction against the generated cameras, the larger
of the two; a pair with an unregistered photo counts as a failure), and the same over
the truly co-visible pairs. Pairs are scored against two ground truths (``scene.py``): every
co-visible pair, and the matchable pairs (pixel overlap >= ``min_overlap`` both ways, seen
within 60 degrees); the retrieval's recall@20 (true neighbours among the 20 retrieved over
min(true neighbours, 20)) uses the matchable ones. Finished sizes are kept (``n<N>/result.json``) and skipped on a
rerun; ``results.json``, ``results.md`` and ``scale.png`` cover every finished size.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ...errors import SekdError
from ...evaluation.metrics import pose_auc
from ...files.atomic import write_atomic
from ...files.locking import exclusive_lock
from ..plotting import save_png
from .measure import Measurement, run_measured
from .projection import growth_exponent, project, projection_markdown
from .scene import SceneConfig, generate_scene, read_covisibility, read_scene

logger = logging.getLogger("sekd")
OUR_STAGES = {"extract": "extract", "pairs": "pairs", "match": "match", "refine": "refine", "database": "import",
              "verification": "verify", "mapping": "map"}
STAGES = ("generate", "extract", "pairs", "match", "refine", "import", "verify", "map")
MB = 1024 * 1024
#: The pairs file of pycolmap's run (COLMAP's imported pairs: "name0 name1" per line).
COLMAP_PAIRS = "pairs-colmap.txt"


@dataclass
class ScaleConfig:
    """Sizes (photos per scene, distractors included) and the scene / baseline settings."""

    sizes: tuple[int, ...] = (250, 500, 1000)
    image_size: int = 640
    #: The scenes' layout (``scene.SceneConfig.layout``): ``block`` or ``ring``, and the cameras' field of view.
    layout: str = "block"
    hfov_deg: float = 60.0
    #: Repeated / mirrored structure of the scenes (``scene.SceneConfig.repeats`` / ``symmetric``).
    repeats: int = 1
    symmetric: bool = False
    spacing: float = 1.5
    seed: int = 0
    baseline: bool = True
    num_threads: int | None = None
    min_overlap: float = 0.1     # ground-truth co-visible pair: shares this fraction of the smaller view
    textures: str | None = None
    #: An earlier benchmark folder whose scenes and pycolmap runs are reused where their inputs are the same
    #: (a variant of our pipeline, e.g. another mapper, then costs only its own run).
    baseline_from: str | None = None
    #: pycolmap's incremental mapper runs up to this many photos; above, the baseline stops after verification.
    #: Its mapping time grows as N^1.6 (measured 250 to 1,000): 47 minutes at 1,000 photos, about 2.5 hours at
    #: 2,000 on 2 cores. None: always.
    baseline_map_max: int | None = 1000


# ----------------------------------------------------------------------------- stages run in child processes

def _generate(scene_dir: str, config: SceneConfig) -> dict:
    path = generate_scene(scene_dir, config, progress=False)
    return {"generation_s": json.loads(Path(path).read_text())["generation_s"]}


def _ours(image_dir: str, work: str, config, num_threads: int | None) -> dict:
    import time

    from ...pipelines.reconstruct import ReconstructionError, reconstruct

    start = time.time()  # after the imports (torch): the stage timeline starts here
    try:
        reconstruct(image_dir, work, config, num_threads=num_threads, progress=False)
    except ReconstructionError as exc:
        return {"failure": str(exc).splitlines()[0], "start": start}
    return {"failure": None, "start": start}


def _colmap_extract(database: str, image_dir: str, max_image_size: int, num_threads: int | None) -> dict:
    import pycolmap  # not sekd_sfm.stages, which loads torch: the baseline's memory is pycolmap's alone

    options = pycolmap.FeatureExtractionOptions()
    options.max_image_size, options.num_threads = max_image_size, num_threads or -1
    pycolmap.extract_features(database, image_dir, camera_mode=pycolmap.CameraMode.SINGLE,
                              extraction_options=options, device=pycolmap.Device.cpu)
    return {}


def _colmap_match(database: str, pairs_path: str | None, num_threads: int | None) -> dict:
    import pycolmap  # not sekd_sfm.stages, which loads torch: the baseline's memory is pycolmap's alone

    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = num_threads or -1
    options.skip_geometric_verification = True  # verification is its own stage, measured apart
    if pairs_path is None:
        pycolmap.match_exhaustive(database, matching_options=options, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = pairs_path
        pycolmap.match_image_pairs(database, matching_options=options, pairing_options=pairing,
                                   device=pycolmap.Device.cpu)
    return {}


def _colmap_verify(database: str, num_threads: int | None) -> dict:
    import pycolmap  # not sekd_sfm.stages, which loads torch: the baseline's memory is pycolmap's alone

    options = pycolmap.GeometricVerifierOptions()
    options.num_threads = num_threads or -1
    pycolmap.geometric_verification(database, verifier_options=options)
    return {}


def _colmap_map(database: str, image_dir: str, model_dir: str, seed: int) -> dict:
    import pycolmap  # not sekd_sfm.stages, which loads torch: the baseline's memory is pycolmap's alone

    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    pycolmap.set_random_seed(seed)
    scratch = Path(model_dir).parent / "mapping-scratch"
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir(parents=True)
    found = pycolmap.incremental_mapping(database, image_dir, str(scratch), options)
    shutil.rmtree(scratch, ignore_errors=True)
    models = sorted(found.values(), key=lambda r: (-r.num_reg_images(), -r.num_points3D()))
    if models:
        Path(model_dir).mkdir(parents=True, exist_ok=True)
        models[0].write_binary(model_dir)
    return {"models": len(models)}


# ----------------------------------------------------------------------------- evaluation

def registered_poses(model_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World-to-camera ``(R, t)`` of the registered images of a COLMAP model folder (empty if none)."""
    if not (model_dir / "images.bin").is_file() and not (model_dir / "images.txt").is_file():
        return {}
    from ...stages.colmap import require_pycolmap
    from ..sfm import poses_of

    return poses_of(require_pycolmap().Reconstruction(str(model_dir)))


def pair_errors(estimated: dict, truth: dict, names: list[str], pairs: np.ndarray) -> np.ndarray:
    """Pose error (deg, max of rotation and translation direction) of each index pair ``P x 2`` of ``names``.

    Pairs with an unregistered image get ``inf``. ``truth`` maps name -> scene.Camera.
    """
    return np.maximum(*pair_rotation_translation_errors(estimated, truth, names, pairs))


def pair_rotation_translation_errors(estimated: dict, truth: dict, names: list[str],
                                     pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rotation, translation-direction)`` errors (deg) of the relative pose of each index pair (``pair_errors``)."""
    if len(pairs) == 0:
        return np.zeros(0), np.zeros(0)
    Rg = np.stack([truth[n].R for n in names])
    tg = np.stack([truth[n].t for n in names])
    known = np.array([n in estimated for n in names])
    Re = np.stack([estimated[n][0] if n in estimated else np.eye(3) for n in names])
    te = np.stack([estimated[n][1] if n in estimated else np.zeros(3) for n in names])
    i, j = pairs[:, 0], pairs[:, 1]

    def relative(R, t):
        Rij = R[j] @ np.transpose(R[i], (0, 2, 1))
        return Rij, t[j] - np.einsum("pab,pb->pa", Rij, t[i])

    (Rr_e, tr_e), (Rr_g, tr_g) = relative(Re, te), relative(Rg, tg)
    cos_r = (np.einsum("pab,pab->p", Rr_e, Rr_g) - 1) / 2  # trace(Re^T Rg) = sum of elementwise products
    rot = np.degrees(np.arccos(np.clip(cos_r, -1, 1)))
    norms = np.linalg.norm(tr_e, axis=1) * np.linalg.norm(tr_g, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_t = np.where(norms > 0, np.einsum("pa,pa->p", tr_e, tr_g) / norms, -1.0)
    trans = np.degrees(np.arccos(np.clip(cos_t, -1, 1)))
    unknown = ~(known[i] & known[j])
    rot[unknown], trans[unknown] = np.inf, np.inf
    return rot, trans


#: What evaluate_model measures of a model (None where no model was made).
MODEL_FIELDS = ("registered", "median_pose_error_deg", "median_rotation_error_deg", "auc5", "auc5_covisible",
                "auc10", "auc10_covisible", "auc20", "auc20_covisible")


def evaluate_model(model_dir: Path, scene: dict, covisible: dict) -> dict:
    """Registered photos, registered distractors and pose AUCs of one pipeline's main model."""
    estimated = registered_poses(model_dir)
    truth = scene["cameras"]
    names = sorted(truth)
    index = {n: k for k, n in enumerate(names)}
    m = len(names)
    all_pairs = np.array([(a, b) for a in range(m) for b in range(a + 1, m)], np.int64).reshape(-1, 2)
    covis = np.array(sorted(tuple(sorted(index[n] for n in p)) for p in covisible), np.int64).reshape(-1, 2)
    rotation, translation = pair_rotation_translation_errors(estimated, truth, names, all_pairs)
    errors, errors_covis = np.maximum(rotation, translation), pair_errors(estimated, truth, names, covis)
    finite = np.isfinite(errors)
    result = {"registered": sum(n in estimated for n in names), "scene_images": m,
              "registered_distractors": sorted(set(estimated) & set(scene["distractors"])),
              "median_pose_error_deg": float(np.median(errors[finite])) if finite.any() else None,
              "median_rotation_error_deg": float(np.median(rotation[finite])) if finite.any() else None}
    for limit in (5, 10, 20):
        result[f"auc{limit}"] = pose_auc(errors.tolist(), limit)
        result[f"auc{limit}_covisible"] = pose_auc(errors_covis.tolist(), limit)
    return result


def pairs_recall(pairs: list[tuple[str, str]], covisible: dict) -> dict:
    """Recall of the ground-truth co-visible pairs by ``pairs``, and the share of ``pairs`` that are co-visible."""
    chosen = {frozenset(p) for p in pairs}
    hit = len(chosen & set(covisible))
    return {"pairs": len(chosen), "covisible_pairs": len(covisible),
            "recall": hit / len(covisible) if covisible else None,
            "precision": hit / len(chosen) if chosen else None}


def retrieval_recall(global_file: Path, names: list[str], truth_pairs: dict, k: int) -> float | None:
    """Recall@k of the retrieval stored in ``global_file`` against ``truth_pairs``; None without the file.

    Per query, found true neighbours among its first ``k`` over ``min(true neighbours, k)``
    (``retrieval.neighbour_recall``); only scene photos are queries and database.
    """
    if not global_file.is_file():
        return None
    from ...stages.retrieval import nearest_neighbors, neighbour_recall

    truth: dict[str, set[str]] = {}
    for a, b in (tuple(p) for p in truth_pairs):
        truth.setdefault(a, set()).add(b)
        truth.setdefault(b, set()).add(a)
    return neighbour_recall(nearest_neighbors(global_file, names, k), truth, k) if truth else None


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) if folder.is_dir() else 0


def _stage_record(m: Measurement) -> dict:
    return {"time_s": round(m.wall_s, 3), "cpu_s": round(m.cpu_s, 2), "peak_rss_mb": round(m.peak_rss / MB, 1),
            "written_mb": round(m.bytes_written / MB, 2)}


# ----------------------------------------------------------------------------- one size

def run_ours(scene_dir: Path, work: Path, config, num_threads: int | None) -> dict:
    """Our pipeline from scratch; per-stage records cut out of one sampled process timeline."""
    # Not at the top: it loads torch, which the baseline's processes (they import this module) never need.
    from ...pipelines.record import read_record

    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    m = run_measured(_ours, (str(scene_dir / "images"), str(work), config, num_threads), work / "measure.json")
    stats = read_record(work) or {}
    timings = {k: v for k, v in stats.get("timings_s", {}).items() if k != "total"}
    start = (m.result or {}).get("start", m.start)
    stages, clock = {}, start
    for stage, seconds in timings.items():
        window = m.window(clock, clock + seconds)
        stages[OUR_STAGES.get(stage, stage)] = {"time_s": round(seconds, 3), "cpu_s": round(window["cpu_s"], 2),
                                                "peak_rss_mb": round(window["peak_rss"] / MB, 1),
                                                "written_mb": round(window["bytes_written"] / MB, 2)}
        clock += seconds
    failure = m.error or (m.result or {}).get("failure")
    features = {}
    if (work / "features.h5").is_file():  # which network made the features: the default model may change
        from ...files.features import read_attrs

        attrs = read_attrs(work / "features.h5")
        features = {"feature": str(attrs.get("feature_type", "")), "model_sha256": str(attrs.get("model_sha256", "")),
                    "weights": Path(str(attrs.get("weights", ""))).name}
    return {"stages": stages, "wall_s": round(m.wall_s - (start - m.start), 2),
            "cpu_s": round(sum(s["cpu_s"] for s in stages.values()), 2),
            "peak_rss_mb": round(m.peak_rss / MB, 1), "written_mb": round(m.bytes_written / MB, 2),
            "disk_mb": round(folder_bytes(work) / MB, 2), "failure": failure, "matches": stats.get("matches"),
            "models": len(stats.get("models") or []), "principal_point": stats.get("principal_point"),
            "config": stats.get("config"), "features": features, "model": str(work / "model")}


def run_pycolmap(scene_dir: Path, work: Path, pairs: list[tuple[str, str]], num_images: int, seed: int,
                 num_threads: int | None, max_image_size: int, map_stage: bool = True) -> dict:
    """pycolmap's SIFT pipeline on the same photos and pairs, each stage in its own process.

    ``map_stage`` False: stop after verification (the record's ``skipped`` lists the stage; no model).
    """
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    database, images = str(work / "database.db"), str(scene_dir / "images")
    exhaustive = len(pairs) == num_images * (num_images - 1) // 2
    pairs_path = None
    if not exhaustive:
        # Imported here, not at the top: sekd_sfm.stages.pairs loads torch, and the baseline's child processes import this module.
        from ...stages.pairs import format_pairs

        pairs_path = work / COLMAP_PAIRS
        pairs_path.write_text(format_pairs(pairs))
    steps = [("extract", _colmap_extract, (database, images, max_image_size, num_threads)),
             ("match", _colmap_match, (database, str(pairs_path) if pairs_path else None, num_threads)),
             ("verify", _colmap_verify, (database, num_threads))]
    if map_stage:
        steps.append(("map", _colmap_map, (database, images, str(work / "model"), seed)))
    stages, failure, wall, cpu, peak, written, models = {}, None, 0.0, 0.0, 0, 0, None
    for stage, target, args in steps:
        m = run_measured(target, args, work / f"measure-{stage}.json")
        stages[stage] = _stage_record(m)
        models = (m.result or {}).get("models", models)
        wall, cpu, peak, written = wall + m.wall_s, cpu + m.cpu_s, max(peak, m.peak_rss), written + m.bytes_written
        if m.error:
            failure = f"{stage}: {m.error}"
            break
    return {"stages": stages, "wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "peak_rss_mb": round(peak / MB, 1),
            "written_mb": round(written / MB, 2), "disk_mb": round(folder_bytes(work) / MB, 2), "failure": failure,
            "matcher": "exhaustive" if exhaustive else "imported pairs", "model": str(work / "model"), "models": models,
            "skipped": [] if map_stage else ["map"]}


def our_config(reconstruct_config) -> dict:
    """Our pipeline's configuration as the run's record keeps it (JSON types), to tell whether a result is current."""
    from ...pipelines.config import config_dict

    return json.loads(json.dumps(config_dict(reconstruct_config), default=str))


def reusable_baseline(previous: dict | None, work: Path, pairs: list[tuple[str, str]], config: ScaleConfig) -> dict | None:
    """The pycolmap result of ``previous`` (an earlier result.json of this size) if it ran on exactly these inputs.

    Same scene settings, same pairs (its pairs file), same pycolmap version: its pipeline is
    deterministic (seeded, one mapping thread) and would give the same model, so only our pipeline reruns.
    """
    from ...runtime import package_versions
    from ...stages.pairs import format_pairs

    if not previous or "pycolmap" not in previous or previous["pycolmap"].get("failure"):
        return None
    settings = previous.get("settings", {})
    same = all(settings.get(k) == getattr(config, k) for k in ("image_size", "spacing", "seed", "textures", "min_overlap"))
    same = same and (settings.get("layout", "block"), settings.get("hfov_deg", 60.0)) == (config.layout, config.hfov_deg)
    same = same and (settings.get("repeats", 1), settings.get("symmetric", False)) == (config.repeats, config.symmetric)
    versions = settings.get("versions", {})
    if not same or versions.get("pycolmap") != package_versions().get("pycolmap"):
        return None
    pairs_file = work / COLMAP_PAIRS
    stored = pairs_file.read_text() if pairs_file.is_file() else None
    if stored != format_pairs(pairs) or not (work / "model").is_dir():
        return None
    return {**previous["pycolmap"], "model": str(work / "model"), "reused_from": str(work)}


def link_scene(source: Path, target: Path, scene_config: SceneConfig) -> bool:
    """Hard-link (else copy) a generated scene of the same configuration from ``source`` to ``target``.

    Returns whether it did; a scene of another configuration is left alone (``target`` is then generated).
    """
    from .scene import _config_record

    try:
        if json.loads((source / "scene.json").read_text()).get("config") != _config_record(scene_config):
            return False
    except (OSError, ValueError):
        return False

    def link(src, dst):
        try:
            os.link(src, dst)
        except OSError:  # another file system
            shutil.copy2(src, dst)

    partial = target.with_name(target.name + ".linking")
    shutil.rmtree(partial, ignore_errors=True)
    shutil.copytree(source, partial, copy_function=link)
    partial.rename(target)  # scene.json appears with the whole folder
    logger.info("%s: scene linked from %s", target, source)
    return True


def run_size(out: Path, size: int, config: ScaleConfig, reconstruct_config, previous: dict | None = None) -> dict:
    """Generate the scene of ``size`` photos and run both pipelines on it; writes ``result.json``.

    ``previous``: this size's earlier result, whose pycolmap run is reused when its inputs are the same.
    """
    scene_dir = out / "scene"
    scene_config = SceneConfig(num_images=size, image_size=config.image_size, spacing=config.spacing,
                               seed=config.seed, textures=config.textures, layout=config.layout,
                               hfov_deg=config.hfov_deg, repeats=config.repeats, symmetric=config.symmetric)
    other = Path(config.baseline_from) / out.name if config.baseline_from else None
    if other is not None and not scene_dir.exists():
        link_scene(other / "scene", scene_dir, scene_config)
    generation = None
    if not (scene_dir / "scene.json").is_file():
        m = run_measured(_generate, (str(scene_dir), scene_config), out / "measure-generate.json")
        if m.error:
            raise SekdError(f"{scene_dir}: scene generation failed: {m.error}")
        generation = _stage_record(m)
    scene = read_scene(scene_dir)
    covisible = read_covisibility(scene_dir, config.min_overlap)
    result = {"size": size, "scene_images": len(scene["cameras"]), "distractors": scene["distractors"],
              "generate": generation or {"time_s": scene["generation_s"]}, "scene": scene["config"]}
    logger.info("n=%d: our pipeline", size)
    ours = run_ours(scene_dir, out / "ours", reconstruct_config, config.num_threads)
    from ...stages.pairs import read_pairs

    pairs = read_pairs(out / "ours" / "pairs.txt") if (out / "ours" / "pairs.txt").is_file() else []
    ours.update(evaluate_model(Path(ours["model"]), scene, covisible))
    result["pairs"] = pairs_recall(pairs, covisible)
    result["pairs"]["mode"] = ((ours.get("config") or {}).get("pairs") or {}).get("mode")
    matchable = read_covisibility(scene_dir, config.min_overlap, matchable=True)
    result["pairs"]["recall_matchable"] = pairs_recall(pairs, matchable)["recall"]
    result["pairs"]["retrieval_recall_at_20"] = retrieval_recall(out / "ours" / "features.global.h5",
                                                                 sorted(scene["cameras"]), matchable, 20)
    result["ours"] = ours
    if config.baseline and pairs:
        base = reusable_baseline(previous, out / "pycolmap", pairs, config)
        if base is None and other is not None and (other / "result.json").is_file():
            base = reusable_baseline(json.loads((other / "result.json").read_text()), other / "pycolmap", pairs, config)
        if base is not None:
            logger.info("n=%d: pycolmap SIFT pipeline ran on the same scene and pairs earlier; its run is reused", size)
        else:
            logger.info("n=%d: pycolmap SIFT pipeline on %d pairs", size, len(pairs))
            map_stage = config.baseline_map_max is None or size <= config.baseline_map_max
            base = run_pycolmap(scene_dir, out / "pycolmap", pairs, size, config.seed, config.num_threads,
                                reconstruct_config.features.resize_max or 3200, map_stage)
        if "map" in base.get("skipped", ()):
            base.update(dict.fromkeys(MODEL_FIELDS), scene_images=result["scene_images"], registered_distractors=[])
        else:
            base.update(evaluate_model(Path(base["model"]), scene, covisible))
        result["pycolmap"] = base
    return result


# ----------------------------------------------------------------------------- whole benchmark

def run_scale_benchmark(output_dir: str | Path, config: ScaleConfig, reconstruct_config=None) -> Path:
    """Every size of ``config`` (finished ones skipped); writes results.json/.md and scale.png. Returns results.json.

    Each size folder is locked while it runs: a second process on the same output folder
    takes the sizes nobody is running (so two processes can share the sizes of one folder)
    and the report covers every finished size.
    """
    from ...pipelines.reconstruct import ReconstructConfig

    reconstruct_config = reconstruct_config or ReconstructConfig()
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    current = our_config(reconstruct_config)
    for size in sorted(config.sizes):
        folder = out / f"n{size}"
        done = folder / "result.json"
        if _finished(done, current):
            logger.info("n=%d: finished earlier (%s), skipped", size, done)
            continue
        folder.mkdir(exist_ok=True)
        with contextlib.ExitStack() as held:
            try:
                held.enter_context(exclusive_lock(folder, "benchmark size folder"))
            except SekdError:
                logger.warning("n=%d: another process is running this size (%s); skipped", size, folder)
                continue
            if _finished(done, current):  # finished by the process that held the lock a moment ago
                continue
            previous = json.loads(done.read_text()) if done.is_file() else None
            if previous:
                logger.info("n=%d: our pipeline's settings changed since %s; it reruns", size, done)
            result = run_size(folder, size, config, reconstruct_config, previous)
            from ...runtime import package_versions, run_record

            result["settings"] = {**asdict(replace(config, sizes=tuple(config.sizes))), "versions": package_versions(),
                                  "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
            result["run"] = run_record()  # commit, version, CPU, command: no table mixes machines silently
            write_atomic(done, json.dumps(result, indent=1, default=str))
    return write_report(out)


def _finished(done: Path, current: dict) -> bool:
    """Whether ``done`` (a size's result.json) exists and our pipeline ran there with the configuration ``current``."""
    if not done.is_file():
        return False
    return (json.loads(done.read_text()).get("ours") or {}).get("config") == current


def load_results(out: Path) -> list[dict]:
    """Every finished size below ``out``, smallest first."""
    results = [json.loads(p.read_text()) for p in out.glob("n*/result.json")]
    return sorted(results, key=lambda r: r["size"])


def exponents(results: list[dict], pipeline: str, key: str = "time_s") -> dict[str, float | None]:
    """Growth exponent of each stage's wall time (``key`` "time_s") or CPU time ("cpu_s"), and of the total."""
    rows = [r for r in results if pipeline in r]
    sizes = [r["size"] for r in rows]
    names = [s for s in STAGES if any(s in r[pipeline]["stages"] for r in rows)]
    fitted = {s: growth_exponent(sizes, [r[pipeline]["stages"].get(s, {}).get(key, 0) for r in rows])
              for s in names}
    whole = [r for r in rows if not r[pipeline].get("skipped")]  # a run that skipped a stage has no total
    fitted["total"] = growth_exponent([r["size"] for r in whole],
                                      [r[pipeline].get("wall_s" if key == "time_s" else "cpu_s", 0) for r in whole])
    return fitted


def write_report(out: Path) -> Path:
    """results.json (every size and the exponents), results.md and scale.png from the finished sizes."""
    results = load_results(out)
    report = {"sizes": [r["size"] for r in results], "results": results,
              "exponents": {p: exponents(results, p) for p in ("ours", "pycolmap")},
              "cpu_exponents": {p: exponents(results, p, "cpu_s") for p in ("ours", "pycolmap")},
              "projection": project(results, STAGES[1:])}
    path = out / "results.json"
    write_atomic(path, json.dumps(report, indent=1, default=str))  # two runs may finish sizes at once
    write_atomic(out / "results.md", scale_markdown(report))
    if results:
        plot_scale(report, out / "scale.png")
    return path


def _f(value, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def scale_markdown(report: dict) -> str:
    """The benchmark's tables: one summary row per size and pipeline, stages per size, growth exponents."""
    rings = any((r.get("scene") or {}).get("layout") == "ring" for r in report["results"])
    scenes = ("Generated turntable rings (N photos of an object from a circle of cameras, no distractors)" if rings
              else "Generated city-block scenes (N photos including ~3% distractors)")
    lines = [(f"{scenes}; our pipeline with its "
              "defaults against pycolmap's SIFT pipeline on the same pairs. AUC over all pairs of scene "
              "photos (an unregistered photo fails its pairs) and over the truly co-visible pairs; models: "
              "how many the mapper made (the scores are the largest's); pose error: the larger of the rotation "
              "and translation-direction errors of a pair, medians over the pairs of registered photos."), "",
             ("| N | pipeline | pairs | retrieval recall@20 | pair recall (matchable / all co-visible) | registered "
              "| models | distractors registered | AUC@5 | AUC@5 co-visible "
              "| median pose err (deg) | median rot. err (deg) | wall (s) | CPU (s) | peak RSS (MB) | written (MB) |"),
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["results"]:
        for name, label in (("ours", "ours"), ("pycolmap", "pycolmap SIFT")):
            if name not in r:
                continue
            p = r[name]
            pr = r["pairs"]
            recall = (f"{_f(pr.get('retrieval_recall_at_20'), 3)} | {_f(pr.get('recall_matchable'), 3)} / "
                      f"{_f(pr['recall'], 3)}") if name == "ours" else "same pairs | same pairs"
            mapped = p["registered"] is not None  # a baseline stopped before mapping has no model
            registered = f"{p['registered']}/{p['scene_images']}" if mapped else "-"
            distractors = f"{len(p['registered_distractors'])}/{len(r['distractors'])}" if mapped else "-"
            models = p.get("models")
            lines.append(f"| {r['size']} | {label} | {pr['pairs']} | {recall} | {registered} "
                         f"| {'-' if models is None or not mapped else models} | {distractors} "
                         f"| {_f(p['auc5'], 3)} | {_f(p['auc5_covisible'], 3)} | {_f(p['median_pose_error_deg'], 2)} "
                         f"| {_f(p.get('median_rotation_error_deg'), 2)} "
                         f"| {_f(p['wall_s'])} | {_f(p.get('cpu_s'))} | {_f(p['peak_rss_mb'], 0)} "
                         f"| {_f(p['written_mb'])} |"
                         + (f" failure: {p['failure']}" if p.get("failure") else "")
                         + (f" (stopped before: {', '.join(p['skipped'])})" if p.get("skipped") else ""))
    models = [f"N = {r['size']}: {r['ours']['features'].get('weights') or '?'}" for r in report["results"]
              if r.get("ours", {}).get("features")]
    if models:
        lines += ["", "SEKD weights of our pipeline: " + ", ".join(models) + "."]
    runs = run_lines(report["results"])
    if runs:
        lines += ["", "Measured: " + "; ".join(runs) + "."]
    lines += ["", "Per stage: wall time (s) / CPU time (s) / peak RSS (MB) / bytes written (MB).", "",
              "| N | pipeline | " + " | ".join(STAGES) + " |", "|---|---|" + "---|" * len(STAGES)]
    for r in report["results"]:
        gen = r.get("generate") or {}
        for name in ("ours", "pycolmap"):
            if name not in r:
                continue
            cells = []
            for stage in STAGES:
                s = gen if stage == "generate" and name == "ours" else r[name]["stages"].get(stage)
                cells.append("-" if not s else f"{_f(s.get('time_s'))} / {_f(s.get('cpu_s'))} / "
                                              f"{_f(s.get('peak_rss_mb'), 0)} / {_f(s.get('written_mb'))}")
            lines.append(f"| {r['size']} | {name} | " + " | ".join(cells) + " |")
    lines += ["", ("Growth exponent b of time ~ N^b (least squares on log-log over the sizes above); CPU time "
                   "is the steadier figure on a shared machine."), "",
              "| pipeline | time | " + " | ".join(STAGES[1:]) + " | total |", "|---|---|" + "---|" * len(STAGES)]
    for key, label in (("exponents", "wall"), ("cpu_exponents", "CPU")):
        for name, fitted in report.get(key, {}).items():
            lines.append(f"| {name} | {label} | " + " | ".join(_f(fitted.get(s), 2) for s in (*STAGES[1:], "total"))
                         + " |")
    projected = projection_markdown(report.get("projection"))
    return "\n".join(lines + ([""] + projected if projected else [])) + "\n"


def run_lines(results: list[dict]) -> list[str]:
    """Where and with what each size ran (``result["run"]``, ``runtime.run_record``): one phrase per machine, commit
    and version, naming its sizes, so a table whose sizes ran on different machines or commits says so."""
    from ...runtime import cpu_text

    groups: dict[tuple, list[int]] = {}
    for r in results:
        run = r.get("run")
        if run:
            groups.setdefault((cpu_text(run.get("cpu", "?")), run.get("commit") or "?", run.get("sekd_sfm", "?")),
                              []).append(r["size"])
    return [f"N = {', '.join(map(str, sizes))} on {cpu}, sekd {version} at commit {commit}"
            for (cpu, commit, version), sizes in groups.items()]


def plot_scale(report: dict, path: Path) -> Path:
    """Log-log wall time and CPU time per stage against N: ours solid, pycolmap dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), sharex=True)
    colours = dict(zip(STAGES[1:], plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    for ax, key, label in ((axes[0], "time_s", "wall time (s)"), (axes[1], "cpu_s", "CPU time (s)")):
        for name, style in (("ours", "-"), ("pycolmap", "--")):
            rows = [r for r in report["results"] if name in r]
            for stage, colour in colours.items():
                points = [(r["size"], r[name]["stages"][stage].get(key, 0)) for r in rows
                          if stage in r[name]["stages"] and r[name]["stages"][stage].get(key, 0) > 0]
                if points:
                    ax.plot(*zip(*points), style, marker="o", color=colour, label=f"{name} {stage}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("photos N")
        ax.set_ylabel(label)
    axes[0].legend(fontsize=7, ncol=2)
    fig.suptitle("Stage cost against collection size (solid: ours, dashed: pycolmap SIFT)")
    fig.tight_layout()
    save_png(fig, path, dpi=120)
    plt.close(fig)
    return path
