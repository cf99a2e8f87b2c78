"""Config inheritance: a run config may say ``extends = "other.toml"`` at top level.

The parent (a path relative to the file that names it; chains allowed, a extends b extends c) is read
first and the file's own tables are laid over it:

* tables merge key by key, recursively (the overlay's value wins);
* arrays (also arrays of tables, ``[[perception.sensors]]``) and scalars are replaced whole.

Paths inside a parent keep meaning what they meant where they were written: ``scenario.net_dir``
of a parent is made absolute against the parent's folder during the merge (an overlay's own
``net_dir`` stays relative to the overlay, as without inheritance). A cycle or a missing parent is an
:class:`InputError` naming the file and ``extends``. The merged data has no ``extends`` key, so the
saved ``config.toml`` of a run is fully resolved and loads on its own.

:func:`resolve_extends` also returns where each key was written (``origins``), so that an error about
an inherited key can name the parent file that wrote it.
"""

from __future__ import annotations

import copy
import os
import re
from pathlib import Path

from couplers.errors import InputError, read_toml

KEY = "extends"
#: Keys holding a path relative to the config file that writes them.
PATH_KEYS = (("scenario", "net_dir"),)


class ConfigData(dict):
    """The merged tables of a config, with ``origins``: key path (tuple) -> the file that wrote it,
    and ``chain``: the files merged, the config itself first. A plain ``dict`` otherwise (copies
    with :func:`copy.deepcopy` keep both attributes)."""

    origins: dict[tuple[str, ...], Path]
    chain: tuple[Path, ...]


def _record(origins: dict, data: dict, prefix: tuple[str, ...], path: Path) -> None:
    for key, value in data.items():
        here = (*prefix, key)
        if not isinstance(value, dict):  # replaced whole: forget what a parent wrote below it
            for k in [k for k in origins if k[:len(here)] == here and len(k) > len(here)]:
                del origins[k]
        origins[here] = path
        if isinstance(value, dict):
            _record(origins, value, here, path)


def merge(parent: dict, overlay: dict) -> dict:
    """``overlay`` laid over ``parent``: tables merged recursively, everything else replaced whole."""
    out = copy.deepcopy(parent)
    for key, value in overlay.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _absolute_paths(data: dict, path: Path) -> dict:
    """A parent's path keys made absolute against the parent's own folder."""
    data = copy.deepcopy(data)
    for table, key in PATH_KEYS:
        t = data.get(table)
        if isinstance(t, dict) and isinstance(t.get(key), str) and t[key]:
            t[key] = str((path.parent / t[key]).resolve())
    return data


def _name(path: Path, top: Path) -> str:
    return os.path.relpath(path, top.parent)


def resolve_extends(data: dict, path: str | Path) -> ConfigData:
    """The config ``data`` read from ``path`` with its ``extends`` chain merged in (no ``extends`` left)."""
    path = Path(path)
    top = path.resolve()
    layers = [(path, data)]  # the config first, then each parent
    seen = [top]
    while KEY in layers[-1][1]:
        file, own = layers[-1]
        parent_ref = own[KEY]
        if not isinstance(parent_ref, str) or not parent_ref:
            raise InputError(file, KEY, f"expected the path of a config file, got {parent_ref!r}")
        parent = (file.parent / parent_ref).resolve()
        if parent in seen:
            cycle = seen[seen.index(parent):] + [parent]
            raise InputError(cycle[0] if cycle[0] != top else path, KEY,
                             "cycle " + " -> ".join(_name(p, top) for p in cycle))
        if not parent.is_file():
            raise InputError(file, KEY, f"no config file at {parent}")
        seen.append(parent)
        layers.append((parent, read_toml(parent, "config file")))
        if "study" in layers[-1][1]:  # experiments/studies: their own schemas, not merged
            raise InputError(file, KEY, f"{parent_ref} is a study config: only run configs can be extended")
    merged: dict = {}
    origins: dict[tuple[str, ...], Path] = {}
    for i, (file, own) in enumerate(reversed(layers)):
        own = {k: v for k, v in own.items() if k != KEY}
        if i < len(layers) - 1:  # a parent: its relative paths are relative to its own folder
            own = _absolute_paths(own, file)
        merged = merge(merged, own)
        _record(origins, own, (), file)
    out = ConfigData(merged)
    out.origins = origins
    out.chain = tuple(f for f, _ in layers)
    return out


def read_config_data(path: str | Path) -> dict:
    """A run config file's tables, its ``extends`` chain merged in (a :class:`ConfigData` if it had one)."""
    data = read_toml(path, "config file")
    return resolve_extends(data, path) if KEY in data else data


def origin_of(data: dict, field: str | None) -> Path | None:
    """The file that wrote the key ``field`` (dotted, list indices allowed) of merged ``data``, or None."""
    origins = getattr(data, "origins", None)
    if not origins or not field:
        return None
    keys = tuple(re.sub(r"\[\d+\]", "", field).split("."))
    for n in range(len(keys), 0, -1):
        if keys[:n] in origins:
            return origins[keys[:n]]
    return None


def chain_text(data: dict) -> str | None:
    """``a.toml -> b.toml -> c.toml`` for merged ``data`` (None for a config without ``extends``)."""
    chain = getattr(data, "chain", None)
    if not chain or len(chain) < 2:
        return None
    return " -> ".join([chain[0].name] + [str(p) for p in chain[1:]])
