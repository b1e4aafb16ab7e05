"""From per-feature responses to a displacement: crop, upsample, fuse, find the peak (ALGORITHM.md 7, 7.5)."""
from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np


def crop_centre(response: np.ndarray, size: int) -> np.ndarray:
    """The size x size square of displacements around the label peak at (H-1, W-1), as an ordinary image.

    out[a, b] = R[(a - h - 1) mod H, (b - h - 1) mod W] with h = (size - 1) / 2: the centre of the output is
    displacement zero.
    """
    rows, cols = _crop_indices(response.shape[-2], response.shape[-1], size)
    return response.take(rows, axis=-2).take(cols, axis=-1)


@lru_cache(maxsize=16)
def _crop_indices(height: int, width: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of crop_centre's square, cached per shape: read-only, as they are shared."""
    half = (size - 1) // 2
    rows, cols = (np.arange(size) - half - 1) % height, (np.arange(size) - half - 1) % width
    rows.flags.writeable = cols.flags.writeable = False
    return rows, cols


def upsample(response: np.ndarray, size: int) -> np.ndarray:
    """Bilinear resize of the cropped response to normalised-pixel resolution."""
    return cv2.resize(response.astype(np.float32), (size, size), interpolation=cv2.INTER_LINEAR)


def fusion_weight(response: np.ndarray) -> float:
    """PSR-like confidence 1 - exp(-(max - mean)^2 / (2 var)); 0 for a flat or non-positive response."""
    variance = float(np.var(response, ddof=1))
    peak = float(response.max())
    if variance <= 0.0 or peak <= 0.0:
        return 0.0
    return float(1.0 - np.exp(-((peak - float(response.mean())) ** 2) / (2 * variance)))


def fuse(responses: list[np.ndarray]) -> np.ndarray:
    """sum_M p_M R_M / max(R_M), with the fusion weights p_M normalised to sum to 1."""
    weights = np.array([fusion_weight(r) for r in responses])
    if weights.sum() <= 0:
        weights = np.ones(len(responses))
    weights /= weights.sum()
    fused = np.zeros_like(responses[0])
    for weight, response in zip(weights, responses):
        peak = float(response.max())
        if weight > 0 and peak > 0:
            fused += (weight / peak) * response
    return fused


def peak_offset(response: np.ndarray) -> np.ndarray:
    """(row, col) of the first maximum (column-major, as MATLAB's find) relative to the centre."""
    flat = int(np.argmax(response.T))
    col, row = divmod(flat, response.shape[0])
    centre = (np.asarray(response.shape) - 1) / 2
    return np.array([row, col], dtype=np.float64) - centre
