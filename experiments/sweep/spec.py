"""A sweep file: its keys, its settings and seeds, the runs it expands to and the resolved spec saved beside them
(the sweep command: :mod:`experiments.sweep.run`)."""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import math
import re
import time
from dataclasses import dataclass
from pathlib import Path

from couplers.errors import SEED_MAX, InputError, read_toml, seed_problem
from experiments.config import OPTIONAL_SECTIONS, SECTIONS, Config, config_from_dict
from experiments.config_toml import toml_value, config_to_toml
from experiments.config_extends import read_config_data
from experiments.sweep.factors import Factor, Variant, apply_relative, factors_toml, flatten_dotted as _flatten, \
    parse_factors, split_overrides, variants

SPEC_KEYS = ("name", "base", "seeds", "methods", "distance_bin_m", "grid", "set", "factors", "bases",
             "tune_seeds", "eval_seeds", "design", "objective")
DESIGNS = ("one_at_a_time", "full", "fractional")  # [sweep] design (experiments.sweep.design)
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
    # [sweep] design: "one_at_a_time" (the preset and each factor's other levels), "full" (every combination of
    # the factors' levels) or "fractional" (a two-level 2^(k-p) fraction of resolution >= IV, these generators).
    design: str = "one_at_a_time"
    generators: tuple[str, ...] = ()
    # [sweep] objective = {method = "icp_da_lc", statistic = "rmse_pos_m"}: what `coloc tune` minimises (the
    # mean over the tuning seeds of the method's scored statistic); None: the sweep cannot be tuned.
    objective: tuple[str, str] | None = None

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
    each factor's non-preset levels; a single None without factors; with a design, its points)."""
    combos = list(itertools.product(*[values for _, values in spec.grid]))
    keys = spec.grid_keys
    vs = variants(spec.factors) if spec.design == "one_at_a_time" else design_points(spec)
    return [(combo, v) for combo in combos for v in vs
            if v is None or v.runs_with(dict(zip(keys, combo)))]


def design_points(spec: SweepSpec) -> list[Variant]:
    """The points of a "full" or "fractional" design, each a Variant combining one level of every factor
    (the first listed level is the low one, -1, of a two-level factor)."""
    from experiments.sweep import design as dsg  # noqa: PLC0415

    if spec.design == "fractional":
        coded = dsg.fractional_design(len(spec.factors), spec.generators)
        picks = [[f.levels[int(c > 0)] for f, c in zip(spec.factors, row)] for row in coded]
    else:
        picks = [list(p) for p in itertools.product(*[f.levels for f in spec.factors])]
    out = []
    for levels in picks:
        overrides = tuple(o for lv in levels for o in lv.overrides)
        relative = tuple(r for lv in levels for r in lv.relative)
        combo = tuple((f.name, lv.label) for f, lv in zip(spec.factors, levels))
        out.append(Variant("design", ",".join(f"{f}={lb}" for f, lb in combo), overrides, None, (), relative, combo))
    return out


def _check_design(design, factors: tuple[Factor, ...], path: Path) -> tuple[str, tuple[str, ...]]:
    """[sweep] design: its name and, for a fraction, the generators (experiments.sweep.design.GENERATORS)."""
    from experiments.sweep import design as dsg  # noqa: PLC0415

    if design not in DESIGNS:
        raise InputError(path, "sweep.design", f"unknown design {design!r} (available: {', '.join(DESIGNS)})")
    if design == "one_at_a_time":
        return design, ()
    if len(factors) < 2:
        raise InputError(path, "sweep.design", f"a {design} design needs at least 2 factors in [sweep.factors]")
    seen: dict[str, str] = {}
    for f in factors:
        for i, lv in enumerate(f.levels):
            where = f"sweep.factors.{f.name}[{i}]"
            if lv.base is not None or lv.only:
                raise InputError(path, where, f"a level of a {design} design takes set, relative or preset = true "
                                              "(no base, no only: every level combines with every other)")
            for key in [k for k, _ in lv.overrides] + [t for t, _, _ in lv.relative]:
                if seen.setdefault(key, f.name) != f.name:
                    raise InputError(path, where, f"{key} is also set by factor {seen[key]}: the factors of a design "
                                                  "set different keys")
        if design == "fractional" and len(f.levels) != 2:
            raise InputError(path, f"sweep.factors.{f.name}", f"a fractional design takes two levels per factor, got "
                                                              f"{len(f.levels)}")
    if design == "full":
        return design, ()
    try:
        _, _, gens = dsg.choose(len(factors))
    except ValueError as exc:
        raise InputError(path, "sweep.design", f"{exc}: use design = \"full\" or more factors") from None
    return design, gens


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
    design, generators = _check_design(sw.get("design", "one_at_a_time"), factors, path)
    objective = _objective(sw.get("objective"), methods, base, path)
    return SweepSpec(objective=objective, path=path.resolve(), name=name.strip(), base=base, seeds=seeds, methods=methods,
                     grid=tuple(grid), fixed=tuple(fixed), distance_bin_m=float(dbin), factors=factors,
                     bases=bases, tune_seeds=tune, eval_seeds=evals, design=design, generators=generators)


OBJECTIVE_STATISTICS = ("rmse_pos_m", "p95_pos_m", "p50_pos_m", "rmse_vel_mps")


def _objective(table, methods, base: Path, path: Path) -> tuple[str, str] | None:
    """[sweep] objective = {method = ..., statistic = ...} (statistic default rmse_pos_m), or None."""
    if table is None:
        return None
    if not isinstance(table, dict):
        raise InputError(path, "sweep.objective", "expected a table {method = \"...\", statistic = \"rmse_pos_m\"}")
    unknown = sorted(set(table) - {"method", "statistic"})
    if unknown:
        raise InputError(path, f"sweep.objective.{unknown[0]}", "unknown key (known: method, statistic)")
    method, stat = table.get("method"), table.get("statistic", "rmse_pos_m")
    if methods is None:
        methods = tuple(read_config_data(base).get("run", {}).get("methods", ()))
    if method not in methods:
        raise InputError(path, "sweep.objective.method", f"{method!r} is not one of the sweep's methods "
                                                         f"({', '.join(methods)})")
    if stat not in OBJECTIVE_STATISTICS:
        raise InputError(path, "sweep.objective.statistic",
                         f"unknown statistic {stat!r} (available: {', '.join(OBJECTIVE_STATISTICS)})")
    return method, stat


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
    if variant is not None and variant.combo:
        parts += [f"{f}={_safe(lb)}" for f, lb in variant.combo]
    elif variant is not None:
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
        overrides = {**fixed, **extra, **dict(params)}
        if variant is not None and variant.relative:  # a mismatch arm: the estimator's model off the world's
            data, overrides = apply_relative(data, overrides, variant.relative, spec.path, where)
        cfg = _config(cspec, data, overrides, where, context=f"with {text}: ")
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
        f"name = {toml_value(spec.name)}",
        f"base = {toml_value(str(spec.base))}",
        f"base_config_sha256 = {toml_value(hashlib.sha256(base_text.encode()).hexdigest())}",
        f"seeds = {toml_value(list(spec.seeds))}",
        *([f"tune_seeds = {toml_value(list(spec.tune_seeds))}", f"eval_seeds = {toml_value(list(spec.eval_seeds))}"]
          if spec.eval_seeds else []),
        f"methods = {toml_value(list(base_cfg.run.methods))}",
        f"distance_bin_m = {toml_value(spec.distance_bin_m)}",
        *([f"design = {toml_value(spec.design)}"] if spec.design != "one_at_a_time" else []),
        *([f"objective = {{method = {toml_value(spec.objective[0])}, statistic = {toml_value(spec.objective[1])}}}"]
          if spec.objective else []),
        *([f"generators = {toml_value(list(spec.generators))}  # added factors in letter order (A, B, ... "
           "the factors in file order)"] if spec.generators else []),
        f"runs = {n_runs}",
        "",
        "[sweep.set]",
    ]
    lines += [f"{toml_value(k)} = {toml_value(v)}" for k, v in spec.fixed]
    lines += ["", "[sweep.grid]"]
    lines += [f"{toml_value(k)} = {toml_value(list(v))}" for k, v in spec.grid]
    if spec.bases:
        lines += ["", "[sweep.bases]"]
        lines += [f"{toml_value(k)} = {{{', '.join(f'{toml_value(v)} = {toml_value(str(b))}' for v, b in pairs)}}}"
                  for k, pairs in spec.bases]
    if spec.factors:
        lines += factors_toml(spec.factors, toml_value)
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
