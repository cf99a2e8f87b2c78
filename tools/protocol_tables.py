#!/usr/bin/env python3
"""The tables of docs/validation/protocol_runs.md from a sweep folder of
experiments/sweeps/realistic_protocol.toml, read from the runs' summary.json files (so a sweep cut short
gives the tables of the runs it finished; every table states its seeds).

Per control, GNSS zone ("all" pools them), arm (fusion.rule) and method: the mean over the seeds of the
run's RMSE and p95 of the 2-D position error, the average NEES over the seeds (each run's time-averaged
NEES, experiments/sweep/consistency.py) with its chi-square band for that many runs, and the mean share of
samples inside the 95 % ellipse. Then the paired differences (same seed, same traffic) LC - GNSS and
known DA - GNSS of RMSE and of p95, with their 95 % paired t intervals (experiments/sweep/paired.py), and
the seeds a +-0.15 m half-width would need from the per-seed differences' standard deviation.

    python tools/protocol_tables.py /work/proto_out/sweep/realistic_protocol [--shared] > tables.md

``--shared`` (reads every run's estimates.parquet from its scored start on): per cell also the share of the
whitened errors' second moment that the samples of one step share (experiments/sweep/consistency.py,
``shared_error_moments``, pooled over the seeds), the correlation time of that shared part (pooled over the
seeds: the non-centred autocorrelation of the steps' mean whitened error at a lag of 240 s, tau = -240 / ln rho,
infinite when rho >= 1) and the 95 % band of the mean share inside for a consistent estimator with those
(``inside_share_band``; the scored window's length as the window).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from coloc.methods import registry
from experiments.sweep.consistency import anees_band, inside_share_band, shared_error_moments, whitened_errors
from experiments.sweep.paired import paired_ci

GNSS, KNOWN, LC = (m.name for m in (registry.GNSS, registry.ICP_KNOWN_DA, registry.ICP_DA_LC))
PAIRS = ((LC, GNSS), (KNOWN, GNSS))
SHORT = {GNSS: "GNSS", KNOWN: "known DA", LC: "LC"}
ARMS = {"split_ci": "after (split CI, as shipped)", "bp": "before (paper BP)"}
# A sweep without the fusion arm (the presets as shipped only) names its runs control=...,seed=...: arm split_ci.
_ID = re.compile(r"(?:rule=(?P<rule>[^,]+),)?control=(?P<control>[^,]+),seed=(?P<seed>\d+)$")


def seeds_for_half_width(sd: float, half: float = 0.15, level: float = 0.95, n_max: int = 100000) -> int:
    """The smallest n with t_{n-1, (1+level)/2} * sd / sqrt(n) <= half, i.e. n = (t sd / half)^2 with t
    taken at that n; at least 2, -1 for an undefined sd."""
    from scipy.stats import norm
    from scipy.stats import t as student_t

    if not math.isfinite(sd) or sd < 0:
        return -1
    if sd == 0:
        return 2
    q = 0.5 + level / 2.0
    # t_{n-1} > z for every n, so the root is at least (z sd / half)^2; from there n only grows
    n = max(2, math.ceil((float(norm.ppf(q)) * sd / half) ** 2))
    while n <= n_max:
        if float(student_t.ppf(q, n - 1)) * sd / math.sqrt(n) <= half:
            return n
        n += 1
    return -1


def run_rows(folder: Path) -> pd.DataFrame:
    """One row per (arm, control, seed, method, zone) of every finished run in ``folder/runs``."""
    rows = []
    for summ in sorted((folder / "runs").glob("*/summary.json")):
        m = _ID.match(summ.parent.name)
        if m is None:
            continue
        data = json.loads(summ.read_text())
        for method, zone, cell in zone_cells(data):
            rows.append({"rule": m["rule"] or "split_ci", "control": m["control"], "seed": int(m["seed"]),
                         "method": method, "zone": zone, **cell, "wall_s": as_float(data.get("wall_seconds"))})
    return pd.DataFrame(rows)


#: The lag of the shared part's correlation time (s): the largest that a 300 s window pairs for a fifth of it.
TAU_LAG_S = 240.0


def protocol_ident(name: str) -> dict | None:
    """A run folder's name as (rule, control, seed) of this sweep; None for a foreign folder."""
    m = _ID.match(name)
    return None if m is None else {"rule": m["rule"] or "split_ci", "control": m["control"], "seed": int(m["seed"])}


def shared_rows(folder: Path, ident=protocol_ident) -> pd.DataFrame:
    """One row per run (its ``ident`` columns, which hold ``seed``), method and zone of every finished run: the
    whitened errors' shared and total moments (``shared_m``, ``total_m``), the scored window (``window_s``)
    and, for the correlation time, the means of the steps' mean whitened error products at lag 0 (less the
    mean's own sampling variance) and at ``TAU_LAG_S`` (``c0``, ``c1``)."""
    rows = []
    for summ in sorted((folder / "runs").glob("*/summary.json")):
        key = ident(summ.parent.name)
        if key is None or not (summ.parent / "estimates.parquet").exists():
            continue
        t0 = float(json.loads(summ.read_text())["analysis"]["scored_from_s"])
        est = pd.read_parquet(summ.parent / "estimates.parquet",
                              columns=["method", "t", "zone", "px", "py", "px_true", "py_true", "var_px", "var_py",
                                       "cov_pxy"])
        est = est[est["t"] >= t0]
        wx, wy = whitened_errors(est["px"] - est["px_true"], est["py"] - est["py_true"], est["var_px"],
                                 est["var_py"], est["cov_pxy"])
        est = est.assign(wx=wx, wy=wy, zone=est["zone"].astype(str))
        window = float(est["t"].max() - t0) if len(est) else math.nan
        for method, gm in est.groupby("method", sort=True):
            for zone, g in [("all", gm), *gm.groupby("zone", sort=True)]:
                grouped = g.groupby("t", sort=True)[["wx", "wy"]]
                mean, var, n = grouped.mean(), grouped.var(ddof=1).sum(axis=1), grouped.count()["wx"]
                # lag 0 without the step mean's own noise (its sample variance over n), as the lagged
                # products have none: unbiased for |c|^2 (shared_error_moments)
                c0 = ((mean.to_numpy() ** 2).sum(axis=1) - (var / n).to_numpy())[n.to_numpy() >= 2]
                mean.index = np.round(mean.index.to_numpy(dtype=float), 6)
                lagged = mean.set_index(np.round(mean.index.to_numpy() + TAU_LAG_S, 6)).add_suffix("_lag")
                both = mean.join(lagged, how="inner")
                rows.append({**key, "method": method, "zone": zone, "window_s": window,
                             **dict(zip(("shared_m", "total_m"), shared_error_moments(g["t"], g["wx"], g["wy"]))),
                             "c0": float(c0.mean()) if c0.size else math.nan,
                             "c1": float((both[["wx", "wy"]].to_numpy() * both[["wx_lag", "wy_lag"]].to_numpy())
                                         .sum(axis=1).mean()) if len(both) else math.nan})
    return pd.DataFrame(rows)


def shared_table(rows: pd.DataFrame, keys=("control", "zone", "rule", "method")) -> pd.DataFrame:
    """Per ``keys`` (every column of :func:`shared_rows` but the seed and the numbers): the shared fraction
    pooled over the seeds (their shared moments over their total, clipped to [0, 1]), the pooled correlation
    time (s) and the 95 % band of the mean share inside for a consistent estimator over that many runs."""
    keys = list(keys)
    out = []
    for key, g in rows.groupby(keys, sort=True):
        total = float(g["total_m"].sum())
        f = np.full(len(g), min(1.0, max(0.0, float(g["shared_m"].sum()) / total))) if total > 0 else np.empty(0)
        rho = float(g["c1"].mean() / g["c0"].mean()) if g["c0"].mean() > 0 else math.nan
        tau = -TAU_LAG_S / math.log(rho) if 0 < rho < 1 else math.inf
        lo, hi = inside_share_band(f, tau_s=tau, window_s=float(g["window_s"].median())) if f.size else (math.nan,) * 2
        out.append(dict(zip(keys, key), shared=float(f.mean()) if f.size else math.nan,
                        tau_s=tau, inside_lo=lo, inside_hi=hi))
    return pd.DataFrame(out)


def shared_cells(r) -> str:
    """The three ``--shared`` cells of a table row ``r`` (from :func:`shared_table`): shared fraction, correlation
    time, band of the share inside."""
    if not math.isfinite(r.shared):
        return " - | - | - |"
    tau = "inf" if not math.isfinite(r.tau_s) else f"{r.tau_s:.0f}"
    return f" {r.shared:.2f} | {tau} | [{100 * r.inside_lo:.1f}, {100 * r.inside_hi:.1f}] % |"


def as_float(v) -> float:
    """A summary value as a float (None: NaN)."""
    return math.nan if v is None else float(v)


def zone_cells(data: dict):
    """(method, zone, cell) of a run's ``summary.json``, zone "all" first, then its zones in order; cell: RMSE and
    p95 of the 2-D position error (m), samples, mean 2-D NEES and the share inside the 95 % ellipse."""
    for method, b in (data.get("methods") or {}).items():
        nees = b.get("nees_pos") or {}
        zones = {"all": (b, nees)}
        for z, zb in sorted((b.get("by_zone") or {}).items()):
            zn = (nees.get("by_zone") or {}).get(z)
            zones[z] = (zb, zn if isinstance(zn, dict) else {})
        for zone, (st, ns) in zones.items():
            yield method, zone, {"rmse": as_float(st.get("rmse_pos_m")), "p95": as_float(st.get("p95_pos_m")),
                                 "n": int(st.get("n") or 0), "nees": as_float(ns.get("mean")),
                                 "inside_95": as_float(ns.get("inside_95"))}


def method_table(rows: pd.DataFrame) -> pd.DataFrame:
    """Per (control, zone, rule, method): seeds, mean RMSE and p95, ANEES and its band, mean share inside."""
    out = []
    for key, g in rows.groupby(["control", "zone", "rule", "method"], sort=True):
        s = int(g["seed"].nunique())
        lo, hi = anees_band(s) if s else (math.nan, math.nan)
        anees = float(g["nees"].mean())
        out.append(dict(zip(["control", "zone", "rule", "method"], key), seeds=s, rmse=float(g["rmse"].mean()),
                        p95=float(g["p95"].mean()), anees=anees, band_lo=lo, band_hi=hi,
                        inside_band=bool(lo <= anees <= hi), inside_95=float(g["inside_95"].mean())))
    return pd.DataFrame(out)


def paired_rows(rows: pd.DataFrame, half: float = 0.15) -> pd.DataFrame:
    """Per (control, zone, rule, pair, statistic): the paired mean difference a - b over the seeds with both,
    its 95 % paired t interval, the per-seed differences' SD and the seeds a +-``half`` m half-width needs."""
    out = []
    for key, g in rows.groupby(["control", "zone", "rule"], sort=True):
        for stat in ("rmse", "p95"):
            wide = g.pivot_table(index="seed", columns="method", values=stat, aggfunc="first")
            for a, b in PAIRS:
                if a not in wide or b not in wide:
                    continue
                mean, lo, hi, n = paired_ci(wide[a].to_numpy(), wide[b].to_numpy())
                d = (wide[a] - wide[b]).to_numpy()
                d = d[np.isfinite(d)]
                sd = float(d.std(ddof=1)) if d.size > 1 else math.nan
                out.append(dict(zip(["control", "zone", "rule"], key), a=a, b=b, stat=stat, mean=mean, ci_lo=lo,
                                ci_hi=hi, seeds=n, sd=sd, a_better=int((d < 0).sum()),
                                seeds_needed=seeds_for_half_width(sd, half) if d.size > 1 else -1))
    return pd.DataFrame(out)


def zone_order(z: str) -> tuple:
    """Sort key: the zones by name, "all" last."""
    return (z == "all", z)


def markdown(rows: pd.DataFrame, shared: pd.DataFrame | None = None) -> str:
    mt, pr = method_table(rows), paired_rows(rows)
    if shared is not None and len(shared):
        mt = mt.merge(shared, on=["control", "zone", "rule", "method"], how="left")
    lines = []
    for control in sorted(rows["control"].unique(), key=lambda c: (c != "tlr", c)):
        for rule in [r for r in ARMS if r in set(rows["rule"])]:
            sub = mt[(mt.control == control) & (mt.rule == rule)]
            if not len(sub):
                continue
            seeds = sorted(rows[(rows.control == control) & (rows.rule == rule)]["seed"].unique())
            s = int(sub["seeds"].max())
            lo, hi = anees_band(s)
            lines += [f"### {control.upper()}, {ARMS[rule]}: seeds {seed_text(seeds)}", "",
                      f"Mean over the seeds; ANEES = average NEES over the runs, chi-square band for {s} runs "
                      f"[{lo:.2f}, {hi:.2f}] (2 is consistent); inside = mean share of samples inside the 95 % "
                      "ellipse.", "",
                      *(["Shared = share of the whitened errors' second moment common to the samples of a step; "
                         "tau = its correlation time; band = the 95 % band of the mean share inside for a consistent "
                         "estimator with that shared part over these runs.", ""] if "shared" in sub else []),
                      "| zone | method | RMSE (m) | p95 (m) | ANEES | in band | inside 95 % |"
                      + (" shared | tau (s) | band of inside |" if "shared" in sub else ""),
                      "|---|---|---|---|---|---|---|" + ("---|---|---|" if "shared" in sub else "")]
            for zone in sorted(sub["zone"].unique(), key=zone_order):
                for method in (GNSS, KNOWN, LC):
                    r = sub[(sub.zone == zone) & (sub.method == method)]
                    if not len(r):
                        continue
                    r = r.iloc[0]
                    line = (f"| {zone} | {SHORT[method]} | {r.rmse:.2f} | {r.p95:.2f} | {short_number(r.anees)} | "
                            f"{'yes' if r.inside_band else 'no'} | {100 * r.inside_95:.1f} % |")
                    lines.append(line + (shared_cells(r) if "shared" in sub else ""))
            lines += ["", "Paired differences over the seeds (same seed, same traffic), mean [95 % paired t "
                          "interval], seeds where the first is lower, SD of the per-seed differences and the "
                          "seeds a +-0.15 m half-width needs:", "",
                      "| zone | difference | RMSE (m) | lower on | SD | seeds for +-0.15 | p95 (m) | lower on | SD "
                      "| seeds for +-0.15 |", "|---|---|---|---|---|---|---|---|---|---|"]
            ps = pr[(pr.control == control) & (pr.rule == rule)] if len(pr) else pd.DataFrame(columns=["zone"])
            for zone in sorted(ps["zone"].unique(), key=zone_order):
                for a, b in PAIRS:
                    cells = []
                    for stat in ("rmse", "p95"):
                        r = ps[(ps.zone == zone) & (ps.a == a) & (ps.b == b) & (ps.stat == stat)]
                        if not len(r):
                            cells += ["-"] * 4
                            continue
                        r = r.iloc[0]
                        ci = (f"[{r.ci_lo:+.2f}, {r.ci_hi:+.2f}]" if math.isfinite(r.ci_lo) else "(one seed: no interval)")
                        cells += [f"{r['mean']:+.2f} {ci}", f"{r.a_better}/{r.seeds}",
                                  f"{r.sd:.2f}" if math.isfinite(r.sd) else "-",
                                  str(r.seeds_needed) if r.seeds_needed > 0 else "-"]
                    lines.append(f"| {zone} | {SHORT[a]} - {SHORT[b]} | " + " | ".join(cells) + " |")
            lines.append("")
    return "\n".join(lines)


def short_number(v: float) -> str:
    """An ANEES as a table prints it: two decimals below 100, none above, "-" if not finite."""
    return "-" if not math.isfinite(v) else (f"{v:.2f}" if v < 100 else f"{v:.0f}")


def seed_text(seeds) -> str:
    """The seeds as a table heading says them: "11-20 (10)" for a run of three or more, else listed."""
    seeds = sorted(int(s) for s in seeds)
    if len(seeds) > 2 and seeds == list(range(seeds[0], seeds[-1] + 1)):
        return f"{seeds[0]}-{seeds[-1]} ({len(seeds)})"
    return ", ".join(map(str, seeds)) + f" ({len(seeds)})"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="sweep folder of experiments/sweeps/realistic_protocol.toml")
    ap.add_argument("--csv", type=Path, help="also write the per-run rows here")
    ap.add_argument("--shared", action="store_true", help="also the shared error fraction and the band of the "
                                                          "share inside (reads every run's estimates.parquet)")
    args = ap.parse_args(argv)
    rows = run_rows(args.folder)
    if not len(rows):
        print(f"{args.folder}: no finished run", file=sys.stderr)
        return 2
    if args.csv:
        rows.to_csv(args.csv, index=False)
    print(markdown(rows, shared_table(shared_rows(args.folder)) if args.shared else None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
