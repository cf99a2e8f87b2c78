"""One exception type for bad input, carrying the file and field it concerns."""

from __future__ import annotations

import tomllib
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


def read_toml(path: str | Path, kind: str = "file") -> dict:
    """Parse a TOML file; a missing file, a directory or broken TOML is an :class:`InputError`.

    ``kind`` names the file in the messages ("config file", "sweep file", ...).
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(path, None, f"{kind} not found") from None
    except IsADirectoryError:
        raise InputError(path, None, f"is a directory, not a {kind}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, None, f"not valid TOML ({exc})") from None
