"""Benchmark: per-step cost of sme, kf (Zhang) and fg_topology_old/new, fg_gps_odom, kf_gps_odom (Gulati)
against the number of vehicles the infrastructure sensor sees.

SME: one predict + update of the joint filter (pseudo-measurements of order N, state 4N).
Factor graphs: batch LM over a run of ``--steps`` steps, reported per step (graph build + solve / steps).

    python bench/sme_fg_cost.py [--vehicles 2,3,4,6,8] [--steps 100] [--repeat 3]

Not a test: it asserts nothing and prints numbers measured in this one run (noisy on a shared machine).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.methods.fg_topology import FgTopologyParams, fg_localize, kf_gps_odom  # noqa: E402
from coloc.methods.registry import FG_TOPOLOGY_NEW, FG_TOPOLOGY_OLD, KF_GPS_ODOM, SME  # noqa: E402
from coloc.methods.sme import SmeFilter, SmeParams  # noqa: E402
from experiments.studies.fg_topology import FgScenario, simulate_run  # noqa: E402


def sme_cost(n: int, steps: int, rng: np.random.Generator) -> dict[str, float]:
    params = SmeParams()
    x0 = np.concatenate([[*rng.uniform(-50, 50, 2), *rng.uniform(-10, 10, 2)] for _ in range(n)])
    cov = np.kron(np.eye(n), np.diag([50.0, 50.0, 25.0, 25.0]))
    out = {}
    for kind in (SME.name, "kf"):
        f = SmeFilter(x0, cov, params, kind)
        t0 = time.perf_counter()
        for t in range(steps):
            pos = f.mean.reshape(n, 4)[:, :2] + rng.normal(0, 7, (n, 2))
            f.step(pos, pos + rng.normal(0, 3, (n, 2)), predict=t > 0)
        out[kind] = (time.perf_counter() - t0) / steps
    return out


def fg_cost(n: int, steps: int, rng: np.random.Generator) -> dict[str, float]:
    params = FgTopologyParams()
    d = simulate_run(n, FgScenario(n_steps=steps), params, rng)
    out = {}
    for name, topo in ((FG_TOPOLOGY_OLD.name, "old"), (FG_TOPOLOGY_NEW.name, "new"), ("fg_gps_odom", "none")):
        t0 = time.perf_counter()
        fg_localize(d.gps, d.odom, d.sensor, params, topo)
        out[name] = (time.perf_counter() - t0) / steps
    t0 = time.perf_counter()
    kf_gps_odom(d.gps, d.odom, params)
    out[KF_GPS_ODOM.name] = (time.perf_counter() - t0) / steps
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--vehicles", default="2,3,4,6,8")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    print(f"per-step cost in ms (best of {args.repeat}; FG per step of a {args.steps}-step batch)")
    header = None
    for n in [int(v) for v in args.vehicles.split(",")]:
        best: dict[str, float] = {}
        for _ in range(args.repeat):
            for k, v in {**sme_cost(n, args.steps, rng), **fg_cost(n, args.steps, rng)}.items():
                best[k] = min(best.get(k, np.inf), v)
        if header is None:
            header = list(best)
            print("N  " + "  ".join(f"{k:>16}" for k in header))
        print(f"{n:<3}" + "  ".join(f"{1e3 * best[k]:16.3f}" for k in header))


if __name__ == "__main__":
    main()
