"""Sequence attributes (fast motion, scale variation, ...) for the per-attribute scores benchmark papers report.

Three sources, one per run (`attributes_of`):
- a table given with `tacf eval --attributes FILE`: one line per sequence, its name (as `--sequences` matches it,
  or only its last part) then its attributes, e.g. `UAV123_10fps/truck2 FM SOB`; OTB's attribute lists
  (`Basketball<TAB>IV, OCC, DEF, OPR, BC`) are such tables;
- the benchmark's own files: the UAV123 release's `anno/<set>/att/<seq>.txt`, one line of 12 flags in the order
  of UAV123_ATTRIBUTES (read by the uav123 loader), and the `attrs.txt` that OTB sequence folders carry in the
  OTB benchmark's Python toolkit (jwlim/tracker_benchmark), one line of codes such as `SV, DEF, FM, OPR, BC`
  (read by the folders loader);
- otherwise the four that UAV123 defines by the ground truth alone (`derived_attributes`), for any dataset.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from .metrics import valid_mask
from .text_files import read_text

log = logging.getLogger(__name__)

#: UAV123's attributes, in the order of its att files' flags (the UAV123 toolkit's attName / attFigName).
UAV123_ATTRIBUTES = {"SV": "scale variation", "ARC": "aspect ratio change", "LR": "low resolution",
                     "FM": "fast motion", "FOC": "full occlusion", "POC": "partial occlusion", "OV": "out of view",
                     "BC": "background clutter", "IV": "illumination variation", "VC": "viewpoint change",
                     "CM": "camera motion", "SOB": "similar object"}
#: OTB's attributes (Wu et al., TPAMI 2015), in the order of its tables.
OTB_ATTRIBUTES = {"IV": "illumination variation", "SV": "scale variation", "OCC": "occlusion", "DEF": "deformation",
                  "MB": "motion blur", "FM": "fast motion", "IPR": "in-plane rotation", "OPR": "out-of-plane rotation",
                  "OV": "out of view", "BC": "background clutter", "LR": "low resolution"}
#: Every attribute code known by name, UAV123's first; the six codes the two share have the same names.
ATTRIBUTE_NAMES = {**UAV123_ATTRIBUTES, **OTB_ATTRIBUTES}

# UAV123's definitions (Mueller et al., ECCV 2016, table 1): a change by more than a factor 2 from the first box,
# a box under 400 pixels, a move of more than 20 pixels between consecutive frames.
CHANGE_FACTOR = 2.0
LOW_RESOLUTION_PIXELS = 400.0
FAST_MOTION_PIXELS = 20.0

_SEPARATORS = re.compile(r"[,\s]+")


def derived_attributes(gt) -> frozenset[str]:
    """The attributes UAV123 defines by the ground truth alone, of an N x 4 x,y,w,h track (NaN rows: absent):
    SV, the box's scale (square root of its area) leaves [1/2, 2] times the first box's; ARC, its aspect ratio
    does; LR, some box has under 400 pixels; FM, the centre moves more than 20 pixels between two consecutive
    frames where the target is present. The thresholds are in frames, so a sequence at 10 fps moves "fast"
    sooner than the same one at 30 fps."""
    gt = np.asarray(gt, dtype=np.float64).reshape(-1, 4)
    present = valid_mask(gt)
    boxes = gt[present]
    if not len(boxes):
        return frozenset()
    found = set()
    scale = np.sqrt(boxes[:, 2] * boxes[:, 3])
    aspect = boxes[:, 2] / boxes[:, 3]
    for name, values in (("SV", scale), ("ARC", aspect)):
        ratio = values / values[0]
        if np.any((ratio > CHANGE_FACTOR) | (ratio < 1.0 / CHANGE_FACTOR)):
            found.add(name)
    if np.any(boxes[:, 2] * boxes[:, 3] < LOW_RESOLUTION_PIXELS):
        found.add("LR")
    centres = gt[:, :2] + gt[:, 2:] / 2.0
    consecutive = present[1:] & present[:-1]
    moves = np.hypot(*(centres[1:] - centres[:-1])[consecutive].T)
    if np.any(moves > FAST_MOTION_PIXELS):
        found.add("FM")
    return frozenset(found)


def read_uav123_flags(path: Path) -> frozenset[str]:
    """A UAV123 att file: 12 comma-separated 0/1 flags in the order of UAV123_ATTRIBUTES."""
    text = read_text(path).strip()
    try:
        flags = [float(p) for p in _SEPARATORS.split(text) if p]
    except ValueError:
        raise ValueError(f"{path}: expected {len(UAV123_ATTRIBUTES)} 0/1 flags, got {text[:80]!r}") from None
    if len(flags) != len(UAV123_ATTRIBUTES):
        raise ValueError(f"{path}: expected {len(UAV123_ATTRIBUTES)} 0/1 flags, got {len(flags)}")
    return frozenset(name for name, flag in zip(UAV123_ATTRIBUTES, flags) if flag > 0)


def read_attribute_list(path: Path) -> frozenset[str]:
    """An OTB sequence folder's attrs.txt: the sequence's attribute codes, separated by commas or spaces."""
    return frozenset(p for p in _SEPARATORS.split(read_text(path)) if p)


def read_attribute_table(path: Path) -> dict[str, frozenset[str]]:
    """`name ATTR ATTR ...` lines (spaces or commas; `#` starts a comment) -> {name: attributes}."""
    table = {}
    for lineno, line in enumerate(read_text(path).splitlines(), 1):
        parts = [p for p in _SEPARATORS.split(line.split("#", 1)[0]) if p]
        if not parts:
            continue
        if parts[0] in table:
            raise ValueError(f"{path}:{lineno}: sequence {parts[0]!r} listed twice")
        table[parts[0]] = frozenset(parts[1:])
    if not table:
        raise ValueError(f"{path}: no sequences listed")
    return table


def attributes_of(sequences, table: dict[str, frozenset[str]] | None = None) -> tuple[str, dict[str, frozenset]]:
    """(source, {sequence name: attributes}) for a run: the table's when one is given (a sequence is found by its
    name or the last part of it), else the benchmark's own when its loader found them, else derived from each
    sequence's ground truth. Sequences a table leaves out get none, with a warning."""
    if table is not None:
        found = {}
        for seq in sequences:
            attributes = table.get(seq.name, table.get(seq.name.rsplit("/", 1)[-1]))
            if attributes is None:
                log.warning("%s: not in the attribute table; it counts for no attribute", seq.name)
            found[seq.name] = attributes or frozenset()
        return "table", found
    if any(seq.attributes is not None for seq in sequences):
        return "dataset", {seq.name: seq.attributes or frozenset() for seq in sequences}
    return "derived", {seq.name: derived_attributes(seq.gt) for seq in sequences}
