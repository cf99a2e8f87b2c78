"""Shared pieces of the paper studies (sme, fg_topology): table validation, resolved TOML, atomic output.

A study config is a few TOML tables of scalars and lists. Each study declares
for each table the allowed keys with a default and a check; :func:`resolve`
fills the defaults, rejects unknown tables and keys and wrong types with an
:class:`couplers.errors.InputError` naming the file and ``table.key``, and
:func:`resolved_toml` writes the result back with provenance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from couplers.errors import InputError
from experiments.config_toml import toml_value
from experiments.ranges import check_nested
from experiments.runner import git_revision


@dataclass(frozen=True)
class Key:
    """One config key: its default, its kind ("int", "float", "str", "bool", "floats", "ints", "list"),
    an optional check returning an error message or None, and a one-line help."""

    default: Any
    kind: str
    check: Callable[[Any], str | None] | None = None
    help: str = ""


def positive(v) -> str | None:
    return None if v > 0 else "must be > 0"


def non_negative(v) -> str | None:
    return None if v >= 0 else "must be >= 0"


def at_least(n):
    return lambda v: None if v >= n else f"must be >= {n}"


def one_of(*choices):
    return lambda v: None if v in choices else "must be one of " + ", ".join(repr(c) for c in choices)


def _convert(value, kind: str, path: Path, field: str):
    def bad(what: str):
        raise InputError(path, field, f"expected {what}, got {value!r}")

    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            bad("an integer")
        return value
    if kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            bad("a number")
        if not math.isfinite(value):
            bad("a finite number")
        return float(value)
    if kind == "str":
        if not isinstance(value, str):
            bad("a string")
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            bad("true or false")
        return value
    if kind in ("floats", "ints"):
        if not isinstance(value, list) or not value:
            bad("a non-empty list")
        inner = "float" if kind == "floats" else "int"
        return [_convert(v, inner, path, field) for v in value]
    if kind == "list":
        if not isinstance(value, list) or not value:
            bad("a non-empty list")
        return value
    raise ValueError(kind)


def resolve(data: dict, path: Path, spec: dict[str, dict[str, Key]], ranges: dict | None = None
            ) -> dict[str, dict[str, Any]]:
    """Defaults filled, every key checked; unknown tables and keys are errors. ``ranges``: the study's
    physical ranges (:data:`experiments.studies.ranges.STUDY_RANGES`), every number checked against them."""
    for name in data:
        if name not in spec:
            raise InputError(path, name, f"unknown table (allowed: {', '.join(spec)})")
    out: dict[str, dict[str, Any]] = {}
    for name, keys in spec.items():
        table = data.get(name, {})
        if not isinstance(table, dict):
            raise InputError(path, name, "must be a table")
        for key in table:
            if key not in keys:
                raise InputError(path, f"{name}.{key}", f"unknown key (allowed: {', '.join(keys)})")
        resolved = {}
        for key, k in keys.items():
            field = f"{name}.{key}"
            value = _convert(table[key], k.kind, path, field) if key in table else k.default
            if k.check is not None:
                msg = k.check(value)
                if msg:
                    raise InputError(path, field, msg)
            if ranges is not None:
                check_nested(value, field, path, ranges)
            resolved[key] = value
        out[name] = resolved
    return out


def resolved_toml(cfg: dict[str, dict[str, Any]], spec: dict[str, dict[str, Key]], source: Path,
                  provenance: dict[str, Any]) -> str:
    lines = [f"# Resolved from {source}", ""]
    for name, table in cfg.items():
        lines.append(f"[{name}]")
        for key, value in table.items():
            note = spec[name][key].help
            lines.append(f"{key} = {toml_value(value)}" + (f"  # {note}" if note else ""))
        lines.append("")
    lines.append("[provenance]")
    for key, val in provenance.items():
        lines.append(f"{key} = {toml_value(val)}")
    return "\n".join(lines) + "\n"


__all__ = ["Key", "resolve", "resolved_toml", "git_revision", "positive", "non_negative",
           "at_least", "one_of"]
