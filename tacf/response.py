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


def fusion_coefficients(responses: list[np.ndarray]) -> np.ndarray:
    """p_M / max(R_M) for each response, the fusion weights p_M normalised to sum to 1 (0 for a non-positive peak)."""
    weights = np.array([fusion_weight(r) for r in responses])
    if weights.sum() <= 0:
        weights = np.ones(len(responses))
    weights /= weights.sum()
    peaks = np.array([float(r.max()) for r in responses])
    return np.where((weights > 0) & (peaks > 0), weights / np.where(peaks > 0, peaks, 1.0), 0.0)


def fuse(responses: list[np.ndarray], coefficients: np.ndarray | None = None) -> np.ndarray:
    """sum_M p_M R_M / max(R_M); `coefficients` (fusion_coefficients of some other maps) replace the responses' own."""
    if coefficients is None:
        coefficients = fusion_coefficients(responses)
    fused = np.zeros_like(responses[0])
    for coefficient, response in zip(coefficients, responses):
        if coefficient > 0:
            fused += coefficient * response
    return fused


def has_peak(response: np.ndarray) -> bool:
    """Whether the response is finite and not flat. np.argmax of one with a NaN is that NaN's index, of a flat one
    its first cell: either would move the box by the whole search radius up and left."""
    return bool(np.isfinite(response).all() and response.max() > response.min())


def peak_offset(response: np.ndarray) -> np.ndarray:
    """(row, col) of the first maximum (column-major, as MATLAB's find) relative to the centre; (0, 0), no move,
    for a response without a peak (has_peak)."""
    return _first_maximum_offset(response) if has_peak(response) else np.zeros(2)


def _first_maximum_offset(response: np.ndarray) -> np.ndarray:
    flat = int(np.argmax(response.T))
    col, row = divmod(flat, response.shape[0])
    centre = (np.asarray(response.shape) - 1) / 2
    return np.array([row, col], dtype=np.float64) - centre


def subcell_peak_offset(response: np.ndarray) -> np.ndarray:
    """(row, col) of the maximum relative to the centre, refined by a parabola through it and its two neighbours on
    each axis (in the response's own units, e.g. cells); (0, 0) as peak_offset for a response without a peak.
    A bilinear upsampling cannot do this: its maximum always sits on an original sample, so the displacement stays
    whole cells."""
    if not has_peak(response):
        return np.zeros(2)
    offset = _first_maximum_offset(response)
    peak = tuple(int(i) for i in offset + (np.asarray(response.shape) - 1) / 2)
    refined = offset.copy()
    for axis in (0, 1):
        index = peak[axis]
        if 0 < index < response.shape[axis] - 1:
            before, after = list(peak), list(peak)
            before[axis] -= 1
            after[axis] += 1
            low, centre, high = response[tuple(before)], response[peak], response[tuple(after)]
            curvature = low - 2 * centre + high
            if curvature < 0:
                refined[axis] += float(np.clip(0.5 * (low - high) / curvature, -0.5, 0.5))
    return refined
