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
    df = table.to_pandas()
    for c in cat_cols:
        if not isinstance(df[c].dtype, pd.CategoricalDtype) or not all(
                isinstance(v, str) for v in df[c].cat.categories):
            df[c] = df[c].astype("string").astype("category")
    return df


@dataclass
class _Run:
    run_dir: Path
    config: dict
    summary: dict
    estimates: pd.DataFrame | None = None
    features: pd.DataFrame | None = None
    traffic: pd.DataFrame | None = None
    association: pd.DataFrame | None = None
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
    cols = _EST_COLS if need_areas else ["method", "t", "err_pos", "err_vel"]
    run = _Run(run_dir=run_dir, config=config, summary=summary)
    run.estimates = _read_parquet(run_dir / "estimates.parquet", cols + (_NEES_COLS if need_areas else []))
    if run.estimates is not None and need_areas:
        est = run.estimates
        if set(_NEES_COLS) <= set(est.columns):
            from experiments.rowstream import position_nees

            col = {c: est[c].to_numpy(dtype=float) for c in _NEES_COLS}
            est["nees"] = position_nees(col["px"] - col["px_true"], col["py"] - col["py_true"], col["var_px"],
                                        col["var_py"], col["cov_pxy"])
        run.estimates = est.drop(columns=[c for c in _NEES_COLS if c in est.columns])
    run.features = _read_parquet(run_dir / "features.parquet", ["method", "t", "err_pos"])
    run.traffic = _read_parquet(
        run_dir / "traffic.parquet",
        ["interval_start_s", "interval_end_s", "mean_vehicles", "exit_flow_vph",
         "mean_queue", "stop_time_s_per_km", "teleports"],
    )
    run.association = _read_parquet(
        run_dir / "association.parquet", ["method", "t", "correct", "wrong", "discarded"]
    )
    if run.estimates is None:
        run.notes.append("estimates.parquet is missing: no accuracy figures.")
    if not run.summary.get("methods") and run.estimates is not None and need_areas:
        run.summary.setdefault("methods", _summary_from_estimates(run.estimates))
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
