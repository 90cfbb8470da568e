"""Feature extractors behind one interface, so every later stage treats them alike.

An extractor has ``name``, ``descriptor_dim``, ``binary`` and
``extract(gray uint8 H x W) -> {'keypoints' N x 2, 'scores' N, 'descriptors' N x D, ...}``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ..inference import SEKDConfig, SEKDExtractor
from ..weights import ModelInfo, load_model
from .classic import CLASSIC_FEATURES, OpenCVExtractor

FEATURE_TYPES = ("sekd",) + CLASSIC_FEATURES


@dataclass
class FeatureConfig:
    """Everything that determines the features of an image (recorded in the output file)."""

    feature: str = "sekd"
    max_keypoints: int = 2000
    resize_max: int | None = None
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
    raise ValueError(f"unknown feature type {config.feature!r}; choose from {', '.join(FEATURE_TYPES)}")


__all__ = ["FEATURE_TYPES", "FeatureConfig", "ModelInfo", "build_extractor"]
