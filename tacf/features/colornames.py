"""Color Names features, 11 channels, as the TACF code computes them (ALGORITHM.md 4.2).

The lookup table is van de Weijer et al. 2009, "Learning Color Names for Real-World Applications" (the
32768x11 ``w2c`` table, shipped with the TACF authors' code as w2c.mat); the package keeps a float32 copy in
``tacf/data/w2c.npz`` (key ``w2c``). It is not the 10-column projected ``w2crs`` table.

Channel order: black, blue, brown, grey, green, orange, pink, purple, red, white, yellow.
"""
from __future__ import annotations

from functools import lru_cache
from importlib import resources

import cv2
import numpy as np

N_CHANNELS = 11


@lru_cache(maxsize=1)
def _color_table() -> np.ndarray:
    """The w2c table transposed to (11, 32768), float32 and C-contiguous, loaded once."""
    with resources.files("tacf.data").joinpath("w2c.npz").open("rb") as handle:
        table = np.load(handle)["w2c"]
    if table.shape != (32768, N_CHANNELS):
        raise ValueError(f"w2c table has shape {table.shape}, expected (32768, {N_CHANNELS})")
    # Channel-first, so indexing with an (h, w) index image gives (11, h, w) directly.
    table = np.ascontiguousarray(table.T, dtype=np.float32)
    table.flags.writeable = False  # shared by every call
    return table


def color_names(patch_bgr: np.ndarray, cell_size: int = 4) -> np.ndarray:
    """Color Names probabilities per cell, float32 ``(11, H // cell_size, W // cell_size)``, C-contiguous.

    ``patch_bgr`` is a uint8 image in OpenCV BGR order, HxWx3. It is first averaged down to the cell grid
    (cv2.INTER_AREA), then each averaged colour is looked up; every output cell sums to 1.
    Grayscale input (HxW or HxWx1) is replicated to three equal channels. This fallback is not in the
    authors' MATLAB code, which crashes on grayscale frames.
    """
    patch_bgr = _as_bgr_uint8(patch_bgr)
    rows, cols = patch_bgr.shape[0] // cell_size, patch_bgr.shape[1] // cell_size
    if rows < 1 or cols < 1:
        raise ValueError(f"patch {patch_bgr.shape[:2]} is smaller than one {cell_size}x{cell_size} cell")
    cells = cv2.resize(patch_bgr, (cols, rows), interpolation=cv2.INTER_AREA).reshape(rows, cols, 3)
    return np.take(_color_table(), _table_index(cells), axis=1)  # (11, rows, cols), C-contiguous


def _as_bgr_uint8(patch: np.ndarray) -> np.ndarray:
    patch = np.asarray(patch)
    if patch.dtype != np.uint8:
        raise TypeError(f"color_names expects a uint8 patch, got {patch.dtype}")
    if patch.ndim == 3 and patch.shape[2] == 1:
        patch = patch[:, :, 0]
    if patch.ndim == 2:
        return np.repeat(patch[:, :, None], 3, axis=2)
    if patch.ndim != 3 or patch.shape[2] != 3:
        raise ValueError(f"expected an HxW, HxWx1 or HxWx3 patch, got shape {patch.shape}")
    return np.ascontiguousarray(patch)


def _table_index(cells_bgr: np.ndarray) -> np.ndarray:
    """Row of the table for each colour: R//8 + 32*(G//8) + 1024*(B//8), R first (the table is RGB)."""
    quantised = (cells_bgr >> 3).astype(np.intp)
    blue, green, red = quantised[:, :, 0], quantised[:, :, 1], quantised[:, :, 2]
    return red + 32 * green + 1024 * blue
