"""One exception type for bad input, carrying the file and field it concerns."""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad user input: the command line prints ``file: field: message`` and exits non-zero."""

    def __init__(self, path: str | Path | None, field: str | None, message: str):
        self.path = None if path is None else str(path)
        self.field = field
        self.message = message
        super().__init__(self.describe())

    def describe(self) -> str:
        parts = [p for p in (self.path, self.field) if p]
        return ": ".join(parts + [self.message])
