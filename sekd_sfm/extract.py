"""Stage 1: images -> features.h5 (``sekd extract``)."""
from __future__ import annotations

import logging
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import featurefile as ff
from .errors import Interrupted, SekdError
from .features import FeatureConfig, build_extractor
from .images import (
    ImageReadError,
    list_images,
    read_image,
    resize_max_side,
    to_original_pixels,
)
from .runtime import package_versions, set_num_threads

logger = logging.getLogger("sekd")
#: Images decoded ahead of the network, on a background thread (OpenCV releases the GIL).
PREFETCH = 3


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
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def _load(path: Path, resize_max: int | None, color: bool):
    image = read_image(path, grayscale=not color)
    small, sx, sy = resize_max_side(image, resize_max)
    return image.shape[:2], small, sx, sy


def _features_of(extractor, loaded) -> dict[str, np.ndarray]:
    (height, width), small, sx, sy = loaded
    result = extractor.extract(small)
    result["keypoints"] = to_original_pixels(result["keypoints"], sx, sy)
    result["image_size"] = np.array([width, height], np.int32)
    return result


def _prefetched(pool: ThreadPoolExecutor, paths: list[Path], resize_max: int | None, color: bool):
    """Yield ``(path, Future)`` with up to PREFETCH images decoding ahead."""
    queue: deque[tuple[Path, Future]] = deque()
    for path in paths:
        queue.append((path, pool.submit(_load, path, resize_max, color)))
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
    checkpoint_seconds: float = 60.0,
) -> Path:
    """Extract features of every image below ``image_dir`` into the HDF5 file ``output``.

    Resumable: images already in ``output`` (or saved as parts by a killed run) are
    skipped. Unreadable images are skipped with a warning (fatal with ``strict``) and
    listed in the file attribute ``failed_images``. Returns ``output``.
    """
    config = config or FeatureConfig()
    image_dir, output = Path(image_dir), Path(output)
    keys = list_images(image_dir)
    set_num_threads(num_threads)
    extractor, model_info = build_extractor(config)
    described = describe_config(config, extractor, model_info)
    attrs = _file_attrs(config, described, extractor, model_info)
    parts = ff.PartStore(output)
    ff.prepare_output(output, attrs, parts, overwrite, compare=("config",))
    done = set(ff.list_keys(output)) | set(parts.load_all())
    todo = [k for k in keys if k not in done]
    logger.info("%s: %d images, %d already done, %d to extract", image_dir, len(keys), len(keys) - len(todo), len(todo))
    failed = _run(extractor, image_dir, todo, config, parts, output, strict, progress, checkpoint_seconds)
    ff.merge_parts(output, parts, {"failed_images": ff.json_attr(failed)})
    # Parts are also merged every checkpoint_seconds, so count the file, not the last merge.
    total = len(ff.list_keys(output))
    logger.info("%s: %d images written this run, %d failed, %d in the file", output, total - len(done), len(failed), total)
    return output


def _run(extractor, image_dir, todo, config, parts, output, strict, progress, checkpoint_seconds) -> list[str]:
    failed: list[str] = []
    last_merge = time.monotonic()
    bar = tqdm(total=len(todo), unit="img", desc=f"extract {config.feature}", disable=not progress, dynamic_ncols=True)
    try:
        with ThreadPoolExecutor(max_workers=1) as pool:
            for path, future in _prefetched(pool, [image_dir / k for k in todo], config.resize_max,
                                           getattr(extractor, "color", False)):
                key = path.relative_to(image_dir).as_posix()
                try:
                    parts.save(key, _features_of(extractor, future.result()))
                except ImageReadError as exc:
                    if strict:
                        raise SekdError(f"{exc} (--strict)") from exc
                    failed.append(key)
                    tqdm.write(f"warning: {exc}; skipped")
                bar.update(1)
                if time.monotonic() - last_merge > checkpoint_seconds:
                    ff.merge_parts(output, parts)
                    last_merge = time.monotonic()
    except KeyboardInterrupt:
        bar.close()
        saved = ff.merge_parts(output, parts)
        raise Interrupted(f"interrupted: {saved} more images saved in {output}; run the same command again to resume") from None
    finally:
        bar.close()
    return failed
