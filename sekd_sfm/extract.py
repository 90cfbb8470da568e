"""Stage 1: images -> features.h5 (``sekd extract``)."""
from __future__ import annotations

import logging
import sys
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .execution import raycluster as cluster
from .files import shards
from .files import features as ff
from .errors import Interrupted, SekdError
from .features import FeatureConfig, build_extractor
from .files.images import DEFAULT_MAX_PIXELS, ImageReadError, list_images, load_scaled, to_original_pixels
from .model.inference import FastSEKD
from .runtime import package_versions, set_num_threads, untune_allocator

logger = logging.getLogger("sekd")
#: Images decoded ahead of the network, on a background thread (OpenCV releases the GIL).
PREFETCH = 3
#: Keypoint detection noise in pixels of the processed image (hloc's ``detection_noise``; 1 for every feature).
DETECTION_NOISE = 1.0


def describe_config(config: FeatureConfig, extractor, model_info) -> dict:
    """The configuration that determines the features (what must match to resume a file)."""
    described = {"feature": config.feature, "max_keypoints": config.max_keypoints, "resize_max": config.resize_max}
    if model_info:
        described["model_sha256"] = model_info.sha256
    if config.feature == "sekd":
        sekd = asdict(config.sekd)
        sekd.pop("device")
        sekd["precision"] = extractor.model.precision  # "auto" resolved: it changes the numbers
        described["sekd"] = sekd
    return described


def _file_attrs(config: FeatureConfig, described: dict, extractor, model_info) -> dict:
    return {
        "format": ff.FORMAT,
        "format_version": ff.FORMAT_VERSION,
        "feature_type": config.feature,
        "descriptor_dim": extractor.descriptor_dim,
        "descriptor_dtype": "uint8" if extractor.binary else "float32",
        "config": ff.json_attr(described),
        "model_sha256": model_info.sha256 if model_info else "",
        "weights": model_info.path if model_info else "",
        "versions": ff.json_attr(package_versions()),
        # How the network ran (sekd_sfm.model.fused; SEKD_FUSED=0): the numbers differ only by float round-off.
        "network_forward": _network_forward(extractor),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def _network_forward(extractor) -> str:
    """``fused`` / ``eager`` for SEKD's fast path, ``int8`` for the quantized one, ``""`` for other features."""
    model = getattr(extractor, "model", None)
    if isinstance(model, FastSEKD):
        return "fused" if model.fused is not None else "eager"
    return "int8" if getattr(model, "precision", None) == "int8" else ""


def _load(path: Path, resize_max: int | None, color: bool, max_pixels: int | None = DEFAULT_MAX_PIXELS):
    # Above the pixel cap, load_scaled decodes at 1/2, 1/4 or 1/8 size and folds that into (sx, sy).
    return load_scaled(path, resize_max, grayscale=not color, max_pixels=max_pixels)


def _features_of(extractor, loaded) -> dict[str, np.ndarray]:
    (height, width), small, sx, sy = loaded
    result = extractor.extract(small)
    result["keypoints"] = to_original_pixels(result["keypoints"], sx, sy)
    result["image_size"] = np.array([width, height], np.int32)
    # Keypoint noise in original pixels, as hloc records it: 1 px at the processed resolution x the resize scale.
    result["uncertainty"] = np.float32(DETECTION_NOISE * (sx + sy) / 2)
    return result


def _prefetched(pool: ThreadPoolExecutor, paths: list[Path], resize_max: int | None, color: bool,
                max_pixels: int | None = DEFAULT_MAX_PIXELS):
    """Yield ``(path, Future)`` with up to PREFETCH images decoding ahead."""
    queue: deque[tuple[Path, Future]] = deque()
    for path in paths:
        queue.append((path, pool.submit(_load, path, resize_max, color, max_pixels)))
        if len(queue) > PREFETCH:
            yield queue.popleft()
    yield from queue


def extract_features(
    image_dir: str | Path,
    output: str | Path,
    config: FeatureConfig | None = None,
    *,
    overwrite: bool = False,
    strict: bool = False,
    num_threads: int | None = None,
    progress: bool = True,
    checkpoint_seconds: float = 10.0,
    executor: str = "local",
    ray_options: cluster.RayOptions | None = None,
) -> Path:
    """Extract features of every image below ``image_dir`` into the HDF5 file ``output``.

    Resumable: images already in ``output`` (or saved as parts by a killed run) are
    skipped. Unreadable images are skipped with a warning (fatal with ``strict``) and
    listed in the file attribute ``failed_images``. Returns ``output``.

    Finished images are saved to ``<output>.parts/`` at least every ``checkpoint_seconds``
    (what a kill loses at most) and written into ``output`` once, at the end (see
    ``featurefile``). Holds ``output``'s lock: a second run on the same file is refused.
    ``executor="ray"`` extracts on a Ray cluster (``cluster``), same file.
    """
    config = config or FeatureConfig()
    image_dir, output = Path(image_dir), Path(output)
    cluster.check_executor(executor, ray_options)
    with ff.writer_lock(output, "features file"):
        try:
            return _extract(image_dir, output, config, overwrite, strict, num_threads, progress, checkpoint_seconds,
                            executor, ray_options)
        finally:  # the network is gone: what runs next in this process (pairs, matching) needs glibc's own heap rules
            untune_allocator()


def _extract(image_dir: Path, output: Path, config: FeatureConfig, overwrite: bool, strict: bool,
             num_threads: int | None, progress: bool, checkpoint_seconds: float, executor: str = "local",
             ray_options: cluster.RayOptions | None = None) -> Path:
    keys = list_images(image_dir)
    set_num_threads(num_threads)
    extractor, model_info = build_extractor(config)
    described = describe_config(config, extractor, model_info)
    attrs = _file_attrs(config, described, extractor, model_info)
    parts = ff.PartStore(output, max_items=64, max_seconds=checkpoint_seconds)
    ff.prepare_output(output, attrs, parts, overwrite, compare=("config",))
    done = set(ff.list_keys(output)) | parts.keys() | shards.all_keys(output)
    todo = [k for k in keys if k not in done]
    logger.info("%s: %d images, %d already done, %d to extract", image_dir, len(keys), len(keys) - len(todo), len(todo))
    merge = None
    try:
        if executor == "local":
            failed = _run(extractor, image_dir, todo, config, parts, output, strict, progress)
        else:
            with cluster.session(executor if todo else "local", ray_options):  # no connection for nothing to do
                if todo and cluster.driver_merges_while_running(ray_options):
                    merge = ff.Merge(output, parts)  # fed with the workers' chunks as they arrive
                    logger.info("Ray: the driver copies the workers' results into the output as they arrive")
                failed = cluster.extract_on_ray(image_dir, todo, config, described, extractor, parts, output,
                                                strict=strict, progress=progress, options=ray_options, merge=merge)
        parts.flush()  # on disk before the merge: a merge that fails or is killed loses nothing
        ff.finish_run(output, parts, {"failed_images": ff.json_attr(failed)}, what="images", merge=merge)
    finally:
        if merge is not None:
            merge.discard()  # after a failure: the file as it was, the chunks for the next run
    # Parts of a killed run are merged too, so count the file, not this run's images.
    total = len(ff.list_keys(output))
    logger.info("%s: %d images written this run, %d failed, %d in the file", output, total - len(done), len(failed), total)
    return output


def _run(extractor, image_dir, todo, config, parts, output, strict, progress) -> list[str]:
    failed: list[str] = []
    bar = tqdm(total=len(todo), unit="img", desc=f"extract {config.feature}", disable=not progress, dynamic_ncols=True)
    try:
        with ThreadPoolExecutor(max_workers=1) as pool:
            for path, future in _prefetched(pool, [image_dir / k for k in todo], config.resize_max,
                                           getattr(extractor, "color", False), config.max_pixels):
                key = path.relative_to(image_dir).as_posix()
                try:
                    parts.save(key, _features_of(extractor, future.result()))
                except ImageReadError as exc:
                    if strict:
                        raise SekdError(f"{exc} (--strict)") from exc
                    failed.append(key)
                    tqdm.write(f"warning: {exc}; skipped", file=sys.stderr)
                bar.update(1)
    except KeyboardInterrupt:
        bar.close()
        saved = ff.finish_run(output, parts, what="images")
        raise Interrupted(f"interrupted: {saved} more images saved in {output}; run the same command again to resume") from None
    except BaseException:
        ff.keep_parts(parts)  # finished images stay for the next run
        raise
    finally:
        bar.close()
    return failed
