"""Felzenszwalb fHOG, 31 channels, laid out as Piotr Dollar's ``gradientMex`` computes it (ALGORITHM.md 4.1).

Settings are those TACF uses: 18 contrast-sensitive orientations (nOrients 9, full circle), hard orientation
binning (softBin -1), bilinear spatial binning with the 8/7 boundary-cell factor, 2x2 block normalisation,
truncation at ``clip`` and no border crop. The all-zero 32nd channel of the original is dropped.

The per-pixel work is three loops compiled with numba (gradients and orientation, bilinear cell binning, block
normalisation), bit for bit what the earlier vectorised numpy form gave, which spent most of its time building
per-pixel temporaries: a 200x200 colour patch took 0.6 ms instead of 2.6 ms (2026-11-23; 0.34 ms on 2026-12-07's
VM). ``fhog_batch`` computes N same-sized images in one call (the DSST scale filter needs 31 small patches per
sample) and ``fhog`` is its N = 1 case; images never mix, so each image's result is what ``fhog`` gives for it
alone. Images are first laid out as one plane per colour channel, so that the gradient loops read contiguous rows.
Constants that depend only on the image size (each pixel's two cells and bilinear weights along each axis) or on
nothing (the orientation lookup table) are computed once in numpy and cached. The compiled code is cached on disk
(tacf.compiled), so a new process does not recompile.

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
exact zeros rather than 1e-10-sized values, and cell sums are accumulated in float64, not float32.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from tacf.compiled import compiled

N_ORIENTS = 9  # contrast-insensitive orientations; the sensitive ones are twice as many
N_SENSITIVE = 2 * N_ORIENTS
N_CHANNELS = N_SENSITIVE + N_ORIENTS + 4
TEXTURE_FACTOR = np.float32(0.2357)
BOUNDARY_FACTOR = 8.0 / 7.0  # boundary cells collect only 7/8 of an interior cell's bilinear weight
PI32 = np.float32(3.14159265)  # the C code's PI, as float32
ACOS_STEPS = 10000  # the C acos table holds acos(i / 10000)
ACOS_GUARD = 10  # extra table entries each side, absorbing rounding beyond +-1
TABLE_SIZE = 2 * (ACOS_STEPS + ACOS_GUARD)
# float32 constants for the compiled loops: a Python float there would promote the arithmetic to float64.
HALF = np.float32(0.5)
ONE = np.float32(1.0)
MAX_INVERSE = np.float32(1e10)
STEPS32 = np.float32(ACOS_STEPS)


def fhog(image: np.ndarray, cell_size: int = 4, clip: float = 0.2, divisor: float = 1.0) -> np.ndarray:
    """fHOG of ``image`` as float32 ``(31, H // cell_size, W // cell_size)``, C-contiguous.

    ``image`` is HxW or HxWxC, of any real dtype, divided by ``divisor`` in float32 first, exactly as
    ``image.astype(np.float32) / divisor``: 255 turns uint8 pixels into 0..1 without a converted copy. The scale
    only changes the effect of the normalisation epsilon. Channels 0-17 are contrast-sensitive orientations, 18-26
    contrast-insensitive, 27-30 texture (one per block normaliser). Gradients use the whole image; only the pixels
    inside the full cells are binned. A grid only one cell high or wide (possible for thin DSST scale patches) is
    normalised as if that cell row or column were duplicated; the C code reads raw energies there instead.
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        raise ValueError(f"expected an HxW or HxWxC image, got shape {image.shape}")
    return fhog_batch(image[None], cell_size, clip, divisor)[0]


def fhog_batch(images: np.ndarray, cell_size: int = 4, clip: float = 0.2, divisor: float = 1.0) -> np.ndarray:
    """fHOG of N same-sized images at once, float32 ``(N, 31, H // cell_size, W // cell_size)``, C-contiguous.

    ``images`` is NxHxW or NxHxWxC. Each image is computed on its own, exactly as ``fhog`` would (gradients
    stop at each image's border, cells and normalisers never mix images), so ``fhog_batch(images)[i]`` equals
    ``fhog(images[i])`` bit for bit.
    """
    planes = _as_planes_float32(images, divisor)
    rows, cols = planes.shape[2] // cell_size, planes.shape[3] // cell_size
    if rows < 1 or cols < 1:
        raise ValueError(f"images {planes.shape[2:4]} are smaller than one {cell_size}x{cell_size} cell")
    row_cells, row_weights = _axis_cells(rows, cell_size)
    col_cells, col_weights = _axis_cells(cols, cell_size)
    out = np.empty((len(planes), N_CHANNELS, rows, cols), dtype=np.float32)
    eps = np.float32(1e-4 / 4 / cell_size**4)
    _fhog_images(planes, _orientation_bins(), row_cells, row_weights / cell_size**2, col_cells, col_weights,
                 eps, np.float32(clip), out)
    return out


def _as_planes_float32(images: np.ndarray, divisor: float) -> np.ndarray:
    """(N, C, H, W) float32 images / divisor, C-contiguous: one plane per colour channel, so the gradient loops
    read rows. One pass: the transpose, the conversion and the division write the planes directly."""
    images = np.asarray(images)
    if images.ndim == 3:
        images = images[:, None]
    elif images.ndim == 4:
        images = images.transpose(0, 3, 1, 2)
    else:
        raise ValueError(f"expected NxHxW or NxHxWxC images, got shape {images.shape}")
    planes = np.empty(images.shape, dtype=np.float32)
    if divisor == 1.0:
        np.copyto(planes, images, casting="unsafe")
    else:
        np.divide(images, np.float32(divisor), out=planes, dtype=np.float32, casting="unsafe")
    return planes


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
    return _read_only((scaled.astype(np.intp) % N_SENSITIVE).astype(np.uint8))  # small: stays in cache


def _read_only(array: np.ndarray) -> np.ndarray:
    """Cached arrays are shared between calls, so they are frozen."""
    array.flags.writeable = False
    return array


@lru_cache(maxsize=64)
def _axis_cells(n_cells: int, cell_size: int) -> tuple[np.ndarray, np.ndarray]:
    """Along one axis: each pixel's two target cells (2, n_cells * cell_size), -1 outside the grid, and their
    bilinear weights, float64.

    A pixel at column c has cell coordinate u = (c + 0.5) / cell - 0.5 and goes to cells floor(u) and
    floor(u) + 1 with weights 1 - frac(u) and frac(u); likewise for rows. The weights also carry the 8/7
    boundary-cell factor (a corner cell gets it from both axes)."""
    u = (np.arange(n_cells * cell_size) + 0.5) / cell_size - 0.5
    low = np.floor(u).astype(np.intp)
    frac = u - low
    cells, weights = np.stack([low, low + 1]), np.stack([1.0 - frac, frac])
    weights[cells == 0] *= BOUNDARY_FACTOR
    weights[cells == n_cells - 1] *= BOUNDARY_FACTOR  # a single cell is both first and last, as in C
    cells[cells >= n_cells] = -1
    return _read_only(cells), _read_only(weights)


# ---------------------------------------------------------------------------------------------- compiled loops

@compiled
def _fhog_images(planes, orientation_bins, row_cells, row_weights, col_cells, col_weights, eps, clip, out):
    """Fill out (N, 31, rows, cols) with the fHOG of each image of planes (N, C, H, W).

    The loops are written out element by element: numba compiles whole-array expressions (slice assignment,
    broadcasting) very slowly, ~9 s each on this machine, against well under a second for the loops."""
    used_height, used_width = row_cells.shape[1], col_cells.shape[1]
    rows, cols = out.shape[2:]
    # Work space for all images of the batch (DSST batches are 31 small patches: allocation would dominate).
    magnitude = np.empty((used_height, used_width), dtype=np.float32)
    orientation = np.empty((used_height, used_width), dtype=np.uint8)
    sensitive = np.empty((N_SENSITIVE, rows, cols), dtype=np.float64)
    histograms = np.empty((N_SENSITIVE + N_ORIENTS, rows, cols), dtype=np.float32)
    energy = np.empty((rows, cols), dtype=np.float32)
    block = np.empty((rows, cols), dtype=np.float32)
    normalisers = np.empty((4, rows, cols), dtype=np.float32)
    for n in range(planes.shape[0]):
        _magnitude_and_orientation(planes[n], orientation_bins, magnitude, orientation)
        _spatial_histograms(magnitude, orientation, row_cells, row_weights, col_cells, col_weights, sensitive)
        _normalise_and_truncate(sensitive.reshape(N_SENSITIVE, rows * cols), eps, clip, histograms, energy, block,
                                normalisers, out[n])


@compiled
def _magnitude_and_orientation(planes, orientation_bins, magnitude, orientation):
    """Gradient magnitude and hard orientation bin of each pixel of the binned area, from the colour channel
    with the largest float32 squared magnitude (the first one on a tie). Gradients are central differences
    x0.5 inside and one-sided (x1) on the image border. The bin is read from _orientation_bins() at the
    truncated cosine, shifted to the table's second half when gy < 0. Row by row, in loops without branches
    on x where possible, so that they compile to vector code."""
    channels, height, width = planes.shape
    used_width = magnitude.shape[1]
    rows = np.empty((6, used_width), dtype=np.float32)
    gx, gy, squared, best_gx, best_gy, best_squared = rows[0], rows[1], rows[2], rows[3], rows[4], rows[5]
    table_index = np.empty(used_width, dtype=np.int32)
    last = width - 1
    for y in range(magnitude.shape[0]):
        up, down = max(y - 1, 0), min(y + 1, height - 1)
        y_scale = HALF if 0 < y < height - 1 else ONE
        for c in range(channels):
            above, row, below = planes[c, up], planes[c, y], planes[c, down]
            gx[0] = row[1] - row[0]
            for x in range(1, min(used_width, last)):
                gx[x] = (row[x + 1] - row[x - 1]) * HALF
            if used_width > last:  # the binned area reaches the right border
                gx[last] = row[last] - row[last - 1]
            for x in range(used_width):
                gy[x] = (below[x] - above[x]) * y_scale
                squared[x] = gx[x] * gx[x] + gy[x] * gy[x]
            for x in range(used_width):
                better = c == 0 or squared[x] > best_squared[x]
                best_gx[x] = gx[x] if better else best_gx[x]
                best_gy[x] = gy[x] if better else best_gy[x]
                best_squared[x] = squared[x] if better else best_squared[x]
        for x in range(used_width):
            norm = np.sqrt(best_squared[x])
            magnitude[y, x] = norm
            inverse = min(ONE / norm, MAX_INVERSE) if norm > 0 else MAX_INVERSE  # flat pixels: gx * 1e10 = 0
            index = np.int32(best_gx[x] * inverse * STEPS32)
            index += TABLE_SIZE // 2 if best_gy[x] >= 0 else TABLE_SIZE + TABLE_SIZE // 2
            table_index[x] = min(max(index, 0), 2 * TABLE_SIZE - 1)
        for x in range(used_width):  # the table lookups apart: the loop above then vectorises
            orientation[y, x] = orientation_bins[table_index[x]]


@compiled
def _spatial_histograms(magnitude, orientation, row_cells, row_weights, col_cells, col_weights, sensitive):
    """Contrast-sensitive histograms R1 (18, rows, cols): bilinear in space (each pixel to its two row cells
    times its two column cells), hard in orientation, summed in float64. row_weights carry the 1 / cell^2
    magnitude factor; the product of the two weights is rounded to float32, as in the C code."""
    sensitive.fill(0.0)
    for y in range(magnitude.shape[0]):
        for i in range(2):
            row = row_cells[i, y]
            if row < 0:
                continue
            row_weight = row_weights[i, y]
            for x in range(magnitude.shape[1]):
                histogram = sensitive[orientation[y, x], row]
                for j in range(2):
                    col = col_cells[j, x]
                    if col >= 0:
                        histogram[col] += np.float32(row_weight * col_weights[j, x]) * magnitude[y, x]


@compiled
def _normalise_and_truncate(sensitive, eps, clip, histograms, energy, block, normalisers, out):
    """The 31 output channels (31, rows, cols) from the float64 histograms R1 (18, rows * cols):
    0.5 * sum_k min(R n_k, clip) for R1 and the contrast-insensitive R2, and the 4 texture channels.
    n_k = 1 / sqrt(energy of a 2x2 block + eps) for the 4 blocks around a cell, in the C code's order: top-left
    cell at offset (0, 0), (-1, 0), (0, -1), (-1, -1); the block grid is clamped at the border. A grid one cell
    high or wide is normalised as if that cell row / column were doubled.
    histograms (27, rows, cols), energy and block (rows, cols) and normalisers (4, rows, cols) are work space.
    Each output value sums its four truncated values in the order k = 0..3 in float32, in one pass."""
    rows, cols = out.shape[1:]
    n_histograms = N_SENSITIVE + N_ORIENTS
    for r in range(rows):  # R1 in float32, R2 and each cell's energy
        for c in range(cols):
            total = np.float32(0.0)
            for o in range(N_SENSITIVE):
                histograms[o, r, c] = sensitive[o, r * cols + c]
            for o in range(N_ORIENTS):
                insensitive = histograms[o, r, c] + histograms[o + N_ORIENTS, r, c]
                histograms[N_SENSITIVE + o, r, c] = insensitive
                total += insensitive * insensitive
            energy[r, c] = total
    block_rows, block_cols = max(rows - 1, 1), max(cols - 1, 1)
    for r in range(block_rows):
        r1 = min(r + 1, rows - 1)
        for c in range(block_cols):
            c1 = min(c + 1, cols - 1)
            block[r, c] = ONE / np.sqrt(energy[r, c] + energy[r1, c] + energy[r, c1] + energy[r1, c1] + eps)
    for k in range(4):  # the four normalisers of each cell, as planes: the loop below then runs along rows
        for r in range(rows):
            for c in range(cols):
                normalisers[k, r, c] = block[min(max(r - k % 2, 0), block_rows - 1),
                                             min(max(c - k // 2, 0), block_cols - 1)]
    textures = out[n_histograms:]
    for k in range(4):
        for r in range(rows):
            for c in range(cols):
                textures[k, r, c] = 0.0
    for o in range(n_histograms):
        with_texture = o < N_SENSITIVE
        for r in range(rows):
            for c in range(cols):
                value = histograms[o, r, c]
                truncated0 = min(value * normalisers[0, r, c], clip)
                truncated1 = min(value * normalisers[1, r, c], clip)
                truncated2 = min(value * normalisers[2, r, c], clip)
                truncated3 = min(value * normalisers[3, r, c], clip)
                out[o, r, c] = (truncated0 + truncated1 + truncated2 + truncated3) * HALF
                if with_texture:
                    textures[0, r, c] += truncated0
                    textures[1, r, c] += truncated1
                    textures[2, r, c] += truncated2
                    textures[3, r, c] += truncated3
    for k in range(4):
        for r in range(rows):
            for c in range(cols):
                textures[k, r, c] *= TEXTURE_FACTOR
