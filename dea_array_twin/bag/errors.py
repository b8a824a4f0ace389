"""The error of the bag writers, shared by the writer and the message definitions it reads."""

from __future__ import annotations

import os

__all__ = ["RecordingError"]


class RecordingError(OSError):
    """The recording cannot go on: a file could not be created or written (e.g. a full disk).

    The message names the file.  The writer is unusable afterwards; a node catching this
    can log it and keep running without recording.
    """

    def __init__(self, message: str, *, path: str | os.PathLike | None = None, errno: int | None = None):
        super().__init__(message)
        self.filename = None if path is None else str(path)
        self.errno = errno

    def __str__(self) -> str:
        return str(self.args[0])
