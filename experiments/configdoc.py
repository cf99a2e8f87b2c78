"""docs/configuration.md, generated from the run-config schema so it cannot drift.

The tables and keys, their types and defaults come from the loader's own schema
(:data:`experiments.config.SECTIONS` and :data:`~experiments.config.OPTIONAL_SECTIONS`:
the frozen dataclasses every TOML table is validated against). Only the unit and
the meaning of each key are written by hand, in :data:`KEY_DOCS` of
:mod:`experiments.configdoc_text` (importable from here too). A key the loader
accepts without an entry there makes :func:`render` fail, and with it
``tests/experiments/test_configuration_doc.py``.

    python -m experiments.configdoc            # rewrite docs/configuration.md
    python -m experiments.configdoc --check    # exit 1 if the committed page is stale
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import types
import typing
from pathlib import Path

from experiments.config import OPTIONAL_SECTIONS, SCENARIO_TABLES, SECTIONS
from experiments.config_toml import toml_value
from experiments.configdoc_text import INFRA_METHODS, KEY_DOCS, NO_UNIT, TABLE_DOCS  # noqa: F401 (public names)
from experiments.ranges import RANGES

DOC_PATH = Path(__file__).resolve().parent.parent / "docs" / "configuration.md"


def schema() -> dict[str, type]:
    """Table name -> dataclass, in file order; a list of tables (``[[perception.sensors]]``) follows its
    table under its dotted name."""
    out: dict[str, type] = {}
    for table, cls in {**SECTIONS, **OPTIONAL_SECTIONS}.items():
        out[table] = cls
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            args = typing.get_args(hints[f.name])
            if typing.get_origin(hints[f.name]) is tuple and args and dataclasses.is_dataclass(args[0]):
                out[f"{table}.{f.name}"] = args[0]
    return out


def accepted_keys() -> list[tuple[str, str]]:
    """(table, key) for every key the loader accepts: the fields of the schema's dataclasses."""
    return [(table, f.name) for table, cls in schema().items() for f in dataclasses.fields(cls)]


def _numeric(annotation) -> bool:
    if annotation in (int, float):
        return True
    origin = typing.get_origin(annotation)
    if origin in (tuple, typing.Union, types.UnionType):
        return any(_numeric(a) for a in typing.get_args(annotation) if a is not Ellipsis)
    return False


def undocumented() -> list[str]:
    """Accepted keys without a meaning, or numeric keys without a unit; and tables without a text."""
    missing = [f"[{t}]" for t in schema() if not TABLE_DOCS.get(t)]
    for table, cls in schema().items():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            unit, meaning = KEY_DOCS.get(table, {}).get(f.name, ("", ""))
            numeric = _numeric(hints[f.name])
            if not meaning.strip() or (numeric and not unit) or (numeric and f"{table}.{f.name}" not in RANGES):
                missing.append(f"{table}.{f.name}")
    return missing


def stale() -> list[str]:
    """Documented keys the loader does not accept (a field was renamed or removed)."""
    accepted = set(accepted_keys())
    return [f"{t}.{k}" for t, keys in KEY_DOCS.items() for k in keys if (t, k) not in accepted] + \
           [f"[{t}]" for t in TABLE_DOCS if t not in schema()]


def _type_name(annotation) -> str:
    simple = {float: "number", int: "integer", bool: "boolean", str: "string"}
    if annotation in simple:
        return simple[annotation]
    args = typing.get_args(annotation)
    origin = typing.get_origin(annotation)
    if dataclasses.is_dataclass(annotation):
        return "table"
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            inner = "table" if dataclasses.is_dataclass(args[0]) else simple[args[0]]
            return f"list of {inner}s"
        return f"list of {len(args)} {simple[args[0]]}s"
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        return f"{_type_name(inner[0])}, optional"
    raise TypeError(f"no type name for {annotation}")


def _default(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return "required"
    if value is None:
        return "not set"
    if isinstance(value, float) and math.isinf(value):
        return "`inf`"
    if isinstance(value, tuple) and value and dataclasses.is_dataclass(value[0]):
        return f"{len(value)} tables (see meaning)"
    return f"`{toml_value(value)}`"


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def render() -> str:
    """The whole of docs/configuration.md. Raises ValueError if a key lacks documentation."""
    missing, extra = undocumented(), stale()
    if missing or extra:
        raise ValueError("config keys without documentation in experiments/configdoc_text.py KEY_DOCS: "
                         + ", ".join(missing) + ("; documented but not accepted: " + ", ".join(extra) if extra else ""))
    out = [
        "# Configuration reference",
        "",
        "<!-- Generated by `python -m experiments.configdoc` from the schema in experiments/config.py;",
        "     do not edit by hand (tests/experiments/test_configuration_doc.py checks it). -->",
        "",
        "A run config is a TOML file whose tables map onto frozen dataclasses "
        "(`experiments/config.py`). It is validated on load: an unknown table or key, a wrong type "
        "or a value out of range prints one line naming the file and the dotted field and exits "
        "with status 2. Every key has a default except `run.name`; a run saves its config fully "
        "resolved (every default spelled out, derived values with a comment saying where they come "
        "from) as `config.toml` in its output folder.",
        "",
        "Every number has a physical range (column range, in the key's unit; `(` and `)` exclude the "
        "bound, `or inf` accepts TOML `inf` meaning \"always in range\"; a list's range holds for each "
        "element), from `experiments/ranges.py`, where each range says where its bounds come from. A "
        "value outside it, NaN or an infinity is refused on load, also when a sweep or a command-line "
        "option sets it and under `coloc sweep --dry-run`. The ranges are generous (every shipped "
        "config and sweep is well inside); the dataclasses' own checks may refuse more (e.g. a "
        "positive value where the range starts at 0).",
        "",
        "Any key can be overridden by a sweep (`\"table.key\" = [...]` in `[sweep.grid]` or "
        "`[sweep.set]`), see [outputs.md](outputs.md) for what a sweep writes. Units: `1` is "
        "dimensionless; strings, booleans and lists of names have none. Numbers in parentheses such "
        "as (13) are equations of Brambilla et al. The study configs of the other papers "
        "(`experiments/rsu_bp.toml`, `sme.toml`, `fg_topology.toml`, with a `[study]` table) have "
        "their own schemas and ranges in `experiments/studies/` (`ranges.py` there) and are not "
        "covered here.",
        "",
        "Tables: " + ", ".join(f"`[{t}]`" for t in schema() if "." not in t) + " ("
        + " and ".join(f"`[{t}]`" for t in SCENARIO_TABLES) + " only with their `scenario.kind`; "
        + ", ".join(f"`[{t}]`" for t in OPTIONAL_SECTIONS) + " optional).",
        "",
        "## Inheritance: `extends`",
        "",
        "A run config may start with `extends = \"other.toml\"` (top level, before any table): the other "
        "config, a path relative to the file that names it, is read first and this file's tables are laid "
        "over it (`experiments/config_extends.py`). Tables merge key by key, recursively (the overlay's "
        "value wins); arrays, arrays of tables such as `[[perception.sensors]]` included, and scalars are "
        "replaced whole. Chains are allowed (a extends b extends c); a cycle or a missing parent is refused "
        "with one line naming the file and `extends`. `scenario.net_dir` stays relative to the file that "
        "writes it, also when that file is a parent in another folder. An error about an inherited key names "
        "the file that wrote the key. A sweep's `base` may be such a config. The saved `config.toml` is fully "
        "resolved (no `extends`; a comment lists the chain) and loads on its own. The arterial presets "
        "(`experiments/arterial_*_{pf,infra,realistic}.toml`, `arterial_vsr.toml`, `arterial_v2x.toml`, "
        "`arterial_ped_*.toml`) and the configs `coloc net import` writes are overlays of "
        "`experiments/arterial_tlr.toml` this way. Study configs do not take `extends`.",
        "",
    ]
    for table, cls in schema().items():
        hints = typing.get_type_hints(cls)
        heading = f"[[{table}]]" if "." in table else f"[{table}]"
        out += [f"## {heading}", "", TABLE_DOCS[table], "",
                "| key | type | unit | range | default | meaning |", "|---|---|---|---|---|---|"]
        for f in dataclasses.fields(cls):
            unit, meaning = KEY_DOCS[table][f.name]
            r = RANGES.get(f"{table}.{f.name}")
            bounds = r.bounds() if r is not None else "-"
            if r is not None:
                meaning = f"{meaning} Range: {r.why}."
            out.append(f"| `{f.name}` | {_type_name(hints[f.name])} | {_cell(unit) or '-'} | {_cell(bounds)} | "
                       f"{_cell(_default(f))} | {_cell(meaning)} |")
        out.append("")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if docs/configuration.md differs")
    ap.add_argument("--out", type=Path, default=DOC_PATH)
    args = ap.parse_args(argv)
    text = render()
    if args.check:
        same = args.out.is_file() and args.out.read_text() == text
        print(f"{args.out}: {'up to date' if same else 'stale: run python -m experiments.configdoc'}")
        return 0 if same else 1
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
