"""Dataset loaders: detect the layout of a ROOT folder and yield Sequence objects (0-based xywh gt).

    from tacf.eval.datasets import load_sequences
    for seq in load_sequences("../shared/data/sequences", pattern="UAV123*"):
        seq.name, seq.frames, seq.gt          # 'UAV123_10fps/wakeboard7', (Path, ...), N x 4 float

Layouts (one module each): `uav123` (data_seq/ + anno/ + range table), `uavdt` (UAV-benchmark-S/ +
UAV-benchmark-SOT_v1.0/anno/), `otb` and `generic` (a folder per sequence; see folders.py).
"""
from __future__ import annotations

import fnmatch
from pathlib import Path

from . import folders, uav123, uavdt
from .base import Sequence, list_frames, read_boxes, write_boxes

__all__ = ["Sequence", "LAYOUTS", "detect_layout", "load_sequences", "match", "read_boxes", "write_boxes",
           "list_frames"]

LAYOUTS = ("uav123", "uavdt", "otb", "generic")


def detect_layout(root: Path) -> str:
    """The layout name of a dataset root; raises FileNotFoundError when nothing is recognised."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset root {root} is not a folder")
    if uav123.is_uav123(root):
        return "uav123"
    if uavdt.is_uavdt(root):
        return "uavdt"
    if folders.sequence_folders(root):
        return "otb" if folders.is_otb(root) else "generic"
    raise FileNotFoundError(
        f"{root}: no known dataset layout (<seq>/img + groundtruth.txt, OTB groundtruth_rect.txt, "
        "UAV123 data_seq/ + anno/, UAVDT UAV-benchmark-S/ + UAV-benchmark-SOT_v1.0/anno/)")


def match(name: str, pattern: str | None) -> bool:
    """fnmatch on the sequence name; `pattern` may hold several comma-separated globs. A glob without a `/` also
    matches the name's last part: `person12_1` and `wakeboard*` select `UAV123_10fps/person12_1` and the like."""
    if not pattern:
        return True
    globs = [p.strip() for p in pattern.split(",") if p.strip()]
    last_part = name.rsplit("/", 1)[-1]
    return any(fnmatch.fnmatchcase(name, glob) or ("/" not in glob and fnmatch.fnmatchcase(last_part, glob))
               for glob in globs)


def load_sequences(root: Path, pattern: str | None = None, layout: str | None = None,
                   **kwargs) -> list[Sequence]:
    """All sequences under `root` whose name matches `pattern`, sorted by name."""
    root = Path(root)
    layout = layout or detect_layout(root)
    if layout == "uav123":
        seqs = uav123.load(root, **kwargs)
    elif layout == "uavdt":
        seqs = uavdt.load(root)
    elif layout in ("otb", "generic"):
        seqs = folders.load(root)
    else:
        raise ValueError(f"unknown layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    return sorted((s for s in seqs if match(s.name, pattern)), key=lambda s: s.name)
