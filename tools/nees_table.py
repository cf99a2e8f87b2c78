"""Accuracy and consistency of every method of one or more runs, from their ``estimates.parquet``.

``python tools/nees_table.py RUN_DIR [RUN_DIR ...] --from 60 [--zones]``: per method (and zone) the
position RMSE, the 95th percentile of the position error, the mean and median 2-D position NEES and
the share of samples inside the 95 % ellipse (NEES <= 5.99), over the rows with ``t >= --from``.
The NEES takes the position covariance's cross term ``cov_pxy`` when the file has it, else the two
variances alone (a diagonal approximation: the ellipse's axes along x and y).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import chi2


def table(runs: list[Path], t_from: float, zones: bool) -> pd.DataFrame:
    d = pd.concat([pd.read_parquet(Path(r) / "estimates.parquet") for r in runs], ignore_index=True)
    d = d[d.t >= t_from]
    ex, ey = d.px - d.px_true, d.py - d.py_true
    vx, vy = d.var_px, d.var_py
    cxy = d.cov_pxy if "cov_pxy" in d else 0.0
    det = vx * vy - cxy * cxy
    d = d.assign(nees=(ex * ex * vy - 2 * ex * ey * cxy + ey * ey * vx) / det)
    keys = ["method", "zone"] if zones else ["method"]
    g = d.groupby(keys, sort=False)
    gate = chi2.ppf(0.95, 2)
    out = pd.DataFrame({
        "n": g.size(),
        "rmse_m": g.err_pos.apply(lambda e: float(np.sqrt(np.mean(e * e)))),
        "p95_m": g.err_pos.quantile(0.95),
        "nees_mean": g.nees.mean(),
        "nees_median": g.nees.median(),
        "inside_95": g.nees.apply(lambda v: float(np.mean(v <= gate))),
    })
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--from", dest="t_from", type=float, default=0.0, help="score rows with t >= this (s)")
    ap.add_argument("--zones", action="store_true", help="one row per method and zone")
    a = ap.parse_args()
    with pd.option_context("display.width", 160, "display.float_format", "{:.3f}".format):
        print(table(a.runs, a.t_from, a.zones))


if __name__ == "__main__":
    main()
