"""Benchmark: per-step cost of the RSU particle BP (Fröhle et al.) against the number of vehicles in
range S, of features K and of particles Np.

The paper states O((K Np)^2 I S P): linear in S, quadratic in K and in Np. The scenario is Sec. V-A
(vehicle 1 with GNSS variance 0.01 m^2, the others 15 m^2, V2F variance 1 m^2, P = 5, I = 1). For
each setting the median wall time per step over ``--steps`` steps (after one warm-up step) is
printed with its ratio to the first row of its block, the ratio the complexity claim predicts and the
time per particle pair through the V2F kernel (2 S K^2 Np^2 pairs per step with I = 1; the rest is
O(S K Np) numpy work, which dominates for small Np).
One sweep varies S (K = 3, Np = 600), one K (S = 2, Np = 600), one Np (S = 2, K = 3).

    python bench/rsu_bp_cost.py [--steps 10] [--vehicles 1,2,4,8] [--features 1,2,3,6] [--particles 150,300,600,1200]

Not a test: it asserts nothing and prints numbers measured in one run (on a shared machine the
absolute times are noisy; the ratios less so).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.methods.rsu_bp import RsuBpParams, initial_beliefs, rsu_bp_step  # noqa: E402
from couplers.frohle_scenario import FrohleScenarioParams, simulate  # noqa: E402


def step_seconds(n_vehicles: int, n_features: int, n_particles: int, steps: int, seed: int = 1) -> float:
    """Median wall time of one rsu_bp_step over ``steps`` steps (after one untimed step)."""
    sc = simulate(FrohleScenarioParams(n_steps=steps + 2, n_features=n_features,
                                       gnss_var=(0.01,) + (15.0,) * (n_vehicles - 1)), seed)
    params = RsuBpParams(n_particles=n_particles)
    rng = np.random.default_rng(seed)
    xs, fs = initial_beliefs(sc.gnss_z[0], sc.gnss_cov, sc.v2f_z[0], sc.v2f_cov, sc.v2f_owner, n_features,
                             params, rng)
    times = []
    for t in range(steps + 1):
        t0 = time.perf_counter()
        res = rsu_bp_step(xs, fs, sc.gnss_z[t], sc.gnss_cov, sc.v2f_z[t], sc.v2f_cov, sc.v2f_owner, params, rng,
                          predict=t > 0)
        if t > 0:
            times.append(time.perf_counter() - t0)
        xs, fs = res.vehicle_particles, res.feature_particles
    return float(np.median(times))


def block(title: str, settings: list[tuple[int, int, int]], predicted, steps: int) -> None:
    print(f"\n{title}")
    print(f"{'S':>3} {'K':>3} {'Np':>6} {'ms/step':>9} {'ratio':>7} {'claim':>7} {'ns/pair':>8}")
    first = None
    for s, k, n in settings:
        sec = step_seconds(s, k, n, steps)
        first = sec if first is None else first
        # particle pairs through the V2F kernel per step: (14)/(21) and (23), S K measurements x K features
        pairs = 2 * s * k * k * n * n
        print(f"{s:>3} {k:>3} {n:>6} {1000 * sec:>9.2f} {sec / first:>7.2f} {predicted(s, k, n):>7.2f} "
              f"{1e9 * sec / pairs:>8.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--vehicles", default="1,2,4,8")
    ap.add_argument("--features", default="1,2,3,6")
    ap.add_argument("--particles", default="150,300,600,1200")
    args = ap.parse_args()
    vehicles = [int(v) for v in args.vehicles.split(",")]
    features = [int(v) for v in args.features.split(",")]
    particles = [int(v) for v in args.particles.split(",")]
    step_seconds(2, 2, 100, 2)  # numba compilation / cache load, untimed
    print("RSU BP per-step cost (median over steps; claim = the ratio O((K Np)^2 I S P) predicts)")
    block("vehicles in range S (K = 3, Np = 600)", [(s, 3, 600) for s in vehicles],
          lambda s, k, n: s / vehicles[0], args.steps)
    block("features K (S = 2, Np = 600)", [(2, k, 600) for k in features],
          lambda s, k, n: (k / features[0]) ** 2, args.steps)
    block("particles Np (S = 2, K = 3)", [(2, 3, n) for n in particles],
          lambda s, k, n: (n / particles[0]) ** 2, args.steps)


if __name__ == "__main__":
    main()
