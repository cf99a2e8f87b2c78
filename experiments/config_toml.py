"""A resolved :class:`~experiments.config.Config` written back as TOML: every default spelled out, the
derived values with a comment naming their source, and the run's provenance (``config.toml`` next to every
result)."""
from __future__ import annotations

import dataclasses

from experiments.config import (OPTIONAL_SECTIONS, SCENARIO_TABLES, SECTIONS, SENSING_SECTIONS, SUMO_ONLY_KEYS,
                                Config)
from experiments.config_extends import KEY as EXTENDS


def toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def table_lines(name: str, obj) -> list[str]:
    """``[name]`` with the fields of a dataclass; a tuple of dataclasses becomes ``[[name.field]]`` tables."""
    lines = [f"[{name}]"]
    nested = []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, tuple) and value and all(dataclasses.is_dataclass(v) for v in value):
            nested.append((f.name, value))
        else:
            lines.append(f"{f.name} = {toml_value(value)}")
    lines.append("")
    for key, items in nested:
        for item in items:
            lines += [f"[{line}]" if line.startswith("[") else line for line in table_lines(f"{name}.{key}", item)]
    return lines


def written_sections(cfg: Config) -> list[str]:
    """Tables a saved config spells out: every section but the unused scenario table(s)."""
    return [n for n in SECTIONS if n not in SCENARIO_TABLES or n == cfg.scenario.kind]


def config_to_toml(cfg: Config, provenance: dict[str, str | int | float]) -> str:
    """The fully resolved config (every default spelled out) plus provenance, as TOML.

    Keys whose value is None (TOML has no null) are written as comments; derived
    values carry a comment naming their source (``cfg.notes``).
    """
    notes = dict(cfg.notes)
    lines = [f"# Resolved from {cfg.path}"]
    if EXTENDS in notes:  # the inheritance chain it was merged from (the config itself first)
        lines.append(f"# Extends: {notes[EXTENDS]}")
    lines.append("")
    for name in written_sections(cfg):
        lines.append(f"[{name}]" + (f"  # {notes[name]}" if name in notes else ""))
        for f in dataclasses.fields(getattr(cfg, name)):
            if name == "scenario" and cfg.is_controlled_scenario and f.name in SUMO_ONLY_KEYS:
                continue
            if name == "sensors" and f.name in SENSING_SECTIONS:
                continue  # written as their own tables
            value = getattr(getattr(cfg, name), f.name)
            note = notes.get(f"{name}.{f.name}")
            if value is None:
                lines.append(f"# {f.name}: not set (the default rule applies)")
                continue
            lines.append(f"{f.name} = {toml_value(value)}" + (f"  # {note}" if note else ""))
        lines.append("")
    for name in OPTIONAL_SECTIONS:
        if getattr(cfg, name) is not None:
            lines += table_lines(name, getattr(cfg, name))
    lines.append("[provenance]")
    for key, val in provenance.items():
        lines.append(f"{key} = {toml_value(val)}")
    return "\n".join(lines) + "\n"
