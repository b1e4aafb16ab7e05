"""Search-area geometry and patch sampling (ALGORITHM.md sections 2, 3 and step 13 of section 7).

Positions are (row, col) target centres in 0-based image pixels and sizes are (height, width), both as float
arrays of shape (2,). The authors' MATLAB code is 1-based; with pos0 = pos1 - 1 every formula below keeps its
form, so only the indexing changes.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft as sfft


def round_half_up(x):
    """MATLAB's round for the non-negative values used here (numpy's round is half-to-even)."""
    return np.floor(np.asarray(x, dtype=np.float64) + 0.5)


def floor_odd(x):
    """Largest odd integer <= x."""
    return 2 * np.floor((np.asarray(x) - 1) / 2) + 1


def search_padding(target_sz: np.ndarray, fixed_area: float) -> float:
    """TACF's adaptive padding, fixed for the whole sequence: big targets get less context."""
    area = float(np.prod(target_sz))
    if area >= fixed_area:
        return 1.0
    if area >= 50.0**2:
        return 2.5
    return 3.0


@dataclass(frozen=True)
class TargetAreas:
    """Background / foreground areas in image pixels and their resize factor to the normalised grid."""

    bg_area: np.ndarray
    fg_area: np.ndarray
    resize_factor: float  # normalised pixels per image pixel ("arf")

    @classmethod
    def around(cls, target_sz: np.ndarray, padding: float, image_hw: tuple[int, int], fixed_area: float,
               inner_padding: float) -> "TargetAreas":
        avg = float(np.sum(target_sz)) / 2
        bg = round_half_up(target_sz + avg * padding)
        bg = np.minimum(bg, np.asarray(image_hw, dtype=np.float64) - 1)
        bg -= np.mod(bg - target_sz, 2)  # keep (bg - target) even so the target sits centred
        fg = round_half_up(target_sz - inner_padding * avg)
        fg = np.maximum(fg, 1)
        fg += np.mod(bg - fg, 2)
        return cls(bg, fg, float(np.sqrt(fixed_area / np.prod(bg))))


@dataclass(frozen=True)
class NormalisedGrid:
    """The fixed working grid of a sequence, set at initialisation (ALGORITHM.md section 2, steps 6-10)."""

    patch_hw: np.ndarray  # norm_bg_area: the sample is resized to this many pixels
    filter_hw: tuple[int, int]  # cf_size: feature and filter grid in cells
    target_hw: np.ndarray  # norm_target_sz (Staple's inversion, inflated for padding > 1 on purpose)
    response_size: int  # norm_delta: side of the square, upsampled response in normalised pixels
    crop_cells: int  # side of the cropped square response in cells (odd)
    sample_growth: np.ndarray  # how much larger than bg_area the sampled area is (1 unless fast_fft)

    @classmethod
    def from_areas(cls, areas: TargetAreas, cell_size: int, fast_fft: bool = False) -> "NormalisedGrid":
        """The authors' grid; with fast_fft, the filter grid grows to the next 2-3-5-smooth size.

        FFTs over a grid with a large prime factor (57 x 43 in the worked example) cost several times those
        over a slightly larger smooth one (60 x 45): the search area then grows by a few per cent, with the
        target's normalised size, the response square and the labels unchanged.
        """
        natural = round_half_up(areas.bg_area * areas.resize_factor)
        patch = natural
        if fast_fft:
            cells = [sfft.next_fast_len(int(n // cell_size), real=True) for n in natural]
            patch = np.array(cells, dtype=np.float64) * cell_size
        filt = (int(patch[0] // cell_size), int(patch[1] // cell_size))
        nb_h, nb_w = natural
        target = round_half_up([0.75 * nb_h - 0.25 * nb_w, 0.75 * nb_w - 0.25 * nb_h])
        target = np.maximum(target, cell_size)
        radius = int(np.min(np.floor((natural - target) / 2)))
        radius = max(radius, cell_size)
        response = 2 * radius + 1
        crop = int(floor_odd(response / cell_size))
        crop = max(1, min(crop, int(floor_odd(min(filt)))))
        return cls(patch, filt, target, response, crop, patch / natural)


def resize_auto(patch: np.ndarray, out_hw) -> np.ndarray:
    """mexResize 'auto': bilinear when enlarging, area averaging when shrinking."""
    rows, cols = int(out_hw[0]), int(out_hw[1])
    if patch.shape[0] == rows and patch.shape[1] == cols:
        return patch
    interp = cv2.INTER_LINEAR if cols > patch.shape[1] else cv2.INTER_AREA
    return cv2.resize(patch, (cols, rows), interpolation=interp)


def crop_replicate(image: np.ndarray, top_left, size_hw) -> np.ndarray:
    """Pixels of the rectangle at integer top_left (row, col) of size_hw, borders replicated."""
    top, left, height, width = int(top_left[0]), int(top_left[1]), int(size_hw[0]), int(size_hw[1])
    first_row, first_col = max(top, 0), max(left, 0)
    end_row, end_col = min(top + height, image.shape[0]), min(left + width, image.shape[1])
    if first_row < end_row and first_col < end_col:  # overlaps the image: slice, then replicate the borders
        inside = image[first_row:end_row, first_col:end_col]
        margins = (first_row - top, top + height - end_row, first_col - left, left + width - end_col)
        return cv2.copyMakeBorder(inside, *margins, cv2.BORDER_REPLICATE) if any(margins) else inside
    # entirely outside the image: every pixel repeats the nearest border pixel
    rows = np.clip(np.arange(top, top + height), 0, image.shape[0] - 1)
    cols = np.clip(np.arange(left, left + width), 0, image.shape[1] - 1)
    return image[rows[:, None], cols[None, :]]


def subwindow(image: np.ndarray, pos: np.ndarray, model_hw, sample_hw) -> np.ndarray:
    """getSubwindow: a sample_hw window centred on pos, border-replicated, resized to model_hw."""
    size = np.maximum(np.asarray(sample_hw, dtype=np.float64), 2)
    count = np.floor(size)
    top_left = round_half_up(pos + 1 - size / 2)
    patch = crop_replicate(image, top_left, count)
    return resize_auto(patch, model_hw)
