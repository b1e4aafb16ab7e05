"""Dimensional attention: a weight per feature channel from its training self-response (ALGORITHM.md 8).

z_d = mean(R_d) + max(R_d), normalised to mean 1; s_d = max(z_d - t, 0) + beta; an EMA over frames,
renormalised to mean 1. Channels whose filter answers its own training sample weakly are damped.
"""
from __future__ import annotations

import numpy as np


class DimensionalAttention:
    def __init__(self, channels: int, threshold: float, floor: float, learning_rate: float):
        self.threshold = threshold
        self.floor = floor
        self.learning_rate = learning_rate
        self.weights = np.ones(channels)

    def update(self, self_response_maxima: np.ndarray, self_response_means: np.ndarray) -> None:
        """Blend in the weights given by the fresh self-responses' maxima and means (C,); applied from the next
        frame."""
        channels = len(self_response_maxima)
        activation = self_response_maxima + self_response_means
        total = activation.sum()
        if not np.isfinite(total) or total <= 0:
            return
        activation = channels * activation / total
        fresh = np.maximum(activation - self.threshold, 0.0) + self.floor
        blended = (1 - self.learning_rate) * self.weights + self.learning_rate * fresh
        self.weights = channels * blended / blended.sum()
