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


# --------------------------------------------------------------------------- #
# What the share inside the 95 % ellipse can show when the vehicles share their error
# --------------------------------------------------------------------------- #
#
# A consistent estimator's samples fall inside their 95 % ellipse with probability 0.95 each, but the share
# of a run's samples inside is a sample mean of dependent indicators. Where the vehicles of a zone share most
# of their error at a step (a receiver's common-mode error: atmosphere, orbit and clock, the same for every
# vehicle of the net, Kaplan and Hegarty 2017, Sec. 7.2) and that shared part changes over tens of minutes,
# a 300 s run holds about one draw of it, and the share inside over a few runs is decided by a few draws. The
# model below: in run r, the error normalised by the claimed covariance (whitened) is c_r(t) + l, with c_r a
# stationary first-order Gauss-Markov process of covariance f_r I and correlation time tau, shared by every
# sample at t, and l ~ N(0, (1 - f_r) I) independent between samples (many vehicles, many local correlation
# times a run); then a run's share inside is the time average of P(|c + l|^2 <= chi2_2(0.95) | c), a
# non-central chi-square cdf, and its spread over runs is drawn.


def shared_error_moments(step, wx, wy) -> tuple[float, float]:
    """(shared, total) second moments of whitened 2-D errors (``wx``, ``wy``: the error premultiplied by the
    inverse Cholesky factor of its claimed covariance, so |w|^2 is the NEES) over the steps with n >= 2
    samples: ``shared`` = the sum over those steps of n (|mean|^2 - s^2 / n), s^2 the step's sample variance
    summed over the axes (n |mean|^2 - s^2 is unbiased for n |c|^2, c the part every sample of the step
    shares), ``total`` = the same steps' sum of |w|^2. Pool runs by summing both: one run holds about one
    draw of a slowly changing shared part, so its own ratio is that draw's, not the model's fraction."""
    df = pd.DataFrame({"t": np.asarray(step), "x": np.asarray(wx, dtype=float), "y": np.asarray(wy, dtype=float)})
    g = df.groupby("t", sort=False)
    n = g["x"].count().to_numpy(dtype=float)
    mean = g[["x", "y"]].mean().to_numpy()
    var = g[["x", "y"]].var(ddof=1).to_numpy()
    total = (df["x"] ** 2 + df["y"] ** 2).groupby(df["t"], sort=False).sum().to_numpy()
    ok = n >= 2
    if not ok.any():
        return 0.0, 0.0
    shared = n[ok] * ((mean[ok] ** 2).sum(axis=1) - var[ok].sum(axis=1) / n[ok])
    return float(shared.sum()), float(total[ok].sum())


def shared_error_fraction(step, wx, wy) -> float:
    """shared / total of :func:`shared_error_moments`, clipped to [0, 1]; NaN without a step of two samples."""
    shared, total = shared_error_moments(step, wx, wy)
    return float(min(1.0, max(0.0, shared / total))) if total > 0 else math.nan


def whitened_errors(ex, ey, var_x, var_y, cov_xy) -> tuple[np.ndarray, np.ndarray]:
    """(wx, wy) = L^-1 (ex, ey) with L L^T = [[var_x, cov_xy], [cov_xy, var_y]] (lower Cholesky factor), so
    wx^2 + wy^2 is the 2-D NEES."""
    a = np.sqrt(np.asarray(var_x, dtype=float))
    b = np.asarray(cov_xy, dtype=float) / a
    c = np.sqrt(np.asarray(var_y, dtype=float) - b * b)
    wx = np.asarray(ex, dtype=float) / a
    return wx, (np.asarray(ey, dtype=float) - b * wx) / c


def inside_share_band(shared, tau_s: float = math.inf, window_s: float = 300.0, level: float = 0.95,
                      draws: int = 20000, seed: int = 0, step_s: float = 10.0) -> tuple[float, float]:
    """The two-sided ``level`` interval of the mean over runs of the share of samples inside the 95 % ellipse
    for a consistent estimator whose errors share the fraction ``shared[r]`` in run r (one value a run; their
    number is the number of runs), the shared part a Gauss-Markov process of correlation time ``tau_s``
    (inf: constant over a run) seen over ``window_s`` at points ``step_s`` apart (the section's model above).
    Drawn ``draws`` times from ``numpy.random.default_rng(seed)``: same arguments, same interval.
    All fractions 0 gives (0.95, 0.95): independent samples, as many as a run has."""
    from scipy.stats import chi2, ncx2

    f = np.clip(np.asarray(shared, dtype=float).ravel(), 0.0, 1.0)
    if f.size == 0 or not np.isfinite(f).all():
        return math.nan, math.nan
    q95 = float(chi2.ppf(0.95, 2))
    rng = np.random.default_rng(seed)
    k = 1 if not math.isfinite(tau_s) else max(1, int(round(window_s / step_s)) + 1)
    phi = 1.0 if not math.isfinite(tau_s) else math.exp(-step_s / tau_s)
    c = rng.standard_normal((draws, f.size, 2))
    z = np.empty((draws, f.size, k))
    z[:, :, 0] = (c ** 2).sum(axis=-1)
    for i in range(1, k):   # AR(1) of unit variance per axis: c' = phi c + sqrt(1 - phi^2) n
        c = phi * c + math.sqrt(1.0 - phi * phi) * rng.standard_normal((draws, f.size, 2))
        z[:, :, i] = (c ** 2).sum(axis=-1)
    share = np.empty((draws, f.size))
    for r, fr in enumerate(f):
        lam = fr * z[:, r, :]                   # |c|^2 with c ~ N(0, fr I)
        if fr >= 1.0 - 1e-12:
            p = (lam <= q95).astype(float)
        elif fr <= 0.0:
            p = np.full(lam.shape, 0.95)
        else:
            grid = np.linspace(0.0, float(lam.max()), 4097)
            table = ncx2.cdf(q95 / (1.0 - fr), 2, grid / (1.0 - fr))
            p = np.interp(lam, grid, table)
        share[:, r] = p.mean(axis=1)
    mean = share.mean(axis=1)
    return float(np.quantile(mean, 0.5 - level / 2.0)), float(np.quantile(mean, 0.5 + level / 2.0))
