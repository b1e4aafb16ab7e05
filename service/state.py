"""StateStore: the session table persisted as a small JSON file, written atomically (tmp + fsync + rename).

A missing file is an empty table; a corrupt one is logged, kept aside as <file>.corrupt and treated as empty,
so a bad file never stops the service from starting.
"""
from __future__ import annotations

import json
import logging
import os
import tempfile
from pathlib import Path
from typing import Union

from pydantic import BaseModel, ConfigDict, ValidationError

from tacf_schemas.models import Box, Id

log = logging.getLogger(__name__)

STATE_VERSION = 1


class PersistedSession(BaseModel):
    model_config = ConfigDict(extra="ignore")

    sid: Id
    image_key: str
    profile: str
    overrides: dict[str, Union[bool, int, float]] = {}
    box: Box
    last_seq: int | None = None
    created_ns: int
    restarts: int = 0


class StateStore:
    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)

    def load(self) -> list[PersistedSession]:
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return []
        except OSError as exc:
            log.error("cannot read state file %s: %s", self.path, exc)
            return []
        try:
            doc = json.loads(text)
            entries = doc["sessions"] if isinstance(doc, dict) else None
            if not isinstance(entries, list):
                raise ValueError("no 'sessions' list")
        except (ValueError, KeyError, TypeError) as exc:
            log.error("state file %s is corrupt (%s); keeping it as .corrupt and starting empty", self.path, exc)
            self._set_aside()
            return []
        sessions = []
        for entry in entries:
            try:
                sessions.append(PersistedSession.model_validate(entry))
            except ValidationError as exc:
                log.warning("skipping an invalid session in %s: %s", self.path, exc.errors()[:1])
        return sessions

    def save(self, sessions: list[PersistedSession]) -> None:
        doc = {"version": STATE_VERSION, "sessions": [s.model_dump(mode="json") for s in sessions]}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=self.path.name + ".", suffix=".tmp", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w") as fh:
                json.dump(doc, fh, indent=1)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise

    def _set_aside(self) -> None:
        try:
            os.replace(self.path, self.path.with_name(self.path.name + ".corrupt"))
        except OSError:
            pass
