"""One exception type for bad input, carrying the file and field it concerns."""

from __future__ import annotations

import contextlib
import contextvars
import tomllib
from pathlib import Path


# The seeds SUMO accepts (``--seed`` is a C++ int): every seed a user gives is checked against this
# range, also where no SUMO runs (controlled scenarios, studies), so one seed works everywhere.
SEED_MAX = 2**31 - 1


def seed_problem(value) -> str | None:
    """Why ``value`` is not a usable seed (None when it is): an integer in [0, 2^31 - 1]."""
    if isinstance(value, bool) or not isinstance(value, int):
        return f"expected an integer, got {value!r}"
    if not 0 <= value <= SEED_MAX:
        return f"must be an integer from 0 to {SEED_MAX} (the seeds SUMO accepts), got {value}"
    return None


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


#: The TOML files :func:`read_toml` read while :func:`recording_reads` is active (None: not recording).
_READS: contextvars.ContextVar[list[Path] | None] = contextvars.ContextVar("coloc_toml_reads", default=None)


@contextlib.contextmanager
def recording_reads():
    """Collect the resolved path of every TOML file :func:`read_toml` reads inside the block (a sweep
    records the configs it was started with, ``extends`` chains included)."""
    reads: list[Path] = []
    token = _READS.set(reads)
    try:
        yield reads
    finally:
        _READS.reset(token)


def read_toml(path: str | Path, kind: str = "file") -> dict:
    """Parse a TOML file; a missing file, a directory or broken TOML is an :class:`InputError`.

    ``kind`` names the file in the messages ("config file", "sweep file", ...).
    """
    path = Path(path)
    reads = _READS.get()
    if reads is not None:
        reads.append(path.resolve())
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(path, None, f"{kind} not found") from None
    except IsADirectoryError:
        raise InputError(path, None, f"is a directory, not a {kind}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, None, f"not valid TOML ({exc})") from None
