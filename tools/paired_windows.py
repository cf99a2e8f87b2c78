#!/usr/bin/env python3
"""Paired comparison of two methods over the seeds of one or more sweep folders.

For each run (``runs/<run_id>/estimates.parquet``) and time window, the mean squared
position error of every method; then per parameter point (the sweep's grid columns,
read from ``sweep.parquet``) the RMSE pooled over the runs and the paired difference
``a - b`` of the per-run window MSE: mean, standard error over the seeds, and on how
many seeds ``a`` was the lower. Runs with the same run id in two folders (a seed run
twice) are refused.

    python tools/paired_windows.py results/fig7_pf results/fig7_pf_more \\
        --a icp_da_pf --b icp_da_lc --windows 10:19,20:30

This is how the README's Fig. 7 PF table was computed (seeds 1-10 and 11-50).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from coloc.methods.registry import ICP_DA_LC, ICP_DA_PF


def parse_windows(text: str) -> list[tuple[float, float]]:
    """``"10:19,20:30"`` -> [(10, 19), (20, 30)] (inclusive bounds, seconds)."""
    out = []
    for part in text.split(","):
        lo, hi = (float(v) for v in part.split(":"))
        if not hi >= lo:
            raise ValueError(f"window {part!r}: end before start")
        out.append((lo, hi))
    return out


def window_mse(folders: list[Path], windows: list[tuple[float, float]]) -> pd.DataFrame:
    """One row per (run, method, window): the window's mean squared position error, plus the grid columns."""
    rows, seen = [], set()
    for folder in folders:
        table = pd.read_parquet(folder / "sweep.parquet")
        cols = list(table.columns)  # run_id, seed, the swept parameters, method, the summary columns
        grid = cols[cols.index("seed") + 1:cols.index("method")]
        runs = table.drop_duplicates("run_id").set_index("run_id")
        for run_id, run in runs.iterrows():
            if run_id in seen:
                raise ValueError(f"{folder}: run {run_id} is also in an earlier folder")
            seen.add(run_id)
            est = pd.read_parquet(folder / "runs" / run_id / "estimates.parquet", columns=["method", "t", "err_pos"])
            for method, g in est.groupby("method"):
                for w, (lo, hi) in enumerate(windows):
                    e = g.err_pos[(g.t >= lo) & (g.t <= hi)].to_numpy()
                    rows.append({**{c: run[c] for c in grid}, "seed": int(run["seed"]), "method": method,
                                 "window": w, "mse": float(np.mean(e**2)) if e.size else np.nan})
    return pd.DataFrame(rows)


def paired(mse: pd.DataFrame, a: str, b: str) -> pd.DataFrame:
    """Per grid point and window: pooled RMSE of a and b, and the paired MSE difference a - b over seeds."""
    grid = [c for c in mse.columns if c not in {"seed", "method", "window", "mse"}]
    out = []
    for key, g in mse.groupby(grid + ["window"], sort=True):
        wide = g.pivot(index="seed", columns="method", values="mse")
        d = (wide[a] - wide[b]).dropna()
        key = key if isinstance(key, tuple) else (key,)
        out.append({**dict(zip(grid + ["window"], key)), "seeds": len(d),
                    f"rmse_{a}": float(np.sqrt(wide[a].mean())), f"rmse_{b}": float(np.sqrt(wide[b].mean())),
                    "dmse_mean": float(d.mean()),
                    "dmse_se": float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else np.nan,
                    "a_lower_on": int((d < 0).sum())})
    return pd.DataFrame(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", type=Path, help="sweep output folders (coloc sweep --out)")
    ap.add_argument("--a", default=ICP_DA_PF.name)
    ap.add_argument("--b", default=ICP_DA_LC.name)
    ap.add_argument("--windows", default="10:19,20:30", help="time windows lo:hi, comma separated (s)")
    args = ap.parse_args(argv)
    try:
        table = paired(window_mse(args.folders, parse_windows(args.windows)), args.a, args.b)
    except (OSError, ValueError, KeyError) as exc:
        print(f"paired_windows: {exc}", file=sys.stderr)
        return 2
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(table.round(4).to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
