"""Spatiotemporal attention: a spatial map from the windowed response plus a motion term (ALGORITHM.md 9).

S = exp(relu(norm(sum_d R_d . window) - mean)) - 0.5, plus gamma_t times S shifted along the last motion,
with gamma_t = gamma |delta| / |target size|. The map, an EMA over frames at spatial_learning_rate (1 by
default: this frame's map), multiplies the response. Responses have their zero displacement at the corner, so
the window is rolled to that origin here (the authors' code built that rolled window but applied the centred one).
"""
from __future__ import annotations

import numpy as np


def _round_half_away(x: np.ndarray) -> np.ndarray:
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def to_response_origin(window: np.ndarray) -> np.ndarray:
    """Roll a patch-centred window so its centre lands on the response's zero displacement (H-1, W-1)."""
    height, width = window.shape
    return np.roll(window, ((height - 1) - (height - 1) // 2, (width - 1) - (width - 1) // 2), axis=(0, 1))


def attention_map(response: np.ndarray, window: np.ndarray) -> np.ndarray:
    """exp(max(Pn - mean(Pn), 0)) - 0.5 with Pn the min-max normalised windowed response."""
    windowed = response * window
    low, high = windowed.min(), windowed.max()
    if high > low:
        normalised = (windowed - low) / (high - low)
    else:
        normalised = np.zeros_like(windowed)
    return np.exp(np.maximum(normalised - normalised.mean(), 0.0)) - 0.5


def add_motion(spatial_map: np.ndarray, displacement: np.ndarray, target_hw: np.ndarray,
               gain: float, wraps: bool = False) -> np.ndarray:
    """S + gamma_t roll(S, shift): favour positions further along the last displacement (image pixels).
    The shift is gamma_t times the grid; past half the grid a roll wraps it round behind the motion, so unless
    `wraps` (the authors' code) it stops at the largest displacement the response holds each way."""
    distance = float(np.hypot(*displacement))
    if distance == 0.0:
        return spatial_map
    gamma_t = gain * distance / float(np.hypot(*target_hw))
    relative = displacement / target_hw
    direction = relative / np.hypot(*relative)
    shift = _round_half_away(gamma_t * np.asarray(spatial_map.shape) * direction).astype(int)
    if not wraps:
        reach = (np.asarray(spatial_map.shape) - 1) // 2
        shift = np.clip(shift, -reach, reach)
    return spatial_map + gamma_t * np.roll(spatial_map, tuple(shift), axis=(0, 1))


class SpatiotemporalAttention:
    def __init__(self, learning_rate: float, motion_gain: float, motion_wraps: bool = False):
        self.learning_rate = learning_rate
        self.motion_gain = motion_gain
        self.motion_wraps = motion_wraps
        self.map: np.ndarray | None = None

    def propose(self, response: np.ndarray, window: np.ndarray, displacement: np.ndarray | None,
                target_hw: np.ndarray) -> np.ndarray:
        """This frame's map folded into the EMA: the map to multiply the response with. Nothing is kept until
        keep(): a frame searched in two places keeps the map of the search it takes."""
        fresh = attention_map(response, window)
        if displacement is not None:
            fresh = add_motion(fresh, displacement, target_hw, self.motion_gain, self.motion_wraps)
        if self.map is None:
            return fresh
        return (1 - self.learning_rate) * self.map + self.learning_rate * fresh

    def keep(self, spatial_map: np.ndarray) -> None:
        self.map = spatial_map
