"""Feature extractors behind one interface, so every later stage treats them alike.

An extractor has ``name``, ``descriptor_dim``, ``binary``, optionally ``color`` (wants RGB
``H x W x 3`` instead of grayscale) and
``extract(uint8 image, mask=None) -> {'keypoints' N x 2, 'scores' N, 'descriptors' N x D, ...}``;
``mask`` (``H x W`` bool, True = detect there) drops the keypoints on ignored pixels before the
strongest ``max_keypoints`` are kept (docs/masks.md).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ..errors import SekdError
from ..files.images import DEFAULT_MAX_PIXELS
from ..model.inference import SEKDConfig, SEKDExtractor
from ..model.weights import ModelInfo, file_sha256, load_model
from ..runtime import resolve_device
from .classic import CLASSIC_FEATURES, OpenCVExtractor
from .peers import PEER_FEATURES, KorniaPeer

FEATURE_TYPES = ("sekd",) + CLASSIC_FEATURES + PEER_FEATURES


@dataclass
class FeatureConfig:
    """Everything that determines the features of an image (recorded in the output file)."""

    feature: str = "sekd"
    max_keypoints: int = 2000
    resize_max: int | None = None
    #: Pixel cap: larger images are decoded at 1/2, 1/4 or 1/8 size (None: no cap). Not part of
    #: the recorded config: it only changes images that would otherwise exhaust memory.
    max_pixels: int | None = DEFAULT_MAX_PIXELS
    sekd: SEKDConfig = field(default_factory=SEKDConfig)
    weights: str | None = None


def build_extractor(config: FeatureConfig):
    """Instantiate the extractor; returns ``(extractor, ModelInfo or None)``."""
    if config.feature == "sekd":
        net, info = load_model(config.weights)
        config.sekd.max_keypoints = config.max_keypoints
        extractor = SEKDExtractor(net, config.sekd)
        extractor.name = "sekd"
        return extractor, info
    if config.feature in CLASSIC_FEATURES:
        return OpenCVExtractor(config.feature, config.max_keypoints), None
    if config.feature in PEER_FEATURES:
        peer = KorniaPeer(config.feature, config.max_keypoints, config.weights, resolve_device(config.sekd.device).type)
        return peer, ModelInfo(str(peer.weights_path), file_sha256(peer.weights_path), {})
    raise SekdError(f"unknown feature type {config.feature!r}; choose from {', '.join(FEATURE_TYPES)}")


__all__ = ["FEATURE_TYPES", "FeatureConfig", "ModelInfo", "build_extractor"]
