"""ServiceError: a failed control operation, carried to the client as reply_err(Error)."""
from __future__ import annotations

from tacf_schemas import Error


class ServiceError(Exception):
    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message

    def to_error(self, node: str | None = None) -> Error:
        return Error(code=self.code, message=self.message[:1024], node=node)
