"""Paired differences between methods over the seeds of one setting, with a t confidence interval.

Two methods of one run see the same traffic, sensors and GNSS draws (same seed), so their difference
per seed removes what the seeds share; the interval is the paired t interval of the per-seed
differences d_i = a_i - b_i: mean(d) +- t_{n-1, (1+level)/2} sd(d) / sqrt(n). The t interval (not a
normal one) because a sweep has few seeds (5 in the shipped studies: t_4 = 2.78 against z = 1.96), and
it holds when the differences are roughly normal, which a difference of two RMSEs over a 15-minute run
of thousands of vehicle-steps is (each RMSE a mean of many squared errors).
"""
from __future__ import annotations

import math

import numpy as np

from coloc.methods.registry import GNSS, ICP_DA_LC, ICP_KNOWN_DA

#: the methods the sweep tables and reports compare LC with (same seed, same traffic)
PAIRS = ((ICP_DA_LC.name, GNSS.name), (ICP_DA_LC.name, ICP_KNOWN_DA.name))


def paired_ci(a, b, level: float = 0.95) -> tuple[float, float, float, int]:
    """Mean of a - b over the pairs with both finite, and its paired t interval: (mean, lo, hi, n).
    n < 2: the interval is (nan, nan) (one seed has no spread); identical differences give lo = hi."""
    from scipy.stats import t as student_t

    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    d = d[np.isfinite(d)]
    n = int(d.size)
    if n == 0:
        return math.nan, math.nan, math.nan, 0
    mean = float(d.mean())
    if n < 2:
        return mean, math.nan, math.nan, n
    half = float(student_t.ppf(0.5 + level / 2.0, n - 1)) * float(d.std(ddof=1)) / math.sqrt(n)
    return mean, mean - half, mean + half, n


def paired_table(rows, keys: list[str], value: str = "rmse_pos_m", pairs=PAIRS, level: float = 0.95):
    """Per setting (``keys``) and pair (a, b): mean of a - b of ``value`` over the seeds, its interval and
    the number of seeds. ``rows``: one row per (setting, seed, method[, zone])."""
    import pandas as pd

    out = []
    methods = set(rows["method"].astype(str))
    for key, g in rows.groupby(keys, sort=True, dropna=False) if keys else [((), rows)]:
        key = key if isinstance(key, tuple) else (key,)
        wide = g.pivot_table(index="seed", columns="method", values=value, aggfunc="first")
        for a, b in pairs:
            if a not in methods or b not in methods or a not in wide or b not in wide:
                continue
            mean, lo, hi, n = paired_ci(wide[a].to_numpy(), wide[b].to_numpy(), level)
            out.append({**dict(zip(keys, key)), "a": a, "b": b, "value": value, "mean": mean,
                        "ci_lo": lo, "ci_hi": hi, "seeds": n})
    cols = [*keys, "a", "b", "value", "mean", "ci_lo", "ci_hi", "seeds"]
    return pd.DataFrame(out, columns=cols)
