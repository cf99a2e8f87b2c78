"""Benchmark: per-step cost of the estimators against the number of vehicles and of features per vehicle.

A synthetic straight road (4 lanes, 10 m/s) with N vehicles at a fixed density
(so the V2V degree and the features per vehicle do not grow with N) and static
features along both sides, spaced so that each vehicle senses about F of them
(Rs = 50 m). Measurements come from ``couplers.sensing.sensors.synthesize_frame`` as in
every run. For each (N, F) the mean wall time per step over the last steps is
printed per method, with ms per vehicle-step: "linear in vehicles" shows as a
flat ms/vehicle column down each F block.

    python bench/scaling.py [--steps 30] [--vehicles 25,50,100,200,400] [--features 2,5,10]

Not a test: it asserts nothing and prints numbers measured in one run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.core.models import MotionParams, input_matrix, transition_matrix  # noqa: E402
from coloc.inference.params import IcpParams  # noqa: E402
from coloc.methods.gnss import GnssTracker  # noqa: E402
from coloc.methods.icp_da_lc import IcpDaLc, LcParams  # noqa: E402
from coloc.methods.icp_known_da import IcpKnownDA  # noqa: E402
from coloc.methods.registry import METHODS  # noqa: E402
from couplers.sensing.sensors import SensorNoise, SensorParams, synthesize_frame  # noqa: E402

VEHICLE_SPACING_M = 12.0  # along the road, over 4 lanes: ~3 vehicles per 10 m of road
RS = 50.0


def road_frames(n: int, feats_per_vehicle: int, steps: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    dt = 1.0
    a, b = transition_matrix(dt), input_matrix(dt)
    length = n * VEHICLE_SPACING_M / 4 + 200.0
    x = np.zeros((n, 4))
    x[:, 0] = rng.uniform(0, length - 200.0, n)
    x[:, 1] = rng.integers(0, 4, n) * 3.5
    x[:, 2] = 10.0
    # A vehicle senses features within 2 Rs of road length on both sides: spacing = 2 Rs / F.
    spacing = 2 * RS / feats_per_vehicle
    fx = np.arange(-RS, length + steps * 10.0 + RS, spacing)
    feats = np.zeros((fx.size, 4))
    feats[:, 0] = fx
    feats[:, 1] = np.where(np.arange(fx.size) % 2, -4.0, 14.0)
    tree = cKDTree(feats[:, :2])
    params = SensorParams(v2f_range_m=RS, v2v_range_m=250.0)
    noise = SensorNoise(seed)
    ids = np.array([f"v{i}" for i in range(n)], dtype=object)
    for t in range(steps):
        acc = np.zeros((n, 2))
        acc[:, 0] = rng.normal(0, 0.3, n)
        if t:
            x = x @ a.T + acc @ b.T
        yield synthesize_frame(
            t=float(t), dt=dt, vehicle_ids=ids, entered=np.full(n, t == 0), x_true=x, accel_true=acc,
            heading=np.zeros(n), gnss_sigma_p=np.full(n, 8.0), gnss_sigma_v=np.full(n, 0.2),
            features_true=feats, feature_tree=tree, params=params, noise=noise,
            zone=np.full(n, "B", dtype=object), area=np.full(n, "road", dtype=object),
        )


def estimators(motion: MotionParams, icp: IcpParams) -> list:
    """The GNSS tracker, the known-association bound and ICP-DA-LC, fresh."""
    return [GnssTracker(motion=motion), IcpKnownDA(icp), IcpDaLc(icp, LcParams(sensing_range_m=RS))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--vehicles", default="25,50,100,200,400")
    ap.add_argument("--features", default="2,5,10")
    args = ap.parse_args()
    motion = MotionParams(sigma_along=0.35, sigma_cross=0.1)
    icp = IcpParams(motion=motion, feature_velocity_prior_sigma=0.1)
    warm = max(args.steps // 3, 1)
    names = [e.name for e in estimators(motion, icp)]
    print(f"{'F':>3} {'N':>5} {'rows/step':>9}  " + "  ".join(f"{m:>24}" for m in names))
    print(f"{'':>3} {'':>5} {'':>9}  " + "  ".join(f"{'ms/step  ms/vehicle':>24}" for _ in range(3)))
    for f in (int(v) for v in args.features.split(",")):
        for n in (int(v) for v in args.vehicles.split(",")):
            frames = list(road_frames(n, f, args.steps))
            rows = np.mean([fr.v2f_z.shape[0] for fr in frames])
            cells = []
            for est in estimators(motion, icp):
                spent = 0.0
                for k, fr in enumerate(frames):
                    blind = fr.without_truth()
                    t0 = time.perf_counter()
                    if METHODS[est.name].known_association:
                        est.step_with_association(blind, fr.truth.v2f_feature)
                    else:
                        est.step(blind)
                    if k >= warm:
                        spent += time.perf_counter() - t0
                ms = 1e3 * spent / (len(frames) - warm)
                cells.append(f"{ms:10.2f} {ms / n:12.4f}")
            print(f"{f:>3} {n:>5} {rows:9.0f}  " + "  ".join(f"{c:>24}" for c in cells), flush=True)


if __name__ == "__main__":
    main()
