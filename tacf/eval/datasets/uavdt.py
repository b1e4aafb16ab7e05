"""The official UAVDT single-object-tracking layout.

    <ROOT>/UAV-benchmark-S/<seq>/img000001.jpg ...
    <ROOT>/UAV-benchmark-SOT_v1.0/anno/<seq>_gt.txt    (comma-separated x,y,w,h, 1-based)
                                  anno/att/<seq>_att.txt (attributes; ignored)

ROOT may also be UAV-benchmark-S itself with UAV-benchmark-SOT_v1.0 beside or inside it.
Sequences are named 'UAVDT/<seq>'.
"""
from __future__ import annotations

import logging
from pathlib import Path

from .base import Sequence, list_frames, make_sequence, read_boxes

log = logging.getLogger(__name__)

FRAMES_DIR = "UAV-benchmark-S"
ANNO_DIR = "UAV-benchmark-SOT_v1.0"


def _dirs(root: Path) -> tuple[Path, Path] | None:
    """(frames dir, anno dir) for a UAVDT root, or None."""
    root = Path(root)
    frames_dir = root / FRAMES_DIR if (root / FRAMES_DIR).is_dir() else (root if root.name == FRAMES_DIR else None)
    if frames_dir is None:
        return None
    for cand in (root / ANNO_DIR / "anno", frames_dir / ANNO_DIR / "anno", frames_dir.parent / ANNO_DIR / "anno"):
        if cand.is_dir():
            return frames_dir, cand
    return None


def is_uavdt(root: Path) -> bool:
    return _dirs(root) is not None


def load(root: Path) -> list[Sequence]:
    dirs = _dirs(root)
    if dirs is None:
        raise FileNotFoundError(f"{root}: not a UAVDT root ({FRAMES_DIR}/ and {ANNO_DIR}/anno/ expected)")
    frames_dir, anno_dir = dirs
    seqs = []
    for seq_dir in sorted(p for p in frames_dir.iterdir() if p.is_dir() and p.name != ANNO_DIR):
        gt_path = anno_dir / f"{seq_dir.name}_gt.txt"
        if not gt_path.is_file():
            log.warning("UAVDT/%s: no annotation %s; skipped", seq_dir.name, gt_path)
            continue
        frames = list_frames(seq_dir, prefix="img") or list_frames(seq_dir)
        # numbered from img000001: a missing first frame would shift every row onto the frame after its own
        seq = make_sequence(f"UAVDT/{seq_dir.name}", frames, read_boxes(gt_path), first_number=1)
        if seq is not None:
            seqs.append(seq)
    return seqs
