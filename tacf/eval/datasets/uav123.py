"""The official UAV123 / UAV123@10fps / UAV20L layout.

    <ROOT>/data_seq/<set>/<folder>/000001.jpg ...
    <ROOT>/anno/<set>/<seq>.txt                   (comma-separated x,y,w,h, 1-based, NaN rows = absent)
    <ROOT>/anno/<set>/att/<seq>.txt               (12 attribute flags, optional; see ..attributes)

Several sequences are frame ranges of one folder (group1_2 = frames 445..839 of data_seq/UAV123_10fps/group1).
The ranges come from the benchmark's own table: the `configSeqs.m` the release ships (struct('name','group1_2',
'path','D:\\data_seq\\UAV123_10fps\\group1\\','startFrame',445,'endFrame',839,...)), or a text table with one
`name folder first_frame last_frame` line per sequence (*ranges*.txt in ROOT, or passed explicitly).
Without a table, a sequence whose annotation file is named like its folder uses the folder's first frames;
the split sequences (name_1, name_2 ...) are skipped with a warning.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

from ..attributes import read_uav123_flags
from .base import Sequence, list_frames, make_sequence, read_boxes

log = logging.getLogger(__name__)

_CONFIG_ENTRY = re.compile(
    r"'name'\s*,\s*'([^']+)'\s*,\s*'path'\s*,\s*'([^']*)'\s*,\s*'startFrame'\s*,\s*(\d+)\s*,\s*'endFrame'\s*,\s*(\d+)")


@dataclass(frozen=True)
class FrameRange:
    name: str
    folder: str      # last component of the table's path, e.g. 'group1'
    first: int       # 1-based, inclusive
    last: int        # 1-based, inclusive


def _folder_name(path: str) -> str:
    parts = [p for p in re.split(r"[\\/]+", path.strip()) if p]
    if not parts:
        raise ValueError(f"empty folder in range table: {path!r}")
    return parts[-1]


def read_ranges(path: Path) -> dict[str, FrameRange]:
    """Parse a range table: configSeqs.m (MATLAB structs) or `name folder first last` text lines."""
    text = Path(path).read_text(errors="replace")
    ranges = {}
    if Path(path).suffix == ".m":
        for name, folder, first, last in _CONFIG_ENTRY.findall(text):
            ranges[name] = FrameRange(name, _folder_name(folder), int(first), int(last))
    else:
        for lineno, line in enumerate(text.splitlines(), 1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            if len(parts) != 4:
                raise ValueError(f"{path}:{lineno}: expected 'name folder first_frame last_frame', got {line!r}")
            ranges[parts[0]] = FrameRange(parts[0], _folder_name(parts[1]), int(parts[2]), int(parts[3]))
    if not ranges:
        raise ValueError(f"{path}: no sequence ranges found")
    return ranges


def _frame_range(frames: list[Path], first: int, last: int) -> list[Path]:
    """Frames numbered first..last (by the number in the file name, e.g. 000445.jpg; by position otherwise)."""
    numbered = {}
    for p in frames:
        digits = re.findall(r"\d+", p.stem)
        if digits:
            numbered.setdefault(int(digits[-1]), p)
    if len(numbered) == len(frames):
        return [numbered[i] for i in range(first, last + 1) if i in numbered]
    return frames[first - 1:last]


def find_range_tables(root: Path) -> list[Path]:
    """configSeqs*.m and *ranges*.txt files in ROOT or one level down (sorted, .m first)."""
    root = Path(root)
    found = []
    for pattern in ("configSeqs*.m", "*/configSeqs*.m", "*ranges*.txt", "*/*ranges*.txt"):
        found += sorted(p for p in root.glob(pattern) if p.is_file())
    return found


def is_uav123(root: Path) -> bool:
    root = Path(root)
    return (root / "anno").is_dir() and (root / "data_seq").is_dir()


def load(root: Path, ranges: dict[str, FrameRange] | Path | None = None) -> list[Sequence]:
    """All sequences of every set under <ROOT>/anno, named '<set>/<seq>'."""
    root = Path(root)
    if ranges is None:
        ranges = {}
        for table in reversed(find_range_tables(root)):  # earlier tables (configSeqs.m) win
            ranges.update(read_ranges(table))
    elif not isinstance(ranges, dict):
        ranges = read_ranges(Path(ranges))
    seqs = []
    for set_dir in sorted(p for p in (root / "anno").iterdir() if p.is_dir()):
        for anno in sorted(set_dir.glob("*.txt")):
            name = anno.stem
            rng = ranges.get(name)
            if rng is None:
                if not (root / "data_seq" / set_dir.name / name).is_dir():
                    log.warning("%s/%s: no frame range for this split sequence (no configSeqs.m or range "
                                "table in %s); skipped", set_dir.name, name, root)
                    continue
                rng = FrameRange(name, name, 1, 0)
            frames = list_frames(root / "data_seq" / set_dir.name / rng.folder)
            if not frames:
                log.warning("%s/%s: no frames in data_seq/%s/%s; skipped", set_dir.name, name, set_dir.name, rng.folder)
                continue
            gt = read_boxes(anno)
            last = rng.last if rng.last else rng.first + len(gt) - 1
            flags = set_dir / "att" / anno.name
            attributes = read_uav123_flags(flags) if flags.is_file() else None
            seqs.append(make_sequence(f"{set_dir.name}/{name}", _frame_range(frames, rng.first, last), gt,
                                      attributes))
    return seqs
