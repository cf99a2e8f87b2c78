"""Benchmark: what [fusion] (split-CI fusion and the receiver model, coloc/methods/coop_fusion.py) costs
per vehicle-step in icp_known_da and icp_da_lc, against the paper's BPA-L, on the same frames.

    python bench/fusion_cost.py [--config experiments/arterial_tlr_realistic.toml] [--duration 300]
                                [--warmup 60]

Builds every method of the config twice, without and with a [fusion] table (rule split_ci, the
config's [gnss_model]), steps both on the same frames of one coupled run, and prints each one's CPU
seconds (time.process_time: a shared machine stretches wall time much more) per step and per
vehicle-step after ``--warmup`` simulated seconds (numba compilation and the filling net are left
out), and the ratio fused / paper. Not a test: it asserts nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.methods.coop_fusion import CoopFusion, FusionParams  # noqa: E402
from coloc.methods.registry import METHODS  # noqa: E402
from couplers.net.folder import load_net_folder  # noqa: E402
from couplers.sumo_coupler import SumoCoupler, SumoScenario  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.runner import build_estimators  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "experiments" / "arterial_tlr_realistic.toml"))
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--warmup", type=float, default=60.0)
    ap.add_argument("--methods", default="icp_known_da,icp_da_lc")
    args = ap.parse_args()
    cfg = load_config(Path(args.config), {"run.duration_s": args.duration, "run.methods": args.methods.split(",")})
    paper_cfg = dataclasses.replace(cfg, fusion=None)
    fused_cfg = dataclasses.replace(cfg, fusion=cfg.fusion or FusionParams())
    fusion = CoopFusion.from_config(fused_cfg.fusion, cfg.gnss_model)
    pairs = list(zip(build_estimators(paper_cfg), build_estimators(fused_cfg)))
    assert all(getattr(f, "fusion", None) == fusion for _, f in pairs)
    net = load_net_folder(cfg.net_dir)
    scenario = SumoScenario(net=net, control=cfg.scenario.control, seed=cfg.run.seed, step_length=cfg.scenario.step_s,
                            duration_s=cfg.run.duration_s, ballistic=cfg.scenario.ballistic)
    cpu = {(name, arm): 0.0 for name in args.methods.split(",") for arm in ("paper", "fused")}
    steps = vehicle_steps = 0
    with SumoCoupler(scenario, cfg.sensors) as coupler:
        for frame in coupler.frames():
            timed = frame.t >= args.warmup
            blind, assoc = frame.without_truth(), frame.truth.v2f_feature
            for paper, fused in pairs:
                known = METHODS[paper.name].known_association
                for arm, est in (("paper", paper), ("fused", fused)):
                    c0 = time.process_time()
                    est.step_with_association(blind, assoc.copy()) if known else est.step(blind)
                    if timed:
                        cpu[(est.name, arm)] += time.process_time() - c0
            if timed:
                steps += 1
                vehicle_steps += frame.n_vehicles
    print(f"{args.config}: {args.duration:.0f} s simulated, timed from {args.warmup:.0f} s: {steps} steps, "
          f"{vehicle_steps} vehicle-steps")
    for name in args.methods.split(","):
        a, b = cpu[(name, "paper")], cpu[(name, "fused")]
        print(f"  {name:>13}: paper {1e3 * a / steps:7.3f} ms/step ({1e6 * a / vehicle_steps:6.2f} us/vehicle-step), "
              f"fused {1e3 * b / steps:7.3f} ms/step ({1e6 * b / vehicle_steps:6.2f} us/vehicle-step), "
              f"ratio {b / a:5.2f}")


if __name__ == "__main__":
    main()
