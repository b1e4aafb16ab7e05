"""Where a result came from: the code, the libraries and the machine, recorded in every summary.json and bench
JSON, so that a number can be traced back, and two runs told apart, long after it was made."""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
from datetime import datetime, timezone
from pathlib import Path

#: The source tree tacf runs from when it is a checkout (an editable install): tacf/eval/ -> the repository.
SOURCE_ROOT = Path(__file__).resolve().parents[2]


def provenance(args: argparse.Namespace | None = None) -> dict:
    """The command's arguments, the time, tacf's version and commit, the numeric libraries, the machine."""
    import cv2
    import numpy
    import scipy

    from tacf import __version__

    record = {}
    if args is not None:
        record["arguments"] = {k: _plain(v) for k, v in sorted(vars(args).items()) if k != "func"}
    record.update({"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "tacf": __version__,
                   "commit": source_commit(), "python": platform.python_version(), "numpy": numpy.__version__,
                   "scipy": scipy.__version__, "opencv": cv2.__version__, "platform": platform.platform(),
                   "cpu": cpu_model(), "cpus": os.cpu_count()})
    return record


def _plain(value):
    """An argument as JSON holds it: numbers, booleans and None as they are, lists item by item, paths absolute."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, Path):
        return str(value.resolve())
    return value if isinstance(value, (int, float, bool, type(None))) else str(value)


def source_commit(root: Path = SOURCE_ROOT) -> str | None:
    """The git commit tacf runs from, with '+dirty' when tracked files have changed since; None when it does not
    run from a git checkout (a wheel install: a repository around site-packages is not ours)."""
    if not (root / ".git").exists() or not (root / "tacf").is_dir():
        return None
    try:
        head = _git(root, "rev-parse", "HEAD")
        changed = _git(root, "status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("+dirty" if changed else "")


def _git(root: Path, *command: str) -> str:
    # --no-optional-locks: `status` refreshes the index under .git/index.lock otherwise, which made a `git commit`
    # run meanwhile fail, and which a git that could not write (a full disk) left behind
    return subprocess.run(["git", "--no-optional-locks", "-C", str(root), *command], capture_output=True, text=True,
                          timeout=10, check=True).stdout.strip()


def cpu_model() -> str:
    """The processor's name (Linux: /proc/cpuinfo's model name), else what the platform module knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
