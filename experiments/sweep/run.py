"""Monte Carlo and parameter sweeps on Dask: ``coloc sweep SWEEP.toml --out DIR``.

A sweep file names a base run config, the seeds and a grid of parameters::

    [sweep]
    name = "fig8_9_crossroad_nf"
    base = "../crossroad.toml"            # relative to the sweep file
    seeds = {start = 1, count = 200}      # or a list: [1, 2, 3]
    methods = ["gnss", "icp_known_da"]    # optional: overrides [run] methods
    distance_bin_m = 20.0                 # optional: bin of the RMSE-vs-distance curves (crossroad)

    [sweep.set]                           # optional: fixed overrides of the base config
    "run.duration_s" = 30.0

    [sweep.grid]                          # dotted keys -> lists; runs = product x seeds
    "crossroad.n_features" = [3, 10, 20, 60]
    "lc.eta_threshold" = [0.5, 1.0]

A grid key may select the base config per value (``[sweep.bases]``, e.g. each control from its own
preset: ``"scenario.control" = {vsr = "../arterial_vsr_realistic.toml"}``); a factor level's own
``base`` still wins.

Any key of a run config's tables can be swept or set, including the optional ``[infra]``
(e.g. ``"infra.rsu_range_m" = [40.0, 70.0, 100.0]``; the base config must have the ``[infra]``
table: a sweep varies infrastructure mode, it does not switch it on). Every run's config is
validated before anything runs and saved fully resolved in its run folder (``config.toml``).

Every run is an ordinary run (:func:`experiments.runner.run_experiment`, without
the per-run HTML report) written to ``DIR/runs/<run_id>/`` where run_id is
built from the swept values and the seed (e.g.
``n_features=20,eta_threshold=0.5,seed=7``). Runs execute on a
``dask.distributed`` LocalCluster of single-threaded worker processes (libsumo
holds one simulation per process), or on a running scheduler given with
``--scheduler`` (its workers must import this package and see DIR).

Resumable: a run folder appears complete or not at all (atomic rename), so a
restart computes only the missing runs and removes the hidden partial folders
a killed run left behind. The resolved sweep (including a hash of the resolved
base config) is stored in ``DIR/sweep.toml``; a restart with a different sweep
into the same DIR is refused. The files the runs read (every config TOML loaded, ``extends``
chains included, and every file of each run's net folder) are stored with their sha256 in
``DIR/inputs.json``: a restart after one of them changed is refused, naming the file, while a
finished run was made with the old one; ``--force`` then recomputes those runs (only the runs that
read the changed file). A lock (``.DIR.lock`` beside DIR) keeps two commands from writing into
one DIR at once.

Outputs, computed from the run files only and byte-identical for the same
sweep (sorted rows, no timestamps):

* ``DIR/sweep.parquet``: one row per (run, method): run_id, seed, every swept
  parameter as a column named by its dotted key, the summary numbers; when runs have
  ``[infra]``, also ``covered_rmse_pos_m``, ``covered_p95_pos_m`` and ``covered_n``: the
  summary's ``within_rsu_coverage`` (every method on the same covered vehicle-steps of a run).
* ``DIR/curves.parquet``: per (setting, method) aggregates over the Monte Carlo
  runs, one ``curve`` kind per figure of Brambilla Sec. V:
  ``time`` (RMSE over time, Fig. 7: x = t), ``feature_time`` (feature RMSE
  over time), ``distance`` (RMSE versus the distance of the true position to
  the junction centre, Figs. 8 and 10: x = bin centre, crossroad only),
  ``association`` (correct / wrong / discarded percentages of all V2F rows,
  Figs. 9 and 11), ``overall`` and ``feature_overall`` (pooled RMSE).
  RMSE = sqrt(mean of the squared error over all runs and vehicles).
* ``DIR/report.html`` with ``DIR/figures/*.png`` (:mod:`experiments.sweep.report`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import itertools
import json
import logging
import math
import os
import re
import shutil
import sys
import threading
import time
import tomllib
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from couplers.errors import SEED_MAX, InputError, read_toml, recording_reads, seed_problem
from couplers.publish import check_target, lock_output, make_folder, mark, write_file_atomic
from experiments.scoring import scored_mask
from experiments.config import OPTIONAL_SECTIONS, SECTIONS, Config, _toml_value, config_from_dict, config_to_toml
from experiments.config_extends import read_config_data
from experiments.sweep.factors import Factor, Variant, factors_toml, flatten_dotted as _flatten, parse_factors, \
    split_overrides, variants
from experiments.sweep.zones import aggregate_zones, degree_partial, zone_partials

SPEC_KEYS = ("name", "base", "seeds", "methods", "distance_bin_m", "grid", "set", "factors", "bases",
             "tune_seeds", "eval_seeds")
FORBIDDEN_KEYS = {"run.seed": "use sweep.seeds", "run.methods": "use sweep.methods", "run.name": "runs are named by the sweep"}
DEFAULT_DISTANCE_BIN_M = 20.0
RUNS_DIR = "runs"
CURVE_KINDS = ("time", "feature_time", "distance", "association", "overall", "feature_overall")
COVERED_COLUMNS = ("rmse_pos_m", "p95_pos_m", "n")  # sweep.parquet "covered_*" (summary within_rsu_coverage)


# --------------------------------------------------------------------------- #
# The sweep file
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class SweepSpec:
    path: Path
    name: str
    base: Path
    seeds: tuple[int, ...]
    methods: tuple[str, ...] | None
    grid: tuple[tuple[str, tuple], ...]  # (dotted key, values) in file order
    fixed: tuple[tuple[str, object], ...]  # [sweep.set]
    distance_bin_m: float
    factors: tuple[Factor, ...] = ()  # [sweep.factors]: one factor at a time (experiments.sweep.factors)
    # [sweep.bases]: (grid key, ((grid value, run config), ...)): the runs with that grid value start from
    # that config instead of `base` (e.g. each control from its own preset: the VSR preset sets more than
    # scenario.control); a factor level's own base still wins.
    bases: tuple[tuple[str, tuple[tuple[str, Path], ...]], ...] = ()
    # [sweep] tune_seeds / eval_seeds (disjoint; both or neither): every seed runs, the tables and the
    # report use the evaluation seeds only (seeds = tune_seeds + eval_seeds). Empty: every seed is scored.
    tune_seeds: tuple[int, ...] = ()
    eval_seeds: tuple[int, ...] = ()

    @property
    def scored_seeds(self) -> tuple[int, ...]:
        return self.eval_seeds or self.seeds

    @property
    def grid_keys(self) -> list[str]:
        return [k for k, _ in self.grid]


@dataclass(frozen=True)
class SweepRun:
    run_id: str
    setting: int  # index of the grid combination (file order)
    seed: int
    params: tuple[tuple[str, object], ...]  # the swept (dotted key, value) of this run
    cfg: Config
    variant: Variant | None = None  # [sweep.factors]: the preset or one factor level


def settings_of(spec: SweepSpec) -> list[tuple[tuple, Variant | None]]:
    """Every setting of a sweep in run order: grid combinations (file order) x variants (the preset, then
    each factor's non-preset levels; a single None without factors)."""
    combos = list(itertools.product(*[values for _, values in spec.grid]))
    keys = spec.grid_keys
    return [(combo, v) for combo in combos for v in variants(spec.factors)
            if v is None or v.runs_with(dict(zip(keys, combo)))]


def _check_dotted(dotted: str, path: Path, where: str) -> None:
    parts = dotted.split(".")
    tables = {**SECTIONS, **OPTIONAL_SECTIONS}
    if len(parts) != 2 or parts[0] not in tables:
        raise InputError(path, where, f"unknown parameter {dotted!r}: expected \"table.key\" with a table among "
                                      f"{', '.join(tables)}")
    names = [f.name for f in dataclasses.fields(tables[parts[0]])]
    if parts[1] not in names:
        raise InputError(path, where, f"unknown parameter {dotted!r} (keys of [{parts[0]}]: {', '.join(names)})")
    if dotted in FORBIDDEN_KEYS:
        raise InputError(path, where, f"{dotted} cannot be swept or set here: {FORBIDDEN_KEYS[dotted]}")


def _seeds(value, path: Path, where: str = "sweep.seeds") -> tuple[int, ...]:
    if isinstance(value, dict):
        unknown = sorted(set(value) - {"start", "count"})
        if unknown:
            raise InputError(path, f"{where}.{unknown[0]}", "unknown key (known: count, start)")
        start, count = value.get("start", 1), value.get("count")
        for key, v in (("start", start), ("count", count)):
            if isinstance(v, bool) or not isinstance(v, int):
                raise InputError(path, f"{where}.{key}", f"expected an integer, got {v!r}")
        if count < 1:
            raise InputError(path, f"{where}.count", "must be >= 1")
        if (why := seed_problem(start)) is not None:
            raise InputError(path, f"{where}.start", why)
        if seed_problem(start + count - 1) is not None:
            raise InputError(path, f"{where}.count", f"the last seed, start + count - 1 = {start + count - 1}, "
                                                     f"is beyond {SEED_MAX} (the largest seed SUMO accepts)")
        return tuple(range(start, start + count))
    if isinstance(value, list):
        if not value:
            raise InputError(path, where, "at least one seed is needed")
        for i, v in enumerate(value):
            if (why := seed_problem(v)) is not None:
                raise InputError(path, f"{where}[{i}]", why)
        if len(set(value)) != len(value):
            raise InputError(path, where, "a seed is listed twice")
        return tuple(value)
    raise InputError(path, where, f"expected a list of integers or a table {{start, count}}, got {value!r}")


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and check a sweep file's own fields (the configs it makes are checked by :func:`expand_runs`)."""
    path = Path(path)
    data = read_toml(path, "sweep file")
    extra = sorted(set(data) - {"sweep"})
    if extra:
        raise InputError(path, extra[0], "unknown table (a sweep file has only [sweep], [sweep.grid], [sweep.set])")
    sw = data.get("sweep")
    if not isinstance(sw, dict):
        raise InputError(path, "sweep", "required table missing")
    unknown = sorted(set(sw) - set(SPEC_KEYS))
    if unknown:
        raise InputError(path, f"sweep.{unknown[0]}", f"unknown key (known: {', '.join(SPEC_KEYS)})")
    split = [k for k in ("tune_seeds", "eval_seeds") if k in sw]
    if split and "seeds" in sw:
        raise InputError(path, f"sweep.{split[0]}", "give sweep.seeds or sweep.tune_seeds + sweep.eval_seeds, not both")
    if len(split) == 1:
        missing = ({"tune_seeds", "eval_seeds"} - set(split)).pop()
        raise InputError(path, f"sweep.{missing}", f"required with sweep.{split[0]}")
    tune, evals = (), ()
    if split:
        tune = _seeds(sw["tune_seeds"], path, "sweep.tune_seeds")
        evals = _seeds(sw["eval_seeds"], path, "sweep.eval_seeds")
        both = sorted(set(tune) & set(evals))
        if both:
            raise InputError(path, "sweep.eval_seeds", f"seed {both[0]} is also a tuning seed (tune_seeds and "
                                                       "eval_seeds must be disjoint)")
        sw = {**sw, "seeds": list(tune + evals)}
    for key in ("name", "base", "seeds"):
        if key not in sw:
            raise InputError(path, f"sweep.{key}", "required key missing")
    name = sw["name"]
    if not isinstance(name, str) or not name.strip():
        raise InputError(path, "sweep.name", f"expected a non-empty string, got {name!r}")
    if not isinstance(sw["base"], str) or not sw["base"]:
        raise InputError(path, "sweep.base", f"expected the path of a run config, got {sw['base']!r}")
    base = (path.parent / sw["base"]).resolve()
    if not base.is_file():
        raise InputError(path, "sweep.base", f"no run config at {base}")
    seeds = _seeds(sw["seeds"], path)
    methods = sw.get("methods")
    if methods is not None:
        if not isinstance(methods, list) or not all(isinstance(m, str) for m in methods):
            raise InputError(path, "sweep.methods", f"expected a list of method names, got {methods!r}")
        methods = tuple(methods)
    dbin = sw.get("distance_bin_m", DEFAULT_DISTANCE_BIN_M)
    if isinstance(dbin, bool) or not isinstance(dbin, (int, float)) or not (math.isfinite(dbin) and dbin > 0):
        raise InputError(path, "sweep.distance_bin_m", f"expected a positive number, got {dbin!r}")
    grid_t = sw.get("grid", {})
    set_t = sw.get("set", {})
    for key, t in (("grid", grid_t), ("set", set_t)):
        if not isinstance(t, dict):
            raise InputError(path, f"sweep.{key}", "expected a table")
    grid = []
    for dotted, values in _flatten(grid_t).items():
        where = f"sweep.grid.{dotted}"
        _check_dotted(dotted, path, where)
        if not isinstance(values, list) or not values:
            raise InputError(path, where, f"expected a non-empty list of values, got {values!r}")
        frozen = [tuple(v) if isinstance(v, list) else v for v in values]
        if len(set(map(repr, frozen))) != len(frozen):
            raise InputError(path, where, "a value is listed twice")
        grid.append((dotted, tuple(values)))
    fixed = []
    for dotted, value in _flatten(set_t).items():
        where = f"sweep.set.{dotted}"
        _check_dotted(dotted, path, where)
        if dotted in dict(grid):
            raise InputError(path, where, "also swept in [sweep.grid]")
        fixed.append((dotted, value))
    factors = parse_factors(sw.get("factors", {}), path, _check_dotted)
    shorts = set(_short_names([k for k, _ in grid]).values())
    for f in factors:
        if f.name in shorts:
            raise InputError(path, f"sweep.factors.{f.name}", "also the name of a swept key: run folders would clash")
        for i, lv in enumerate(f.levels):
            for dotted, _ in lv.overrides:
                if dotted in dict(grid):
                    raise InputError(path, f"sweep.factors.{f.name}[{i}].set.{dotted}", "also swept in [sweep.grid]")
            for key, values in lv.only:
                if key not in dict(grid):
                    raise InputError(path, f"sweep.factors.{f.name}[{i}].only.{key}", "not a key of [sweep.grid]")
                unknown = [v for v in values if v not in dict(grid)[key]]
                if unknown:
                    raise InputError(path, f"sweep.factors.{f.name}[{i}].only.{key}",
                                     f"{unknown[0]!r} is not one of the grid's values")
    bases = _grid_bases(sw.get("bases", {}), dict(grid), path)
    return SweepSpec(path=path.resolve(), name=name.strip(), base=base, seeds=seeds, methods=methods,
                     grid=tuple(grid), fixed=tuple(fixed), distance_bin_m=float(dbin), factors=factors,
                     bases=bases, tune_seeds=tune, eval_seeds=evals)


def _grid_bases(table, grid: dict, path: Path) -> tuple:
    """``[sweep.bases]``: ``"scenario.control" = {vsr = "../arterial_vsr_realistic.toml"}`` (one grid key)."""
    if not isinstance(table, dict):
        raise InputError(path, "sweep.bases", "expected a table: grid key -> {grid value = run config}")
    if len(table) > 1:
        raise InputError(path, f"sweep.bases.{sorted(table)[1]}", "only one grid key may select the base config")
    out = []
    for key, by_value in table.items():
        where = f"sweep.bases.{key}"
        if key not in grid:
            raise InputError(path, where, "not a key of [sweep.grid]")
        if not isinstance(by_value, dict) or not by_value:
            raise InputError(path, where, "expected a table {grid value = run config}")
        pairs = []
        for value, rel in by_value.items():
            if value not in [str(v) for v in grid[key]]:
                raise InputError(path, f"{where}.{value}", "not one of the grid's values")
            if not isinstance(rel, str) or not rel:
                raise InputError(path, f"{where}.{value}", f"expected the path of a run config, got {rel!r}")
            bpath = (path.parent / rel).resolve()
            if not bpath.is_file():
                raise InputError(path, f"{where}.{value}", f"no run config at {bpath}")
            pairs.append((value, bpath))
        out.append((key, tuple(pairs)))
    return tuple(out)


def _grid_base(spec: SweepSpec, params: tuple) -> Path | None:
    """The run config [sweep.bases] gives the runs of these grid values, or None."""
    p = dict(params)
    for key, pairs in spec.bases:
        for value, bpath in pairs:
            if str(p.get(key)) == value:
                return bpath
    return None


def _load_base(spec: SweepSpec) -> dict:
    return read_config_data(spec.base)


def _config(spec: SweepSpec, base_data: dict, overrides: dict, where: str, swept_key: str | None = None,
            context: str = "") -> Config:
    """A config of the sweep; errors name the sweep file and the sweep field that caused them."""
    try:
        return config_from_dict(base_data, spec.base, overrides)
    except InputError as exc:
        detail = exc.message if exc.field in (None, swept_key) else f"{exc.field}: {exc.message}"
        raise InputError(spec.path, where, context + detail) from None


def _value_text(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "x".join(_value_text(v) for v in value)
    return str(value)


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._+-]", "_", text)


def _short_names(keys: list[str]) -> dict[str, str]:
    """Run-id names of the grid keys: the key without its table unless two would collide."""
    last = [k.split(".")[1] for k in keys]
    return {k: (s if last.count(s) == 1 else k) for k, s in zip(keys, last)}


def run_id_of(params: tuple[tuple[str, object], ...], seed: int, short: dict[str, str],
              variant: Variant | None = None) -> str:
    parts = [f"{short[k]}={_safe(_value_text(v))}" for k, v in params]
    if variant is not None:
        parts.append(variant.factor if variant.factor == "preset" else f"{variant.factor}={_safe(variant.level)}")
    return ",".join(parts + [f"seed={seed}"])


def expand_runs(spec: SweepSpec) -> tuple[Config, list[SweepRun]]:
    """The base config (with [sweep.set] and methods) and every run, each config validated."""
    base_data = _load_base(spec)
    config_from_dict(base_data, spec.base)  # the base alone: its own errors name the base file
    fixed = dict(spec.fixed)
    if spec.methods is not None:
        _config(spec, base_data, {"run.methods": list(spec.methods)}, "sweep.methods", "run.methods")
        fixed["run.methods"] = list(spec.methods)
    for dotted, value in spec.fixed:
        _config(spec, base_data, {dotted: value}, f"sweep.set.{dotted}", dotted)
    base_cfg = _config(spec, base_data, fixed, "sweep.set")
    for dotted, values in spec.grid:
        for i, value in enumerate(values):
            _config(spec, base_data, {**fixed, dotted: value}, f"sweep.grid.{dotted}[{i}]", dotted)
    short = _short_names(spec.grid_keys)
    runs: list[SweepRun] = []
    bases: dict = {}
    for setting, (combo, variant) in enumerate(settings_of(spec)):
        params = tuple(zip(spec.grid_keys, combo))
        text = ", ".join(f"{k} = {_value_text(v)}" for k, v in params)
        data, extra, where, cspec = base_data, {}, "sweep.grid", spec
        gbase = _grid_base(spec, params)
        if gbase is not None:
            cspec = dataclasses.replace(spec, base=gbase)
            data = bases.setdefault(gbase, read_config_data(gbase))
        if variant is not None and variant.factor != "preset":
            where = f"sweep.factors.{variant.factor}"
            if variant.base is not None:
                cspec = dataclasses.replace(spec, base=variant.base)
                data = bases.setdefault(variant.base, read_config_data(variant.base))
            data, extra = split_overrides(data, variant.overrides, spec.path, where)
            text = ", ".join(x for x in (text, f"{variant.factor} = {variant.level}") if x)
        cfg = _config(cspec, data, {**fixed, **extra, **dict(params)}, where, context=f"with {text}: ")
        for seed in spec.seeds:
            run_id = run_id_of(params, seed, short, variant)
            run_cfg = dataclasses.replace(
                cfg, run=dataclasses.replace(cfg.run, seed=seed, name=f"{spec.name}/{run_id}"))
            runs.append(SweepRun(run_id=run_id, setting=setting, seed=seed, params=params, cfg=run_cfg,
                                 variant=variant))
    ids = [r.run_id for r in runs]
    if len(set(ids)) != len(ids):
        dup = next(i for i in ids if ids.count(i) > 1)
        raise InputError(spec.path, "sweep.grid", f"two runs get the same folder name {dup!r}; make the values distinct")
    return base_cfg, runs


def resolved_spec_toml(spec: SweepSpec, base_cfg: Config, n_runs: int) -> str:
    """What DIR/sweep.toml holds: the sweep as resolved; a restart must resolve to the same."""
    base_text = config_to_toml(base_cfg, {})
    lines = [
        f"# coloc sweep resolved from {spec.path}",
        "# A restart into this folder must resolve to the same values (the sweep file's path may differ).",
        "",
        "[sweep]",
        f"name = {_toml_value(spec.name)}",
        f"base = {_toml_value(str(spec.base))}",
        f"base_config_sha256 = {_toml_value(hashlib.sha256(base_text.encode()).hexdigest())}",
        f"seeds = {_toml_value(list(spec.seeds))}",
        *([f"tune_seeds = {_toml_value(list(spec.tune_seeds))}", f"eval_seeds = {_toml_value(list(spec.eval_seeds))}"]
          if spec.eval_seeds else []),
        f"methods = {_toml_value(list(base_cfg.run.methods))}",
        f"distance_bin_m = {_toml_value(spec.distance_bin_m)}",
        f"runs = {n_runs}",
        "",
        "[sweep.set]",
    ]
    lines += [f"{_toml_value(k)} = {_toml_value(v)}" for k, v in spec.fixed]
    lines += ["", "[sweep.grid]"]
    lines += [f"{_toml_value(k)} = {_toml_value(list(v))}" for k, v in spec.grid]
    if spec.bases:
        lines += ["", "[sweep.bases]"]
        lines += [f"{_toml_value(k)} = {{{', '.join(f'{_toml_value(v)} = {_toml_value(str(b))}' for v, b in pairs)}}}"
                  for k, pairs in spec.bases]
    if spec.factors:
        lines += factors_toml(spec.factors, _toml_value)
    return "\n".join(lines) + "\n"


def _first_difference(a: dict, b: dict, prefix: str = "") -> str | None:
    for key in list(a) + [k for k in b if k not in a]:
        if key not in a or key not in b:
            return f"{prefix}{key}"
        if isinstance(a[key], dict) and isinstance(b[key], dict):
            d = _first_difference(a[key], b[key], f"{prefix}{key}.")
            if d:
                return d
        elif a[key] != b[key]:
            return f"{prefix}{key}"
    return None


# --------------------------------------------------------------------------- #
# Output folder: lock, spec check, leftovers
# --------------------------------------------------------------------------- #


def _acquire_lock(out: Path, spec_path: Path):
    return lock_output(out)  # the lock of every coloc output (couplers.publish)


def _check_spec(out: Path, text: str, spec_path: Path, ignore: tuple[str, ...] = ()) -> None:
    """Refuse a sweep that resolves differently from the one stored in ``out/sweep.toml`` (``ignore``:
    keys of [sweep] left out of the comparison)."""
    target = out / "sweep.toml"
    try:
        old = tomllib.loads(target.read_text())
    except tomllib.TOMLDecodeError:
        old = {}
    new = tomllib.loads(text)
    for d in (old, new):
        for key in ignore:
            d.get("sweep", {}).pop(key, None)
    if old != new:
        diff = _first_difference(new, old) or "sweep"
        raise InputError(spec_path, diff,
                         f"{out} holds a different sweep ({target} has another {diff}); "
                         "use another --out folder, or remove that one to start over")


def _check_or_write_spec(out: Path, text: str, spec_path: Path, ignore: tuple[str, ...] = ()) -> None:
    target = out / "sweep.toml"
    if target.exists():
        _check_spec(out, text, spec_path, ignore)
        if ignore and target.read_text() != text:  # --force over changed configs: the sweep as resolved now
            write_file_atomic(target, text)
        return
    if (out / RUNS_DIR).exists():
        raise InputError(spec_path, None, f"{out / RUNS_DIR} exists without {target}: not a sweep folder of this sweep")
    write_file_atomic(target, text)


INPUTS_FILE = "inputs.json"


def _sha256(path: Path) -> str | None:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    except FileNotFoundError:
        return None
    return h.hexdigest()


def _net_files(net_dir: Path) -> list[Path]:
    """Every file of a net folder (hidden ones, e.g. an editor's swap files, left out)."""
    return sorted(p.resolve() for p in net_dir.rglob("*")
                  if p.is_file() and not any(part.startswith(".") for part in p.relative_to(net_dir).parts))


def sweep_inputs(spec: SweepSpec, runs: list[SweepRun], config_files: list[Path]) -> dict:
    """What ``DIR/inputs.json`` holds: the sha256 of every file the runs read, and per run the files it
    read. ``config_files``: the TOML files read while the configs were loaded (bases, ``extends``
    chains, net folders' scenario.toml); a factor's own base counts only for that factor's runs. The
    sweep file itself is checked by its resolved values (``DIR/sweep.toml``), not by its bytes."""
    own_bases = {Path(lv.base).resolve() for f in spec.factors for lv in f.levels if lv.base is not None}
    net_dirs = {Path(r.cfg.scenario.net_dir) for r in runs if r.cfg.scenario.net_dir}
    # a net folder's files count for the runs on that net only
    shared = sorted({Path(p) for p in config_files if not any(Path(p).is_relative_to(d) for d in net_dirs)}
                    - (own_bases - {spec.base}) - {spec.path})
    nets: dict[str, list[Path]] = {}
    per_run: dict[str, list[str]] = {}
    for run in runs:
        files = set(shared)
        if run.variant is not None and run.variant.base is not None:
            files.add(Path(run.variant.base).resolve())
        net_dir = run.cfg.scenario.net_dir
        if net_dir and Path(net_dir).is_dir():
            files.update(nets.setdefault(net_dir, _net_files(Path(net_dir))))
        per_run[run.run_id] = sorted(str(p) for p in files)
    hashes = {p: _sha256(Path(p)) for p in sorted({p for ps in per_run.values() for p in ps})}
    return {"files": hashes, "runs": per_run}


def _inputs_text(inputs: dict) -> str:
    return json.dumps(inputs, indent=1, sort_keys=True) + "\n"


def _check_inputs(out: Path, inputs: dict, runs: list[SweepRun], force: bool) -> tuple[frozenset[str], tuple[str, ...]]:
    """Compare the inputs with those a resumed sweep was started with (``out/inputs.json``).

    Returns the finished runs to recompute (``force`` only) and the sweep.toml keys to leave out of its
    check (the resolved base config's hash, when a config file changed and ``force`` recomputes its
    runs). Without ``force``, a changed, removed or added file read by a finished run is an InputError
    naming the file. A folder without inputs.json (written before it existed) is not checked."""
    try:
        old = json.loads((out / INPUTS_FILE).read_text())
        old_files, old_runs = dict(old["files"]), dict(old["runs"])
    except FileNotFoundError:
        return frozenset(), ()
    except (ValueError, KeyError, TypeError):
        raise InputError(out / INPUTS_FILE, None, "not the record of a sweep's inputs (damaged): remove the "
                                                  "sweep folder to start over") from None
    new_files = inputs["files"]
    changed: dict[str, list[str]] = {}  # file -> finished runs made with its old version
    for run in runs:
        if run.run_id not in old_runs or not run_complete(out / RUNS_DIR / run.run_id):
            continue  # computed with the inputs of now
        before = {p: old_files.get(p) for p in old_runs[run.run_id]}
        now = {p: new_files.get(p) for p in inputs["runs"][run.run_id]}
        for p in sorted(set(before) | set(now)):
            if before.get(p) != now.get(p):
                changed.setdefault(p, []).append(run.run_id)
    if not changed:
        return frozenset(), ()
    redo = frozenset(r for ids in changed.values() for r in ids)
    if force:
        net_dirs = {r.cfg.scenario.net_dir for r in runs if r.cfg.scenario.net_dir}
        configs_changed = any(not any(Path(p).is_relative_to(d) for d in net_dirs) for p in changed)
        return redo, ("base_config_sha256",) if configs_changed else ()
    first = next(iter(changed))
    if first not in old_files:
        state = "is new"
    elif new_files.get(first) is None:
        state = "is no longer read by the runs" if Path(first).exists() else "was removed"
    else:
        state = "changed"
    others = f" (and {len(changed) - 1} other file(s))" if len(changed) > 1 else ""
    raise InputError(first, None,
                     f"{state} since the sweep in {out} started{others}: {len(redo)} finished run(s) read the old "
                     f"inputs (e.g. {min(redo)}); restore it, pass --force to recompute those runs, or use another "
                     "--out folder")


def _restart_changed(out: Path, inputs: dict, redo: frozenset[str]) -> None:
    """Remove the finished runs to recompute (through a hidden name, so a kill leaves a leftover that
    :func:`clean_leftovers` removes, never a half-removed run), then record the inputs of now."""
    for run_id in sorted(redo):
        run_dir = out / RUNS_DIR / run_id
        if run_dir.exists():
            hidden = run_dir.with_name(f".{run_id}.old-{os.getpid()}")
            os.replace(run_dir, hidden)
            shutil.rmtree(hidden)
    text = _inputs_text(inputs)
    target = out / INPUTS_FILE
    if not target.is_file() or target.read_text() != text:
        write_file_atomic(target, text)


def clean_leftovers(out: Path) -> list[Path]:
    """Remove the hidden partial folders and temporary files a killed sweep or run left behind."""
    removed = []
    candidates = list(out.glob(".*.tmp-*")) + list(out.glob(".report-*"))
    runs = out / RUNS_DIR
    if runs.is_dir():
        candidates += [p for p in runs.iterdir() if p.name.startswith(".") and (".partial-" in p.name or ".old-" in p.name)]
    for p in sorted(candidates):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        removed.append(p)
    return removed


def run_complete(run_dir: Path) -> bool:
    # run_experiment renames a finished folder into place: if it exists it is complete.
    return (run_dir / "summary.json").is_file()


# --------------------------------------------------------------------------- #
# Work done on a Dask worker
# --------------------------------------------------------------------------- #

# libsumo holds one simulation per process: on a multi-threaded worker, SUMO runs are serialised.
_SUMO_LOCK = threading.Lock()


def execute_run(cfg: Config, run_dir: str, distance_bin_m: float) -> dict:
    """Run (unless already complete) and return the run's partial sums for the sweep outputs.

    Never raises: errors (libsumo's cannot be pickled) come back as text.
    """
    run_dir = Path(run_dir)
    status = "present"
    try:
        if not run_complete(run_dir):
            from experiments.runner import run_experiment

            if cfg.is_controlled_scenario:
                run_experiment(cfg, run_dir, progress=False, write_report=False)
            else:
                with _SUMO_LOCK:
                    run_experiment(cfg, run_dir, progress=False, write_report=False)
            status = "computed"
        centre = tuple(cfg.crossroad.centre) if cfg.scenario.kind == "crossroad" else None
        return {"status": status, "partials": run_partials(run_dir, centre, distance_bin_m)}
    except BaseException as exc:  # noqa: BLE001 - reported to the client as text
        if isinstance(exc, KeyboardInterrupt):
            raise
        msg = exc.describe() if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"
        return {"status": "error", "error": msg, "traceback": traceback.format_exc()}


def _sse(df: pd.DataFrame, keys: list[str], cols: dict[str, str]) -> pd.DataFrame:
    """Sums of squares of ``cols`` (source -> output name) and counts per ``keys``."""
    tmp = df[keys].copy()
    for src, dst in cols.items():
        v = df[src].to_numpy(dtype=float)
        tmp[dst] = v * v
    tmp["n"] = 1
    return tmp.groupby(keys, sort=True, observed=True).sum().reset_index()


def run_partials(run_dir: Path, centre: tuple[float, float] | None, distance_bin_m: float) -> dict:
    """Per-run sums for the sweep outputs, read from the run's files (never from memory)."""
    import pyarrow.parquet as pq

    summary = json.loads((run_dir / "summary.json").read_text())
    coverage = summary.get("within_rsu_coverage")
    rows = []
    for method, block in summary["methods"].items():
        assoc = (summary.get("association") or {}).get(method) or {}
        feat = block.get("features") or {}
        row = {
            "method": method,
            "rmse_pos_m": block.get("rmse_pos_m"), "rmse_vel_mps": block.get("rmse_vel_mps"),
            "p50_pos_m": block.get("p50_pos_m"), "p95_pos_m": block.get("p95_pos_m"), "n": block.get("n"),
            "correct_pct": assoc.get("correct_pct"), "wrong_pct": assoc.get("wrong_pct"),
            "discarded_pct": assoc.get("discarded_pct"),
            "feature_rmse_pos_m": feat.get("rmse_pos_m"),
        }
        if coverage is not None:  # infrastructure mode: the same covered vehicle-steps for every method
            cb = coverage["methods"].get(method) or {}
            row.update({f"covered_{k}": cb.get(k) for k in COVERED_COLUMNS})
        rows.append(row)
    est = pq.read_table(run_dir / "estimates.parquet",
                        columns=["method", "t", "err_pos", "err_vel", "px_true", "py_true", "zone"]).to_pandas()
    est["method"] = est["method"].astype(str)
    # [analysis] warmup_s: the tables score what the run's summary scored (t >= scored_from_s)
    t0 = (summary.get("analysis") or {}).get("scored_from_s")
    if t0 is not None:
        est = est[scored_mask(est["t"], t0)]
    out = {"summary": rows}
    out["zone_sums"], out["zone_hist"] = zone_partials(est)
    out["degree"] = degree_partial(summary)
    out["time"] = _sse(est, ["method", "t"], {"err_pos": "sse_pos", "err_vel": "sse_vel"}).rename(columns={"t": "x"})
    out["overall"] = _sse(est, ["method"], {"err_pos": "sse_pos", "err_vel": "sse_vel"})
    if centre is not None:
        d = np.hypot(est["px_true"].to_numpy() - centre[0], est["py_true"].to_numpy() - centre[1])
        est["x"] = (np.floor(d / distance_bin_m) + 0.5) * distance_bin_m
        out["distance"] = _sse(est, ["method", "x"], {"err_pos": "sse_pos", "err_vel": "sse_vel"})
    fpath = run_dir / "features.parquet"
    if fpath.exists():
        feat = pq.read_table(fpath, columns=["method", "t", "err_pos"]).to_pandas()
        feat["method"] = feat["method"].astype(str)
        if t0 is not None:
            feat = feat[scored_mask(feat["t"], t0)]
        out["feature_time"] = _sse(feat, ["method", "t"], {"err_pos": "sse_pos"}).rename(columns={"t": "x"})
        out["feature_overall"] = _sse(feat, ["method"], {"err_pos": "sse_pos"})
    assoc = pq.read_table(run_dir / "association.parquet",
                          columns=["method", "t", "correct", "wrong", "discarded"]).to_pandas()
    assoc["method"] = assoc["method"].astype(str)
    assoc = (assoc[scored_mask(assoc["t"], t0)] if t0 is not None else assoc).drop(columns="t")
    out["association"] = assoc.groupby("method", sort=True).sum().reset_index()
    return out


# --------------------------------------------------------------------------- #
# Aggregation (client side, deterministic)
# --------------------------------------------------------------------------- #


def _param_columns(spec: SweepSpec, settings: np.ndarray) -> dict[str, np.ndarray | pd.Series]:
    """One column per swept key for the given setting indices, typed from the values; with factors, the
    string columns ``factor`` and ``level``."""
    all_settings = settings_of(spec)
    combos = [c for c, _ in all_settings]
    cols = {}
    for j, (key, values) in enumerate(spec.grid):
        vals = [c[j] for c in combos]
        if all(isinstance(v, bool) for v in values):
            arr = np.array(vals, dtype=bool)
        elif all(isinstance(v, int) and not isinstance(v, bool) for v in values):
            arr = np.array(vals, dtype=np.int64)
        elif all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            arr = np.array(vals, dtype=np.float64)
        else:
            arr = np.array([v if isinstance(v, str) else _toml_value(v) for v in vals], dtype=object)
        col = arr[settings]
        cols[key] = pd.Series(col, dtype="string") if col.dtype == object else col
    if spec.factors:
        for name, attr in (("factor", "factor"), ("level", "level")):
            arr = np.array([getattr(v, attr) for _, v in all_settings], dtype=object)
            cols[name] = pd.Series(arr[settings], dtype="string")
    return cols


def paired_partials(spec: SweepSpec, runs: list[SweepRun], partials: list[dict]) -> pd.DataFrame:
    """``DIR/paired.parquet``: per setting and GNSS zone ("all" pools them), LC minus GNSS and LC minus
    known association of the per-seed RMSE (same seed, same traffic), mean over the seeds with its 95 %
    paired t interval and the number of seeds (:mod:`experiments.sweep.paired`). Empty without LC."""
    from experiments.sweep.paired import paired_table

    rows = []
    for run, part in zip(runs, partials):
        zs = part.get("zone_sums")
        if zs is None or not len(zs):
            continue
        for r in zs.itertuples(index=False):
            rows.append({"_setting": run.setting, "zone": str(r.zone), "seed": run.seed, "method": str(r.method),
                         "rmse_pos_m": math.sqrt(r.sse_pos / r.n) if r.n else math.nan})
    if not rows:
        return pd.DataFrame()
    t = paired_table(pd.DataFrame(rows), ["_setting", "zone"])
    if not len(t):
        return pd.DataFrame()
    params = _param_columns(spec, t["_setting"].to_numpy(dtype=np.int64))
    front = pd.DataFrame(params)
    rest = t.drop(columns=["_setting"]).reset_index(drop=True)
    rest["seeds"] = rest["seeds"].astype("int64")
    return pd.concat([front.reset_index(drop=True), rest], axis=1)


def aggregate(spec: SweepSpec, runs: list[SweepRun], partials: list[dict]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """sweep.parquet and curves.parquet tables from the runs' partial sums (in run order)."""
    method_rank = {m: i for i, m in enumerate(runs[0].cfg.run.methods)} if runs else {}
    # sweep.parquet: one row per (run, method)
    rows = []
    for k, (run, part) in enumerate(zip(runs, partials)):
        for r in part["summary"]:
            rows.append({"_run": k, "_setting": run.setting, "run_id": run.run_id, "seed": run.seed, **r})
    sweep = pd.DataFrame(rows)
    if len(sweep):
        sweep["_rank"] = sweep["method"].map(lambda m: method_rank.get(m, len(method_rank)))
        sweep = sweep.sort_values(["_setting", "seed", "_rank", "method"], kind="mergesort").reset_index(drop=True)
    params = _param_columns(spec, sweep["_setting"].to_numpy(dtype=np.int64))
    front = pd.DataFrame({"run_id": sweep["run_id"].astype("string"), "seed": sweep["seed"].astype("int64"), **params})
    numeric = ["rmse_pos_m", "rmse_vel_mps", "p50_pos_m", "p95_pos_m", "correct_pct", "wrong_pct",
               "discarded_pct", "feature_rmse_pos_m"]
    blocks = [front, sweep[["method"]].astype("string"), sweep[numeric].astype("float64"),
              sweep[["n"]].astype("int64")]
    if "covered_n" in sweep.columns:  # some run has [infra]: within-coverage columns (NaN / 0 for runs without)
        blocks += [sweep[[f"covered_{k}" for k in COVERED_COLUMNS if k != "n"]].astype("float64"),
                   sweep[["covered_n"]].fillna(0).astype("int64")]
    table = pd.concat(blocks, axis=1)

    # curves.parquet
    n_runs = np.bincount([r.setting for r in runs], minlength=len(settings_of(spec)))
    parts = []
    for kind in CURVE_KINDS:
        frames = []
        for run, part in zip(runs, partials):
            df = part.get(kind)
            if df is not None and len(df):
                df = df.copy()
                df.insert(0, "_setting", run.setting)
                frames.append(df)
        if not frames:
            continue
        df = pd.concat(frames, ignore_index=True)
        keys = ["_setting", "method"] + (["x"] if "x" in df.columns else [])
        g = df.groupby(keys, sort=True, observed=True).sum(numeric_only=True).reset_index()
        res = pd.DataFrame({"_setting": g["_setting"].to_numpy(dtype=np.int64), "method": g["method"].astype(str)})
        res["x"] = g["x"].to_numpy(dtype=float) if "x" in g else np.nan
        res["n_runs"] = n_runs[res["_setting"].to_numpy()]
        nan = np.full(len(g), np.nan)
        if kind == "association":
            total = (g["correct"] + g["wrong"] + g["discarded"]).to_numpy(dtype=float)
            safe = np.where(total > 0, total, np.nan)
            res["n_samples"] = total.astype(np.int64)
            res["rmse_pos_m"], res["rmse_vel_mps"] = nan, nan
            for c in ("correct", "wrong", "discarded"):
                res[f"{c}_pct"] = 100.0 * g[c].to_numpy(dtype=float) / safe
        else:
            n = g["n"].to_numpy(dtype=float)
            res["n_samples"] = g["n"].to_numpy(dtype=np.int64)
            res["rmse_pos_m"] = np.sqrt(g["sse_pos"].to_numpy(dtype=float) / n)
            res["rmse_vel_mps"] = np.sqrt(g["sse_vel"].to_numpy(dtype=float) / n) if "sse_vel" in g else nan
            for c in ("correct", "wrong", "discarded"):
                res[f"{c}_pct"] = nan
        res.insert(0, "curve", kind)
        parts.append(res)
    cols = ["curve", "_setting", "method", "x", "n_runs", "n_samples", "rmse_pos_m", "rmse_vel_mps",
            "correct_pct", "wrong_pct", "discarded_pct"]
    curves = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=cols)
    curves["_kind"] = curves["curve"].map({k: i for i, k in enumerate(CURVE_KINDS)})
    curves["_rank"] = curves["method"].map(lambda m: method_rank.get(m, len(method_rank)))
    curves = curves.sort_values(["_kind", "_setting", "_rank", "method", "x"], kind="mergesort").reset_index(drop=True)
    params = _param_columns(spec, curves["_setting"].to_numpy(dtype=np.int64))
    curves_out = pd.concat([
        pd.DataFrame({"curve": curves["curve"].astype("string"), **params,
                      "method": curves["method"].astype("string")}),
        curves[["x"]].astype("float64"),
        curves[["n_runs", "n_samples"]].astype("int64"),
        curves[["rmse_pos_m", "rmse_vel_mps", "correct_pct", "wrong_pct", "discarded_pct"]].astype("float64"),
    ], axis=1)
    return table, curves_out


# --------------------------------------------------------------------------- #
# Driver
# --------------------------------------------------------------------------- #


@dataclass
class SweepResult:
    out: Path
    n_runs: int
    computed: int
    present: int
    failed: list[tuple[str, str]]
    seconds: float
    workers: int
    dry_run: bool = False
    recomputed: int = 0  # finished runs computed again (--force) because a file they read changed
    workers_asked: int | None = None  # --workers when it was capped (:func:`cap_workers`), else None


class SweepFailed(Exception):
    """Some runs of a sweep failed; the completed ones are kept for a restart."""


def default_workers() -> int:
    try:
        ncpu = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        ncpu = os.cpu_count() or 1
    return max(1, min(ncpu, 4))


def usable_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def cap_workers(asked: int, to_compute: int) -> int:
    """Local worker processes worth starting: at most the runs still to compute (a worker computes one
    run at a time, one more would only start and idle) and at most the usable cores (each worker is one
    single-threaded process: more than the cores only share them, each with its own SUMO and imports,
    and 100 workers starting at once on 2 cores time out connecting to the scheduler); at least 1."""
    return max(1, min(asked, to_compute, usable_cores()))


class _DaskClient:
    """A Client on a new LocalCluster of processes, or on a running scheduler."""

    def __init__(self, scheduler: str | None, workers: int, connect_timeout: str = "20s"):
        self.scheduler, self.workers, self.connect_timeout = scheduler, workers, connect_timeout
        self.cluster = self.client = None

    def __enter__(self):
        from dask.distributed import Client, LocalCluster

        if self.scheduler:
            try:
                self.client = Client(self.scheduler, timeout=self.connect_timeout)
            except (OSError, TimeoutError, ValueError) as exc:  # ValueError: not an address (no port, ...)
                raise InputError(None, "--scheduler", f"cannot connect to {self.scheduler} ({exc})") from None
        else:
            self.cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                        dashboard_address=None, silence_logs=logging.ERROR)
            self.client = Client(self.cluster)
        return self.client

    def __exit__(self, *exc):
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def run_sweep(spec_path: str | Path, out: str | Path, scheduler: str | None = None, workers: int | None = None,
              progress: bool = True, dry_run: bool = False, write_report: bool = True,
              connect_timeout: str = "20s", force: bool = False) -> SweepResult:
    """Run (or resume) a sweep; returns counts. Raises InputError on bad input, SweepFailed on failed runs."""
    t0 = time.perf_counter()
    spec = load_sweep(spec_path)
    with recording_reads() as config_files:
        base_cfg, runs = expand_runs(spec)
    out = Path(out)
    # An empty folder or a sweep folder (``force``: any folder; never a file). Checked for --dry-run too.
    check_target(out, ("sweep",), force=force, replaces_folder=False)
    told, workers = workers, workers or default_workers()
    if dry_run:
        return SweepResult(out, len(runs), 0, 0, [], time.perf_counter() - t0, workers, dry_run=True)
    if workers < 1:
        raise InputError(None, "--workers", "must be >= 1")
    spec_text = resolved_spec_toml(spec, base_cfg, len(runs))
    inputs = sweep_inputs(spec, runs, config_files)
    if (out / "sweep.toml").exists():  # another sweep, then the same one on changed files (named by the file)
        _check_spec(out, spec_text, spec.path, ("base_config_sha256",))
    redo, ignore = _check_inputs(out, inputs, runs, force)
    if (out / "sweep.toml").exists():
        _check_spec(out, spec_text, spec.path, ignore)  # refuse a different sweep before starting anything
    need = [r for r in runs if r.run_id in redo or not run_complete(out / RUNS_DIR / r.run_id)]
    asked, workers = workers, workers if scheduler else cap_workers(workers, len(need))
    capped = told is not None and workers != asked and bool(need)  # a default is capped silently
    if capped and progress:
        print(f"{spec.name}: {workers} local worker(s), not {asked}: {len(need)} run(s) to compute on "
              f"{usable_cores()} usable core(s)", file=sys.stderr)
    # Nothing to compute (e.g. rebuilding the outputs): the runs are read here, no cluster needed.
    # Otherwise the cluster is started (or the scheduler reached) before anything is written.
    with (_DaskClient(scheduler, workers, connect_timeout) if need else contextlib.nullcontext()) as client:
        make_folder(out)
        mark(out, "sweep")
        lock = _acquire_lock(out, spec.path)
        try:
            _check_or_write_spec(out, spec_text, spec.path, ignore)
            _restart_changed(out, inputs, redo)
            res = _run_locked(spec, runs, out, spec_text, client, progress, write_report, workers, t0)
            return dataclasses.replace(res, recomputed=len(redo), workers_asked=asked if capped else None)
        finally:
            lock.close()


def _run_locked(spec: SweepSpec, runs: list[SweepRun], out: Path, spec_text: str, client, progress: bool,
                write_report: bool, workers: int, t0: float) -> SweepResult:
    _check_or_write_spec(out, spec_text, spec.path)
    clean_leftovers(out)
    (out / RUNS_DIR).mkdir(exist_ok=True)
    partials: list[dict | None] = [None] * len(runs)
    failed: list[tuple[str, str]] = []
    computed = present = 0
    from tqdm import tqdm

    # Redirected stderr (logs, CI): a line every 30 s instead of a carriage-return stream.
    bar = tqdm(total=len(runs), desc=spec.name, unit="run", file=sys.stderr, disable=not progress,
               mininterval=0.5 if sys.stderr.isatty() else 30.0)

    def collect(k: int, res: dict) -> None:
        nonlocal computed, present
        if res["status"] == "error":
            failed.append((runs[k].run_id, res["error"]))
        else:
            partials[k] = res["partials"]
            computed += res["status"] == "computed"
            present += res["status"] == "present"
        bar.set_postfix(computed=computed, present=present, failed=len(failed), refresh=False)
        bar.update(1)

    if client is None:
        for k, run in enumerate(runs):
            collect(k, execute_run(run.cfg, str(out / RUNS_DIR / run.run_id), spec.distance_bin_m))
    else:
        from dask.distributed import as_completed

        futures = {}
        for k, run in enumerate(runs):
            fut = client.submit(execute_run, run.cfg, str(out / RUNS_DIR / run.run_id), spec.distance_bin_m,
                                key=f"coloc-sweep-{k}-{os.getpid()}-{time.time_ns()}", pure=False)
            futures[fut] = k
        for fut in as_completed(futures):
            collect(futures[fut], fut.result())
            fut.release()
    bar.close()
    if failed:
        failed.sort()
        raise SweepFailed(f"{len(failed)} of {len(runs)} runs failed (first: {failed[0][0]}: {failed[0][1]}); "
                          "completed runs are kept: rerun the same command to retry the others")
    if spec.eval_seeds:  # the tables and the report score the evaluation seeds only
        keep = [k for k, r in enumerate(runs) if r.seed in set(spec.eval_seeds)]
        runs, partials = [runs[k] for k in keep], [partials[k] for k in keep]
    table, curves = aggregate(spec, runs, partials)
    paired = paired_partials(spec, runs, partials)
    method_rank = {m: i for i, m in enumerate(runs[0].cfg.run.methods)} if runs else {}
    n_runs = np.bincount([r.setting for r in runs], minlength=len(settings_of(spec)))
    zones, v2v = aggregate_zones(runs, partials, lambda st: _param_columns(spec, st), n_runs, method_rank)
    from experiments.runner import write_parquet

    outputs = [("sweep.parquet", table), ("curves.parquet", curves)]
    outputs += [(name, df) for name, df in (("zones.parquet", zones), ("v2v.parquet", v2v),
                                            ("paired.parquet", paired)) if len(df)]
    for name, df in outputs:
        buf = io.BytesIO()
        write_parquet(df, buf)
        write_file_atomic(out / name, buf.getvalue())
    if write_report:
        from experiments.sweep.report import write_sweep_report

        write_sweep_report(out)
    return SweepResult(out, len(runs), computed, present, [], time.perf_counter() - t0, workers)
