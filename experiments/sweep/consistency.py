"""Consistency across the seeds of a sweep: ``DIR/consistency.parquet``, per setting, method and GNSS zone
("all" pools the zones).

The statistic (the average NEES of Bar-Shalom, Li and Kirubarajan, *Estimation with Applications to
Tracking and Navigation*, 2001, Sec. 5.4.2, taken over runs): ``anees`` = the mean over the S seeds of each
run's time-averaged 2-D position NEES (its summary.json ``nees_pos`` mean, after the run's warm-up).

Its band. Samples inside one run are not independent (every vehicle's error is correlated over tens of
seconds, and the vehicles share the traffic and, in the field GNSS model, part of their error), so a
chi-square band with 2 x (vehicle-steps) degrees of freedom would be far too narrow. The runs are
independent (one seed each). The band counts each run as ONE 2-dof sample: for a consistent estimator
the S x anees lies inside the two-sided 95 % interval of a chi-square with 2 S degrees of freedom,
``[chi2_{2S}(0.025) / S, chi2_{2S}(0.975) / S]``. This is conservative: a run's time average of NEES
values each with mean 2 and variance 4 has mean 2 and a variance of at most 4 (equality when its samples
are fully correlated), so the per-run averages of a consistent estimator spread at most as much as the
band assumes. A method outside the band is inconsistent at (at least) that level; inside, it is not
shown inconsistent. Beside it, ``t_lo`` / ``t_hi``: the 95 % t interval of the per-run means (S - 1
dof), which uses the spread the runs actually show (a tighter check when the runs agree, none with one
seed). ``inside_95``: the mean over the runs of the share of samples inside the 95 % ellipse (0.95 when
consistent).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

ALL = "all"
COLUMNS = ["seeds", "anees", "band_lo", "band_hi", "inside_band", "t_lo", "t_hi", "inside_95"]


def nees_partial(summary: dict) -> pd.DataFrame | None:
    """One run's NEES rows (method, zone, nees_mean, inside_95) from its summary.json (None: no NEES blocks,
    e.g. a summary written before they had the share inside)."""
    rows = []
    for method, block in (summary.get("methods") or {}).items():
        nees = (block or {}).get("nees_pos") or {}
        if nees.get("mean") is None or "inside_95" not in nees:
            continue
        rows.append({"method": method, "zone": ALL, "nees_mean": nees["mean"], "inside_95": nees["inside_95"]})
        for zone, b in sorted((nees.get("by_zone") or {}).items()):
            if isinstance(b, dict) and b.get("mean") is not None:
                rows.append({"method": method, "zone": str(zone), "nees_mean": b["mean"], "inside_95": b["inside_95"]})
    return pd.DataFrame(rows) if rows else None


def anees_band(seeds: int, level: float = 0.95) -> tuple[float, float]:
    """The two-sided ``level`` interval of the average of ``seeds`` independent chi-square(2) samples:
    [chi2_{2S}((1 - level) / 2), chi2_{2S}((1 + level) / 2)] / S."""
    from scipy.stats import chi2

    s = int(seeds)
    return float(chi2.ppf(0.5 - level / 2.0, 2 * s)) / s, float(chi2.ppf(0.5 + level / 2.0, 2 * s)) / s


def consistency_row(nees_means, inside, level: float = 0.95) -> dict:
    """The module's statistics of one (setting, method, zone) from its per-run means and shares."""
    from scipy.stats import t as student_t

    m = np.asarray(nees_means, dtype=float)
    ok = np.isfinite(m)
    m, inside = m[ok], np.asarray(inside, dtype=float)[ok]
    s = int(m.size)
    if s == 0:
        return {"seeds": 0, **{c: math.nan for c in COLUMNS[1:]}, "inside_band": False}
    lo, hi = anees_band(s, level)
    anees = float(m.mean())
    t_lo = t_hi = math.nan
    if s > 1:
        half = float(student_t.ppf(0.5 + level / 2.0, s - 1)) * float(m.std(ddof=1)) / math.sqrt(s)
        t_lo, t_hi = anees - half, anees + half
    return {"seeds": s, "anees": anees, "band_lo": lo, "band_hi": hi, "inside_band": bool(lo <= anees <= hi),
            "t_lo": t_lo, "t_hi": t_hi, "inside_95": float(inside.mean())}


def consistency_table(runs, partials: list[dict], param_columns, method_rank: dict) -> pd.DataFrame:
    """consistency.parquet from the runs' NEES partials (``partials[k]["nees"]``); empty when none has them."""
    frames = []
    for run, part in zip(runs, partials):
        df = part.get("nees")
        if df is not None and len(df):
            frames.append(df.assign(_setting=run.setting, seed=run.seed))
    if not frames:
        return pd.DataFrame()
    df = pd.concat(frames, ignore_index=True)
    rows = []
    for (setting, method, zone), g in df.groupby(["_setting", "method", "zone"], sort=True):
        rows.append({"_setting": setting, "method": method, "zone": zone,
                     **consistency_row(g["nees_mean"].to_numpy(), g["inside_95"].to_numpy())})
    out = pd.DataFrame(rows)
    out["_rank"] = out["method"].map(lambda m: method_rank.get(m, len(method_rank)))
    out["_zone_rank"] = (out["zone"] == ALL).astype(int)
    out = out.sort_values(["_setting", "_rank", "method", "_zone_rank", "zone"], kind="mergesort").reset_index(drop=True)
    settings = out["_setting"].to_numpy(dtype=np.int64)
    return pd.concat([
        pd.DataFrame({**param_columns(settings), "method": out["method"].astype("string"),
                      "zone": out["zone"].astype("string")}),
        out[["seeds"]].astype("int64"),
        out[["anees", "band_lo", "band_hi"]].astype("float64"),
        out[["inside_band"]].astype(bool),
        out[["t_lo", "t_hi", "inside_95"]].astype("float64"),
    ], axis=1)
