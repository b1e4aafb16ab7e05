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

Names repeat across sets (UAV123's and UAV20L's bike1), so a configSeqs.m entry belongs to the set of the
`seq<set> = {...}` list that holds it. The frames are in the data_seq folder the table's path names, else in the
set's own, else in the one data_seq/* folder that holds them: the release keeps UAV20L's in data_seq/UAV123/.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

from ..attributes import read_uav123_flags
from .base import Sequence, frame_number, list_frames, make_sequence, read_boxes

log = logging.getLogger(__name__)

_CONFIG_ENTRY = re.compile(
    r"'name'\s*,\s*'([^']+)'\s*,\s*'path'\s*,\s*'([^']*)'\s*,\s*'startFrame'\s*,\s*(\d+)\s*,\s*'endFrame'\s*,\s*(\d+)")
_CONFIG_LIST = re.compile(r"\bseq(\w+)\s*=\s*\{")  # seqUAV20L = {struct(...), ...}: the set of the entries after it


@dataclass(frozen=True)
class FrameRange:
    name: str
    folder: str             # last component of the table's path, e.g. 'group1'
    first: int              # 1-based, inclusive
    last: int               # 1-based, inclusive
    set_folder: str | None = None   # the component before it, e.g. 'UAV123' for UAV20L's (None for a bare folder)


def _parse_range(name: str, path: str, first: str, last: str) -> FrameRange:
    parts = [p for p in re.split(r"[\\/]+", path.strip()) if p]
    if not parts:
        raise ValueError(f"empty folder in range table: {path!r}")
    return FrameRange(name, parts[-1], int(first), int(last), parts[-2] if len(parts) > 1 else None)


def read_ranges(path: Path) -> dict[tuple[str | None, str], FrameRange]:
    """Parse a range table: configSeqs.m (MATLAB structs) or `name folder first last` text lines. Keyed by (set,
    name), the set being that of the configSeqs.m list holding the entry (None in a text table or outside one)."""
    text = Path(path).read_text(errors="replace")
    ranges = {}
    if Path(path).suffix == ".m":
        lists = [(m.start(), m.group(1)) for m in _CONFIG_LIST.finditer(text)]
        for m in _CONFIG_ENTRY.finditer(text):
            set_name = next((name for start, name in reversed(lists) if start < m.start()), None)
            ranges[set_name, m.group(1)] = _parse_range(*m.groups())
    else:
        for lineno, line in enumerate(text.splitlines(), 1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            if len(parts) != 4:
                raise ValueError(f"{path}:{lineno}: expected 'name folder first_frame last_frame', got {line!r}")
            ranges[None, parts[0]] = _parse_range(*parts)
    if not ranges:
        raise ValueError(f"{path}: no sequence ranges found")
    return ranges


def _range_of(ranges: dict[tuple[str | None, str], FrameRange], set_name: str, name: str) -> FrameRange | None:
    """The table's range of set_name/name: the set's own entry, else the one of a table naming no set, else the
    only entry of that name (a list named otherwise)."""
    if (set_name, name) in ranges or (None, name) in ranges:
        return ranges.get((set_name, name)) or ranges[None, name]
    others = [r for (_, n), r in ranges.items() if n == name]
    return others[0] if len(others) == 1 else None


def _frames_in_range(frames: list[Path], first: int, last: int) -> list[Path]:
    """Frames numbered first..last (by the number in the file name, e.g. 000445.jpg; by position otherwise)."""
    numbered = {}
    for p in frames:
        number = frame_number(p)
        if number is not None:
            numbered.setdefault(number, p)
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


def _frames_of(root: Path, set_name: str, rng: FrameRange) -> tuple[list[Path], list[str]]:
    """(the frames of a range's folder, the data_seq/* folders that hold it): in data_seq/<the table's set folder>,
    else data_seq/<set_name>, else in the one other data_seq/* folder that has them (none when two do, say a 30 fps
    and a 10 fps release side by side)."""
    data_seq = root / "data_seq"
    for set_folder in dict.fromkeys(s for s in (rng.set_folder, set_name) if s):
        frames = list_frames(data_seq / set_folder / rng.folder)
        if frames:
            return frames, [set_folder]
    holding = {p.name: list_frames(p / rng.folder) for p in sorted(data_seq.iterdir()) if p.is_dir()}
    holding = {folder: frames for folder, frames in holding.items() if frames}
    return next(iter(holding.values())) if len(holding) == 1 else [], list(holding)


def load(root: Path, ranges: dict[tuple[str | None, str], FrameRange] | Path | None = None) -> list[Sequence]:
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
            rng = _range_of(ranges, set_dir.name, name)
            untabled = rng is None
            rng = rng or FrameRange(name, name, 1, 0)  # a whole folder named like the sequence
            frames, holders = _frames_of(root, set_dir.name, rng)
            if not frames:
                if holders:
                    folders = " and ".join(f"data_seq/{h}/{rng.folder}" for h in holders)
                    why = f"frames in {folders}; a range table's path must choose"
                elif untabled:
                    why = f"no frame range for this split sequence (no configSeqs.m or range table in {root})"
                else:
                    why = f"no frames in data_seq/*/{rng.folder}"
                log.warning("%s/%s: %s; skipped", set_dir.name, name, why)
                continue
            gt = read_boxes(anno)
            last = rng.last if rng.last else rng.first + len(gt) - 1
            flags = set_dir / "att" / anno.name
            attributes = read_uav123_flags(flags) if flags.is_file() else None
            seq = make_sequence(f"{set_dir.name}/{name}", _frames_in_range(frames, rng.first, last), gt, attributes,
                                first_number=rng.first)
            if seq is not None:
                seqs.append(seq)
    return seqs
