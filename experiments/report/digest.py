"""estimates.parquet reduced, batch by batch, to what the run report draws: memory that does not grow
with the vehicles.

* per (method, step): the sums of squared position and velocity errors and their counts, the sum of
  the finite position NEES, how many of them lie inside the 95 % ellipse and their count (RMSE and
  NEES over time; one row per method and step);
* per (method, area, step): the sums of squared along- and cross-track errors and their counts (the
  track figures);
* per (zone or area, method): a histogram of the finite position errors of the scored rows, with
  :data:`CDF_BITS` bits of resolution (1024 bins per power of two: a bin is at most 2^-10 = 0.098 %
  of its lower edge wide, from 2^-30 m to 2^30 m; an underflow and an overflow bin), and the
  smallest and largest error. The CDF curves are read from it: each quantile lies in the same bin as
  the exact one (at most 0.098 % of the value, e.g. 2 mm at 2 m), and is exact at 0 and 1.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from experiments.streamstats import bin_edges, bin_index, n_bins

#: Resolution of the CDF histograms: 2^CDF_BITS bins per power of two of the error.
CDF_BITS = 10


@dataclass
class ErrorHistogram:
    """Histogram of one curve's errors (:func:`experiments.streamstats.bin_index`, :data:`CDF_BITS`)."""

    counts: np.ndarray = field(default_factory=lambda: np.zeros(n_bins(CDF_BITS), dtype=np.int64))
    lo: float = np.inf
    hi: float = -np.inf

    @property
    def n(self) -> int:
        return int(self.counts.sum())

    def add(self, x: np.ndarray) -> None:
        if x.size:
            self.counts += np.bincount(bin_index(x, CDF_BITS), minlength=self.counts.size)
            self.lo, self.hi = min(self.lo, float(x.min())), max(self.hi, float(x.max()))

    def quantiles(self, grid: np.ndarray) -> np.ndarray:
        """``np.quantile`` of the errors at ``grid``, to the bin: the order statistics at (n - 1) q
        placed evenly within their bin (the i-th of a bin's c values at its (i + 1/2)/c), then
        interpolated as numpy does; the first and last are the smallest and largest error."""
        n = self.n
        edges = bin_edges(CDF_BITS)
        ends = np.cumsum(self.counts)
        v = (n - 1) * np.asarray(grid, dtype=float)
        k = np.floor(v).astype(np.int64)

        def order_stat(r: np.ndarray) -> np.ndarray:
            b = np.searchsorted(ends, r, side="right")
            c = self.counts[b]
            below = ends[b] - c
            lo, hi = edges[b], np.minimum(edges[b + 1], self.hi)
            lo = np.maximum(lo, self.lo)
            x = lo + (hi - lo) * (r - below + 0.5) / np.maximum(c, 1)
            return np.where(r == 0, self.lo, np.where(r == n - 1, self.hi, x))  # the extremes are known

        a = order_stat(np.minimum(k, n - 1))
        b = order_stat(np.minimum(k + 1, n - 1))
        out = a + (b - a) * (v - k)
        return np.clip(out, self.lo, self.hi)


@dataclass
class EstimateDigest:
    """What :mod:`experiments.report.figures` draws of estimates.parquet (module docstring)."""

    steps: pd.DataFrame  # method, t, sq_pos, n_pos, sq_vel, n_vel, nees, inside, n_nees
    area_steps: pd.DataFrame  # method, area, t, sq_along, n_along, sq_cross, n_cross
    cdf: dict[str, dict[tuple[str, str], ErrorHistogram]]  # "zone" / "area" -> (label, method) -> histogram
    columns: frozenset[str]  # the columns the file has
    labels: dict[str, list[str]]  # "zone" / "area" -> the labels in the file
    t_min: float = float("nan")

    @property
    def methods(self) -> list[str]:
        return [str(m) for m in self.steps["method"].unique()]

    def __len__(self) -> int:
        return len(self.steps)


def _sums(df: pd.DataFrame, keys: list[str], cols: dict[str, str]) -> pd.DataFrame:
    """Per ``keys``: the sum of squares (``sq_<name>``) and count (``n_<name>``) of each column's finite values."""
    out = df[keys].copy()
    for name, c in cols.items():
        v = df[c].to_numpy(dtype=float)
        ok = np.isfinite(v)
        out[f"sq_{name}"] = np.where(ok, v * v, 0.0)
        out[f"n_{name}"] = ok.astype(np.int64)
    return out.groupby(keys, sort=False, observed=True).sum()


def digest_estimates(path: Path, t0: float | None) -> EstimateDigest | None:
    """estimates.parquet of a run folder (None when absent) reduced batch by batch; ``t0``: the first
    scored time ([analysis] warmup_s) for the CDFs, None: every row."""
    if not path.exists():
        return None
    import pyarrow as pa

    from experiments.report.load import _EST_COLS, _NEES_COLS, _batches, _valid_label
    from experiments.rowstream import position_nees
    from experiments.scoring import CHI2_2_95
    from couplers.errors import InputError

    cols, batches = _batches(path, _EST_COLS + _NEES_COLS, ["method", "zone", "area"])
    with_nees = set(_NEES_COLS) <= set(cols)
    groups = [g for g in ("zone", "area") if g in cols]
    steps, area_steps = [], []
    cdf: dict[str, dict[tuple[str, str], ErrorHistogram]] = {g: {} for g in groups}
    labels: dict[str, set] = {g: set() for g in groups}
    t_min = np.inf
    try:
        for b in batches:
            df = b.to_pandas()
            for c in ["method", *groups]:
                df[c] = df[c].astype(str)
            t = df["t"].to_numpy(dtype=float)
            if t.size:
                t_min = min(t_min, float(np.nanmin(t)))
            step = _sums(df, ["method", "t"], {"pos": "err_pos"} | ({"vel": "err_vel"} if "err_vel" in cols else {}))
            if with_nees:
                v = {c: df[c].to_numpy(dtype=float) for c in _NEES_COLS}
                nees = position_nees(v["px"] - v["px_true"], v["py"] - v["py_true"], v["var_px"], v["var_py"],
                                     v["cov_pxy"])
                ok = np.isfinite(nees)
                tmp = pd.DataFrame({"method": df["method"], "t": t, "nees": np.where(ok, nees, 0.0),
                                    "inside": (ok & (nees <= CHI2_2_95)).astype(np.int64),
                                    "n_nees": ok.astype(np.int64)})
                step = step.join(tmp.groupby(["method", "t"], sort=False).sum())
            steps.append(step)
            if "area" in cols and {"err_along", "err_cross"} <= set(cols):
                area_steps.append(_sums(df, ["method", "area", "t"], {"along": "err_along", "cross": "err_cross"}))
            err = df["err_pos"].to_numpy(dtype=float)
            scored = np.isfinite(err) & (t >= t0 - 1e-9 if t0 is not None else True)
            for g in groups:
                labels[g] |= set(df[g].unique().tolist())
                sub = pd.DataFrame({"g": df[g][scored], "m": df["method"][scored], "e": err[scored]})
                for (lab, m), part in sub.groupby(["g", "m"], sort=False):
                    if _valid_label(lab):
                        cdf[g].setdefault((str(lab), str(m)), ErrorHistogram()).add(part["e"].to_numpy())
    except (pa.ArrowException, OSError) as exc:
        raise InputError(path, None, f"not a readable Parquet file ({str(exc).splitlines()[0]}): "
                                     "is the run folder complete?") from None

    def merged(parts: list, keys: list[str]) -> pd.DataFrame:
        if not parts:
            return pd.DataFrame(columns=keys)
        return pd.concat(parts).groupby(level=list(range(len(keys))), sort=False).sum().reset_index()

    return EstimateDigest(steps=merged(steps, ["method", "t"]), area_steps=merged(area_steps, ["method", "area", "t"]),
                          cdf=cdf, columns=frozenset(cols) | ({"nees"} if with_nees else frozenset()),
                          labels={g: sorted(v) for g, v in labels.items()},
                          t_min=float(t_min) if np.isfinite(t_min) else float("nan"))
