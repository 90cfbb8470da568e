"""Stage 1: images -> features.h5 (``sekd extract``)."""
from __future__ import annotations

import logging
import sys
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .errors import SekdError
from .execution import RayOptions, Result, Stage, check_executor, open_executor
from .features import FeatureConfig, build_extractor
from .files import features as ff
from .files import locking, partstore, shards
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


class ExtractWorker:
    """Extraction's worker (``execution.Stage``): builds the extractor once per process, then extracts batches of
    image keys (paths below ``image_dir``), decoding ahead on a background thread (OpenCV releases the GIL).

    ``described``: the driver's ``describe_config``; a worker that would compute other features
    (another model or package version on a Ray node) refuses to start. ``extractor``: one the
    caller built already (the driver's own; then nothing is built or checked).
    """

    def __init__(self, image_dir: str, config: FeatureConfig, described: dict | None = None, extractor=None):
        self.image_dir, self.config = Path(image_dir), config
        if extractor is None:
            extractor = self._build(config, described)
        self.extractor = extractor
        self.color = getattr(extractor, "color", False)
        self.pool = ThreadPoolExecutor(max_workers=1)

    @staticmethod
    def _build(config: FeatureConfig, described: dict | None):
        try:
            extractor, info = build_extractor(config)
        except (SekdError, OSError) as exc:
            raise SekdError(f"cannot build the extractor: {exc}") from exc
        mine = describe_config(config, extractor, info)
        if described is not None and mine != described:
            raise SekdError(f"would compute other features ({ff.json_attr(mine)}) than the driver "
                            f"({ff.json_attr(described)}); install the same sekd-sfm and weights on every node")
        return extractor

    def __call__(self, keys: list[str]) -> Iterator[Result]:
        paths = [self.image_dir / key for key in keys]
        for key, (_, future) in zip(keys, _prefetched(self.pool, paths, self.config.resize_max, self.color,
                                                       self.config.max_pixels)):
            try:
                yield key, _features_of(self.extractor, future.result()), ""
            except ImageReadError as exc:
                yield key, None, str(exc)


def worker_config(config: FeatureConfig, extractor) -> FeatureConfig:
    """The configuration other processes build: ``auto`` precision and a relative weights path resolved here."""
    weights = str(Path(config.weights).resolve()) if config.weights else None
    if config.feature == "sekd":
        return replace(config, weights=weights, sekd=replace(config.sekd, precision=extractor.model.precision))
    return replace(config, weights=weights)


def _on_cpu(extractor) -> bool:
    """Whether ``extractor`` runs on the CPU (the driver's helper must compute exactly what CPU workers do)."""
    device = getattr(getattr(extractor, "model", None), "device", None) or getattr(extractor, "device", "cpu")
    return str(device) == "cpu"


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
    ray_options: RayOptions | None = None,
) -> Path:
    """Extract features of every image below ``image_dir`` into the HDF5 file ``output``.

    Resumable: images already in ``output`` (or saved as parts by a killed run) are
    skipped. Unreadable images are skipped with a warning (fatal with ``strict``) and
    listed in the file attribute ``failed_images``. Returns ``output``.

    Finished images are saved to ``<output>.parts/`` at least every ``checkpoint_seconds``
    (what a kill loses at most) and written into ``output`` once, at the end (see
    ``featurefile``). Holds ``output``'s lock: a second run on the same file is refused.
    ``executor="ray"`` extracts on a Ray cluster (``execution``), same file.
    """
    config = config or FeatureConfig()
    image_dir, output = Path(image_dir), Path(output)
    check_executor(executor, ray_options)
    with locking.writer_lock(output, "features file"):
        try:
            return _extract(image_dir, output, config, overwrite, strict, num_threads, progress, checkpoint_seconds,
                            executor, ray_options)
        finally:  # the network is gone: what runs next in this process (pairs, matching) needs glibc's own heap rules
            untune_allocator()


def _extract(image_dir: Path, output: Path, config: FeatureConfig, overwrite: bool, strict: bool,
             num_threads: int | None, progress: bool, checkpoint_seconds: float, executor: str = "local",
             ray_options: RayOptions | None = None) -> Path:
    keys = list_images(image_dir)
    set_num_threads(num_threads)
    extractor, model_info = build_extractor(config)
    described = describe_config(config, extractor, model_info)
    attrs = _file_attrs(config, described, extractor, model_info)
    parts = partstore.PartStore(output, max_items=64, max_seconds=checkpoint_seconds)
    partstore.prepare_output(output, attrs, parts, overwrite, compare=("config",))
    done = set(ff.list_keys(output)) | parts.keys() | shards.all_keys(output)
    todo = [k for k in keys if k not in done]
    logger.info("%s: %d images, %d already done, %d to extract", image_dir, len(keys), len(keys) - len(todo), len(todo))
    stage = Stage(
        name=f"extract {config.feature}", worker=ExtractWorker,
        args=(str(image_dir.resolve()), worker_config(config, extractor), described),
        batches=[[key] for key in todo], output=output, write_group=ff.write_image_group,
        unit="img", items="images", verb="extracted", joinable=True, per_task=4, shardable=True,
        built=ExtractWorker(str(image_dir), config, extractor=extractor), driver_may_help=_on_cpu(extractor))
    failed: list[str] = []

    def on_error(key: str, error: str) -> None:
        if strict:
            raise SekdError(f"{error} (--strict)")
        failed.append(key)
        tqdm.write(f"warning: {error}; skipped", file=sys.stderr)

    def failed_images() -> dict:
        order = {key: i for i, key in enumerate(todo)}  # a local run's order, whatever order Ray's tasks finished in
        return {"failed_images": ff.json_attr(sorted(failed, key=order.__getitem__))}

    with open_executor(executor, ray_options) as runner:
        runner.run(stage, parts, on_error, progress=progress, attrs=failed_images)
    # Parts of a killed run are merged too, so count the file, not this run's images.
    total = len(ff.list_keys(output))
    logger.info("%s: %d images written this run, %d failed, %d in the file", output, total - len(done), len(failed), total)
    return output
