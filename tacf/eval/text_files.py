"""Reading the text files of the benchmarks and of other tools' results; writing the result and report files."""
from __future__ import annotations

import contextlib
from pathlib import Path


def read_text(path: Path) -> str:
    """A ground-truth, attribute or result file's text: UTF-8, whatever the platform's locale, and without the
    byte-order mark Windows Notepad puts first (it made the first line "not a number")."""
    return Path(path).read_text(encoding="utf-8-sig")


def drawable(name: str) -> str:
    """A name as text to draw (a plot's title, a video's band): the bytes of a file name that are not UTF-8 (a GBK
    folder name, decoded by Python to lone surrogates) as U+FFFD; matplotlib refuses such a name, and OpenCV's
    putText crashes the process (SIGSEGV) on it."""
    return name.encode(errors="surrogateescape").decode(errors="replace")


class CannotWrite(OSError):
    """An output file that could not be written: 'cannot write PATH: REASON' (a full disk's OSError named no
    file)."""

    @classmethod
    def naming(cls, exc: OSError, path: Path) -> CannotWrite:
        """`exc`, raised while writing `path`, naming it."""
        return cls(exc.errno, exc.strerror or str(exc), str(path))

    def __str__(self) -> str:
        return f"cannot write {self.filename}: {self.strerror}"


def write_atomically(path: Path, data: str | bytes) -> None:
    """Write `path` (its folders made) whole or not at all: `data` (str: UTF-8) goes to PATH.part, which then
    replaces it, so that a full disk leaves the file of an earlier run, or none, never a cut one. CannotWrite
    when it fails, PATH.part removed (as on an interrupt). A path that is there and not a regular file is written
    to in place."""
    # surrogateescape: a sequence named by a folder whose name is not UTF-8 (GBK) keeps that name's bytes
    path, data = Path(path), data.encode(errors="surrogateescape") if isinstance(data, str) else data
    part = path.with_name(path.name + ".part")
    try:
        if path.exists() and not path.is_file():
            # a device, a pipe (`--json /dev/stdout`): written to, never replaced (as root, a rename in /dev would)
            path.write_bytes(data)
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        part.write_bytes(data)
        part.replace(path)
    except BaseException as exc:        # a Ctrl-C too: no PATH.part left beside the results
        with contextlib.suppress(OSError):
            part.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise CannotWrite.naming(exc, path) from None
        raise
