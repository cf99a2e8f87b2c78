#!/usr/bin/env python3
"""How well does the world's reported velocity explain its reported positions? For every vehicle present
in two consecutive steps with both speeds above 1 m/s: the displacement minus the trapezoid of the two
reported velocities, ``x_t - x_{t-1} - Ts (v_{t-1} + v_t) / 2`` (model (1)'s kinematics with SUMO's
ballistic update); its RMS over all such steps and over the sharp-turn steps (heading change above
0.3 rad in one step), for each ``[scenario] reference_point``.

    python tools/world_residual.py sumo_nets/arterial --control tlr --seed 101 --duration 300

docs/validation/consistency.md "Kinematics of the world".
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

MOVING_MPS = 1.0  # both speeds above this: a moving step
SHARP_TURN_RAD = 0.3  # heading change in one step above this: a sharp-turn step


def residuals(net_dir: str, control: str, seed: int, duration_s: float, reference_point: str,
              step_s: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
    """(residual norms (M,) m, heading changes (M,) rad) of the moving steps of a SUMO run."""
    from couplers.net.folder import load_net_folder
    from couplers.sumo_coupler import SumoScenario
    from couplers.traffic.sumo import SumoTraffic

    scen = SumoScenario(net=load_net_folder(net_dir), control=control, seed=seed, step_length=step_s,
                        duration_s=duration_s, reference_point=reference_point)
    res, turn = [], []
    prev = None
    with SumoTraffic(scen.sumo_options(), reference_point) as traffic:
        while not traffic.done():
            s = traffic.step()
            if prev is not None:
                r = s.prev_row
                ok = (r >= 0) & ~s.entered
                i, j = np.flatnonzero(ok), r[ok]
                moving = (np.hypot(*s.velocity[i].T) > MOVING_MPS) & (np.hypot(*prev.velocity[j].T) > MOVING_MPS)
                i, j = i[moving], j[moving]
                d = s.xy[i] - prev.xy[j] - 0.5 * step_s * (s.velocity[i] + prev.velocity[j])
                res.append(np.hypot(*d.T))
                turn.append(np.abs(np.angle(np.exp(1j * (s.heading[i] - prev.heading[j])))))
            prev = s
    return np.concatenate(res), np.concatenate(turn)


def table(net_dir: str, control: str, seed: int, duration_s: float) -> list[str]:
    lines = [f"{'reference point':<16}{'moving steps':>14}{'RMS m':>9}{'sharp-turn steps':>18}{'RMS m':>9}"]
    for ref in ("front_bumper", "centre"):
        r, h = residuals(net_dir, control, seed, duration_s, ref)
        sharp = h > SHARP_TURN_RAD
        lines.append(f"{ref:<16}{r.size:>14}{np.sqrt(np.mean(r**2)):>9.3f}{int(sharp.sum()):>18}"
                     f"{np.sqrt(np.mean(r[sharp]**2)) if sharp.any() else float('nan'):>9.3f}")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("net_dir")
    ap.add_argument("--control", default="tlr")
    ap.add_argument("--seed", type=int, default=101)
    ap.add_argument("--duration", type=float, default=300.0)
    args = ap.parse_args(argv)
    print(f"{args.net_dir} {args.control} seed {args.seed}, {args.duration:g} s")
    print("\n".join(table(args.net_dir, args.control, args.seed, args.duration)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
