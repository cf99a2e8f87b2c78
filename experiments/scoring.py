"""Scoring against truth, outside the estimators: errors, RMSE, percentiles, per area/zone."""

from __future__ import annotations

import numpy as np
import pandas as pd


def along_cross_errors(err_xy: np.ndarray, heading: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed position error along and across the true heading (paper Figs. 18-19)."""
    c, s = np.cos(heading), np.sin(heading)
    along = err_xy[:, 0] * c + err_xy[:, 1] * s
    cross = -err_xy[:, 0] * s + err_xy[:, 1] * c
    return along, cross


def _rmse(x: pd.Series | np.ndarray) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def _q(x: pd.Series | np.ndarray, q: float) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.quantile(x, q)) if x.size else float("nan")


def _nan_to_none(d):
    if isinstance(d, dict):
        return {k: _nan_to_none(v) for k, v in d.items()}
    if isinstance(d, float) and not np.isfinite(d):
        return None
    return d


def method_summary(est: pd.DataFrame) -> dict:
    """summary.json "methods" block for one method's rows (DESIGN schema)."""
    out = {
        "rmse_pos_m": _rmse(est["err_pos"]),
        "rmse_vel_mps": _rmse(est["err_vel"]),
        "p50_pos_m": _q(est["err_pos"], 0.5),
        "p95_pos_m": _q(est["err_pos"], 0.95),
        "n": int(len(est)),
    }
    for key in ("area", "zone"):
        groups = {}
        for name, g in est.groupby(key, sort=True, observed=True):
            groups[str(name)] = {
                "rmse_pos_m": _rmse(g["err_pos"]),
                "p50_pos_m": _q(g["err_pos"], 0.5),
                "p95_pos_m": _q(g["err_pos"], 0.95),
                "rmse_along_m": _rmse(g["err_along"]),
                "rmse_cross_m": _rmse(g["err_cross"]),
                "n": int(len(g)),
            }
        out[f"by_{key}"] = groups
    return _nan_to_none(out)


def feature_summary(err_pos: np.ndarray) -> dict:
    """summary.json "features" block of a method: accuracy of its feature estimates."""
    return {"rmse_pos_m": _rmse(err_pos), "p95_pos_m": _q(err_pos, 0.95), "n": int(np.asarray(err_pos).size)}


def traffic_summary(traffic: pd.DataFrame) -> dict:
    """Whole-run traffic figures from the 5-minute rows (time-weighted)."""
    if traffic.empty:
        return {"mean_vehicles": 0.0, "exit_flow_vph": 0.0, "mean_queue": 0.0, "stop_time_s_per_km": 0.0, "teleports": 0}
    span = float((traffic["interval_end_s"] - traffic["interval_start_s"]).sum())
    w = (traffic["interval_end_s"] - traffic["interval_start_s"]) / span
    dist = float(traffic["distance_km"].sum())
    stop = float((traffic["stop_time_s_per_km"] * traffic["distance_km"]).sum())
    return {
        "mean_vehicles": float((traffic["mean_vehicles"] * w).sum()),
        "exit_flow_vph": float(traffic["arrived"].sum() * 3600.0 / span),
        "mean_queue": float((traffic["mean_queue"] * w).sum()),
        "stop_time_s_per_km": stop / dist if dist > 0 else 0.0,
        "teleports": int(traffic["teleports"].sum()),
    }
