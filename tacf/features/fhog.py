"""Felzenszwalb fHOG, 31 channels, laid out as Piotr Dollar's ``gradientMex`` computes it (ALGORITHM.md 4.1).

Settings are those TACF uses: 18 contrast-sensitive orientations (nOrients 9, full circle), hard orientation
binning (softBin -1), bilinear spatial binning with the 8/7 boundary-cell factor, 2x2 block normalisation,
truncation at ``clip`` and no border crop. The all-zero 32nd channel of the original is dropped.

Everything is vectorised, over a batch of same-sized images as well: ``fhog_batch`` computes N images in one
pass (the DSST scale filter needs 31 small patches per sample, where the fixed per-call cost dominates), and
``fhog`` is its N = 1 case. Large images go through in chunks of about CHUNK_PIXELS pixels. Images never mix: gradients stop at each image's border and every image has its own
histogram bins, so each image's result is bit for bit what ``fhog`` gives for it alone. Constants that depend
only on the image size (each pixel's four target cells and bilinear weights) or on nothing (the orientation
lookup table) are computed once and cached.

Orientation binning follows the C code step by step: cos(theta) is truncated to the 10000-step acos table,
pi is added for gy < 0, and the bin is floor(theta * 18 / (2 pi) + 0.5) in float32. All of this is folded
into one lookup table indexed by the truncated cosine and the sign of gy, so the per-pixel work is a single
table lookup. A purely vertical gradient with gy < 0 sits exactly on a bin boundary (theta = 3 pi / 2):
evaluated as (theta * 18) / (2 pi), as ALGORITHM.md 4.1 writes it, it gives 13.99999, i.e. bin 13 like the
measured compiled original. Multiplying by a float32-rounded 18 / (2 pi), as the C source reads, gives bin 14
instead, and a plain `g++ -O2` build of gradientMex.cpp does give 14: the bin-13 build presumably folded the
constant differently. Over the whole table this is the only entry where the two evaluation orders disagree;
with it switched, this module matches such a build to ~1e-4 on real patches (rare single-pixel bin flips
from the approximate reciprocal square root aside).

Known deviations from the compiled original, below 1e-3 relative (ALGORITHM.md, open question 4): the
magnitude is an exact square root, not the SSE approximate reciprocal square root, so a flat image gives
exact zeros rather than 1e-10-sized values, and cell sums are accumulated in float64 (np.bincount), not float32.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

N_ORIENTS = 9  # contrast-insensitive orientations; the sensitive ones are twice as many
N_SENSITIVE = 2 * N_ORIENTS
N_CHANNELS = N_SENSITIVE + N_ORIENTS + 4
TEXTURE_FACTOR = np.float32(0.2357)
BOUNDARY_FACTOR = 8.0 / 7.0  # boundary cells collect only 7/8 of an interior cell's bilinear weight
PI32 = np.float32(3.14159265)  # the C code's PI, as float32
ACOS_STEPS = 10000  # the C acos table holds acos(i / 10000)
ACOS_GUARD = 10  # extra table entries each side, absorbing rounding beyond +-1
TABLE_SIZE = 2 * (ACOS_STEPS + ACOS_GUARD)
# Pixels per vectorised pass: beyond ~50k the per-pixel temporaries fall out of the L2 cache and a batch of
# 200x200 patches runs ~40% slower per pixel than the same patches one at a time.
CHUNK_PIXELS = 50_000


def fhog(image: np.ndarray, cell_size: int = 4, clip: float = 0.2) -> np.ndarray:
    """fHOG of ``image`` as float32 ``(31, H // cell_size, W // cell_size)``, C-contiguous.

    ``image`` is HxW or HxWxC (float32; 0..1 or 0..255, the scale only changes the effect of the
    normalisation epsilon). Channels 0-17 are contrast-sensitive orientations, 18-26 contrast-insensitive,
    27-30 texture (one per block normaliser). Gradients use the whole image; only the pixels inside the
    full cells are binned. A grid only one cell high or wide (possible for thin DSST scale patches) is
    normalised as if that cell row or column were duplicated; the C code reads raw energies there instead.
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        raise ValueError(f"expected an HxW or HxWxC image, got shape {image.shape}")
    return fhog_batch(image[None], cell_size, clip)[0]


def fhog_batch(images: np.ndarray, cell_size: int = 4, clip: float = 0.2) -> np.ndarray:
    """fHOG of N same-sized images at once, float32 ``(N, 31, H // cell_size, W // cell_size)``, C-contiguous.

    ``images`` is NxHxW or NxHxWxC. Each image is computed on its own, exactly as ``fhog`` would (gradients
    stop at each image's border, cells and normalisers never mix images), so ``fhog_batch(images)[i]`` equals
    ``fhog(images[i])`` bit for bit; one call replaces N small calls and their fixed per-call cost.
    """
    images = _as_nhwc_float32(images)
    rows, cols = images.shape[1] // cell_size, images.shape[2] // cell_size
    if rows < 1 or cols < 1:
        raise ValueError(f"images {images.shape[1:3]} are smaller than one {cell_size}x{cell_size} cell")
    per_chunk = max(1, CHUNK_PIXELS // (images.shape[1] * images.shape[2]))
    if len(images) > per_chunk:
        return np.concatenate([_fhog_chunk(images[i:i + per_chunk], cell_size, clip, rows, cols)
                               for i in range(0, len(images), per_chunk)])
    return _fhog_chunk(images, cell_size, clip, rows, cols)


def _fhog_chunk(images: np.ndarray, cell_size: int, clip: float, rows: int, cols: int) -> np.ndarray:
    """fhog_batch of one chunk, in one vectorised pass."""
    gx, gy, squared = _max_channel_gradients(images)
    used = (slice(None), slice(0, rows * cell_size), slice(0, cols * cell_size))
    magnitude, table_index = _magnitude_and_table_index(gx[used], gy[used], squared[used])
    sensitive = _spatial_histograms(magnitude, table_index, cell_size, rows, cols)
    return _normalise_and_truncate(sensitive, cell_size, np.float32(clip))


def _as_nhwc_float32(images: np.ndarray) -> np.ndarray:
    images = np.asarray(images, dtype=np.float32)
    if images.ndim == 3:
        return images[..., None]
    if images.ndim != 4:
        raise ValueError(f"expected NxHxW or NxHxWxC images, got shape {images.shape}")
    return images


def _gradients(images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel (gx, gy) of NxHxWxC images: central difference x0.5 inside, one-sided on each image's border.

    Plain numpy on purpose: OpenCV's filters are multi-threaded, which costs more than it saves on a
    patch this small when the cores are shared.
    """
    gx = _axis_gradient(images.swapaxes(0, 2)).swapaxes(0, 2)
    gy = _axis_gradient(images.swapaxes(0, 1)).swapaxes(0, 1)
    return gx, gy


def _axis_gradient(array: np.ndarray) -> np.ndarray:
    """Gradient along axis 0, computed in float32 as (next - previous) * 0.5; other axes are independent."""
    grad = np.empty_like(array)
    np.subtract(array[2:], array[:-2], out=grad[1:-1])
    grad[1:-1] *= np.float32(0.5)
    np.subtract(array[1], array[0], out=grad[0])
    np.subtract(array[-1], array[-2], out=grad[-1])
    return grad


def _max_channel_gradients(images: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(gx, gy, gx^2 + gy^2), each NxHxW, of the colour channel with the largest squared magnitude.

    Squares are float32 as in the C code, since they decide ties; on a tie the first channel wins.
    """
    gx, gy = _gradients(images)
    squared = gx * gx
    squared += gy * gy
    if images.shape[3] == 1:
        return gx[..., 0], gy[..., 0], squared[..., 0]
    best_squared = squared[..., 0].copy()
    for c in range(1, images.shape[3]):
        np.maximum(best_squared, squared[..., c], out=best_squared)
    # Index of the first channel reaching the maximum (uint8 arithmetic is the cheapest here),
    # then one flat gather per gradient.
    channel = np.zeros(best_squared.shape, dtype=np.uint8)
    undecided = np.ones(best_squared.shape, dtype=np.uint8)
    for c in range(images.shape[3] - 1):
        undecided &= (squared[..., c] != best_squared).view(np.uint8)
        channel += undecided
    flat = _pixel_starts(gx.shape) + channel.ravel()
    return (gx.ravel().take(flat).reshape(best_squared.shape),
            gy.ravel().take(flat).reshape(best_squared.shape), best_squared)


@lru_cache(maxsize=16)
def _pixel_starts(shape: tuple[int, ...]) -> np.ndarray:
    """Flat index of channel 0 of every pixel of a C-ordered array of ``shape`` (channels last)."""
    return _read_only(np.arange(0, int(np.prod(shape)), shape[-1]))


@lru_cache(maxsize=1)
def _acos_table() -> np.ndarray:
    """float32 acos(i / 10000) for i in [-10010, 10009], clamped below pi as in the C table."""
    i = np.arange(-ACOS_STEPS - ACOS_GUARD, ACOS_STEPS + ACOS_GUARD)
    cosine = i.astype(np.float32) / np.float32(ACOS_STEPS)  # float32 division, as in the C code
    table = np.arccos(np.clip(cosine.astype(np.float64), -1.0, 1.0)).astype(np.float32)
    table[i < -ACOS_STEPS] = PI32
    table[i >= ACOS_STEPS] = 0.0
    # The C code clamps every entry below pi - 1e-6 so that theta + pi stays below 2 pi.
    np.minimum(table, PI32 - np.float32(1e-6), out=table)
    return _read_only(table)


@lru_cache(maxsize=1)
def _orientation_bins() -> np.ndarray:
    """Hard orientation bin for each (sign of gy, truncated cosine) pair, flat int array of 2 * TABLE_SIZE.

    Entry j + TABLE_SIZE / 2 is for gy >= 0 and cosine index j: theta = acos(j / 10000). The next
    TABLE_SIZE entries are for gy < 0, where the C code looks up -j and adds pi. The bin is
    floor(theta * 18 / (2 pi) + 0.5) evaluated left to right in float32, which puts theta = 3 pi / 2 in bin
    13 as the compiled original does; 18 wraps to 0.
    """
    table = _acos_table()
    cosine_index = np.arange(TABLE_SIZE) - TABLE_SIZE // 2
    mirrored = table[np.clip(TABLE_SIZE // 2 - cosine_index, 0, TABLE_SIZE - 1)]  # the entry for -j
    theta = np.concatenate([table, mirrored + PI32])
    scaled = theta * np.float32(N_SENSITIVE) / (np.float32(2.0) * PI32) + np.float32(0.5)
    return _read_only(scaled.astype(np.intp) % N_SENSITIVE)


@lru_cache(maxsize=16)
def _bin_offsets(n_cells: int) -> np.ndarray:
    """_orientation_bins() scaled to the start of each bin's plane in the flat (18, rows, cols) histogram."""
    return _read_only(_orientation_bins() * n_cells)


def _read_only(array: np.ndarray) -> np.ndarray:
    """Cached arrays are shared between calls, so they are frozen."""
    array.flags.writeable = False
    return array


def _magnitude_and_table_index(gx: np.ndarray, gy: np.ndarray, squared: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray]:
    """Gradient magnitude and each pixel's index into _orientation_bins()."""
    magnitude = np.sqrt(squared)
    with np.errstate(divide="ignore"):
        inverse = np.minimum(np.float32(1.0) / magnitude, np.float32(1e10))  # flat pixels: gx * 1e10 = 0
    cosine_index = (gx * inverse * np.float32(ACOS_STEPS)).astype(np.intp)  # astype truncates like (int)
    # For gy < 0 the C code reads the table at -cosine_index; the second half of the lookup holds that.
    cosine_index += np.where(gy < 0, TABLE_SIZE + TABLE_SIZE // 2, TABLE_SIZE // 2)
    return magnitude, cosine_index


@lru_cache(maxsize=16)
def _bilinear_layout(cell_size: int, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat target-cell indices and weights, shape (4, rows*cell, cols*cell), of each pixel's 4 cells.

    A pixel at column c has cell coordinate u = (c + 0.5) / cell - 0.5 and goes to cells floor(u) and
    floor(u) + 1 with weights 1 - frac(u) and frac(u); likewise for rows. Targets outside the grid get
    weight 0 (and a harmless in-range index). The weights also carry the 1 / cell^2 magnitude factor and
    the 8/7 boundary-cell factor (twice for corner cells).
    """
    row_cells, row_weights = _axis_cells(rows, cell_size)
    col_cells, col_weights = _axis_cells(cols, cell_size)
    indices, weights = [], []
    for row_cell, row_weight in zip(row_cells, row_weights):
        for col_cell, col_weight in zip(col_cells, col_weights):
            valid = (row_cell[:, None] >= 0) & (col_cell[None, :] >= 0)
            indices.append(np.where(valid, row_cell[:, None] * cols + col_cell[None, :], 0))
            weights.append(np.where(valid, np.outer(row_weight, col_weight), 0.0) / cell_size**2)
    # float32 weights: the product with the magnitude is then as cheap as the C code's float32 one.
    return _read_only(np.stack(indices)), _read_only(np.stack(weights).astype(np.float32))


def _axis_cells(n_cells: int, cell_size: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Along one axis: each pixel's two target cells, with weights; targets outside the grid are -1."""
    u = (np.arange(n_cells * cell_size) + 0.5) / cell_size - 0.5
    low = np.floor(u).astype(np.intp)
    frac = u - low
    cells, weights = [low, low + 1], [1.0 - frac, frac]
    for cell, weight in zip(cells, weights):
        weight[cell == 0] *= BOUNDARY_FACTOR
        weight[cell == n_cells - 1] *= BOUNDARY_FACTOR  # a single cell is both first and last, as in C
        cell[cell >= n_cells] = -1
    return cells, weights


def _spatial_histograms(magnitude: np.ndarray, table_index: np.ndarray, cell_size: int,
                        rows: int, cols: int) -> np.ndarray:
    """Contrast-sensitive histograms R1, float32 (N, 18, rows, cols): bilinear in space, hard in orientation.

    One bincount for the whole batch: image n owns the flat bins n * 18 * rows * cols onwards. Each bin sums
    its contributions in the same order as for a batch of one, so the batch changes no rounding.
    """
    cell_index, cell_weight = _bilinear_layout(cell_size, rows, cols)
    n_images, n_cells = magnitude.shape[0], rows * cols
    bin_start = _bin_offsets(n_cells).take(table_index, mode="clip")
    bin_start += _image_offsets(n_images, N_SENSITIVE * n_cells)
    target = cell_index[:, None] + bin_start  # (4, N, h, w): each pixel's 4 cells
    histogram = np.bincount(target.ravel(), (cell_weight[:, None] * magnitude).ravel(),
                            minlength=n_images * N_SENSITIVE * n_cells)
    return histogram.reshape(n_images, N_SENSITIVE, rows, cols).astype(np.float32)


@lru_cache(maxsize=16)
def _image_offsets(n_images: int, bins_per_image: int) -> np.ndarray:
    """The first flat histogram bin of each image of the batch, shaped (N, 1, 1) to broadcast over pixels."""
    return _read_only(np.arange(n_images).reshape(n_images, 1, 1) * bins_per_image)


def _block_normalisers(insensitive: np.ndarray, cell_size: int) -> np.ndarray:
    """The 4 block normalisers of every cell, float32 (N, 4, rows, cols).

    n = 1 / sqrt(energy of a 2x2 block + eps); the (rows-1)x(cols-1) block grid is edge-padded so every
    cell sees 4 blocks. Order k = 0..3 as in the C code: the blocks whose top-left cell is at offset
    (0, 0), (-1, 0), (0, -1), (-1, -1) from the cell.
    """
    rows, cols = insensitive.shape[2:]
    energy = insensitive[:, 0] * insensitive[:, 0]  # summed orientation by orientation, in a fixed order
    for o in range(1, N_ORIENTS):
        energy += insensitive[:, o] * insensitive[:, o]
    if rows == 1 or cols == 1:  # degenerate grid: duplicate the single cell row / column (see fhog)
        energy = np.pad(energy, ((0, 0), (0, rows == 1), (0, cols == 1)), mode="edge")
    eps = np.float32(1e-4 / 4 / cell_size**4)
    block = energy[:, :-1, :-1] + energy[:, 1:, :-1] + energy[:, :-1, 1:] + energy[:, 1:, 1:] + eps
    block_rows, block_cols = _neighbour_blocks(rows, cols)
    return (np.float32(1.0) / np.sqrt(block))[:, block_rows, block_cols]


@lru_cache(maxsize=16)
def _neighbour_blocks(rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Row (4, rows, 1) and column (4, 1, cols) block indices of each cell's 4 blocks, clamped to the grid."""
    row_offsets, col_offsets = np.array([0, 1, 0, 1]), np.array([0, 0, 1, 1])
    block_rows = np.clip(np.arange(rows) - row_offsets[:, None], 0, max(rows - 2, 0))
    block_cols = np.clip(np.arange(cols) - col_offsets[:, None], 0, max(cols - 2, 0))
    return _read_only(block_rows[:, :, None]), _read_only(block_cols[:, None, :])


def _normalise_and_truncate(sensitive: np.ndarray, cell_size: int, clip: np.float32) -> np.ndarray:
    """The 31 output channels, (N, 31, rows, cols): 0.5 * sum_k min(R n_k, clip) for R1 and R2, and the
    4 texture channels."""
    insensitive = sensitive[:, :N_ORIENTS] + sensitive[:, N_ORIENTS:]
    histograms = np.concatenate([sensitive, insensitive], axis=1)  # the 27 orientation channels, R1 then R2
    out = np.zeros(sensitive.shape[:1] + (N_CHANNELS,) + sensitive.shape[2:], dtype=np.float32)
    orientation_out, texture_out = out[:, : N_SENSITIVE + N_ORIENTS], out[:, N_SENSITIVE + N_ORIENTS:]
    truncated = np.empty_like(histograms)
    clip_array = np.full_like(histograms, clip)  # numpy's minimum is several times faster array-to-array
    normalisers = _block_normalisers(insensitive, cell_size)
    for k in range(normalisers.shape[1]):
        np.minimum(np.multiply(histograms, normalisers[:, k, None], out=truncated), clip_array, out=truncated)
        orientation_out += truncated
        np.sum(truncated[:, :N_SENSITIVE], axis=1, out=texture_out[:, k])
    orientation_out *= np.float32(0.5)
    texture_out *= TEXTURE_FACTOR
    return out
