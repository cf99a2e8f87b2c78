#!/usr/bin/env python3
"""Each method's share of the oracle's gain over ``gnss``, on the protocol's own runs.

The oracle replays (``tools/oracle_sat_replay.py --estimates``) write the oracle's scored rows only; the other
methods' rows are the protocol run's of the same seed (``coloc sweep`` of ``experiments/sweeps/
realistic_protocol.toml``: the same world, the frames the oracle replays are that run's). Every method is scored
on the oracle's samples, joined on (t, vehicle), so all columns of a seed count the same vehicle-steps; truth and
zone come from the run's ``gnss`` rows.

Per seed and zone: RMSE, p95 of the 2-D position error (m), mean 2-D NEES and the share inside the 95 % ellipse
(NEES <= 5.99). Over the seeds: the means, and a method's share of the oracle's gain,
(gnss - X) / (gnss - oracle), from the means over the seeds (n.d. where the oracle gains less than 0.05 m), with a
95 % bootstrap interval over the seeds (the seeds resampled with replacement, the share of the resampled means;
10 000 draws, ``--seed``).

    python tools/oracle_protocol_shares.py ORACLE.parquet:RUN_DIR [...] [--method icp_da_lc] [--label tlr]

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

from coloc.methods.registry import GNSS, ICP_DA_LC, ICP_KNOWN_DA  # noqa: E402
from experiments.rowstream import position_nees  # noqa: E402
from experiments.scoring import CHI2_2_95  # noqa: E402
from tools.oracle_shares import MIN_GAIN_M, _pct, share  # noqa: E402

ZONES = ("A", "B", "C", "all")


def _scores(err2: np.ndarray, nees: np.ndarray) -> dict:
    e = np.sqrt(err2)
    return {"rmse": float(np.sqrt(err2.mean())), "p95": float(np.percentile(e, 95)),
            "nees_mean": float(nees.mean()), "inside": float((nees <= CHI2_2_95).mean()), "n": int(e.size)}


def seed_scores(oracle: pd.DataFrame, run: pd.DataFrame, methods: tuple[str, ...]) -> dict:
    """{method: {zone: scores}} for the run's ``methods`` and the oracle (keyed by its own method name), all on
    the oracle's (t, vehicle) samples."""
    key = ["t", "vehicle"]
    o = oracle.assign(t=oracle["t"].round(6))
    g = run[run["method"] == GNSS.name]
    truth = g.assign(t=g["t"].round(6))[key + ["px_true", "py_true", "zone"]]
    j = o.merge(truth, on=key, how="inner")
    if len(j) != len(o):
        raise ValueError(f"{len(o) - len(j)} of the oracle's rows have no gnss row in the run")
    out = {}
    name = str(o["method"].iloc[0])
    cols = {name: (j["x"] - j["px_true"], j["y"] - j["py_true"], j["cov_xx"], j["cov_xy"], j["cov_yy"], j["zone"])}
    for m in methods:
        r = run[run["method"] == m]
        r = r.assign(t=r["t"].round(6))[key + ["px", "py", "var_px", "cov_pxy", "var_py"]]
        jm = j[key + ["px_true", "py_true", "zone"]].merge(r, on=key, how="inner")
        if len(jm) != len(j):
            raise ValueError(f"{m}: {len(j) - len(jm)} of the oracle's samples have no row in the run")
        cols[m] = (jm["px"] - jm["px_true"], jm["py"] - jm["py_true"], jm["var_px"], jm["cov_pxy"], jm["var_py"],
                   jm["zone"])
    for m, (dx, dy, sxx, sxy, syy, zone) in cols.items():
        dx, dy, sxx, sxy, syy = (np.asarray(v, dtype=float) for v in (dx, dy, sxx, sxy, syy))
        err2, nees, zone = dx * dx + dy * dy, position_nees(dx, dy, sxx, syy, sxy), np.asarray(zone).astype(str)
        out[m] = {z: _scores(err2[zone == z] if z != "all" else err2, nees[zone == z] if z != "all" else nees)
                  for z in ZONES if z == "all" or (zone == z).any()}
    return out


def share_of_gain(g: np.ndarray, x: np.ndarray, ref: np.ndarray) -> float | None:
    """:func:`tools.oracle_shares.share` of the means over the seeds: (mean g - mean x) / (mean g - mean ref);
    None where the reference gains < MIN_GAIN_M."""
    v = share(float(np.mean(g)), float(np.mean(x)), float(np.mean(ref)))
    return None if v is None else float(v)


def share_interval(g, x, ref, rng: np.random.Generator, draws: int = 10_000) -> tuple[float, float] | None:
    """95 % percentile bootstrap interval of :func:`share_of_gain`, the seeds resampled with replacement
    (resamples where the reference gains < MIN_GAIN_M are dropped; None if more than 5 % of them are)."""
    g, x, ref = (np.asarray(v, dtype=float) for v in (g, x, ref))
    idx = rng.integers(0, g.size, size=(draws, g.size))
    gm, xm, rm = g[idx].mean(axis=1), x[idx].mean(axis=1), ref[idx].mean(axis=1)
    ok = gm - rm >= MIN_GAIN_M
    if ok.mean() < 0.95:
        return None
    s = (gm[ok] - xm[ok]) / (gm[ok] - rm[ok])
    lo, hi = np.percentile(s, [2.5, 97.5])
    return float(lo), float(hi)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", help="ORACLE.parquet:RUN_DIR (RUN_DIR holds the run's estimates.parquet)")
    ap.add_argument("--method", action="append", help="a method whose share is printed (default: "
                    f"{ICP_DA_LC.name} and {ICP_KNOWN_DA.name})")
    ap.add_argument("--label", default="")
    ap.add_argument("--seed", type=int, default=0, help="the bootstrap's seed")
    args = ap.parse_args(argv)
    shares_of = tuple(args.method or (ICP_DA_LC.name, ICP_KNOWN_DA.name))
    methods = tuple(dict.fromkeys((GNSS.name, ICP_KNOWN_DA.name, ICP_DA_LC.name, *shares_of)))
    per_seed = {}
    for pair in args.pairs:
        oracle_path, _, run_dir = pair.partition(":")
        oracle = pd.read_parquet(oracle_path)
        if len(oracle["method"].unique()) != 1:
            print(f"{oracle_path}: method: one oracle a file", file=sys.stderr)
            return 2
        run = pd.read_parquet(Path(run_dir) / "estimates.parquet",
                              columns=["method", "t", "vehicle", "px", "py", "px_true", "py_true", "zone", "var_px",
                                       "cov_pxy", "var_py"])
        try:
            per_seed[Path(oracle_path).stem] = seed_scores(oracle, run, methods)
        except ValueError as e:
            print(f"{pair}: {e}", file=sys.stderr)
            return 2
    ref = next(m for m in next(iter(per_seed.values())) if m not in methods)
    names = (*methods, ref)
    label = f"{args.label} " if args.label else ""
    print(f"| {label}seed, zone | " + " | ".join(f"`{m}`" for m in names) + " |")
    print("|---" * (len(names) + 1) + "|")
    for seed, tab in per_seed.items():
        for z in ZONES:
            if z not in tab[GNSS.name]:
                continue
            cells = [f"{tab[m][z]['rmse']:.2f} / {tab[m][z]['p95']:.2f}, {tab[m][z]['nees_mean']:.2f}, "
                     f"{100 * tab[m][z]['inside']:.1f} %" for m in names]
            print(f"| {seed} {z} | " + " | ".join(cells) + " |")
    tabs = list(per_seed.values())
    zones = [z for z in ZONES if all(z in t[GNSS.name] for t in tabs)]
    print(f"\n{label}means over {len(tabs)} seeds, RMSE / p95 (m), ANEES, inside:")
    print("| zone | " + " | ".join(f"`{m}`" for m in names) + " |\n" + "|---" * (len(names) + 1) + "|")
    for z in zones:
        cells = []
        for m in names:
            v = {k: np.mean([t[m][z][k] for t in tabs]) for k in ("rmse", "p95", "nees_mean", "inside")}
            cells.append(f"{v['rmse']:.2f} / {v['p95']:.2f}, {v['nees_mean']:.2f}, {100 * v['inside']:.1f} %")
        print(f"| {z} | " + " | ".join(cells) + " |")
    rng = np.random.default_rng(args.seed)
    print(f"\n{label}share of `{ref}`'s gain over `gnss`, from the means over the seeds [95 % bootstrap over seeds]; "
          "per seed in brackets:")
    print("| method | zone | RMSE | p95 |\n|---|---|---|---|")
    for m in shares_of:
        for z in zones:
            cells = []
            for k in ("rmse", "p95"):
                g, x, r = ([t[n][z][k] for t in tabs] for n in (GNSS.name, m, ref))
                ci = share_interval(g, x, r, rng)
                per = " / ".join(_pct(share(a, b, c)) for a, b, c in zip(g, x, r))
                s = share_of_gain(g, x, r)
                cells.append(f"{_pct(s)}{'' if s is None else ' %'} "
                             f"[{'n.d.' if ci is None else f'{_pct(ci[0])}, {_pct(ci[1])}'}] ({per})")
            print(f"| `{m}` | {z} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
