"""Reading the text files of the benchmarks and of other tools' results."""
from __future__ import annotations

from pathlib import Path


def read_text(path: Path) -> str:
    """A ground-truth, attribute or result file's text: UTF-8, whatever the platform's locale, and without the
    byte-order mark Windows Notepad puts first (it made the first line "not a number")."""
    return Path(path).read_text(encoding="utf-8-sig")
