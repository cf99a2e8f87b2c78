"""A run folder read back for the reports (config, summary, Parquet files), with fallback statistics."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from couplers.errors import InputError, read_toml
from experiments.report.styles import order_methods


# --------------------------------------------------------------------------- #
# Loading
# --------------------------------------------------------------------------- #

_EST_COLS = ["method", "t", "err_pos", "err_vel", "err_along", "err_cross", "zone", "area"]
#: What the 2-D position NEES is computed from (cov_pxy: files written since it was added); replaced by "nees".
_NEES_COLS = ["px", "py", "px_true", "py_true", "var_px", "var_py", "cov_pxy"]


#: Columns a report cannot do without, per file of a run folder (the others it reads are optional:
#: written by later versions, or only in some scenarios).
REQUIRED_COLUMNS = {
    "estimates.parquet": ("method", "t", "err_pos"),
    "features.parquet": ("method", "t", "err_pos"),
    "traffic.parquet": ("interval_start_s",),
    "association.parquet": ("method",),
}


def require_columns(path: Path, names, required) -> None:
    """An :class:`InputError` naming ``path`` and every column of ``required`` that ``names`` lacks."""
    missing = [c for c in required if c not in set(names)]
    if missing:
        raise InputError(path, None, f"missing column{'s' if len(missing) > 1 else ''} {', '.join(missing)}: "
                                     "not the file coloc writes there (from another tool, or edited?)")


def _read_parquet(path: Path, wanted: list[str]) -> pd.DataFrame | None:
    """Read the wanted columns that exist; None when the file is absent. The file's
    :data:`REQUIRED_COLUMNS` must be there."""
    if not path.exists():
        return None
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        names = set(pq.read_schema(path).names)
        require_columns(path, names, [c for c in REQUIRED_COLUMNS.get(path.name, ()) if c in wanted])
        cols = [c for c in wanted if c in names]
        cat_cols = [c for c in ("method", "zone", "area", "run") if c in cols]
        # Label columns are read dictionary-encoded (-> pandas categoricals): millions of rows
        # would otherwise become millions of Python strings.
        table = pq.read_table(path, columns=cols, read_dictionary=cat_cols)
    except (pa.ArrowException, OSError) as exc:
        raise InputError(path, None, f"not a readable Parquet file ({str(exc).splitlines()[0]}): "
                                     "is the run folder complete?") from None
    return _labels_as_categories(table.to_pandas(), cat_cols)


def _labels_as_categories(df: pd.DataFrame, cat_cols: list[str]) -> pd.DataFrame:
    for c in cat_cols:
        if not isinstance(df[c].dtype, pd.CategoricalDtype) or not all(
                isinstance(v, str) for v in df[c].cat.categories):
            df[c] = df[c].astype("string").astype("category")
    return df


#: Rows read at a time where a file is read in batches (the row groups coloc writes hold 1 Mi rows).
BATCH_ROWS = 1 << 18


def _batches(path: Path, wanted: list[str], cat_cols: list[str]):
    """(columns read, iterator of record batches) of ``path``, the :data:`REQUIRED_COLUMNS` checked; the
    label columns dictionary-encoded."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        names = set(pq.read_schema(path).names)
        require_columns(path, names, [c for c in REQUIRED_COLUMNS.get(path.name, ()) if c in wanted])
        cols = [c for c in wanted if c in names]
        pf = pq.ParquetFile(path, read_dictionary=[c for c in cat_cols if c in names])
        batches = pf.iter_batches(batch_size=BATCH_ROWS, columns=cols)
    except (pa.ArrowException, OSError) as exc:
        raise InputError(path, None, f"not a readable Parquet file ({str(exc).splitlines()[0]}): "
                                     "is the run folder complete?") from None
    return cols, batches


def _read_estimates(path: Path, wanted: list[str], nees: bool) -> pd.DataFrame | None:
    """The wanted columns of estimates.parquet (None when absent), read batch by batch; with ``nees``
    and a file that has the :data:`_NEES_COLS`, a ``nees`` column (the 2-D position NEES,
    :func:`experiments.rowstream.position_nees`) computed per batch, the seven columns it comes from
    never held for the whole file (a city hour: 2.4 M rows, 130 MB of them)."""
    if not path.exists():
        return None
    import pyarrow as pa

    from experiments.rowstream import position_nees

    cat_cols = [c for c in ("method", "zone", "area", "run") if c in wanted]
    cols, batches = _batches(path, wanted + (_NEES_COLS if nees else []), cat_cols)
    cat_cols = [c for c in cat_cols if c in cols]
    with_nees = nees and set(_NEES_COLS) <= set(cols)
    keep = [c for c in cols if c not in _NEES_COLS]
    parts = []
    try:
        for b in batches:
            part = pa.Table.from_batches([b]).select(keep)
            if with_nees:
                v = {c: b.column(c).to_numpy(zero_copy_only=False).astype(float) for c in _NEES_COLS}
                part = part.append_column("nees", pa.array(position_nees(
                    v["px"] - v["px_true"], v["py"] - v["py_true"], v["var_px"], v["var_py"], v["cov_pxy"])))
            parts.append(part)
    except (pa.ArrowException, OSError) as exc:
        raise InputError(path, None, f"not a readable Parquet file ({str(exc).splitlines()[0]}): "
                                     "is the run folder complete?") from None
    if not parts:
        return _read_parquet(path, keep)  # no row: the empty frame with its columns
    table = pa.concat_tables(parts)
    return _labels_as_categories(table.to_pandas(), cat_cols)


def _read_feature_steps(path: Path) -> pd.DataFrame | None:
    """features.parquet reduced to one row per (method, t): ``sq`` the sum of the squared finite
    position errors and ``n`` their count (None when absent). What the reports draw of the feature
    tracks (RMSE per time bin) needs no more; an hour of a city's tracks is 14 M rows, this a few
    thousand."""
    if not path.exists():
        return None
    import pyarrow as pa

    _cols, batches = _batches(path, ["method", "t", "err_pos"], ["method"])
    parts = []
    try:
        for b in batches:
            df = b.to_pandas()
            e = df["err_pos"].to_numpy(dtype=float)
            ok = np.isfinite(e)
            parts.append(pd.DataFrame({"method": df["method"].astype(str)[ok], "t": df["t"].to_numpy(dtype=float)[ok],
                                       "sq": e[ok] * e[ok], "n": np.ones(int(ok.sum()), dtype=np.int64)})
                         .groupby(["method", "t"], sort=False).sum())
    except (pa.ArrowException, OSError) as exc:
        raise InputError(path, None, f"not a readable Parquet file ({str(exc).splitlines()[0]}): "
                                     "is the run folder complete?") from None
    if not parts:
        return pd.DataFrame({"method": pd.Categorical([]), "t": np.empty(0), "sq": np.empty(0),
                             "n": np.empty(0, dtype=np.int64)})
    out = pd.concat(parts).groupby(level=[0, 1], sort=False).sum().reset_index()
    out["method"] = out["method"].astype("category")
    return out


@dataclass
class _Run:
    run_dir: Path
    config: dict
    summary: dict
    estimates: pd.DataFrame | None = None
    features: pd.DataFrame | None = None
    traffic: pd.DataFrame | None = None
    association: pd.DataFrame | None = None
    #: estimates.parquet reduced for the run report (experiments.report.digest); comparisons read ``estimates``
    digest: Any = None
    notes: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return str(self.config.get("run", {}).get("name") or self.run_dir.name)

    @property
    def seed(self):
        s = self.config.get("run", {}).get("seed")
        return self.summary.get("seed", s) if s is None else s

    @property
    def begin_s(self) -> float:
        """The run's begin on the scenario's clock ([scenario] begin_s; 0 for runs without one)."""
        val = self.config.get("scenario", {}).get("begin_s", 0.0)
        return float(val) if isinstance(val, (int, float)) and not isinstance(val, bool) else 0.0

    @property
    def control(self) -> str:
        return str(self.config.get("scenario", {}).get("control", "") or "")

    @property
    def methods(self) -> list[str]:
        ms: set[str] = set(self.summary.get("methods", {}) or {})
        if self.estimates is not None and len(self.estimates):
            ms |= {str(m) for m in self.estimates["method"].unique()}
        if self.digest is not None:
            ms |= set(self.digest.methods)
        return order_methods(ms)


def _load_run(run_dir: Path, *, need_areas: bool = True) -> _Run:
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.toml"
    config: dict = read_toml(cfg_path, "config file") if cfg_path.exists() else {}
    summary: dict = {}
    if (run_dir / "summary.json").exists():
        try:
            summary = json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))
        except (ValueError, UnicodeDecodeError) as exc:
            raise InputError(run_dir / "summary.json", None, f"not valid JSON ({exc}): is the run folder complete?") \
                from None
        if not isinstance(summary, dict):
            raise InputError(run_dir / "summary.json", None, "not a coloc summary (expected a JSON object)")
    run = _Run(run_dir=run_dir, config=config, summary=summary)
    if need_areas:  # the run report: per-step sums and histograms, read batch by batch (not the rows)
        from experiments.report.digest import digest_estimates

        t0 = (summary.get("analysis") or {}).get("scored_from_s")
        run.digest = digest_estimates(run_dir / "estimates.parquet", t0)
    else:
        run.estimates = _read_estimates(run_dir / "estimates.parquet", ["method", "t", "err_pos", "err_vel"], nees=False)
    run.features = _read_feature_steps(run_dir / "features.parquet")
    run.traffic = _read_parquet(
        run_dir / "traffic.parquet",
        ["interval_start_s", "interval_end_s", "mean_vehicles", "exit_flow_vph",
         "mean_queue", "stop_time_s_per_km", "teleports"],
    )
    run.association = _read_parquet(
        run_dir / "association.parquet", ["method", "t", "correct", "wrong", "discarded"]
    )
    if not (run_dir / "estimates.parquet").exists():
        run.notes.append("estimates.parquet is missing: no accuracy figures.")
    elif not run.summary.get("methods") and need_areas:
        run.summary.setdefault("methods", _summary_from_estimates(
            _read_estimates(run_dir / "estimates.parquet", _EST_COLS, nees=False)))
        run.notes.append("summary.json has no per-method statistics: computed from estimates.parquet.")
    return run


def _rmse(x: pd.Series) -> float:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def _summary_from_estimates(est: pd.DataFrame) -> dict:
    """Fallback statistics in the summary.json schema (only used when summary lacks them)."""
    out: dict = {}
    for m, g in est.groupby("method", observed=True, sort=False):
        e = g["err_pos"].to_numpy(dtype=float)
        e = e[np.isfinite(e)]
        d: dict[str, Any] = {
            "rmse_pos_m": _rmse(e),
            "rmse_vel_mps": _rmse(g["err_vel"]) if "err_vel" in g else float("nan"),
            "p50_pos_m": float(np.quantile(e, 0.5)) if e.size else float("nan"),
            "p95_pos_m": float(np.quantile(e, 0.95)) if e.size else float("nan"),
        }
        for key, col in (("by_area", "area"), ("by_zone", "zone")):
            if col not in g:
                continue
            d[key] = {}
            for lab, gg in g.groupby(col, observed=True):
                ee = gg["err_pos"].to_numpy(dtype=float)
                ee = ee[np.isfinite(ee)]
                if not ee.size or not _valid_label(lab):
                    continue
                d[key][str(lab)] = {"rmse_pos_m": _rmse(ee),
                                    "p95_pos_m": float(np.quantile(ee, 0.95)), "n": int(ee.size)}
        out[str(m)] = d
    return out


def _valid_label(v) -> bool:
    if v is None or (isinstance(v, float) and math.isnan(v)) or v is pd.NA:
        return False
    return str(v).strip().lower() not in ("", "nan", "none", "<na>", "-")
