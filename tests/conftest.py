"""Session-wide test setup, and fixtures several test files share."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest


def pytest_sessionstart(session) -> None:
    """Compile the tracker's numba loops (fHOG, the colour lookup) once, up front: on a fresh checkout the service
    tests' worker processes would otherwise each compile them at the same time (seconds each) instead of loading
    the on-disk cache."""
    from tacf.tracker import compile_loops

    compile_loops()


@pytest.fixture
def unprivileged(tmp_path) -> list[str]:
    """The prefix that runs a command without the power to read what file modes forbid it. Root (the tests run as
    root here) reads everything: setpriv runs the command as root still, but without the capabilities that override
    file modes (CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH), so that modes apply to it as to the files' owner. Not as user
    nobody: the interpreter may lie under root's home, which only root may enter (it does here, under pyenv)."""
    if os.geteuid() != 0:
        return []
    if not shutil.which("setpriv"):
        pytest.skip("no setpriv (util-linux) to run a command without root's power to read every file")
    prefix = ["setpriv", "--bounding-set", "-dac_override,-dac_read_search"]
    locked = tmp_path / "probe"
    locked.mkdir()
    locked.chmod(0)
    probe = subprocess.run(prefix + [sys.executable, "-c", "import os, sys, tacf_clients; os.listdir(sys.argv[1])",
                                     str(locked)], capture_output=True, text=True, timeout=60)
    if "PermissionError" not in probe.stderr:
        reason = probe.stderr.strip()[-300:] or "root still lists a chmod 000 folder"
        pytest.skip(f"cannot take root's power to read every file here: {reason}")
    return prefix
