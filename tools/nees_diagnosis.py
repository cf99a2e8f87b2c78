"""Where a method's overconfidence lives: 2-D position NEES and the share inside the 95 % ellipse of
runs' ``estimates.parquet``, binned by one covariate at a time, per method (and zone).

``python tools/nees_diagnosis.py RUN_DIR [RUN_DIR ...] --switch-on 600 [--from 600] [--by since_on|since_entry|speed|gnss_nis]``

Rows with ``t`` before ``--from`` (default: the switch-on) are left out after the covariates are computed, so the
cells score what ``summary.json`` and ``tools/nees_table.py --from`` score: a run with a sensed warm-up keeps its
warm-up rows in ``estimates.parquet`` (``[analysis] warmup_s`` only moves what the statistics score).

Covariates (all from the files, nothing rerun):
* ``since_on``: t minus the switch-on time (``--switch-on``, the end of a traffic-only warm-up);
* ``since_entry``: t minus the vehicle's first row in the run; vehicles present at the run's first
  estimated step (the switch-on) are labelled ``on`` (that row is the switch-on, not an entry);
* ``speed``: the true speed |v_true| (m/s);
* ``gnss_err``: the ``gnss`` method's own NEES for the same vehicle and step (a proxy for the receiver's
  error state, e.g. NLOS episodes: the fixes themselves are not in the outputs).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import chi2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from coloc.methods.registry import GNSS  # noqa: E402

GATE = chi2.ppf(0.95, 2)


def load(runs: list[Path], switch_on: float, scored_from: float | None = None) -> pd.DataFrame:
    """Every run's rows with the NEES and the covariates; with ``scored_from``, the rows with ``t >= scored_from``
    only (entries are found on every row first)."""
    parts = []
    for i, r in enumerate(runs):
        d = pd.read_parquet(Path(r) / "estimates.parquet",
                            columns=["method", "t", "vehicle", "px", "py", "px_true", "py_true", "vx_true",
                                     "vy_true", "err_pos", "zone", "var_px", "var_py", "cov_pxy"])
        d["run"] = i
        parts.append(d)
    d = pd.concat(parts, ignore_index=True)
    ex, ey = d.px - d.px_true, d.py - d.py_true
    det = d.var_px * d.var_py - d.cov_pxy ** 2
    d["nees"] = (ex * ex * d.var_py - 2 * ex * ey * d.cov_pxy + ey * ey * d.var_px) / det
    d["speed"] = np.hypot(d.vx_true, d.vy_true)
    first = d.groupby(["run", "method", "vehicle"]).t.transform("min")
    d["since_on"] = d.t - switch_on
    start = d.groupby("run").t.transform("min")  # the first estimated step: switch-on (or the run's start)
    d["since_entry"] = np.where(first <= start + 1e-6, np.nan, d.t - first)
    g = d[d.method == GNSS.name][["run", "t", "vehicle", "nees"]].rename(columns={"nees": "gnss_nees"})
    d = d.merge(g, on=["run", "t", "vehicle"], how="left")
    if scored_from is not None:
        d = d[d.t >= scored_from].reset_index(drop=True)
    return d


BINS = {
    "since_on": [0, 15, 60, 120, 300.1],
    "since_entry": [0, 15, 60, 120, 300.1],
    "speed": [0, 0.5, 3, 8, 12, 40],
    "gnss_nees": [0, 2, 6, 14, 50, np.inf],
}


def table(d: pd.DataFrame, by: str, zones: bool) -> pd.DataFrame:
    col = d[by]
    lab = pd.cut(col, BINS[by], right=False).astype(str)
    if by == "since_entry":
        lab = lab.where(col.notna(), "on")
    d = d.assign(bin=lab)
    keys = ["method"] + (["zone"] if zones else []) + ["bin"]
    g = d.groupby(keys, sort=True)
    return pd.DataFrame({
        "share": g.size() / d.groupby(keys[:-1]).size().reindex(g.size().index.droplevel(-1)).to_numpy(),
        "rmse_m": g.err_pos.apply(lambda e: float(np.sqrt(np.mean(e * e)))),
        "nees_mean": g.nees.mean(),
        "nees_median": g.nees.median(),
        "inside_95": g.nees.apply(lambda v: float(np.mean(v <= GATE))),
    })


def pivot(d: pd.DataFrame, by: str) -> pd.DataFrame:
    """Compact form: one row per method and zone (and all zones), one column per bin, each cell
    "inside % (ANEES)"; the bins' shares of the samples in a last row per method."""
    col = d[by]
    edges = BINS[by]
    names = [f"{a:g}-{b:g}" for a, b in zip(edges[:-1], edges[1:])]
    lab = pd.cut(col, edges, right=False, labels=names).astype(str)
    if by == "since_entry":
        lab = lab.where(col.notna(), "on")
    d = d.assign(bin=lab, inside=d.nees <= GATE)
    out = []
    for zone_all in (False, True):
        keys = ["method", "bin"] if zone_all else ["method", "zone", "bin"]
        g = d.groupby(keys).agg(inside=("inside", "mean"), anees=("nees", "mean"), n=("nees", "size")).reset_index()
        if zone_all:
            g["zone"] = "all"
        g["cell"] = [f"{100 * a:.1f} ({b:.2f})" for a, b in zip(g.inside, g.anees)]
        out.append(g.pivot(index=["method", "zone"], columns="bin", values="cell"))
    t = pd.concat(out).sort_index()
    return t[[c for c in ["on"] + names if c in t.columns]]


def markdown(t: pd.DataFrame) -> str:
    """A markdown table of a frame with a (method, zone) index (no tabulate dependency)."""
    cols = [str(c) for c in t.columns]
    lines = ["| method | zone | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
    for (m, z), row in t.iterrows():
        lines.append(f"| {m} | {z} | " + " | ".join("" if pd.isna(v) else str(v) for v in row) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--switch-on", type=float, default=600.0)
    ap.add_argument("--from", dest="scored_from", type=float, default=None,
                    help="score rows with t >= this (s; default: the switch-on)")
    ap.add_argument("--by", nargs="+", default=["since_on", "since_entry", "speed", "gnss_nees"])
    ap.add_argument("--zones", action="store_true")
    ap.add_argument("--pivot", action="store_true", help="one row per method and zone, one column per bin")
    a = ap.parse_args()
    d = load(a.runs, a.switch_on, a.switch_on if a.scored_from is None else a.scored_from)
    with pd.option_context("display.width", 250, "display.max_columns", 20, "display.max_rows", 500, "display.float_format", "{:.3f}".format):
        for by in a.by:
            print(f"\n== by {by}")
            print(markdown(pivot(d, by)) if a.pivot else table(d, by, a.zones))


if __name__ == "__main__":
    main()
