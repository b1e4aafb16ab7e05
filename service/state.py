"""StateStore: the session table persisted as a small JSON file, written atomically (tmp + fsync + rename).

Next to it, <file>.frames/<sid>.msgpack holds a Frame of each session with the box computed on it, so that a
restored session re-initialises its tracker on the very frame its box belongs to, then catches up on the live
feed, instead of applying a stale box to a frame where the target has moved. The table is saved every second,
the frames at every start, reinit and shutdown and otherwise every 5 s (manager.FRAME_SAVE_PERIOD_S): a frame a
second of each session was a megabyte a second to disk for six 720p feeds, worn into an edge box's SD card.

A missing file is an empty table; a corrupt one is logged, kept aside as <file>.corrupt (<file>.corrupt.1 and on
beside earlier ones) and treated as empty, so a bad file never stops the service from starting. A table of another
version (a newer service's) is kept aside as <file>.v<version> rather than read with the wrong meaning and
overwritten.

A service holds <file>.lock (an OS lock, gone with the process) while it uses the file: a second service given the
same file would restore the first one's sessions, and each would overwrite the other's table.
"""
from __future__ import annotations

import glob
import itertools
import json
import logging
import os
import tempfile
from pathlib import Path

try:
    import fcntl
except ImportError:         # Windows
    fcntl = None
    import msvcrt

from pydantic import BaseModel, ConfigDict, ValidationError

from tacf_schemas.codec import unique_keys
from tacf_schemas.models import Box, Count, Id, Override, Seq, StampNs

log = logging.getLogger(__name__)

STATE_VERSION = 1


class PersistedSession(BaseModel):
    """A session as saved: its fields as the wire's SessionInfo bounds them, so that a restored session always
    makes a valid reply (an entry with created_ns -1 used to make every list and its status fail)."""
    model_config = ConfigDict(extra="ignore")

    sid: Id
    image_key: str
    profile: str
    overrides: dict[str, Override] = {}
    box: Box
    last_seq: Seq | None = None
    created_ns: StampNs
    restarts: Count = 0
    # The stored frame's seq and the box computed on it (older than box and last_seq between two frame saves).
    frame_seq: Seq | None = None
    frame_box: Box | None = None


class StateError(Exception):
    """The state file cannot be used (in use by another service, or not writable)."""


class StateStore:
    def __init__(self, path: str | os.PathLike) -> None:
        # The file a link names: through the link, a second service took a lock of its own beside it, restored the
        # first one's sessions and shared its file, and its first save replaced the link with a file.
        self.path = Path(os.path.realpath(path))
        self._lock_file = None
        # The entries of the file that load() skipped (invalid, or a sid given twice): save() writes them back as
        # they were, so that a hand edit gone wrong can be mended rather than lost at the first save.
        self._unread: list = []

    def lock(self) -> None:
        """Take the state file for this service (StateError if another service holds it, or it cannot be read).
        Creating the lock file also finds, at start, a state file that could never be saved."""
        if self.path.is_dir():
            raise StateError(f"state file {self.path} is a directory")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            lock_file = open(self.path.with_name(self.path.name + ".lock"), "ab")
        except OSError as exc:
            raise StateError(f"cannot use state file {self.path}: {exc}") from None
        try:
            _lock_exclusively(lock_file)
        except OSError:
            lock_file.close()
            raise StateError(f"state file {self.path} is in use by another service") from None
        self._lock_file = lock_file
        self._check_readable()
        self._remove_partial_writes()

    def _check_readable(self) -> None:
        """Refuse a state file that is there but cannot be read (its owner or mode, a loop of links, a disk error):
        a service that started empty on it would replace it, and the sessions it holds, at its first save."""
        try:
            self.path.read_bytes()
        except FileNotFoundError:
            return
        except OSError as exc:
            self.unlock()
            raise StateError(f"cannot read state file {self.path}: {exc.strerror or exc}") from None

    def _remove_partial_writes(self) -> None:
        """Remove what a service killed in the middle of a write left (its temporary files, frames of up to
        48 MiB among them): this service holds the lock, so no write of another is under way."""
        ours = [p for p in self.path.parent.glob(f"{glob.escape(self.path.name)}.*.tmp")
                if "." not in p.name[len(self.path.name) + 1:-len(".tmp")]]   # not sessions.json.edge2's
        frames = self.frames_dir.glob("*.tmp") if self.frames_dir.is_dir() else []
        for leftover in [*ours, *frames]:
            try:
                leftover.unlink()
            except OSError:
                pass

    def unlock(self) -> None:
        if self._lock_file is not None:
            self._lock_file.close()         # closing the file releases the lock
            self._lock_file = None

    def load(self) -> list[PersistedSession]:
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            return []
        except OSError as exc:
            log.error("cannot read state file %s: %s", self.path, exc)
            return []
        try:
            doc = json.loads(data, object_pairs_hook=unique_keys)    # a key given twice: which one was meant?
            if not isinstance(doc, dict):
                raise ValueError("not a JSON object")
        except (ValueError, RecursionError) as exc:     # bad UTF-8 is a ValueError too
            log.error("state file %s is corrupt (%s); keeping it as %s and starting empty", self.path, exc,
                      self._set_aside(".corrupt"))
            return []
        # The version first: a newer service's table may have another shape. An int, exactly: True and 1.0 equal 1.
        version = doc.get("version")
        if type(version) is not int or version != STATE_VERSION:
            suffix = f".v{version}" if type(version) is int and version > STATE_VERSION else ".corrupt"
            log.error("state file %s has version %r, this service reads version %d; keeping it as %s and starting "
                      "empty", self.path, version, STATE_VERSION, self._set_aside(suffix))
            return []
        entries = doc.get("sessions")
        if not isinstance(entries, list):
            log.error("state file %s is corrupt (no 'sessions' list); keeping it as %s and starting empty", self.path,
                      self._set_aside(".corrupt"))
            return []
        sessions: dict[str, PersistedSession] = {}
        self._unread = []
        for entry in entries:
            try:
                session = PersistedSession.model_validate(entry)
            except ValidationError as exc:
                error = exc.errors()[0]
                sid = entry.get("sid") if isinstance(entry, dict) else None
                log.warning("skipping an invalid session %r in %s (kept in the file): %s: %s", sid, self.path,
                            ".".join(map(str, error["loc"])) or "the entry", error["msg"])
                self._unread.append(entry)
                continue
            if session.sid in sessions:
                log.warning("skipping a second session %s in %s (kept in the file)", session.sid, self.path)
                self._unread.append(entry)
                continue
            sessions[session.sid] = session
        return list(sessions.values())

    def save(self, sessions: list[PersistedSession]) -> None:
        doc = {"version": STATE_VERSION, "sessions": [s.model_dump(mode="json") for s in sessions] + self._unread}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        _atomic_write(self.path, json.dumps(doc, indent=1).encode())

    @property
    def frames_dir(self) -> Path:
        return self.path.with_name(self.path.name + ".frames")

    def frame_path(self, sid: str) -> Path:
        return self.frames_dir / f"{sid}.msgpack"

    def save_frame(self, sid: str, payload: bytes) -> None:
        """Atomically store the Frame (msgpack bytes) a session's last box belongs to."""
        self.frames_dir.mkdir(parents=True, exist_ok=True)
        _atomic_write(self.frame_path(sid), payload)

    def load_frame(self, sid: str) -> bytes | None:
        try:
            return self.frame_path(sid).read_bytes()
        except OSError:
            return None

    def prune_frames(self, keep: set[str]) -> None:
        if not self.frames_dir.is_dir():
            return
        keep = keep | {entry["sid"] for entry in self._unread
                       if isinstance(entry, dict) and isinstance(entry.get("sid"), str)}
        for path in self.frames_dir.glob("*.msgpack"):
            if path.stem not in keep:
                try:
                    path.unlink()
                except OSError:
                    pass

    def _set_aside(self, suffix: str) -> str:
        """Move the file to <file><suffix>, or <file><suffix>.N beside earlier ones (each of which may be all that
        is left of some table); what became of it, for the log."""
        kept = self.path.with_name(self.path.name + suffix)
        for n in itertools.count(1):
            if not os.path.lexists(kept):
                break
            kept = self.path.with_name(f"{self.path.name}{suffix}.{n}")
        try:
            os.replace(self.path, kept)
        except OSError as exc:
            return f"nothing (it cannot be moved to {kept.name}: {exc.strerror or exc}; the next save replaces it)"
        return kept.name


def _lock_exclusively(lock_file) -> None:
    """Lock an open file for this process without waiting (OSError if another holds it)."""
    if fcntl is not None:
        fcntl.flock(lock_file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    else:
        msvcrt.locking(lock_file.fileno(), msvcrt.LK_NBLCK, 1)


def _atomic_write(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        _sync_folder(path.parent)       # the rename itself survives a power cut
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _sync_folder(folder: Path) -> None:
    if not hasattr(os, "O_DIRECTORY"):      # Windows: a folder cannot be opened to sync it
        return
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
