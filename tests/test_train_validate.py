"""Validation helpers of training."""
import math

import numpy as np
import pytest

from sekd_sfm.train.validate import mean_pairwise_cosine


@pytest.mark.parametrize("descriptors, expected", [
    ([[1, 0], [0, 1], [1, 0]], 1 / 3),          # pairs: 0, 1, 0
    ([[1, 0], [1, 0]], 1.0),                      # collapsed
    ([[1, 0], [-1, 0]], -1.0),
    ([[0.6, 0.8], [0.8, 0.6], [0, 1], [1, 0]], (0.96 + 0.8 + 0.6 + 0.6 + 0.8 + 0) / 6),
])
def test_mean_pairwise_cosine_by_hand(descriptors, expected):
    assert mean_pairwise_cosine(np.array(descriptors, np.float32)) == pytest.approx(expected, abs=1e-6)


@pytest.mark.parametrize("n", [0, 1])
def test_mean_pairwise_cosine_needs_two(n):
    assert math.isnan(mean_pairwise_cosine(np.zeros((n, 128), np.float32)))
