"""The Sequence record and the helpers every loader shares (box files, frame listing)."""
from __future__ import annotations

import io
import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...images import is_image
from ..text_files import read_text, write_atomically

log = logging.getLogger(__name__)

_SEPARATORS = re.compile(r"[,\s;]+")
_DIGITS = re.compile(r"(\d+)")


@dataclass(frozen=True, eq=False)
class Sequence:
    """One annotated sequence: `name` relative to the dataset root (posix, e.g. 'UAV123_10fps/wakeboard7'),
    `frames` the image paths in order, `gt` an N x 4 float array of 0-based x,y,w,h (NaN rows = target absent),
    `attributes` the benchmark's own attribute labels (e.g. 'FM', 'SV'), None where it ships none."""

    name: str
    frames: tuple[Path, ...]
    gt: np.ndarray = field(repr=False)
    attributes: frozenset[str] | None = None

    def __post_init__(self) -> None:
        gt = np.asarray(self.gt, dtype=np.float64)
        if gt.ndim != 2 or gt.shape[1] != 4:
            raise ValueError(f"{self.name}: ground truth must be N x 4, got shape {gt.shape}")
        if len(self.frames) != len(gt):
            raise ValueError(f"{self.name}: {len(self.frames)} frames but {len(gt)} ground-truth rows")
        object.__setattr__(self, "frames", tuple(Path(p) for p in self.frames))
        object.__setattr__(self, "gt", gt)

    def __len__(self) -> int:
        return len(self.frames)


def read_boxes(path: Path, one_based: bool = True) -> np.ndarray:
    """N x 4 float boxes from a text file; comma, tab, space or semicolon separated; 'NaN' rows kept; a row of 8
    numbers, a VOT polygon x1,y1,...,x4,y4, becomes the axis-aligned box enclosing it.

    With `one_based` (the benchmarks' MATLAB convention) 1 is subtracted from x and y.
    """
    return parse_boxes(read_text(path).splitlines(), path, one_based)


def parse_boxes(lines: list[str], path: Path, one_based: bool = True) -> np.ndarray:
    """`read_boxes` on the lines of a file already read (`path` names it in errors)."""
    rows = []
    for lineno, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("m"):
            raise ValueError(f"{path}:{lineno}: a VOT segmentation mask; tacf evaluates boxes: use the rectangle "
                             "(VOT-STb) or polygon ground truth")
        parts = [p for p in _SEPARATORS.split(line) if p]
        if len(parts) < 4:
            raise ValueError(f"{path}:{lineno}: expected 4 numbers x,y,w,h, got {line!r}")
        try:
            values = [float(p) for p in parts[:8 if len(parts) == 8 else 4]]
        except ValueError:
            raise ValueError(f"{path}:{lineno}: not a number in {line!r}") from None
        if len(values) == 8:  # read as x,y,w,h, its first corners would make a box elsewhere and of another size
            corners = np.reshape(values, (4, 2))
            low, high = corners.min(axis=0), corners.max(axis=0)
            values = [*low, *(high - low)]
        rows.append(values)
    boxes = np.asarray(rows, dtype=np.float64).reshape(-1, 4)
    if one_based:
        boxes[:, :2] -= 1.0
    return boxes


def write_boxes(path: Path, boxes: np.ndarray, one_based: bool = True) -> None:
    """Write N x 4 0-based boxes as `%.3f` comma-separated lines (1-based when `one_based`), atomically."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4).copy()
    if one_based:
        boxes[:, :2] += 1.0
    write_rows(path, boxes, "%.3f")


def write_rows(path: Path, rows: np.ndarray, fmt: str, header: str = "") -> None:
    """Rows as comma-separated lines in `fmt` (numpy.savetxt's), under a '# ' header if given, atomically."""
    text = io.StringIO()
    np.savetxt(text, rows, fmt=fmt, delimiter=",", header=header)
    write_atomically(path, text.getvalue())


def natural_key(path: Path) -> list:
    """Sort key that orders img2.jpg before img10.jpg."""
    # isdecimal, what \d matches: isdigit is also true of a '²' between the digit runs, which int() refuses
    return [int(t) if t.isdecimal() else t.lower() for t in _DIGITS.split(Path(path).name)]


def frame_number(path: Path) -> int | None:
    """The number a frame file's name carries (its last run of digits: img000445.jpg -> 445), or None."""
    digits = _DIGITS.findall(Path(path).stem)
    return int(digits[-1]) if digits else None


def missing_frame_numbers(frames: list[Path], first: int | None = None) -> list[int]:
    """The numbers absent between consecutively numbered frames (000004 between 000003 and 000005), and, given
    `first`, the number the first frame must carry (a UAV123 range's start), those absent before the first frame
    on disk; none when some frame carries no number, nor gaps when no two are consecutive (names such as time
    stamps)."""
    numbers = [frame_number(p) for p in frames]
    if not numbers or None in numbers:
        return []
    before = list(range(first, numbers[0])) if first is not None else []
    if len(numbers) < 2 or min(b - a for a, b in zip(numbers, numbers[1:])) != 1:
        return before
    return before + [n for a, b in zip(numbers, numbers[1:]) for n in range(a + 1, b)]


def list_frames(folder: Path, prefix: str = "") -> list[Path]:
    """The image files of a folder in natural order (optionally only those whose name starts with `prefix`)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    files = [p for p in folder.iterdir() if p.name.startswith(prefix) and is_image(p)]
    return sorted(files, key=natural_key)


def make_sequence(name: str, frames: list[Path], gt: np.ndarray, attributes: frozenset[str] | None = None,
                  first_number: int | None = None) -> Sequence | None:
    """A Sequence, cutting frames or ground truth to the shorter of the two (with a warning); None (with a warning)
    when either is empty, or when numbered frames are missing on disk between those the ground truth covers, or
    before the first one on disk when the number the first frame must carry is known (`first_number`): every row
    after the gap would be scored against the frame after its own."""
    missing = missing_frame_numbers(frames[:len(gt)], first_number)
    if missing:
        listed = ", ".join(map(str, missing[:5])) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        log.warning("%s: frame%s %s missing from %s: the ground truth after it would meet the wrong frames; skipped",
                    name, "s" * (len(missing) > 1), listed, Path(frames[0]).parent)
        return None
    n = min(len(frames), len(gt))
    if n == 0:
        log.warning("%s: %d frames and %d ground-truth rows, nothing to track; skipped", name, len(frames), len(gt))
        return None
    if len(frames) != len(gt):
        log.warning("%s: %d frames but %d ground-truth rows; using the first %d", name, len(frames), len(gt), n)
    return Sequence(name, tuple(frames[:n]), gt[:n], attributes)
