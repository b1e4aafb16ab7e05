"""Contextual attention: context patches as hard negatives, weighted by PME ratios (ALGORITHM.md 10, paper A).

Every `interval` frames the patches above, left of, below and right of the target are added to the HOG
filter's denominator. Each patch's penalty grows with how strongly the filter responds to it (its challenge
factor c_s = PME(R_s) / PME(R_object)), so distractors that look like the target are suppressed hardest.
"""
from __future__ import annotations

import numpy as np


def median(values: np.ndarray):
    """np.median of all values, by one partition: np.median's NaN pass and generic mean make it ~8x slower on
    a 101 x 101 response. A NaN gives some value here, not NaN (pme then returns 0 from its energy)."""
    flat = values.ravel()
    half = flat.size // 2
    if flat.size % 2:
        return np.partition(flat, half)[half]
    # the mean of the two middle values in their dtype, as np.median (NumPy 1.x made (low + high) / 2 a float64)
    return np.partition(flat, [half - 1, half])[half - 1:half + 1].mean()


def pme(response: np.ndarray) -> float:
    """Peak-to-median energy: (R_max - R_med)^2 / mean((R - R_med)^2); 0 for a flat response."""
    median_value = median(response)
    energy = float(np.mean((response - median_value) ** 2))
    if energy <= 0.0 or not np.isfinite(energy):
        return 0.0
    return float((response.max() - median_value) ** 2 / energy)


def context_offsets(target_hw: np.ndarray) -> np.ndarray:
    """(row, col) offsets of the four context patches: up, left, down, right, one current target size away.

    The authors' code keeps the initial size forever; scaling with the target keeps the patches adjacent.
    """
    height, width = target_hw
    return np.array([[-height, 0.0], [0.0, -width], [height, 0.0], [0.0, width]])


class ContextualAttention:
    def __init__(self, interval: int, penalty_total: float, challenge_floor: float, penalty_rate: float,
                 lambda2: float):
        self.interval = interval
        self.penalty_total = penalty_total
        self.challenge_floor = challenge_floor
        self.penalty_rate = penalty_rate
        self.sqrt_lambda2 = float(np.sqrt(lambda2))
        self.penalties = np.full(4, penalty_total / 4)  # one per context patch, context_offsets' order

    def is_context_frame(self, frame_number: int) -> bool:
        """Frames 1, 1 + interval, 1 + 2 interval, ... (1-based), as in the authors' code."""
        return (frame_number - 1) % self.interval == 0

    def update_penalties(self, object_pme: float, context_pmes: np.ndarray) -> None:
        """p_s = total c_s^2 / sum_j c_j^2 with c_s = PME(R_s) / PME(R_0), floored, then an EMA."""
        if object_pme <= 0.0:
            return
        challenge = np.maximum(np.asarray(context_pmes) / object_pme, self.challenge_floor)
        fresh = self.penalty_total * challenge**2 / np.sum(challenge**2)
        self.penalties = self.penalty_rate * fresh + (1 - self.penalty_rate) * self.penalties

    def feature_scales(self) -> np.ndarray:
        """P_s = sqrt(lambda2) p_s, applied to the context features before the kernel (as the code does)."""
        return self.sqrt_lambda2 * self.penalties
