"""Per-zone accuracy and the V2V degree of a sweep: ``zones.parquet`` and ``v2v.parquet``.

The realistic-sensing and V2X studies report RMSE *and* the 95th percentile of the position error by
GNSS zone for every setting, pooled over its Monte Carlo runs. A pooled percentile needs the pooled
errors; each run contributes a histogram of its errors per (method, zone) in 1 cm bins up to 100 m
(larger errors counted in an overflow bin that keeps their exact maximum), so the pooled p95 is exact
to the bin width (1 cm) and the partials stay small. RMSE is exact (sums of squares).

The V2V degree (neighbours within Rc of a vehicle at a step, the intended graph ``frame.neighbors``)
comes from each run's ``summary.json`` ``v2v.degree_counts``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

ERR_BIN_M = 0.01
ERR_BINS = 10_000  # 0 .. 100 m; index ERR_BINS is the overflow bin
ALL_ZONES = "all"


def zone_partials(est: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(sums per method and zone, sparse error histogram per method and zone) of one run's estimates
    (columns method, zone, err_pos); zone "all" pools the zones."""
    err = est["err_pos"].to_numpy(dtype=float)
    ok = np.isfinite(err)
    est, err = est[ok], err[ok]
    zone = est["zone"].astype(str).to_numpy()
    method = est["method"].astype(str).to_numpy()
    b = np.minimum((err / ERR_BIN_M).astype(np.int64), ERR_BINS)
    frames_s, frames_h = [], []
    for z_col in (zone, np.full(zone.shape, ALL_ZONES, dtype=object)):
        df = pd.DataFrame({"method": method, "zone": z_col, "sse_pos": err * err, "n": 1,
                           "max_pos": err, "bin": b})
        s = df.groupby(["method", "zone"], sort=True).agg(sse_pos=("sse_pos", "sum"), n=("n", "sum"),
                                                          max_pos=("max_pos", "max")).reset_index()
        h = df.groupby(["method", "zone", "bin"], sort=True).size().rename("count").reset_index()
        frames_s.append(s)
        frames_h.append(h)
    return pd.concat(frames_s, ignore_index=True), pd.concat(frames_h, ignore_index=True)


def p95_from_histogram(bins: np.ndarray, counts: np.ndarray, max_err: float, q: float = 0.95) -> float:
    """The q-quantile (inverted CDF) of pooled errors from their 1 cm histogram: the upper edge of the
    bin holding it, or the exact maximum when it lies in the overflow bin."""
    order = np.argsort(bins, kind="stable")
    bins, counts = bins[order], counts[order]
    cum = np.cumsum(counts)
    k = int(np.searchsorted(cum, q * cum[-1], side="left"))
    if bins[k] >= ERR_BINS:
        return float(max_err)
    return float(min((bins[k] + 1) * ERR_BIN_M, max_err))


def degree_partial(summary: dict) -> pd.DataFrame | None:
    counts = (summary.get("v2v") or {}).get("degree_counts")
    if not counts:
        return None
    return pd.DataFrame({"degree": np.arange(len(counts), dtype=np.int64), "count": np.asarray(counts, dtype=np.int64)})


def aggregate_zones(runs, partials: list[dict], param_columns, n_runs: np.ndarray, method_rank: dict
                    ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(zones.parquet, v2v.parquet): per (setting, method, zone) pooled RMSE and p95, and per (setting,
    degree) the vehicle-steps; ``param_columns(settings)`` gives the swept-key columns."""
    sums, hists, degs = [], [], []
    for run, part in zip(runs, partials):
        if part.get("zone_sums") is not None:
            sums.append(part["zone_sums"].assign(_setting=run.setting))
            hists.append(part["zone_hist"].assign(_setting=run.setting))
        if part.get("degree") is not None:
            degs.append(part["degree"].assign(_setting=run.setting))
    zones = pd.DataFrame()
    if sums:
        s = pd.concat(sums, ignore_index=True).groupby(["_setting", "method", "zone"], sort=True).agg(
            sse_pos=("sse_pos", "sum"), n=("n", "sum"), max_pos=("max_pos", "max")).reset_index()
        h = pd.concat(hists, ignore_index=True).groupby(["_setting", "method", "zone", "bin"], sort=True)["count"].sum()
        max_pos = s.set_index(["_setting", "method", "zone"])["max_pos"]
        p95 = {key: p95_from_histogram(sub.index.get_level_values("bin").to_numpy(), sub.to_numpy(),
                                       float(max_pos.loc[key]))
               for key, sub in h.groupby(level=[0, 1, 2], sort=True)}
        s["p95_pos_m"] = [p95[k] for k in zip(s["_setting"], s["method"], s["zone"])]
        s["rmse_pos_m"] = np.sqrt(s["sse_pos"] / s["n"])
        s["_rank"] = s["method"].map(lambda m: method_rank.get(m, len(method_rank)))
        s["_zone_rank"] = (s["zone"] == ALL_ZONES).astype(int)
        s = s.sort_values(["_setting", "_rank", "method", "_zone_rank", "zone"], kind="mergesort").reset_index(drop=True)
        settings = s["_setting"].to_numpy(dtype=np.int64)
        zones = pd.concat([
            pd.DataFrame({**param_columns(settings), "method": s["method"].astype("string"),
                          "zone": s["zone"].astype("string")}),
            pd.DataFrame({"n_runs": n_runs[settings].astype(np.int64), "n_samples": s["n"].astype(np.int64)}),
            s[["rmse_pos_m", "p95_pos_m"]].astype("float64"),
        ], axis=1)
    v2v = pd.DataFrame()
    if degs:
        d = pd.concat(degs, ignore_index=True).groupby(["_setting", "degree"], sort=True)["count"].sum().reset_index()
        d = d[d["count"] > 0].reset_index(drop=True)
        settings = d["_setting"].to_numpy(dtype=np.int64)
        v2v = pd.concat([pd.DataFrame(param_columns(settings)),
                         pd.DataFrame({"n_runs": n_runs[settings].astype(np.int64),
                                       "degree": d["degree"].astype(np.int64),
                                       "vehicle_steps": d["count"].astype(np.int64)})], axis=1)
    return zones, v2v
