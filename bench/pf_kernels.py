"""Particle-pair evaluations per second of the ICP-DA-PF kernels: brute force and the k-d tree kernel.

Each problem is one Gauss transform of (25)-(27): Jf feature particles onto Jv vehicle particles
under the V2F likelihood (4), with clouds shaped like the paper's scenarios. Printed: pair
evaluations each kernel made, the time, and the fast / brute ratios of pairs and time, all from one run (timings are of this machine at this moment, not assertions).

    python bench/pf_kernels.py [--particles 5000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from coloc.pf_kernels import transform_batch

CASES = {
    # name: (position sigma m, velocity sigma m/s, V2F sigma_p, sigma_v)
    "single road, GNSS 8 m clouds": (8.0, 0.1, 0.2, 0.1),
    "single road, cooperative 1.5 m": (1.5, 0.1, 0.2, 0.1),
    "arterial, 0.7 m / 0.2 m/s": (0.7, 0.2, 0.1, 0.1),
}


def run_case(j: int, sp: float, sv: float, rp: float, rv: float, kernel: str, seed: int = 0):
    rng = np.random.default_rng(seed)
    spread = np.array([sp, sp, sv, sv])
    vehicles = rng.normal(size=(1, j, 4)) * spread
    features = rng.normal(size=(1, j, 4)) * spread
    r = np.diag([rp * rp, rp * rp, rv * rv, rv * rv])[None]
    args = (features, np.zeros((1, j)), np.zeros(1, np.int64), np.zeros((1, 4)), vehicles, np.zeros(1, np.int64),
            np.zeros((1, 4)), r, kernel)
    transform_batch(*args)  # compile / warm
    t0 = time.perf_counter()
    _, pairs = transform_batch(*args)
    return int(pairs.sum()), time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=5000, help="Jv = Jf")
    args = ap.parse_args()
    j = args.particles
    print(f"Jv = Jf = {j}: one Gauss transform ({j * j:.2e} particle pairs)")
    for name, (sp, sv, rp, rv) in CASES.items():
        pb, tb = run_case(j, sp, sv, rp, rv, "brute")
        line = f"{name:32s} brute {pb:.2e} pairs {tb:.3f} s ({pb / tb:.2e}/s)"
        for kernel in ("tree",):
            pk, tk = run_case(j, sp, sv, rp, rv, kernel)
            line += f" | {kernel} {pk:.2e} pairs {tk:.3f} s, vs brute: pairs {pk / pb:.3f} time {tk / tb:.3f}"
        print(line)

if __name__ == "__main__":
    main()
