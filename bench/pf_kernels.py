"""Particle-pair evaluations per second of the ICP-DA-PF kernels: brute force and the k-d tree kernel.

Each problem is one Gauss transform of (25)-(27): Jf feature particles onto Jv vehicle particles
under the V2F likelihood (4), with clouds shaped like the paper's scenarios, with the bare V2F
kernel R and with the kernel density messages of ``message_bandwidth = "prior"`` (ICP-DA-PF's
default: kernel R + h^2 Cov of the source set, Silverman's h at J). Printed: pair evaluations
each kernel made, the time, and the fast / brute ratios of pairs and time, all from one run
(timings are of this machine at this moment, not assertions); for the kernel matrices BPA-L keeps
through its iterations (``pf.kernel_cache_mb``), the build and each later sum; and the *least* share of pairs any
summation exact to the same 1e-6 must evaluate: per target, the fewest largest terms whose
remainder is at most 1e-6 of the sum (``--least``; sorts every target's J terms).

The fast path (``[pf] kernel = "fast"``, :mod:`coloc.kernels.pf_fast`, every entry within 1e-3) is printed on
a second line under each case: its one-off sum (eta, the output set) against the tree, its 16-bit kept matrix
(build, each later sum) against the exact float32 one, and its largest relative error against the tree's sum.

    python bench/pf_kernels.py [--particles 5000] [--least]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from coloc.inference.particles import silverman_factor
from coloc.kernels.pf import KernelWorkspace, fixed_transforms, transform_batch, transform_fixed
from coloc.kernels.pf_fast import FastRepeatedTransforms, fast_transform_batch

CASES = {
    # name: (position sigma m, velocity sigma m/s, V2F sigma_p, sigma_v, kernel density smoothing)
    "single road, GNSS 8 m clouds": (8.0, 0.1, 0.2, 0.1, False),
    "single road, cooperative 1.5 m": (1.5, 0.1, 0.2, 0.1, False),
    "arterial, 0.7 m / 0.2 m/s": (0.7, 0.2, 0.1, 0.1, False),
    "single road, 8 m, smoothed": (8.0, 0.1, 0.2, 0.1, True),
    "single road, 1.5 m, smoothed": (1.5, 0.1, 0.2, 0.1, True),
    "arterial, 0.7 m, smoothed": (0.7, 0.2, 0.1, 0.1, True),
}
REL_TOL = 1e-6


def case_problem(j: int, sp: float, sv: float, rp: float, rv: float, smoothed: bool, seed: int = 0):
    """(sources, targets, kernel covariance) of one case: Gaussian clouds, kernel R (+ h^2 Cov)."""
    rng = np.random.default_rng(seed)
    spread = np.array([sp, sp, sv, sv])
    vehicles = rng.normal(size=(j, 4)) * spread
    features = rng.normal(size=(j, 4)) * spread
    r = np.diag([rp * rp, rp * rp, rv * rv, rv * rv])
    if smoothed:
        r = r + silverman_factor(j) * np.cov(features, rowvar=False)
    return features, vehicles, r


def run_case(src: np.ndarray, tgt: np.ndarray, r: np.ndarray, kernel: str):
    j = src.shape[0]
    args = (src[None], np.zeros((1, j)), np.zeros(1, np.int64), np.zeros((1, 4)), tgt[None],
            np.zeros(1, np.int64), np.zeros((1, 4)), r[None], kernel, REL_TOL)
    transform_batch(*args)  # compile / warm
    t0 = time.perf_counter()
    _, pairs = transform_batch(*args)
    return int(pairs.sum()), time.perf_counter() - t0


def least_exact_share(src: np.ndarray, tgt: np.ndarray, r: np.ndarray, rel_tol: float = REL_TOL,
                      chunk: int = 256) -> float:
    """Mean over targets of the fewest terms whose remainder is <= rel_tol of the target's sum, / J.

    No summation that is exact to rel_tol per entry can evaluate fewer pairs (it must at least
    touch those terms); the k-d tree's share divided by this is what pruning could still gain.
    """
    linv = np.linalg.inv(np.linalg.cholesky(r))
    us, ut = src @ linv.T, tgt @ linv.T
    counts = []
    for a in range(0, ut.shape[0], chunk):
        d2 = ((ut[a:a + chunk, None, :] - us[None, :, :]) ** 2).sum(-1)
        terms = np.exp(-0.5 * (d2 - d2.min(axis=1, keepdims=True)))
        terms = -np.sort(-terms, axis=1)
        total = terms.sum(axis=1, keepdims=True)
        remainder = total - np.cumsum(terms, axis=1)
        counts.append((remainder > rel_tol * total).sum(axis=1) + 1)
    return float(np.concatenate(counts).mean()) / src.shape[0]


def run_kept(src: np.ndarray, tgt: np.ndarray, r: np.ndarray) -> tuple[float, float]:
    """Seconds to build the kept kernel matrix of one problem and for one sum with it (BPA-L's later
    iterations, :func:`coloc.kernels.pf.transform_fixed`)."""
    j = src.shape[0]
    args = (src[None], np.zeros(1, np.int64), np.zeros((1, 4)), tgt[None], np.zeros(1, np.int64),
            np.zeros((1, 4)), r[None], "tree", REL_TOL, 8.0 * j * j)
    storage = KernelWorkspace().arrays(j * j)[0]
    transform_fixed(fixed_transforms(*args, storage), np.zeros((1, j)))  # compile / warm, touch the storage
    t0 = time.perf_counter()
    fixed = fixed_transforms(*args, storage)
    t1 = time.perf_counter()
    transform_fixed(fixed, np.zeros((1, j)))
    return t1 - t0, time.perf_counter() - t1


def run_fast(src: np.ndarray, tgt: np.ndarray, r: np.ndarray) -> tuple[float, float, float, float]:
    """The fast path on one problem: seconds of a one-off sum, of building the 16-bit kept matrix (with the
    first sum, as BPA-L's first iteration) and of one later sum; largest relative error against the tree."""
    j = src.shape[0]
    one = (src[None], np.zeros((1, j)), np.zeros(1, np.int64), np.zeros((1, 4)), tgt[None], np.zeros(1, np.int64),
           np.zeros((1, 4)), r[None])
    fast_transform_batch(*one)  # compile / warm
    t0 = time.perf_counter()
    out, _ = fast_transform_batch(*one)
    direct = time.perf_counter() - t0
    exact, _ = transform_batch(*one, "tree", REL_TOL)
    err = float(np.max(np.abs(np.expm1(out - exact))))
    problem = (src[None], np.zeros(1, np.int64), np.zeros((1, 4)), tgt[None], np.zeros(1, np.int64), np.zeros((1, 4)),
               r[None], 4.0 * j * j)
    storage = np.empty(j * j, np.uint16)
    warm = FastRepeatedTransforms(*problem, storage)
    warm.sum(np.zeros((1, j)))
    warm.sum(np.zeros((1, j)))
    kept = FastRepeatedTransforms(*problem, storage)
    t0 = time.perf_counter()
    kept.sum(np.zeros((1, j)))
    t1 = time.perf_counter()
    kept.sum(np.zeros((1, j)))
    return direct, t1 - t0, time.perf_counter() - t1, err


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=5000, help="Jv = Jf")
    ap.add_argument("--least", action="store_true", help="also the least share of pairs an exact sum needs")
    args = ap.parse_args()
    j = args.particles
    print(f"Jv = Jf = {j}: one Gauss transform ({j * j:.2e} particle pairs)")
    for name, case in CASES.items():
        src, tgt, r = case_problem(j, *case)
        pb, tb = run_case(src, tgt, r, "brute")
        line = f"{name:30s} brute {pb:.2e} pairs {tb:.3f} s ({pb / tb:.2e}/s)"
        pk, tk = run_case(src, tgt, r, "tree")
        line += f" | tree {pk:.2e} pairs {tk:.3f} s, vs brute: pairs {pk / pb:.3f} time {tk / tb:.3f}"
        build, each = run_kept(src, tgt, r)
        line += f" | kept: build {build:.3f} s, each sum {each:.4f} s ({pb / each:.2e}/s, {each / tk:.2f} of the tree)"
        if args.least:
            line += f" | least exact share {least_exact_share(src, tgt, r):.3f}"
        print(line)
        direct, fbuild, feach, err = run_fast(src, tgt, r)
        print(f"{'':30s} fast: one-off {direct:.3f} s ({direct / tk:.2f} of the tree) | 16-bit kept: build "
              f"{fbuild:.3f} s ({fbuild / build:.2f} of the exact build), each sum {feach:.4f} s ({feach / each:.2f} "
              f"of the exact) | largest relative error {err:.1e}")


if __name__ == "__main__":
    main()
