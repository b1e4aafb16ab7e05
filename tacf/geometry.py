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
from scipy.signal.windows import hann


def round_half_up(x):
    """Halves rounded up: MATLAB's round for non-negative values (numpy's round is half-to-even). Negative values
    occur too (subwindow's top-left corner near the top and left borders; areas of thin targets before their
    floor), and there a half goes up, -2.5 to -2, where MATLAB's round gives -3."""
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

    def cosine_window(self) -> np.ndarray:
        """MATLAB's hann(rows) * hann(cols)' over the filter grid (symmetric: zero at the borders), float32."""
        rows, cols = self.filter_hw
        return np.outer(hann(rows, sym=True), hann(cols, sym=True)).astype(np.float32)

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


def resize_auto(patch: np.ndarray, out_hw, fast: bool = False) -> np.ndarray:
    """Resize a sampled patch to out_hw (rows, cols).

    fast=False is mexResize 'auto' as ALGORITHM.md 3.2 ports it: bilinear when the width grows, area averaging
    otherwise (the authors' compiled mexResize compares the new width with the old height, a quirk not reproduced).
    fast=True (TrackerConfig.fast_resize) halves the patch by exact 2x2 means while it is at least twice the output
    on both axes (OpenCV's integer area path; an odd size first repeats its last row or column), then samples that
    level bilinearly where the patch's own geometry puts each output pixel: a mipmap, which neither shifts nor
    stretches the content. Enlargements are the same either way. OpenCV's general area resize runs a scalar loop
    over weight tables: a 586x528 colour crop to 216x192 takes 1.1 ms that way and 0.25 ms this way. On real frames
    the two differ by 0.3 grey levels on average (mean absolute difference) for shrinks under 1.3x and by 1-2 for
    larger ones (tests/test_geometry.py); the tracker's accuracy is unchanged within its noise (docs/decisions.md).
    A shrink of 2x or more on one axis alone (DSST's scale patches of tall or wide targets) is not halved: one
    bilinear sample, which aliases (5.5 grey levels from area averaging on person12_1's); halving each axis on its
    own was measured and not adopted (docs/decisions.md).
    """
    rows, cols = int(out_hw[0]), int(out_hw[1])
    if patch.shape[0] == rows and patch.shape[1] == cols:
        return patch
    if not fast:
        interp = cv2.INTER_LINEAR if cols > patch.shape[1] else cv2.INTER_AREA
        return cv2.resize(patch, (cols, rows), interpolation=interp)
    level, factor = patch, 1
    while level.shape[0] >= 2 * rows and level.shape[1] >= 2 * cols:
        odd_rows, odd_cols = level.shape[0] % 2, level.shape[1] % 2
        if odd_rows or odd_cols:  # the border pixel repeated, as resizes do beyond the border
            level = cv2.copyMakeBorder(level, 0, odd_rows, 0, odd_cols, cv2.BORDER_REPLICATE)
        level = cv2.resize(level, (level.shape[1] // 2, level.shape[0] // 2), interpolation=cv2.INTER_AREA)
        factor *= 2
    if factor == 1:
        return cv2.resize(patch, (cols, rows), interpolation=cv2.INTER_LINEAR)
    # Output pixel x samples the patch at (x + 0.5) s - 0.5 with s = patch size / output size, as a resize would:
    # that is the level at (x + 0.5) s / factor - 0.5, the padding of odd sizes notwithstanding.
    scale_x, scale_y = patch.shape[1] / (cols * factor), patch.shape[0] / (rows * factor)
    to_level = np.array([[scale_x, 0.0, 0.5 * scale_x - 0.5], [0.0, scale_y, 0.5 * scale_y - 0.5]])
    return cv2.warpAffine(level, to_level, (cols, rows), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


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


# A crop of more pixels than this (a box about as large as a 4K frame: its search area, context sample and scale
# patches) is shrunk while it is cut. Cut whole at full resolution, with its replicated borders, a frame-sized box
# took 0.45 s a frame and 640 MB on 3840x2160, and 1.5 GB on 6000x4000. Smaller crops, all those of the UAV
# benchmarks' frames, are cut as before, pixel for pixel.
LARGE_CROP_PIXELS = 1 << 22


def sample_patch(image: np.ndarray, top_left, size_hw, out_hw, fast_resize: bool = False) -> np.ndarray:
    """The rectangle at integer top_left (row, col) of size_hw, borders replicated (crop_replicate), resized to
    out_hw (resize_auto). Over LARGE_CROP_PIXELS, and at least four times out_hw on both axes, the rectangle is
    first averaged over blocks of f x f pixels (f a power of two): inside the image over its pixels, beyond its
    borders over the replicated border pixels (a block across a border counts as beyond it). No full-resolution
    copy of the rectangle is made."""
    height, width = int(size_hw[0]), int(size_hw[1])
    factor = 1      # doubled while the crop is large, and stays twice out_hw once shrunk by the doubled factor
    while (height * width > LARGE_CROP_PIXELS * factor**2 and height >= 4 * factor * int(out_hw[0])
           and width >= 4 * factor * int(out_hw[1])):
        factor *= 2
    if factor == 1:
        return resize_auto(crop_replicate(image, top_left, size_hw), out_hw, fast_resize)
    small_hw = (height // factor, width // factor)
    rows = _blocks_inside(int(top_left[0]), small_hw[0], image.shape[0], factor)
    cols = _blocks_inside(int(top_left[1]), small_hw[1], image.shape[1], factor)
    return resize_auto(_shrunk_crop(image, rows, cols, factor, small_hw), out_hw, fast_resize)


def _shrunk_crop(image: np.ndarray, rows, cols, factor: int, small_hw) -> np.ndarray:
    """sample_patch's crop shrunk by `factor`: the mean of each block inside the image, and beyond its borders
    the means of the replicated border pixels (as a block of the crop cut whole would have)."""
    (row0, top, n_rows), (col0, left, n_cols) = rows, cols
    row_span, col_span = slice(row0, row0 + n_rows * factor), slice(col0, col0 + n_cols * factor)
    last_row, last_col = image.shape[0] - 1, image.shape[1] - 1

    def block_means(pixels: np.ndarray, hw) -> np.ndarray:
        if 0 in hw:                 # no whole block in the image on this axis: all lie beyond a border
            return np.empty((*hw, *image.shape[2:]), image.dtype)
        return cv2.resize(pixels, (hw[1], hw[0]), interpolation=cv2.INTER_AREA).reshape(*hw, *image.shape[2:])

    small = np.empty((*small_hw, *image.shape[2:]), image.dtype)
    inner_rows, inner_cols = slice(top, top + n_rows), slice(left, left + n_cols)
    below, right = top + n_rows, left + n_cols
    small[inner_rows, inner_cols] = block_means(image[row_span, col_span], (n_rows, n_cols))
    small[:top, inner_cols] = block_means(image[:1, col_span], (1, n_cols))
    small[below:, inner_cols] = block_means(image[last_row:, col_span], (1, n_cols))
    small[inner_rows, :left] = block_means(image[row_span, :1], (n_rows, 1))
    small[inner_rows, right:] = block_means(image[row_span, last_col:], (n_rows, 1))
    small[:top, :left], small[:top, right:] = image[0, 0], image[0, last_col]
    small[below:, :left], small[below:, right:] = image[last_row, 0], image[last_row, last_col]
    return small


def _blocks_inside(start: int, blocks: int, limit: int, factor: int) -> tuple[int, int, int]:
    """Of `blocks` blocks of `factor` pixels from `start`: the first pixel, index and count of those lying within
    [0, limit). With none inside, the index is the count of blocks starting before 0 (those repeat pixel 0, the
    rest the last one)."""
    first = min(blocks, max(0, (factor - 1 - start) // factor))     # ceil(-start / factor)
    end = min(blocks, (limit - start) // factor)
    return start + first * factor, first, max(end - first, 0)


def subwindow(image: np.ndarray, pos: np.ndarray, model_hw, sample_hw, fast_resize: bool = False) -> np.ndarray:
    """getSubwindow: a sample_hw window centred on pos, border-replicated, resized to model_hw (sample_patch)."""
    size = np.maximum(np.asarray(sample_hw, dtype=np.float64), 2)
    count = np.floor(size)
    top_left = round_half_up(pos + 1 - size / 2)
    return sample_patch(image, top_left, count, model_hw, fast_resize)
