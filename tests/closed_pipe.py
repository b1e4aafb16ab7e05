"""A command whose standard output is read by `head`: the reader takes a few lines and closes the pipe."""
from __future__ import annotations

import subprocess
import sys


def head(argv: list[str], lines: int, timeout: float = 120) -> tuple[int, list[str], str]:
    """Run `python -m tacf.cli ARGV | head -LINES`: (exit code, the lines read, standard error)."""
    process = subprocess.Popen([sys.executable, "-m", "tacf.cli", *argv], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    read = [process.stdout.readline() for _ in range(lines)]
    process.stdout.close()
    try:
        _, err = process.communicate(timeout=timeout)
    finally:
        if process.poll() is None:
            process.kill()
    return process.returncode, read, err
