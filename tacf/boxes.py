"""The box that starts tracking: which (x, y, w, h) Tracker.init accepts, checked once for the tracker and the
service (tacf_service.frames.box_problem).

Only numpy is imported, so that the service's main process can check boxes without loading OpenCV or SciPy.
"""
from __future__ import annotations

import numpy as np


def check_box(box, frame_shape) -> np.ndarray:
    """The box as four float64 values (x, y, w, h); ValueError unless they are finite, w and h at least a pixel, the
    box overlaps the frame of shape (height, width, ...) and is no larger than it: the search area grows with the
    box (a 5000x5000 box on a 320x240 frame took 16 s to initialise, a 1e5 one failed allocating 120 GB)."""
    try:
        values = np.asarray(box, dtype=np.float64).reshape(-1)
    except OverflowError:  # an int past the float range (10**400); not printed: over 4,300 digits, str() raises
        raise ValueError("box must be four finite numbers (x, y, w, h), got one past the float range") from None
    except (TypeError, ValueError):
        raise ValueError(f"box must be four numbers (x, y, w, h), got {box!r}") from None
    if values.size != 4 or not np.all(np.isfinite(values)):
        raise ValueError(f"box must be four finite numbers (x, y, w, h), got {box!r}")
    # True and False are numbers to numpy: (True, True, True, True) was a 1x1 box at (1, 1)
    if any(isinstance(v, (bool, np.bool_)) for v in np.asarray(box, dtype=object).reshape(-1)):
        raise ValueError(f"box must be four numbers (x, y, w, h), not booleans: got {box!r}")
    x, y, w, h = values
    if w <= 0 or h <= 0:
        raise ValueError(f"box width and height must be positive, got w={w}, h={h}")
    if w < 1 or h < 1:      # a box in normalised coordinates, most likely: it was tracked, as a box of a pixel
        raise ValueError(f"box width and height must be at least a pixel (boxes are in pixels, not normalised), got "
                         f"w={w}, h={h}")
    height, width = frame_shape[:2]
    if x >= width or y >= height or x + w <= 0 or y + h <= 0:
        # tolist(): plain numbers in the message, which reaches service clients (not numpy 2's np.float64(...))
        raise ValueError(f"box {tuple(values.tolist())} lies outside the {width}x{height} image")
    if w > width or h > height:
        raise ValueError(f"box {tuple(values.tolist())} is larger than the {width}x{height} image")
    return values


def box_around(pos, size_hw) -> tuple[float, float, float, float]:
    """(x, y, w, h) of the box of size (height, width) centred on pos (row, col): what the trackers report."""
    height, width = size_hw
    return (float(pos[1] - width / 2), float(pos[0] - height / 2), float(width), float(height))


def overlapping(pos, size_hw, frame_shape) -> np.ndarray:
    """pos (row, col) moved as little as needed for the box of size (height, width) around it to overlap the frame
    by a pixel, as check_box requires of a first box. Not into the frame: a first box may have its centre outside,
    and a clip of the centre into the frame moved it on the first update (10 px on identical frames). Within the
    frame, where ordinary targets are, nothing changes."""
    half = np.asarray(size_hw, dtype=np.float64) / 2
    return np.clip(pos, 1 - half, np.asarray(frame_shape[:2]) - 1 + half)


def visible_fraction(pos, size_hw, frame_shape) -> float:
    """The fraction of the box of size (height, width) around pos (row, col) that lies inside the frame."""
    pos, half = np.asarray(pos, dtype=np.float64), np.asarray(size_hw, dtype=np.float64) / 2
    inside = np.minimum(pos + half, frame_shape[:2]) - np.maximum(pos - half, 0)
    return float(np.prod(np.clip(inside / (2 * half), 0, 1)))
