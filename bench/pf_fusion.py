"""Benchmark: ICP-DA-PF with and without ``[fusion]`` (split CI with the receiver model,
coloc/methods/pf_fusion.py) on the same frames of one coupled run, with the ``gnss`` benchmark of the config.

    python bench/pf_fusion.py [--config experiments/arterial_tlr_realistic.toml] [--seed 1] [--duration 300]
                              [--warmup 60] [--particles 1000]

The frames are the runner's (experiments.runner.frame_source: the config's sensing, GNSS world and entry
protocol). Prints per method: position RMSE and p95 (m), mean and median 2-D position NEES and the share of
samples inside the 95 % ellipse (NEES <= 5.991), over every vehicle-step from ``--warmup`` simulated seconds,
and CPU seconds (time.process_time) per vehicle-step. ``--particles``: Jv = Jf (default the config's). The
estimators read the truth-free frame; the score reads the truth. Not a test: it asserts nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.methods.coop_fusion import FusionParams  # noqa: E402
from coloc.methods.registry import GNSS, ICP_DA_PF  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.runner import build_estimators, frame_source  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "experiments" / "arterial_tlr_realistic.toml"))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--warmup", type=float, default=60.0)
    ap.add_argument("--particles", type=int, default=0)
    args = ap.parse_args()
    over = {"run.duration_s": args.duration, "run.seed": args.seed, "run.methods": [GNSS.name, ICP_DA_PF.name]}
    if args.particles:
        over.update({"pf.vehicle_particles": args.particles, "pf.feature_particles": args.particles})
    cfg = load_config(Path(args.config), over)
    gnss, paper = build_estimators(dataclasses.replace(cfg, fusion=None))
    fused = build_estimators(dataclasses.replace(cfg, fusion=cfg.fusion or FusionParams()))[1]
    arms = {GNSS.name: gnss, ICP_DA_PF.name: paper, ICP_DA_PF.name + "+fusion": fused}
    err = {k: [] for k in arms}
    nees = {k: [] for k in arms}
    cpu = dict.fromkeys(arms, 0.0)
    vehicle_steps = 0
    with frame_source(cfg) as source:
        for frame in source.frames():
            blind = frame.without_truth()
            timed = frame.t >= args.warmup
            for key, est in arms.items():
                c0 = time.process_time()
                out = est.step(blind)
                if not timed:
                    continue
                cpu[key] += time.process_time() - c0
                e = frame.truth.x_true[:, :2] - out.mean[:, :2]
                err[key].append(np.sqrt((e * e).sum(axis=1)))
                nees[key].append(np.einsum("ni,ni->n", e, np.linalg.solve(out.cov[:, :2, :2], e[..., None])[..., 0]))
            if timed:
                vehicle_steps += frame.n_vehicles
    print(f"{args.config} seed {args.seed}: {args.duration:.0f} s, scored from {args.warmup:.0f} s, "
          f"{vehicle_steps} vehicle-steps, J = {cfg.pf.vehicle_particles}")
    print("| method | RMSE (m) | p95 (m) | mean NEES | median NEES | inside 95 % | CPU us/vehicle-step |")
    print("|---|---|---|---|---|---|---|")
    for key in arms:
        d, q = np.concatenate(err[key]), np.concatenate(nees[key])
        print(f"| {key} | {np.sqrt((d * d).mean()):.2f} | {np.percentile(d, 95):.2f} | {q.mean():.2f} | "
              f"{np.median(q):.2f} | {100 * (q <= 5.991).mean():.1f} % | {1e6 * cpu[key] / vehicle_steps:.0f} |")


if __name__ == "__main__":
    main()
