"""Benchmark: per-step cost of the infrastructure methods (rsu_bp, sme, fg_topology_new) against
the number of vehicles within RSU range, on SUMO frames of a shipped infra config.

The frames are produced once (SUMO + coupler, not timed), then each method runs over them alone;
its step times are binned by the number of covered vehicles of the step (all RSUs together).

    python bench/infra_cost.py [--config experiments/arterial_tlr_infra.toml] [--duration 300]
                               [--methods gnss,fg_topology_new]

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

from coloc.methods.infra import home_rsu  # noqa: E402
from coloc.methods.registry import GNSS, METHODS, build_method  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.runner import frame_source, method_params  # noqa: E402

#: The GNSS tracker and the infrastructure methods, in registry order.
DEFAULT_METHODS = tuple(m.name for m in METHODS.values() if m.runnable and (m is GNSS or m.infrastructure))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "experiments" / "arterial_tlr_infra.toml"))
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--bins", default="0,5,10,15,20,30,60")
    ap.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                    help="comma separated subset of the default (rsu_bp dominates the time)")
    args = ap.parse_args(argv)
    cfg = load_config(args.config, {"run.duration_s": args.duration})
    t0 = time.perf_counter()
    with frame_source(cfg) as src:
        frames = [f.without_truth() for f in src.frames()]
    print(f"{len(frames)} frames of {cfg.run.name} ({args.duration:.0f} s) in {time.perf_counter() - t0:.1f} s")
    covered = np.array([int((home_rsu(f.infra.v2i) >= 0).sum()) if f.n_vehicles else 0 for f in frames])
    edges = [int(x) for x in args.bins.split(",")]
    params = method_params(cfg)
    makers = {m: (lambda m=m: build_method(m, params)) for m in DEFAULT_METHODS}
    wanted = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = sorted(set(wanted) - set(makers))
    if unknown:
        ap.error(f"unknown method {unknown[0]!r} (known: {', '.join(makers)})")
    methods = {m: makers[m] for m in wanted}
    times = {}
    for name, make in methods.items():
        est = make()
        dt = np.empty(len(frames))
        for i, f in enumerate(frames):
            t = time.perf_counter()
            est.step(f)
            dt[i] = time.perf_counter() - t
        times[name] = dt
        if getattr(est, "stats", None):
            print(f"{name}: " + ", ".join(f"{k} {v}" for k, v in est.stats.items()))
    head = "covered vehicles | steps | " + " | ".join(f"{m} ms/step (ms/veh)" for m in methods)
    print(head)
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (covered >= lo) & (covered < hi)
        if not sel.any():
            continue
        mean_cov = covered[sel].mean()
        cells = []
        for m in methods:
            ms = 1e3 * times[m][sel].mean()
            cells.append(f"{ms:8.2f} ({ms / mean_cov:6.2f})" if mean_cov > 0 else f"{ms:8.2f} (   -  )")
        print(f"[{lo:>3}, {hi:>3}) mean {mean_cov:5.1f} | {int(sel.sum()):5d} | " + " | ".join(cells))
    print("total seconds: " + ", ".join(f"{m} {times[m].sum():.1f}" for m in methods))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
