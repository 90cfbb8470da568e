"""The methods a benchmark compares, named on the command line.

``sift``, ``orb``, ``akaze``, ``brisk``, ``kaze``: OpenCV. ``disk``, ``aliked``, ``xfeat``:
kornia with local weights. ``sekd``: the default embedded model; ``sekd:own``,
``sekd:authors``: the embedded model of that name (``--model``); ``sekd:PATH``: SEKD with the
checkpoint at PATH (labelled by the file name, e.g. ``sekd:.../sekd_wo_affine.pth`` ->
``sekd_wo_affine``); ``LABEL=sekd:PATH`` sets the label explicitly.
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from ..errors import Interrupted, SekdError
from ..features import FEATURE_TYPES, FeatureConfig
from ..features.peers import PEER_FEATURES, peer_weights_path
from ..files import features as ff
from ..model.inference import SEKDConfig
from ..model.weights import EMBEDDED_MODELS, file_sha256, resolve_weights_path
from ..stages.extract import extract_features

logger = logging.getLogger("sekd")


@dataclass(frozen=True)
class Method:
    """One benchmarked method: a label for tables, a feature type, optional weights."""

    label: str
    feature: str
    weights: str | None = None

    def feature_config(self, max_keypoints: int, precision: str = "auto", threshold: float = 0.4,
                       nms_radius: int = 4) -> FeatureConfig:
        # Only SEKD reads the SEKD settings; leaving them at their defaults for other features
        # keeps those features' cache files valid when a SEKD setting changes.
        # Integer keypoints, as the SEKD paper's protocol and every figure in docs/benchmarks.md.
        sekd = SEKDConfig(max_keypoints=max_keypoints, threshold=threshold, nms_radius=nms_radius, precision=precision,
                          subpixel=False)
        return FeatureConfig(feature=self.feature, max_keypoints=max_keypoints, weights=self.weights,
                             sekd=sekd if self.feature == "sekd" else SEKDConfig(max_keypoints=max_keypoints))


def with_weights(specs, weights: str | None) -> list[str]:
    """Method specs with a bare ``sekd`` (or ``LABEL=sekd``) bound to ``weights`` when given.

    ``--model lite -m sekd`` then means SEKD-Lite, as ``--model`` means in every other
    command; ``sekd:own``, ``sekd:PATH`` and other features stay as written.
    """
    if not weights:
        return list(specs)
    return [f"{spec}:{weights}" if spec.rpartition("=")[2] == "sekd" else spec for spec in specs]


def parse_method(text: str) -> Method:
    """Parse ``[LABEL=]FEATURE[:WEIGHTS]``; SekdError for an unknown feature."""
    label, _, spec = text.rpartition("=") if "=" in text.split(":", 1)[0] else ("", "", text)
    feature, _, weights = spec.partition(":")
    if feature == "sekd" and weights in EMBEDDED_MODELS:  # sekd:own, sekd:authors = the embedded models
        weights = str(EMBEDDED_MODELS[weights])
    if feature not in FEATURE_TYPES:
        raise SekdError(f"unknown method {text!r}: the feature must be one of {', '.join(FEATURE_TYPES)}")
    if not label:
        label = Path(weights).stem if weights else feature
    return Method(label, feature, weights or None)


def available(methods: list[Method]) -> list[Method]:
    """Drop peers whose weights are absent, with one clear message each (they are skipped, not fatal)."""
    kept = []
    for method in methods:
        if method.feature in PEER_FEATURES:
            try:
                peer_weights_path(method.feature, method.weights)
            except SekdError as exc:
                logger.warning("skipping %s: %s", method.label, exc)
                continue
        kept.append(method)
    return kept


def evaluate_each(methods: list[Method], evaluate: Callable[[Method], dict]) -> dict[str, dict]:
    """``label -> evaluate(method)`` for every available method.

    A method that fails is recorded as ``{"error": message}`` and the others go on; Ctrl-C
    (``Interrupted``) stops the whole benchmark instead of being recorded as a failure.
    """
    entries = {}
    for method in available(methods):
        try:
            entries[method.label] = evaluate(method)
        except (Interrupted, KeyboardInterrupt):
            raise
        except Exception as exc:  # noqa: BLE001 - one failing method is reported, not fatal
            logger.warning("%s failed: %s", method.label, exc)
            entries[method.label] = {"error": str(exc)}
    return entries


def cache_file(method: Method, config: FeatureConfig, image_root: Path, cache: Path, tag: str = "") -> Path:
    """``cache/LABEL-HASH.h5``: HASH covers the configuration, the images, ``tag`` and the SEKD model."""
    # The SEKD checkpoint's content, not only its path: shipping a new embedded model (same
    # path, weights None) or overwriting a .pth must not reuse the old model's features.
    model = file_sha256(resolve_weights_path(config.weights)) if config.feature == "sekd" else ""
    root, home = Path(image_root).resolve(), Path(cache).resolve()
    # Images prepared inside the cache (the homography protocol's) count by their place in it, so a
    # copied or moved output folder keeps its features; images elsewhere by their absolute path.
    images = str(root.relative_to(home)) if root.is_relative_to(home) else str(root)
    digest = hashlib.sha1(json.dumps([asdict(config), tag, images, model], sort_keys=True,
                                     default=str).encode()).hexdigest()[:8]
    return Path(cache) / f"{method.label}-{digest}.h5"


def cached_features(method: Method, config: FeatureConfig, image_root: Path, cache: Path, tag: str = "",
                    num_threads: int | None = None) -> tuple[Path, float]:
    """Features of every image below ``image_root`` for one method, cached in ``cache``.

    The file name carries a hash of the feature configuration, the SEKD checkpoint's content
    and ``tag`` (e.g. the image preparation), so a changed setting or model gets a new file. Returns the file and the seconds
    per image measured by the run that extracted it (decode + network + write); ``num_threads``
    CPU threads (None: every usable core) for what this call extracts. A file taken from the
    cache keeps the timing of the run that wrote it, whatever its thread count.
    """
    output = cache_file(method, config, image_root, cache, tag)
    timing = output.with_suffix(".time.json")
    before = len(ff.list_keys(output)) if output.exists() else 0
    start = time.perf_counter()
    extract_features(image_root, output, config, progress=True, num_threads=num_threads)
    extracted = len(ff.list_keys(output)) - before
    if extracted:
        timing.write_text(json.dumps({"seconds_per_image": (time.perf_counter() - start) / extracted}))
    seconds = json.loads(timing.read_text())["seconds_per_image"] if timing.exists() else float("nan")
    return output, seconds
