#!/usr/bin/env python3
"""The oracle's bound beside its error: for each seed and GNSS zone, the RMSE of an oracle's scored estimates
(``tools/oracle_sat_replay.py --estimates``) and the root mean trace of its position covariance.

For a linear-Gaussian state-space model the posterior Cramer-Rao bound's information recursion is the Kalman
filter's (Tichavsky, Muravchik and Nehorai, IEEE Trans. Signal Process. 46(5), 1998, Sec. IV): the joint oracle's
covariance, which its measurements' values do not change (only the reported covariances, the association it is
told and its gate's exclusions, which it takes as given), is the bound of its own linear-Gaussian model of the
world, conditional on those. sqrt(mean trace P_pos) is that bound as an RMSE. The world is not that model (the
reflected signals' errors are not Gaussian), so the oracle's RMSE can be above it or, on one seed, below it: the
common-mode error is one draw a run.

The oracle's rows carry no truth and no zone: they are joined on (t, vehicle) with a protocol run's ``gnss`` rows
of the same seed (the same world: the frames the oracle replays are that run's).

    python tools/oracle_bound.py ORACLE.parquet:RUN_DIR [ORACLE.parquet:RUN_DIR ...]

Not a test.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.methods.registry import GNSS  # noqa: E402


def bound_rows(oracle: pd.DataFrame, run: pd.DataFrame) -> list[dict]:
    """Per zone ("all" first): the oracle's RMSE, its bound (sqrt of the mean trace of its position covariance)
    and the rows joined."""
    o = oracle.assign(t=oracle["t"].round(6))
    r = run[run["method"] == GNSS.name][["t", "vehicle", "px_true", "py_true", "zone"]]
    j = o.merge(r.assign(t=r["t"].round(6)), on=["t", "vehicle"], how="inner")
    j = j.assign(se=(j["x"] - j["px_true"]) ** 2 + (j["y"] - j["py_true"]) ** 2, tr=j["cov_xx"] + j["cov_yy"])
    out = []
    for zone, g in [("all", j), *j.groupby(j["zone"].astype(str), sort=True)]:
        out.append({"zone": zone, "rmse": float(np.sqrt(g["se"].mean())), "bound": float(np.sqrt(g["tr"].mean())),
                    "n": int(len(g))})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", help="ORACLE.parquet:RUN_DIR (RUN_DIR holds the run's estimates.parquet)")
    args = ap.parse_args(argv)
    rows = []
    for pair in args.pairs:
        oracle_path, _, run_dir = pair.partition(":")
        oracle = pd.read_parquet(oracle_path)
        run = pd.read_parquet(Path(run_dir) / "estimates.parquet",
                              columns=["method", "t", "vehicle", "px_true", "py_true", "zone"])
        if len(oracle["method"].unique()) != 1:
            print(f"{oracle_path}: method: one oracle a file", file=sys.stderr)
            return 2
        for r in bound_rows(oracle, run):
            rows.append({"file": Path(oracle_path).name, **r})
    df = pd.DataFrame(rows)
    print("| file | zone | RMSE (m) | bound (m) | rows |\n|---|---|---|---|---|")
    for r in df.itertuples():
        print(f"| {r.file} | {r.zone} | {r.rmse:.3f} | {r.bound:.3f} | {r.n} |")
    # over the seeds as root mean squares: the bound is an expected squared error
    pooled = df.assign(mse=df["rmse"] ** 2, tr=df["bound"] ** 2).groupby("zone", sort=False)[["mse", "tr"]].mean()
    print("\n| zone | RMSE over the seeds (m) | bound over the seeds (m) |\n|---|---|---|")
    for zone, r in pooled.iterrows():
        print(f"| {zone} | {np.sqrt(r.mse):.3f} | {np.sqrt(r.tr):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
