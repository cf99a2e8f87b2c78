"""Scoring against truth, outside the estimators: errors, RMSE, percentiles, per area/zone."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the functions take pandas objects; importing pandas is left to their callers
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
    """summary.json "methods" block for one method's rows (docs/architecture.md "Output schemas")."""
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


#: The 95 % point of the chi-square distribution with 2 degrees of freedom, -2 ln(0.05): a 2-D position error
#: lies inside the 95 % ellipse of its covariance when its NEES is at most this.
CHI2_2_95 = -2.0 * math.log(0.05)


def _nees_stats(nees: np.ndarray) -> dict:
    return {"mean": float(nees.mean()), "median": float(np.median(nees)),
            "inside_95": float(np.mean(nees <= CHI2_2_95)), "n": int(nees.size)}


def nees_summary(nees: np.ndarray, zone: np.ndarray) -> dict:
    """summary.json "nees_pos" block: the 2-D position NEES e^T P^-1 e (from px, py, var_px, var_py, cov_pxy of
    estimates.parquet: :func:`experiments.rowstream.position_nees`), overall and per GNSS zone: ``mean``
    (2 = consistent; larger = the covariance claims more than the estimate delivers), ``median`` (1.386 =
    2 ln 2 for a consistent Gaussian), ``inside_95`` (the share of samples inside the 95 % ellipse: 0.95
    when consistent), ``n``. Samples with a singular covariance (non-finite NEES) are left out."""
    nees = np.asarray(nees, dtype=float)
    zone = np.asarray(zone)
    ok = np.isfinite(nees)
    out = _nees_stats(nees[ok]) if ok.any() else {"mean": None, "median": None, "inside_95": None, "n": 0}
    out["by_zone"] = {}
    for z in sorted(set(zone[ok].tolist())):
        out["by_zone"][str(z)] = _nees_stats(nees[ok & (zone == z)])
    return out


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


# --------------------------------------------------------------------------- #
# Association scoring (docs/architecture.md "Features without a map": tracks are mapped to true
# features outside the estimator)
# --------------------------------------------------------------------------- #


def track_labels(track: np.ndarray, feature: np.ndarray) -> dict[int, int]:
    """Label each feature track with the true feature it was most often paired with.

    ``track`` and ``feature`` are the paired (track id, true feature index) of
    every V2F row that was not discarded, over the whole run. Ties go to the
    smallest feature index. Tracks never paired with a row get no label.
    """
    track = np.asarray(track, dtype=np.int64)
    feature = np.asarray(feature, dtype=np.int64)
    if track.size == 0:
        return {}
    # The distinct (track, feature) pairs and their counts: one lexsort of the two columns and the runs
    # of equal pairs (what np.unique(..., axis=0, return_counts=True) gives, in its order; its sort of
    # the rows as a structured dtype took 1 s for the 1.9M rows of an arterial hour).
    by_pair = np.lexsort((feature, track))
    t_s, f_s = track[by_pair], feature[by_pair]
    first_of_run = np.ones(t_s.size, dtype=bool)
    first_of_run[1:] = (t_s[1:] != t_s[:-1]) | (f_s[1:] != f_s[:-1])
    starts = np.flatnonzero(first_of_run)
    pairs = np.stack([t_s[starts], f_s[starts]], axis=1)
    counts = np.diff(np.append(starts, t_s.size))
    return labels_from_pairs(pairs, counts)


def labels_from_pairs(pairs: np.ndarray, counts: np.ndarray) -> dict[int, int]:
    """:func:`track_labels` from the distinct (track, feature) pairs (P, 2) and how often each occurred."""
    if pairs.shape[0] == 0:
        return {}
    # Order: track ascending, count descending, feature ascending; the first row per track wins.
    order = np.lexsort((pairs[:, 1], -counts, pairs[:, 0]))
    pairs = pairs[order]
    first = np.ones(len(pairs), dtype=bool)
    first[1:] = pairs[1:, 0] != pairs[:-1, 0]
    return {int(t): int(f) for t, f in pairs[first]}


def label_arrays(labels: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The labels of :func:`track_labels` as sorted track ids and their features, for :func:`labelled`."""
    keys = np.array(sorted(labels), dtype=np.int64)
    return keys, np.array([labels[k] for k in keys], dtype=np.int64)


def labelled(ids: np.ndarray, keys: np.ndarray, vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which track ids carry a label of a true feature (not -1, a ghost), and that feature (0 where not);
    ``keys`` must not be empty."""
    pos = np.minimum(np.searchsorted(keys, ids), keys.size - 1)
    ok = (keys[pos] == ids) & (vals[pos] >= 0)
    return ok, np.where(ok, vals[pos], 0)


def score_association(steps: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, dict[int, int]]:
    """Correct / wrong / discarded V2F rows per step.

    ``steps``: per step, (assignment (O,), true feature (O,)), where assignment is
    the feature-track id the estimator paired each V2F row with, -1 = discarded.
    A row is correct when it comes from a real feature (true index >= 0) and that
    feature is its track's label (:func:`track_labels` over the whole run), wrong
    otherwise, discarded when its assignment is -1. A clutter row (true index -1)
    kept on any track is wrong, also on a track born from clutter (label -1: a
    ghost track). Returns the (S, 3) int64 counts [correct, wrong, discarded] and
    the track labels.
    """
    assign = [np.asarray(a, dtype=np.int64) for a, _ in steps]
    truth = [np.asarray(f, dtype=np.int64) for _, f in steps]
    for a, f in zip(assign, truth):
        if a.shape != f.shape:
            raise ValueError(f"assignment {a.shape} and true features {f.shape} differ in shape")
    all_a = np.concatenate(assign) if assign else np.empty(0, dtype=np.int64)
    all_f = np.concatenate(truth) if truth else np.empty(0, dtype=np.int64)
    step = np.repeat(np.arange(len(steps)), [a.size for a in assign]).astype(np.int64)
    kept = all_a >= 0
    labels = track_labels(all_a[kept], all_f[kept])
    correct = _correct_rows(all_a, all_f, labels)
    n = len(steps)
    counts = np.stack([
        np.bincount(step[correct], minlength=n),
        np.bincount(step[kept & ~correct], minlength=n),
        np.bincount(step[~kept], minlength=n),
    ], axis=1).astype(np.int64)
    return counts, labels


def _correct_rows(assign: np.ndarray, truth: np.ndarray, labels: dict[int, int]) -> np.ndarray:
    """Rows kept on a track whose label is the row's true feature (module rules of :func:`score_association`)."""
    kept = assign >= 0
    keys = np.array(sorted(labels), dtype=np.int64)
    vals = np.array([labels[k] for k in keys], dtype=np.int64)
    correct = np.zeros(assign.size, dtype=bool)
    if keys.size:
        pos = np.minimum(np.searchsorted(keys, assign[kept]), keys.size - 1)
        correct[kept] = (keys[pos] == assign[kept]) & (vals[pos] == truth[kept]) & (truth[kept] >= 0)
    return correct


def association_by_group(steps: list[tuple[np.ndarray, np.ndarray]], groups: list[np.ndarray],
                         labels: dict[int, int]) -> dict:
    """:func:`association_summary` per group of rows (e.g. the GNSS zone of the measuring vehicle), with
    the run's track ``labels`` of :func:`score_association`."""
    if not steps:
        return {}
    a = np.concatenate([np.asarray(x, dtype=np.int64) for x, _ in steps])
    f = np.concatenate([np.asarray(y, dtype=np.int64) for _, y in steps])
    g = np.concatenate([np.asarray(z).astype(str) for z in groups])
    correct = _correct_rows(a, f, labels)
    kept = a >= 0
    out = {}
    for name in sorted(set(g.tolist())):
        sel = g == name
        out[name] = association_summary(int((correct & sel).sum()), int((kept & ~correct & sel).sum()),
                                        int((~kept & sel).sum()))
    return out


def association_summary(correct: int, wrong: int, discarded: int) -> dict:
    """summary.json "association" block: counts and percentages of all V2F rows."""
    total = correct + wrong + discarded
    pct = (lambda n: 100.0 * n / total) if total else (lambda n: None)
    return {
        "correct": int(correct), "wrong": int(wrong), "discarded": int(discarded),
        "correct_pct": pct(correct), "wrong_pct": pct(wrong), "discarded_pct": pct(discarded),
    }


def coverage_summary(est: pd.DataFrame, methods: list[str]) -> dict:
    """Infrastructure mode: every method on the vehicle-steps within RSU coverage only
    (``covered`` column of estimates.parquet: the vehicle is within V2I range of some RSU; the
    same rows for every method), overall and per area, plus vehicle-steps per RSU."""
    cov = est[est["covered"]]
    out = {"methods": {}, "rsu_vehicle_steps": {}}
    for m in methods:
        e = cov[cov["method"] == m]
        block = {"rmse_pos_m": _rmse(e["err_pos"]), "p95_pos_m": _q(e["err_pos"], 0.95), "n": int(len(e)),
                 "by_area": {}}
        for name, g in e.groupby("area", sort=True, observed=True):
            block["by_area"][str(name)] = {"rmse_pos_m": _rmse(g["err_pos"]), "p95_pos_m": _q(g["err_pos"], 0.95),
                                           "n": int(len(g))}
        out["methods"][m] = block
    first = cov[cov["method"] == methods[0]] if methods else cov.iloc[:0]
    for name, g in first.groupby("rsu", sort=True, observed=True):
        out["rsu_vehicle_steps"][str(name)] = int(len(g))
    return _nan_to_none(out)


#: summary.json ``detections`` keys: what each V2F row truly is (couplers.sensing.road_users KIND_*).
DETECTION_KINDS = ("landmark", "clutter", "persistent_clutter", "vehicle", "pedestrian")


def detection_kinds(truth) -> np.ndarray:
    """Counts of one frame's V2F rows by kind, from the truth: ``v2f_kind`` when the coupler set it, else
    a row of a feature is a landmark (a pedestrian where ``feature_class`` says so) and -1 clutter."""
    if truth.v2f_kind is not None:
        return np.bincount(np.asarray(truth.v2f_kind, dtype=np.int64), minlength=len(DETECTION_KINDS))
    feat = np.asarray(truth.v2f_feature, dtype=np.int64)
    out = np.zeros(len(DETECTION_KINDS), dtype=np.int64)
    real = feat[feat >= 0]
    out[1] = feat.size - real.size
    ped = int(np.count_nonzero(np.asarray(truth.feature_class)[real] == 1)) if truth.feature_class is not None else 0
    out[0], out[4] = real.size - ped, ped
    return out


def scored_from(cfg) -> float | None:
    """First scored time of a run on its clock: ``scenario.begin_s + analysis.warmup_s``; None when the
    config has no warm-up (``[analysis]`` absent or ``warmup_s = 0``: every estimate is scored)."""
    analysis = getattr(cfg, "analysis", None)
    if analysis is None or not analysis.warmup_s > 0:
        return None
    return float(cfg.scenario.begin_s or 0.0) + float(analysis.warmup_s)


def traffic_only_s(cfg) -> float:
    """Seconds after the begin that SUMO simulates alone (``[analysis] warmup_start = "traffic"``: the warm-up),
    0 otherwise."""
    analysis = getattr(cfg, "analysis", None)
    if analysis is None or analysis.warmup_start != "traffic":
        return 0.0
    return float(analysis.warmup_s)


def scored_mask(t, t0: float | None) -> np.ndarray:
    """Which rows of time ``t`` are scored: t >= t0 (all when ``t0`` is None). The estimates files keep
    every row; this filter is applied to the statistics only, so that they can be recomputed."""
    t = np.asarray(t, dtype=float)
    if t0 is None:
        return np.ones(t.shape, dtype=bool)
    return t >= t0 - 1e-9


def analysis_summary(cfg) -> dict | None:
    """summary.json "analysis" block (None without [analysis]: the summary is as before)."""
    analysis = getattr(cfg, "analysis", None)
    if analysis is None:
        return None
    start = {} if analysis.warmup_start == "sensed" else {"warmup_start": analysis.warmup_start}
    return {"warmup_s": float(analysis.warmup_s), **start,
            "scored_from_s": float(cfg.scenario.begin_s or 0.0) + float(analysis.warmup_s)}
