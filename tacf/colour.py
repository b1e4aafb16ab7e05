"""Colour-histogram likelihood used as a detection window (Staple's model; ALGORITHM.md section 6).

Foreground and background histograms (32 bins per channel) are learnt on the normalised patch; at detection
the per-pixel foreground likelihood, min-max normalised and floored, multiplies the cosine window so that
features on background-coloured pixels count less. TACF does not merge it into the response; the Staple peer
(tacf.staple) does, as Staple itself did.
"""
from __future__ import annotations

import cv2
import numpy as np

from tacf.compiled import compiled


@compiled
def _per_pixel(values: np.ndarray, patch: np.ndarray, shift: int, bits: int) -> np.ndarray:
    """values[bin of each pixel] as float32 (H, W), for an (H, W, C) uint8 patch with C = 3 or 1: the joint bin of
    the channels quantised by `shift`, the first channel varying slowest (bits = log2 of bins per channel), or the
    quantised gray value. One pass over the pixels (the numpy form took five, ~3x the time)."""
    height, width, channels = patch.shape
    out = np.empty((height, width), np.float32)
    for y in range(height):
        for x in range(width):
            index = np.intp(patch[y, x, 0] >> shift)
            if channels == 3:
                index = (index << (2 * bits)) | (np.intp(patch[y, x, 1] >> shift) << bits) | (patch[y, x, 2] >> shift)
            out[y, x] = values[index]
    return out


def _centre_mask(area_hw: np.ndarray, block_hw: np.ndarray, inside: bool) -> np.ndarray:
    """A binary mask on an area-sized grid: the centred block set (inside) or cleared (not inside)."""
    height, width = (int(v) for v in area_hw)
    pad_r, pad_c = (max(int((a - b) // 2), 1) for a, b in zip(area_hw, block_hw))
    mask = np.zeros((height, width), np.uint8) if inside else np.ones((height, width), np.uint8)
    mask[pad_r:height - pad_r, pad_c:width - pad_c] = 1 if inside else 0
    return mask


class ColourModel:
    """Foreground and background colour histograms of the patches the tracker samples. The sizes (height, width)
    share one unit: `patch_hw` is the area the patch covers, `fg_area` the foreground block at its centre and
    `target_hw` the target, left out of the background; the masks they make are resized to the patch."""

    def __init__(self, patch: np.ndarray, patch_hw: np.ndarray, fg_area: np.ndarray, target_hw: np.ndarray,
                 bins: int, learning_rate: float, floor: float):
        if 256 % bins or bins & (bins - 1):
            raise ValueError(f"hist_bins must be a power of two dividing 256, got {bins}")
        self.bins = bins
        self.learning_rate = learning_rate
        self.floor = floor
        patch_wh = patch.shape[1], patch.shape[0]
        self.bg_mask = cv2.resize(_centre_mask(patch_hw, target_hw, inside=False), patch_wh,
                                  interpolation=cv2.INTER_NEAREST)
        self.fg_mask = cv2.resize(_centre_mask(patch_hw, fg_area, inside=True), patch_wh,
                                  interpolation=cv2.INTER_NEAREST)
        self.fg_hist, self.bg_hist = self._histograms(patch)

    def _histograms(self, patch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised joint histograms under the foreground and background masks, flat in _per_pixel's order.

        OpenCV counts them (the first channel varies slowest, as in _per_pixel), in float32, exact up to 2^24
        pixels, ~2x faster than indexing and np.bincount."""
        channels = 1 if patch.ndim == 2 else patch.shape[2]
        hists = []
        for mask in (self.fg_mask, self.bg_mask):
            hist = cv2.calcHist([patch], list(range(channels)), mask, [self.bins] * channels,
                                [0, 256] * channels).ravel().astype(np.float64)
            hists.append(hist / max(hist.sum(), 1.0))
        return hists[0], hists[1]

    def update(self, patch: np.ndarray) -> None:
        """EMA of both histograms on the training patch (the same area the masks were drawn for)."""
        fg_hist, bg_hist = self._histograms(patch)
        rate = self.learning_rate
        self.fg_hist = (1 - rate) * self.fg_hist + rate * fg_hist
        self.bg_hist = (1 - rate) * self.bg_hist + rate * bg_hist

    def pixel_likelihood(self, patch: np.ndarray) -> np.ndarray:
        """P(foreground | colour) of every pixel, fg / (fg + bg) of its bin (0 for colours never seen), float32."""
        total = self.fg_hist + self.bg_hist  # per bin, then one lookup per pixel
        per_bin = np.divide(self.fg_hist, total, out=np.zeros_like(total), where=total > 0).astype(np.float32)
        bits = self.bins.bit_length() - 1
        return _per_pixel(per_bin, patch.reshape(*patch.shape[:2], -1), 8 - bits, bits)

    def likelihood_window(self, patch: np.ndarray, grid_hw: tuple[int, int]) -> np.ndarray:
        """Foreground likelihood on the feature grid, normalised to [floor, 1]."""
        likelihood = cv2.resize(self.pixel_likelihood(patch), (grid_hw[1], grid_hw[0]), interpolation=cv2.INTER_AREA)
        low, high = likelihood.min(), likelihood.max()
        if high <= low:
            return np.ones(grid_hw, np.float32)
        likelihood = (likelihood - low) / (high - low)
        if likelihood.mean() < 0.01:
            return np.ones(grid_hw, np.float32)
        return np.maximum(likelihood, self.floor)
