"""Stage 1: images -> features.h5 (``sekd extract``)."""
from __future__ import annotations

import logging
import shutil
import sys
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import SekdError
from ..execution import Executor, RayOptions, Result, Stage, using
from ..failures import first_line, is_out_of_memory
from ..features import FeatureConfig, build_extractor
from ..files import features as ff
from ..files import locking, partstore, shards
from ..files.images import (
    DEFAULT_MAX_PIXELS,
    ImageReadError,
    PhotoMask,
    file_sha256,
    kept_at,
    list_images,
    load_scaled,
    mask_path,
    read_mask,
    scale_mask,
    to_original_pixels,
)
from ..model.inference import FastSEKD
from ..runtime import package_versions, set_num_threads, untune_allocator
from .retrieval import global_path

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


def _load(path: Path, resize_max: int | None, color: bool, max_pixels: int | None = DEFAULT_MAX_PIXELS,
          mask_file: Path | None = None) -> tuple[tuple, PhotoMask | None]:
    """The image as ``load_scaled`` returns it, and its mask (None without ``mask_file``)."""
    # Above the pixel cap, load_scaled decodes at 1/2, 1/4 or 1/8 size and folds that into (sx, sy).
    loaded = load_scaled(path, resize_max, grayscale=not color, max_pixels=max_pixels)
    return loaded, None if mask_file is None else read_mask(mask_file, loaded[0])


def _features_of(extractor, loaded, mask: PhotoMask | None = None) -> dict[str, np.ndarray]:
    """The arrays of one photo: ``loaded`` as ``load_scaled`` returns it; ``mask`` its mask, if it has a file."""
    (height, width), small, sx, sy = loaded
    keep = None if mask is None else mask.keep  # H x W at the original size; None: the photo is used whole
    # The extractor gets the mask at its resolution, conservatively (a pixel touching an ignored one is ignored).
    result = extractor.extract(small) if keep is None else extractor.extract(small, scale_mask(keep, small.shape[:2]))
    result["keypoints"] = to_original_pixels(result["keypoints"], sx, sy)
    if keep is not None:
        result = _on_kept_pixels(result, keep)
    result["image_size"] = np.array([width, height], np.int32)
    # Keypoint noise in original pixels, as hloc records it: 1 px at the processed resolution x the resize scale.
    result["uncertainty"] = np.float32(DETECTION_NOISE * (sx + sy) / 2)
    if mask is not None and mask.sha256:
        result.update(_mask_record(mask))
    return result


def _on_kept_pixels(result: dict[str, np.ndarray], keep: np.ndarray) -> dict[str, np.ndarray]:
    """``result`` (per-keypoint arrays, keypoints in original pixels) without keypoints on an ignored pixel of
    ``keep`` (``H x W`` original). The extractors drop those already; this guarantees it against round-off at
    the mask's edge after the resize and the sub-pixel refinement (it drops none on the fountain's photos)."""
    kept = kept_at(keep, result["keypoints"])
    return result if kept.all() else {name: array[kept] for name, array in result.items()}


def _mask_record(mask: PhotoMask) -> dict[str, np.ndarray]:
    """What the feature file records of a photo's mask (``features.MASK_ATTRS``), as 0-d arrays."""
    record = {"mask_sha256": np.array(mask.sha256), "mask_ignored": np.array(mask.ignored, np.float64)}
    if mask.refused:
        record["mask_refused"] = np.array(mask.refused)
    return record


def _prefetched(pool: ThreadPoolExecutor, paths: list[Path], resize_max: int | None, color: bool,
                max_pixels: int | None = DEFAULT_MAX_PIXELS, mask_files: list[Path | None] | None = None):
    """Yield ``(path, Future)`` with up to PREFETCH images (and their masks) decoding ahead."""
    queue: deque[tuple[Path, Future]] = deque()
    for path, mask_file in zip(paths, mask_files or [None] * len(paths)):
        queue.append((path, pool.submit(_load, path, resize_max, color, max_pixels, mask_file)))
        if len(queue) > PREFETCH:
            yield queue.popleft()
    yield from queue


class ExtractWorker:
    """Extraction's worker (``execution.Stage``): builds the extractor once per process, then extracts batches of
    image keys (paths below ``image_dir``), decoding ahead on a background thread (OpenCV releases the GIL).

    ``described``: the driver's ``describe_config``; a worker that would compute other features
    (another model or package version on a Ray node) refuses to start. ``masks``: the masks
    folder (``MASKS/<key>.png``, docs/masks.md) or None. ``extractor``: one the caller built
    already (the driver's own; then nothing is built or checked).
    """

    def __init__(self, image_dir: str, config: FeatureConfig, described: dict | None = None, masks: str | None = None,
                 extractor=None):
        self.image_dir, self.config = Path(image_dir), config
        self.masks = Path(masks) if masks else None
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
        mask_files = [mask_path(self.masks, key) for key in keys] if self.masks else None
        for key, (_, future) in zip(keys, _prefetched(self.pool, paths, self.config.resize_max, self.color,
                                                       self.config.max_pixels, mask_files)):
            try:
                loaded, mask = future.result()
                if mask is not None and mask.refused:  # logged where it is found: a Ray worker's log reaches the driver
                    logger.warning("warning: %s", mask.refused)
                arrays = _features_of(self.extractor, loaded, mask)
            except ImageReadError as exc:
                yield key, None, str(exc)
                continue
            except (MemoryError, RuntimeError) as exc:
                if not (isinstance(exc, MemoryError) or is_out_of_memory(exc)):
                    raise
                # One photo too large for this machine's memory must not stop the others (nor block the resume).
                yield key, None, (f"{self.image_dir / key}: out of memory extracting it ({first_line(exc)[:80]}); "
                                  "lower --resize-max or --max-pixels for it")
                continue
            yield key, arrays, ""


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
    executor: str | Executor = "local",
    ray_options: RayOptions | None = None,
    masks: str | Path | None = None,
) -> Path:
    """Extract features of every image below ``image_dir`` into the HDF5 file ``output``.

    Resumable: images already in ``output`` (or saved as parts by a killed run) are
    skipped. Unreadable images are skipped with a warning (fatal with ``strict``) and
    listed in the file attribute ``failed_images``. Returns ``output``.

    ``masks``: a folder of masks, COLMAP's convention (docs/masks.md): photo ``NAME``'s is
    ``masks/NAME.png``, zero = ignore; keypoints on ignored pixels are dropped before the
    strongest ``max_keypoints`` are kept. The file records each mask's SHA-256, so a photo
    whose mask changed (or appeared, or went) since it was extracted is extracted again.

    Finished images are saved to ``<output>.parts/`` at least every ``checkpoint_seconds``
    (what a kill loses at most) and written into ``output`` once, at the end (see
    ``files.partstore``). Holds ``output``'s lock: a second run on the same file is refused.
    ``executor``: an open executor (a pipeline's ``run.executor``), or the name of one to open for this call
    (``"ray"`` extracts on a Ray cluster with ``ray_options``, ``execution``); the same file either way.
    """
    config = config or FeatureConfig()
    image_dir, output = Path(image_dir), Path(output)
    masks = Path(masks) if masks is not None else None
    # Opened (and so checked) before the lock: a wrong executor setting leaves no file behind.
    with using(executor, ray_options) as runner, locking.writer_lock(output, "features file"):
        try:
            return _extract(image_dir, output, config, overwrite, strict, num_threads, progress, checkpoint_seconds,
                            runner, masks)
        finally:  # the network is gone: what runs next in this process (pairs, matching) needs glibc's own heap rules
            untune_allocator()


def _extract(image_dir: Path, output: Path, config: FeatureConfig, overwrite: bool, strict: bool,
             num_threads: int | None, progress: bool, checkpoint_seconds: float, executor: Executor,
             masks: Path | None = None) -> Path:
    keys = list_images(image_dir)
    check_masks(masks, keys, image_dir)
    set_num_threads(num_threads)
    extractor, model_info = build_extractor(config)
    described = describe_config(config, extractor, model_info)
    attrs = _file_attrs(config, described, extractor, model_info) | _masks_attr(output, masks, new=True)
    parts = partstore.PartStore(output, max_items=64, max_seconds=checkpoint_seconds)
    partstore.prepare_output(output, attrs, parts, overwrite, compare=("config",))
    changed = _masks_changed(output, parts, keys, masks, executor)
    done = (set(ff.list_keys(output)) | parts.keys() | shards.all_keys(output)) - set(changed)
    todo = [k for k in keys if k not in done]
    logger.info("%s: %d images, %d already done, %d to extract", image_dir, len(keys), len(keys) - len(todo), len(todo))
    mask_dir = str(masks.resolve()) if masks else None
    stage = Stage(
        name=f"extract {config.feature}", worker=ExtractWorker,
        args=(str(image_dir.resolve()), worker_config(config, extractor), described, mask_dir),
        batches=[[key] for key in todo], output=output, write_group=ff.write_image_group,
        unit="img", items="images", verb="extracted", joinable=True, per_task=4, shardable=True,
        built=ExtractWorker(str(image_dir), config, masks=mask_dir, extractor=extractor),
        driver_may_help=_on_cpu(extractor))
    failed: list[str] = []

    def on_error(key: str, error: str) -> None:
        if strict:
            raise SekdError(f"{error} (--strict)")
        failed.append(key)
        tqdm.write(f"warning: {error}; skipped", file=sys.stderr)

    def failed_images() -> dict:
        order = {key: i for i, key in enumerate(todo)}  # a local run's order, whatever order Ray's tasks finished in
        return {"failed_images": ff.json_attr(sorted(failed, key=order.__getitem__)),
                **_masks_attr(output, masks, new=False)}

    executor.run(stage, parts, on_error, progress=progress, attrs=failed_images)
    # Parts of a killed run are merged too, so count the file, not this run's images.
    total = len(ff.list_keys(output))
    logger.info("%s: %d images written this run, %d failed, %d in the file", output, total - len(done), len(failed), total)
    return output


def check_masks(masks: Path | None, keys: list[str], image_dir: Path | None = None) -> None:
    """SekdError when ``masks`` is not a folder, or lies inside ``image_dir`` (its PNGs would be taken for photos);
    one warning when it holds no mask for any photo (a likely typo)."""
    if masks is None:
        return
    if not masks.is_dir():
        raise SekdError(f"--masks {masks}: not a folder; give the folder of the masks (MASKS/NAME.png for photo NAME)")
    if image_dir is not None and masks.resolve().is_relative_to(image_dir.resolve()):
        raise SekdError(f"--masks {masks}: inside the image folder {image_dir}, where its masks would be taken for "
                        "photos; move it beside the image folder")
    if keys and not any(mask_path(masks, key).is_file() for key in keys):
        logger.warning("warning: %s: holds no mask for any of the %d photos (expected e.g. %s); every photo is used "
                       "whole. A typo in --masks?", masks, len(keys), mask_path(masks, keys[0]))


def _masks_attr(output: Path, masks: Path | None, *, new: bool) -> dict[str, str]:
    """The file attribute naming the masks folder: set by a run with masks; emptied by a run without them on a file
    that had them (``new``: for a file about to be created, which has none); absent otherwise, as before masks."""
    if masks is not None:
        return {ff.MASKS: str(masks.resolve())}
    return {ff.MASKS: ""} if not new and _had_masks(output) else {}


def _had_masks(output: Path) -> bool:
    """Whether a run with masks wrote ``output`` (its ``masks`` attribute names a folder)."""
    try:
        return bool(ff.read_attrs(output, role="output").get(ff.MASKS, ""))
    except SekdError:
        return False


def _current_sha256(masks: Path | None, key: str) -> str:
    """SHA-256 of the photo's mask file now ("" without one, or when it cannot be read: the worker says why)."""
    try:
        return file_sha256(mask_path(masks, key)) if masks is not None else ""
    except OSError:
        return ""


def changed_masks(output: Path, masks: Path | None, keys: list[str] | None = None) -> list[str]:
    """The photos (of ``keys``, default all) in the feature file ``output`` whose mask is not the one they were
    extracted with: changed, added or removed (``masks`` None: every photo extracted with a mask). [] when
    ``output`` is missing or not a sekd feature file (nothing there to extract again)."""
    if not Path(output).is_file() or (masks is None and not _had_masks(output)):
        return []
    try:
        recorded = ff.mask_records(output)
    except OSError:
        return []
    return [key for key in (recorded if keys is None else keys)
            if key in recorded and recorded[key] != _current_sha256(masks, key)]


def _masks_changed(output: Path, parts: partstore.PartStore, keys: list[str], masks: Path | None,
                   executor: Executor) -> list[str]:
    """``changed_masks`` of a run about to resume ``output``, with what a killed run left (parts, shards) merged
    in first (their records are read there); the global descriptors of ``output`` go when a photo changes."""
    if masks is None and not _had_masks(output):
        return []  # a file never made with masks: resumed exactly as before masks existed
    partstore.merge_parts(output, parts)  # nothing to do (and no copy) when the killed run left nothing
    changed = changed_masks(output, masks, keys)
    if not changed:
        return changed
    if executor.virtual_merge:
        raise SekdError(f"{output}: the masks of {len(changed)} photo(s) changed since they were extracted (first: "
                        f"{changed[0]}); --ray-merge virtual cannot replace features in place: use --ray-merge copy "
                        "for this run, or --overwrite")
    what = ("have another mask than when they were extracted (changed, added or removed)" if masks is not None
            else "were extracted with masks, and no --masks is given now")
    logger.warning("warning: %s: %d photo(s) %s, first %s: extracting them again (matches made from this file before "
                   "are stale for them: match again with --overwrite)", output, len(changed), what, changed[0])
    _forget_global_descriptors(output)
    return changed


def _forget_global_descriptors(output: Path) -> None:
    """Delete the retrieval's global descriptors of ``output`` (``retrieval.global_path``): made from the local
    descriptors of photos extracted again, they would be reused as they are. Pairing makes them again."""
    path = global_path(output)
    path.unlink(missing_ok=True)
    shutil.rmtree(path.with_name(path.name + ".parts"), ignore_errors=True)
