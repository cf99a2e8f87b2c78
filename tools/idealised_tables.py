#!/usr/bin/env python3
"""The tables of docs/validation/consistency.md "Idealised paper configs under consistent fusion: the
protocol" from a sweep folder of experiments/sweeps/idealised_consistency.toml, read from the runs'
summary.json files (a sweep cut short gives the tables of the runs it finished; every table states its seeds).

An arm is a run folder's name without its seed (``control=tlr,arm=sci_centre``). Per control, arm, GNSS zone
("all" pools them) and method: the mean over the seeds of the run's RMSE and p95 of the 2-D position error,
the average NEES over the seeds (each run's time-averaged NEES) with its chi-square band for that many runs
(experiments/sweep/consistency.py), the mean share of samples inside the 95 % ellipse and the lowest run's.
Then, per arm against the reference arm (``--reference``, default the paper configs as shipped), the paired
difference of each method's RMSE (same seed, same traffic): mean [95 % paired t interval] in metres and
in per cent of the reference (the per-seed ratios a / b - 1, their mean and paired t interval).

    python tools/idealised_tables.py results/idealised_consistency > tables.md
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from coloc.methods import registry  # noqa: E402
from experiments.sweep.consistency import anees_band  # noqa: E402
from experiments.sweep.paired import paired_ci  # noqa: E402
from tools.protocol_tables import (as_float, seed_text, shared_cells, shared_rows, shared_table,  # noqa: E402
                                  short_number, zone_cells, zone_order)

ORDER = [m.name for m in (registry.GNSS, registry.ICP_KNOWN_DA, registry.ICP_DA_LC, registry.JOINT_ORACLE)]
SHORT = dict(zip(ORDER, ("GNSS", "known DA", "LC", "oracle")))
_SEED = re.compile(r"^(?:(?P<arm>.*),)?seed=(?P<seed>\d+)$")  # a sweep without grid or factors: "seed=N"


def preset_label(folder: Path) -> str:
    """The preset's arm as ``factor=label`` from the sweep folder's sweep.toml (``preset`` without factors)."""
    import tomllib

    path = folder / "sweep.toml"
    factors = (tomllib.loads(path.read_text()).get("sweep", {}).get("factors") or {}) if path.exists() else {}
    for name, levels in factors.items():
        for lv in levels:
            if lv.get("preset"):
                return f"{name}={lv['label']}"
    return "preset"


def run_ident(name: str, preset: str) -> dict | None:
    """A run folder's name as (control, arm, seed); ``preset``: the preset arm's label; None: a foreign folder."""
    m = _SEED.match(name)
    if m is None:
        return None
    parts = dict((p.split("=", 1) if "=" in p else (p, None)) for p in (m["arm"] or "").split(",") if p)
    control = parts.pop("control", "-")
    arm = ",".join(preset if v is None else f"{k}={v}" for k, v in parts.items()) or preset
    return {"control": control, "arm": arm, "seed": int(m["seed"])}


def run_key(run_dir: Path, preset: str) -> dict | None:
    """:func:`run_ident` of a run folder, the control read from the run's own config when its name has none (a
    sweep without grid or factors names its runs ``seed=N``)."""
    key = run_ident(run_dir.name, preset)
    if key is not None and key["control"] == "-" and (run_dir / "config.toml").exists():
        import tomllib

        key["control"] = tomllib.loads((run_dir / "config.toml").read_text()).get("scenario", {}).get("control", "-")
    return key


def run_rows(folder: Path) -> pd.DataFrame:
    """One row per (control, arm, seed, method, zone) of every finished run in ``folder/runs``."""
    rows = []
    preset = preset_label(folder)
    for summ in sorted((folder / "runs").glob("*/summary.json")):
        key = run_key(summ.parent, preset)
        if key is None:
            continue
        control, arm = key["control"], key["arm"]
        data = json.loads(summ.read_text())
        for method, zone, cell in zone_cells(data):
            rows.append({"control": control, "arm": arm, "seed": key["seed"], "method": method, "zone": zone,
                         **cell, "wall_s": as_float(data.get("wall_seconds"))})
    return pd.DataFrame(rows)


def method_table(rows: pd.DataFrame) -> pd.DataFrame:
    out = []
    for key, g in rows.groupby(["control", "arm", "zone", "method"], sort=True):
        s = int(g["seed"].nunique())
        lo, hi = anees_band(s)
        anees = float(g["nees"].mean())
        out.append(dict(zip(["control", "arm", "zone", "method"], key), seeds=s, rmse=float(g["rmse"].mean()),
                        p95=float(g["p95"].mean()), anees=anees, band_lo=lo, band_hi=hi,
                        in_band=bool(lo <= anees <= hi), inside=float(g["inside_95"].mean()),
                        inside_min=float(g["inside_95"].min())))
    return pd.DataFrame(out)


def paired_rows(rows: pd.DataFrame, reference: str) -> pd.DataFrame:
    """Per (control, arm != reference, zone, method): RMSE and p95 of the arm minus the reference's, paired by
    seed, in metres and in per cent."""
    out = []
    for (control, zone, method), g in rows.groupby(["control", "zone", "method"], sort=True):
        for stat in ("rmse", "p95"):
            wide = g.pivot_table(index="seed", columns="arm", values=stat, aggfunc="first")
            if reference not in wide:
                continue
            b = wide[reference].to_numpy()
            for arm in wide.columns:
                if arm == reference:
                    continue
                a = wide[arm].to_numpy()
                mean, lo, hi, n = paired_ci(a, b)
                # the per-seed change in per cent, 100 (a / b - 1), and its t interval
                pm, plo, phi, _ = paired_ci(100.0 * a / b, np.full_like(b, 100.0))
                out.append(dict(control=control, arm=arm, zone=zone, method=method, stat=stat, mean=mean,
                                lo=lo, hi=hi, seeds=n, pct=pm, pct_lo=plo, pct_hi=phi))
    return pd.DataFrame(out)


def markdown(rows: pd.DataFrame, reference: str, shared: pd.DataFrame | None = None) -> str:
    mt, pr = method_table(rows), paired_rows(rows, reference)
    if shared is not None and len(shared):
        mt = mt.merge(shared, on=["control", "arm", "zone", "method"], how="left")
    lines = []
    methods = [m for m in ORDER if m in set(rows["method"])]
    for control in sorted(rows["control"].unique(), key=lambda c: (c != "tlr", c)):
        for arm in sorted(rows[rows.control == control]["arm"].unique(), key=lambda a: (a != reference, a)):
            sub = mt[(mt.control == control) & (mt.arm == arm)]
            seeds = rows[(rows.control == control) & (rows.arm == arm)]["seed"].unique()
            s = int(sub["seeds"].max())
            lo, hi = anees_band(s)
            lines += [f"#### {control.upper()}, {arm}: seeds {seed_text(seeds)}", "",
                      f"ANEES band for {s} runs [{lo:.2f}, {hi:.2f}]; inside: mean share of samples inside the "
                      "95 % ellipse (lowest run in brackets)"
                      + ("; shared, tau, band: as tools/protocol_tables.py --shared." if "shared" in sub else "."), "",
                      "| zone | method | RMSE (m) | p95 (m) | ANEES | in band | inside 95 % |"
                      + (" shared | tau (s) | band of inside |" if "shared" in sub else ""),
                      "|---|---|---|---|---|---|---|" + ("---|---|---|" if "shared" in sub else "")]
            for zone in sorted(sub["zone"].unique(), key=zone_order):
                for method in methods:
                    r = sub[(sub.zone == zone) & (sub.method == method)]
                    if not len(r):
                        continue
                    r = r.iloc[0]
                    line = (f"| {zone} | {SHORT[method]} | {r.rmse:.3f} | {r.p95:.3f} | {short_number(r.anees)} | "
                            f"{'yes' if r.in_band else 'no'} | {100 * r.inside:.1f} ({100 * r.inside_min:.1f}) % |")
                    lines.append(line + (shared_cells(r) if "shared" in sub else ""))
            lines.append("")
        ps = pr[pr.control == control] if len(pr) else pr
        if not len(ps):
            continue
        lines += [f"#### {control.upper()}: against {reference} (paired by seed)", "",
                  "Mean difference [95 % paired t interval], in metres and in per cent of the reference run's value.",
                  "", "| arm | zone | method | RMSE (m) | RMSE (%) | p95 (m) | p95 (%) |", "|---|---|---|---|---|---|---|"]
        for arm in sorted(ps["arm"].unique()):
            for zone in sorted(ps[ps.arm == arm]["zone"].unique(), key=zone_order):
                for method in methods:
                    cells = []
                    for stat in ("rmse", "p95"):
                        r = ps[(ps.arm == arm) & (ps.zone == zone) & (ps.method == method) & (ps.stat == stat)]
                        if not len(r):
                            cells += ["-", "-"]
                            continue
                        r = r.iloc[0]
                        cells += [f"{r['mean']:+.3f} [{r.lo:+.3f}, {r.hi:+.3f}]",
                                  f"{r.pct:+.1f} [{r.pct_lo:+.1f}, {r.pct_hi:+.1f}]"]
                    if cells != ["-"] * 4:
                        lines.append(f"| {arm} | {zone} | {SHORT[method]} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, nargs="+", help="sweep folder(s) of experiments/sweeps/idealised_consistency.toml")
    ap.add_argument("--reference", default="arm=paper", help="the arm the differences are taken against")
    ap.add_argument("--csv", type=Path, help="also write the per-run rows here")
    ap.add_argument("--shared", action="store_true", help="also the shared error fraction and the band of the "
                                                          "share inside (tools/protocol_tables.py --shared)")
    args = ap.parse_args(argv)
    rows = pd.concat([run_rows(f) for f in args.folder], ignore_index=True)
    if not len(rows):
        print(f"{', '.join(map(str, args.folder))}: no finished run", file=sys.stderr)
        return 2
    if args.csv:
        rows.to_csv(args.csv, index=False)
    shared = None
    if args.shared:
        ident = [lambda name, f=f, p=preset_label(f): run_key(f / "runs" / name, p) for f in args.folder]
        shared = shared_table(pd.concat([shared_rows(f, i) for f, i in zip(args.folder, ident)], ignore_index=True),
                              keys=("control", "arm", "zone", "method"))
    print(markdown(rows, args.reference, shared))
    return 0


if __name__ == "__main__":
    sys.exit(main())
