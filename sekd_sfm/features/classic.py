"""Classic OpenCV features (SIFT, ORB, AKAZE, BRISK, KAZE) behind the same interface as SEKD."""
from __future__ import annotations

import cv2
import numpy as np

# name -> (factory taking max_keypoints, descriptor size, binary?)
_OPENCV = {
    "sift": (lambda n: cv2.SIFT_create(nfeatures=n), 128, False),
    "orb": (lambda n: cv2.ORB_create(nfeatures=n), 32, True),
    "akaze": (lambda n: cv2.AKAZE_create(), 61, True),
    "brisk": (lambda n: cv2.BRISK_create(), 64, True),
    "kaze": (lambda n: cv2.KAZE_create(), 64, False),
}
CLASSIC_FEATURES = tuple(_OPENCV)
#: Detectors that keep their ``nfeatures`` strongest BEFORE applying a mask (OpenCV's SIFT), which would leave a
#: masked photo short of ``max_keypoints``: with a mask they run uncapped and the cut is made here, after it.
_CAP_BEFORE_MASK = ("sift",)


class OpenCVExtractor:
    """An OpenCV detector/descriptor returning the strongest ``max_keypoints`` by response.

    Outputs keypoints ``N x 2`` float32 (OpenCV pixel centres), scores (detector response),
    descriptors ``N x D`` (float32, or uint8 bytes for binary descriptors), plus the
    keypoint ``scales`` (diameter in px) and ``orientations`` (degrees).
    """

    def __init__(self, name: str, max_keypoints: int):
        factory, self.descriptor_dim, self.binary = _OPENCV[name]
        self.name = name
        self.max_keypoints = max_keypoints
        self.detector = factory(max_keypoints or 0)
        # The detector of masked photos: the same one, unless it would cap before the mask (_CAP_BEFORE_MASK).
        self.masked_detector = factory(0) if name in _CAP_BEFORE_MASK else self.detector

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """``mask``: ``H x W`` bool, True = detect there (None: everywhere); masked keypoints are dropped before
        the strongest ``max_keypoints`` are kept."""
        if mask is None:
            keypoints, descriptors = self.detector.detectAndCompute(image, None)
        else:
            keypoints, descriptors = self.masked_detector.detectAndCompute(image, mask.astype(np.uint8) * 255)
        dtype = np.uint8 if self.binary else np.float32
        if descriptors is None or not keypoints:
            keypoints, descriptors = [], np.zeros((0, self.descriptor_dim), dtype)
        order = np.argsort([-k.response for k in keypoints], kind="stable")[: self.max_keypoints or None]
        keypoints = [keypoints[i] for i in order]
        return {
            "keypoints": np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2),
            "scores": np.array([k.response for k in keypoints], np.float32),
            "descriptors": np.asarray(descriptors)[order].astype(dtype).reshape(-1, self.descriptor_dim),
            "scales": np.array([k.size for k in keypoints], np.float32),
            "orientations": np.array([k.angle for k in keypoints], np.float32),
        }
