"""One factor at a time around a preset: the ``[sweep.factors]`` table of a sweep file.

A full product of the realistic-sensing factors (detection probability x clutter x occlusion x GNSS
correlation x pedestrians x eta_TH x control) would be days of CPU; the study
varies one factor at a time around the base config (the *preset*) and keeps the rest at their
preset values::

    [sweep.factors]
    clutter_per_scan = [
        {label = "0", set = {"perception.sensors[*].clutter_per_scan" = 0.0}},
        {label = "1", preset = true},                     # the preset's own level: no run of its own
        {label = "5", set = {"perception.sensors[*].clutter_per_scan" = 5.0}},
    ]
    idealised = [{label = "idealised", base = "../arterial_tlr.toml"}]   # another base config

Each level is ``label`` plus either ``preset = true`` (the base config's own level, drawn at its place
on the factor's axis from the one preset run) or ``set`` (dotted overrides as in ``[sweep.set]``;
``"table.key[*].field"`` sets ``field`` in every table of the array ``table.key``, e.g. every
``[[perception.sensors]]``), optionally ``base`` (another run config, relative to the sweep file) and
``only`` (``{"scenario.control" = ["tlr"]}``: the level runs only with those values of grid keys, e.g.
on a net that has no VSR variant) and ``relative`` (a mismatch arm: the estimator's model set to a
multiple of the simulated world's value, read from the run's own resolved config)::

    clutter_model = [
        {label = "x0.5", relative = {"estimator_sensors.sensors[*].clutter_per_scan" =
                                     {of = "perception.sensors[*].clutter_per_scan", times = 0.5}}},
        {label = "matched", preset = true},
        {label = "x1.5", relative = {"estimator_sensors.sensors[*].clutter_per_scan" =
                                     {of = "perception.sensors[*].clutter_per_scan", times = 1.5}}},
    ]
    visibility_model = [{label = "x0.5", relative = {"lc.visibility" = {times = 0.5}}}]  # of: the key itself

``of`` is read after the level's base, its ``set``, ``[sweep.set]`` and the grid (so a VSR run scales the VSR
preset's value); a ``[*]`` key pairs the tables of two arrays one by one (the same number of sensors).
The runs of a sweep are then every ``[sweep.grid]`` combination times the variants: the preset once,
and every level that is not the preset. A run's folder name ends in ``<factor>=<label>`` (or
``preset``); ``sweep.parquet`` and ``curves.parquet`` gain the string columns ``factor`` and
``level`` ("preset" / "preset" for the preset runs).
"""

from __future__ import annotations

import copy
import re
from dataclasses import dataclass
from pathlib import Path

from couplers.errors import InputError

LEVEL_KEYS = ("label", "preset", "set", "base", "only", "relative")
RELATIVE_KEYS = ("of", "times")
PRESET = "preset"
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_STAR = re.compile(r"^([a-z_]+)\.([a-z_]+)\[\*\]\.([a-z_]+)$")


@dataclass(frozen=True)
class Level:
    label: str
    preset: bool
    overrides: tuple[tuple[str, object], ...]  # dotted keys, "table.key[*].field" allowed
    base: Path | None  # another base config, or None
    only: tuple[tuple[str, tuple], ...] = ()  # grid keys and the values this level runs with (empty: all)
    relative: tuple[tuple[str, str, float], ...] = ()  # (target key, world key "of", times): a mismatch arm


@dataclass(frozen=True)
class Factor:
    name: str
    levels: tuple[Level, ...]


@dataclass(frozen=True)
class Variant:
    """One variant of the base config: the preset, or one non-preset level of one factor."""

    factor: str
    level: str
    overrides: tuple[tuple[str, object], ...] = ()
    base: Path | None = None
    only: tuple[tuple[str, tuple], ...] = ()
    relative: tuple[tuple[str, str, float], ...] = ()
    combo: tuple[tuple[str, str], ...] = ()  # a design point ([sweep] design): (factor, level label) of every factor

    def runs_with(self, params: dict) -> bool:
        """Whether this variant runs with the grid combination ``params`` ({dotted key: value})."""
        return all(params.get(k) in values for k, values in self.only)



PRESET_VARIANT = Variant(PRESET, PRESET)


def parse_factors(table, path: Path, check_dotted) -> tuple[Factor, ...]:
    """``[sweep.factors]`` of a sweep file; ``check_dotted(dotted, path, where)`` validates a plain key."""
    if not isinstance(table, dict):
        raise InputError(path, "sweep.factors", "expected a table of factors (name = [levels])")
    factors = []
    for name, levels in table.items():
        where = f"sweep.factors.{name}"
        if not _NAME.match(name) or name == PRESET:
            raise InputError(path, where, "a factor name is letters, digits and _ (and not 'preset')")
        if not isinstance(levels, list) or not levels:
            raise InputError(path, where, "expected a non-empty list of levels ({label = ..., set = {...}})")
        parsed, labels = [], set()
        for i, lv in enumerate(levels):
            lw = f"{where}[{i}]"
            if not isinstance(lv, dict):
                raise InputError(path, lw, "expected a table {label = ..., preset = true} or {label = ..., set = {...}}")
            unknown = sorted(set(lv) - set(LEVEL_KEYS))
            if unknown:
                raise InputError(path, f"{lw}.{unknown[0]}", f"unknown key (known: {', '.join(LEVEL_KEYS)})")
            label = lv.get("label")
            if not isinstance(label, str) or not label.strip() or label.strip() == PRESET:
                raise InputError(path, f"{lw}.label", f"expected a non-empty string other than 'preset', got {label!r}")
            if label in labels:
                raise InputError(path, f"{lw}.label", f"{label!r} is listed twice")
            labels.add(label)
            preset = lv.get("preset", False)
            if not isinstance(preset, bool):
                raise InputError(path, f"{lw}.preset", f"expected true or false, got {preset!r}")
            sets = lv.get("set", {})
            if not isinstance(sets, dict):
                raise InputError(path, f"{lw}.set", "expected a table of dotted keys")
            base = lv.get("base")
            relative = _parse_relative(lv.get("relative", {}), path, f"{lw}.relative", check_dotted)
            if preset and (sets or base is not None or relative):
                raise InputError(path, lw, "the preset level takes no set, base or relative: it is the base config")
            if not preset and not sets and base is None and not relative:
                raise InputError(path, lw, "a level sets something (set = {...}, relative = {...}) or names another "
                                           "base config")
            clash = [t for t, _, _ in relative if t in flatten_dotted(sets)]
            if clash:
                raise InputError(path, f"{lw}.relative.{clash[0]}", "also in the level's set")
            overrides = []
            for dotted, value in flatten_dotted(sets).items():
                if _STAR.match(dotted):
                    pass  # checked when applied (the base config must have that array of tables)
                else:
                    check_dotted(dotted, path, f"{lw}.set.{dotted}")
                overrides.append((dotted, value))
            bpath = None
            if base is not None:
                if not isinstance(base, str) or not base:
                    raise InputError(path, f"{lw}.base", f"expected the path of a run config, got {base!r}")
                bpath = (path.parent / base).resolve()
                if not bpath.is_file():
                    raise InputError(path, f"{lw}.base", f"no run config at {bpath}")
            only = lv.get("only", {})
            if not isinstance(only, dict) or preset and only:
                raise InputError(path, f"{lw}.only", "expected a table {\"grid.key\" = [values]} (not on the preset)")
            only_t = []
            for key, values in flatten_dotted(only).items():
                if not isinstance(values, list) or not values:
                    raise InputError(path, f"{lw}.only.{key}", f"expected a non-empty list of values, got {values!r}")
                only_t.append((key, tuple(values)))
            parsed.append(Level(label=label, preset=preset, overrides=tuple(overrides), base=bpath, only=tuple(only_t),
                                relative=relative))
        if sum(lv.preset for lv in parsed) > 1:
            raise InputError(path, where, "more than one level is the preset")
        factors.append(Factor(name=name, levels=tuple(parsed)))
    return tuple(factors)


def flatten_dotted(table: dict, prefix: str = "") -> dict:
    """Grid / set / level tables: quoted dotted keys ("a.b" = ...) or TOML's nested form (a.b = ...);
    a "[*]" stays in the key."""
    out = {}
    for key, value in table.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten_dotted(value, dotted + "."))
        else:
            out[dotted] = value
    return out


def variants(factors: tuple[Factor, ...]) -> list[Variant | None]:
    """The preset, then every non-preset level in file order; [None] without factors (a plain grid)."""
    if not factors:
        return [None]
    out = [PRESET_VARIANT]
    for f in factors:
        out += [Variant(f.name, lv.label, lv.overrides, lv.base, lv.only, lv.relative) for lv in f.levels
                if not lv.preset]
    return out


def split_overrides(data: dict, overrides: tuple[tuple[str, object], ...], path: Path, where: str) -> tuple[dict, dict]:
    """(a copy of the config ``data`` with the "[*]" overrides applied, the plain dotted overrides)."""
    data = copy.deepcopy(data)
    plain = {}
    for dotted, value in overrides:
        m = _STAR.match(dotted)
        if m is None:
            plain[dotted] = value
            continue
        sec, key, fld = m.groups()
        items = data.get(sec, {}).get(key) if isinstance(data.get(sec), dict) else None
        if not isinstance(items, list) or not items or not all(isinstance(t, dict) for t in items):
            raise InputError(path, f"{where}.set.{dotted}", f"the base config has no [[{sec}.{key}]] tables")
        for t in items:
            t[fld] = value
    return data, plain


def _parse_relative(table, path: Path, where: str, check_dotted) -> tuple[tuple[str, str, float], ...]:
    """A level's ``relative = {"target.key" = {of = "world.key", times = x}}`` (quoted dotted keys)."""
    if not isinstance(table, dict):
        raise InputError(path, where, "expected a table {\"table.key\" = {of = \"table.key\", times = x}}")
    out = []
    for target, spec in table.items():
        w = f"{where}.{target}"
        if not isinstance(spec, dict) or "times" not in spec:
            raise InputError(path, w, "expected a table {of = \"table.key\", times = x} (times required)")
        unknown = sorted(set(spec) - set(RELATIVE_KEYS))
        if unknown:
            raise InputError(path, f"{w}.{unknown[0]}", f"unknown key (known: {', '.join(RELATIVE_KEYS)})")
        of = spec.get("of", target)
        if not isinstance(of, str) or not of:
            raise InputError(path, f"{w}.of", f"expected a dotted key, got {of!r}")
        times = spec["times"]
        if isinstance(times, bool) or not isinstance(times, (int, float)) or not (times == times and times >= 0
                                                                                   and times != float("inf")):
            raise InputError(path, f"{w}.times", f"expected a finite number >= 0, got {times!r}")
        if bool(_STAR.match(target)) != bool(_STAR.match(of)):
            raise InputError(path, f"{w}.of", "a [*] key is relative to a [*] key (sensor by sensor), a plain key "
                                              "to a plain key")
        for key, kw in ((target, w), (of, f"{w}.of")):
            if not _STAR.match(key):
                check_dotted(key, path, kw)
        out.append((target, of, float(times)))
    return tuple(out)


def _optional(section: str) -> bool:
    from experiments.config import OPTIONAL_SECTIONS  # noqa: PLC0415 - experiments.config imports this package

    return section in OPTIONAL_SECTIONS


def _default_of(dotted: str):
    """The dataclass default of a config key (plain "table.key" or "table.key[*].field"), or None."""
    import dataclasses  # noqa: PLC0415

    from experiments.config import OPTIONAL_SECTIONS, SECTIONS  # noqa: PLC0415 - experiments.config imports this package

    m = _STAR.match(dotted)
    sec, key = (m.group(1), m.group(2)) if m else dotted.split(".")
    cls = {**SECTIONS, **OPTIONAL_SECTIONS}.get(sec)
    if cls is None:
        return None
    if m:
        from couplers.sensing.perception import SensorSpec  # noqa: PLC0415 - the tables of [*] arrays

        fields = {f.name: f for f in dataclasses.fields(SensorSpec)}
        f = fields.get(m.group(3))
    else:
        f = {f.name: f for f in dataclasses.fields(cls)}.get(key)
    return None if f is None or f.default is dataclasses.MISSING else f.default


def apply_relative(data: dict, plain: dict, relative: tuple[tuple[str, str, float], ...], path: Path,
                   where: str) -> tuple[dict, dict]:
    """(config ``data``, plain overrides) with the mismatch arm's targets set to ``times`` x the world's value,
    read from ``plain`` (the run's dotted overrides) before ``data`` (the base with the level's [*] sets)."""
    if not relative:
        return data, plain
    data, plain = copy.deepcopy(data), dict(plain)
    for target, of, times in relative:
        w = f"{where}.relative.{target}"
        m_of, m_t = _STAR.match(of), _STAR.match(target)
        if m_of is None:
            sec, key = of.split(".")
            if of not in plain and sec not in data and _optional(sec):
                raise InputError(path, f"{w}.of", f"the run's config has no [{sec}]: no world value to be relative to")
            value = plain[of] if of in plain else (data.get(sec) or {}).get(key, _default_of(of))
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise InputError(path, f"{w}.of", f"{of} is {value!r} in this run, not a number")
            if target in plain and target != of:
                raise InputError(path, w, "also set by [sweep.set] or the grid")
            plain[target] = times * value
            continue
        items = []
        for m, role in ((m_of, "of"), (m_t, "target")):
            sec, key = m.group(1), m.group(2)
            arr = data.get(sec, {}).get(key) if isinstance(data.get(sec), dict) else None
            if not isinstance(arr, list) or not arr or not all(isinstance(t, dict) for t in arr):
                raise InputError(path, w if role == "target" else f"{w}.of", f"the run's config has no [[{sec}.{key}]] "
                                                                             "tables")
            items.append(arr)
        world, model = items
        if len(world) != len(model):
            raise InputError(path, w, f"{len(model)} tables against {len(world)} in {m_of.group(1)}.{m_of.group(2)}: "
                                      "the sensors are paired one by one")
        fo, ft = m_of.group(3), m_t.group(3)
        values = [t.get(fo, _default_of(of)) for t in world]
        for v in values:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise InputError(path, f"{w}.of", f"{of} is {v!r} in this run, not a number")
        for t, v in zip(model, values):
            t[ft] = times * v
    return data, plain


def factor_levels(factors: tuple[Factor, ...]) -> dict[str, list[str]]:
    """Each factor's level labels in file order (the preset's where the file puts it)."""
    return {f.name: [lv.label for lv in f.levels] for f in factors}


def preset_labels(factors: tuple[Factor, ...]) -> dict[str, str | None]:
    return {f.name: next((lv.label for lv in f.levels if lv.preset), None) for f in factors}


def factors_toml(factors: tuple[Factor, ...], toml_value) -> list[str]:
    """``[sweep.factors]`` lines of the resolved sweep (bases as absolute paths)."""
    lines = ["", "[sweep.factors]"]
    for f in factors:
        items = []
        for lv in f.levels:
            parts = [f"label = {toml_value(lv.label)}"]
            if lv.preset:
                parts.append("preset = true")
            if lv.overrides:
                parts.append("set = {" + ", ".join(f"{toml_value(k)} = {toml_value(v)}" for k, v in lv.overrides) + "}")
            if lv.base is not None:
                parts.append(f"base = {toml_value(str(lv.base))}")
            if lv.relative:
                parts.append("relative = {" + ", ".join(
                    f"{toml_value(t)} = {{of = {toml_value(o)}, times = {toml_value(x)}}}" for t, o, x in lv.relative) + "}")
            if lv.only:
                parts.append("only = {" + ", ".join(f"{toml_value(k)} = {toml_value(list(v))}" for k, v in lv.only) + "}")
            items.append("{" + ", ".join(parts) + "}")
        lines.append(f"{f.name} = [" + ", ".join(items) + "]")
    return lines
