"""Sequence-per-folder layouts: the generic layout of ../shared/data/sequences and OTB.

generic: <ROOT>/[<dataset>/...]<seq>/img/*.jpg + groundtruth.txt (comma-separated, 1-based); the official
         VOT layouts (frames beside a groundtruth.txt of polygons, or in color/ as the VOT toolkit of 2020 on
         keeps them) read each polygon as its enclosing box.
         The VOT folders of ../shared/data also hold groundtruth_poly.txt, which is ignored.
OTB:     <ROOT>/<seq>/img/*.jpg + groundtruth_rect.txt (comma, tab or space separated, 1-based); the
         two-target sequences ship groundtruth_rect.1.txt / .2.txt and become <seq>-1 / <seq>-2.
         An attrs.txt beside them (OTB's Python toolkit: `SV, DEF, FM, OPR, BC`) gives the attributes.
Folders may be nested to any depth; a sequence's name is its folder path relative to ROOT.
"""
from __future__ import annotations

import logging
import os
import re
from pathlib import Path

from ..attributes import read_attribute_list
from ...images import IMAGE_SUFFIXES
from .base import Sequence, list_frames, make_sequence, read_boxes

log = logging.getLogger(__name__)

GENERIC_GT = "groundtruth.txt"
ATTRIBUTES = "attrs.txt"
OTB_GT = re.compile(r"^groundtruth_rect(?:\.(\d+))?\.txt$")
# OTB sequences whose annotation starts later than image 1 (OTB-100 configSeqs: David starts at frame 300).
OTB_FIRST_FRAME = {"david": 300}


def _gt_files(folder: Path) -> list[tuple[str, Path]]:
    """(suffix, path) of the ground-truth files of one folder: '' for a single target, '-N' for target N."""
    names = set(os.listdir(folder))
    if GENERIC_GT in names:
        return [("", folder / GENERIC_GT)]
    found = []
    for name in sorted(names):
        m = OTB_GT.match(name)
        if m:
            found.append((f"-{m.group(1)}" if m.group(1) else "", folder / name))
    return found


FRAME_FOLDERS = ("img", "color")      # color/: the VOT toolkit's layout since 2020 (with depth/ or ir/ beside)


def frames_of(folder: Path) -> list[Path]:
    """A sequence folder's frames: those of its img/ (or VOT's color/) when it has one, else its own."""
    for name in FRAME_FOLDERS:
        frames = list_frames(folder / name)
        if frames:
            return frames
    return list_frames(folder)


def annotated_folders(root: Path) -> list[Path]:
    """Every folder under `root` (including root) that holds a ground-truth file, sorted."""
    out = []
    for dirpath, dirnames, _ in os.walk(root):
        folder = Path(dirpath)
        dirnames[:] = sorted(d for d in dirnames if d not in FRAME_FOLDERS and not d.startswith("."))
        if _gt_files(folder):
            out.append(folder)
    return sorted(out)


def sequence_folders(root: Path) -> list[Path]:
    """The folders under `root` (including root) that hold a ground-truth file and frames, sorted."""
    return [folder for folder in annotated_folders(root) if frames_of(folder)]


def is_otb(root: Path) -> bool:
    """True when the folders found use OTB's groundtruth_rect*.txt names."""
    return any(not (f / GENERIC_GT).is_file() for f in sequence_folders(root))


def load(root: Path) -> list[Sequence]:
    """All sequences of a generic or OTB root."""
    root = Path(root)
    seqs = []
    for folder in annotated_folders(root):
        rel = folder.relative_to(root).as_posix()
        # the folder's own name, which "." and ".." lack (`tacf eval .` in a sequence folder named it "", and
        # in OTB's David folder matched its ground truth with the frames from 1 instead of 300)
        own_name = Path(os.path.abspath(folder)).name
        base = own_name if rel == "." else rel
        frames = frames_of(folder)
        if not frames:
            log.warning("%s: ground truth but no frames (%s files) in %s, its img/ or its color/; skipped", base,
                        ", ".join(IMAGE_SUFFIXES), folder)
            continue
        attributes = read_attribute_list(folder / ATTRIBUTES) if (folder / ATTRIBUTES).is_file() else None
        for suffix, gt_path in _gt_files(folder):
            gt = read_boxes(gt_path)
            first = OTB_FIRST_FRAME.get(own_name.lower(), 1) if len(frames) > len(gt) else 1
            # Fewer frames than rows: some are missing. Before the first on disk when it is numbered past where
            # the ground truth starts (000002.jpg first: every row would meet the frame after its own).
            seq = make_sequence(base + suffix, frames[first - 1:], gt, attributes,
                                first_number=first if len(frames) - (first - 1) < len(gt) else None)
            if seq is not None:
                seqs.append(seq)
    return seqs
