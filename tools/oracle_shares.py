"""The tables of docs/validation/oracle.md from the per-seed JSONs of ``tools/oracle_sat_replay.py --seed-json``:
per seed and zone RMSE / p95 (m), mean NEES, inside the 95 % ellipse for each method; the average over seeds of the
mean NEES (ANEES) and of the share inside; and a method's share of a reference's gain over ``gnss``,
(gnss - X) / (gnss - reference), RMSE and p95, per seed and from the means over the seeds (n.d. where the reference gains less than 0.05 m).

    python tools/oracle_shares.py tlr_11.json tlr_12.json ... [--method icp_da_lc] [--reference joint_oracle_fix]

Not a test.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.methods.registry import GNSS, ICP_DA_LC, JOINT_ORACLE  # noqa: E402

ZONES = ("A", "B", "C", "all")


#: below this gain of the reference over gnss (m) a share is not defined (n.d.): the tables print 0.01 m
MIN_GAIN_M = 0.05


def share(g: float, x: float, ref: float) -> float | None:
    """(g - x) / (g - ref); None where the reference gains less than :data:`MIN_GAIN_M` over g."""
    return (g - x) / (g - ref) if g - ref >= MIN_GAIN_M else None


def _pct(v: float | None) -> str:
    return "n.d." if v is None else f"{100 * v:.0f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seeds", type=Path, nargs="+")
    ap.add_argument("--method", default=ICP_DA_LC.name)
    ap.add_argument("--reference", default=f"{JOINT_ORACLE.name}_fix")
    args = ap.parse_args()
    tabs = {p.stem: json.loads(p.read_text()) for p in args.seeds}
    methods = list(next(iter(tabs.values())))
    print("| seed, zone | " + " | ".join(f"`{m}`" for m in methods) + " |")
    print("|---" * (len(methods) + 1) + "|")
    for seed, tab in tabs.items():
        for z in ZONES:
            cells = [f"{tab[m][z]['rmse']:.2f} / {tab[m][z]['p95']:.2f}, {tab[m][z]['nees_mean']:.2f}, "
                     f"{100 * tab[m][z]['inside']:.1f} %" for m in methods]
            print(f"| {seed} {z} | " + " | ".join(cells) + " |")
    print()
    for m in methods:
        print(f"{m}: ANEES by zone " + " / ".join(f"{np.mean([t[m][z]['nees_mean'] for t in tabs.values()]):.2f}"
                                                 for z in ZONES)
              + ", inside " + " / ".join(f"{100 * np.mean([t[m][z]['inside'] for t in tabs.values()]):.1f} %"
                                         for z in ZONES))
    print()
    g, x, r = GNSS.name, args.method, args.reference
    print(f"share of `{r}`'s gain over `{g}` taken by `{x}`: from the means over {len(tabs)} seeds (per seed "
          f"{' / '.join(tabs)})")
    print("| zone | RMSE | p95 |")
    print("|---|---|---|")
    for z in ZONES:
        cells = []
        for k in ("rmse", "p95"):
            mean = share(*(np.mean([t[m][z][k] for t in tabs.values()]) for m in (g, x, r)))
            per = " / ".join(_pct(share(t[g][z][k], t[x][z][k], t[r][z][k])) for t in tabs.values())
            cells.append(f"{_pct(mean)} % ({per})")
        print(f"| {z} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
