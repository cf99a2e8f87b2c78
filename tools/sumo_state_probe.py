#!/usr/bin/env python3
"""Does SUMO's saved state restart a run exactly? A run to W saves its state (``--save-state.rng``, full
precision) and goes on; a second run loads that state (``--load-state``) and goes on; the two are compared
step by step (vehicle ids, positions, speeds, traffic-light phases).

    python tools/sumo_state_probe.py sumo_nets/arterial --control tlr --seed 3 --at 60 --steps 80

Why ``[analysis] warmup_start`` has no saved-state mode: docs/protocol.md "Warm-up".
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path


def _trace(libsumo, steps: int) -> list[tuple]:
    out = []
    for _ in range(steps):
        libsumo.simulationStep()
        ids = libsumo.vehicle.getIDList()
        tls = tuple((libsumo.trafficlight.getRedYellowGreenState(t), libsumo.trafficlight.getPhase(t))
                    for t in libsumo.trafficlight.getIDList())
        out.append((libsumo.simulation.getTime(), tuple(ids), tuple(libsumo.vehicle.getPosition(v) for v in ids),
                    tuple(libsumo.vehicle.getSpeed(v) for v in ids), tls))
    return out


def probe(net_dir: str, control: str, seed: int, at_s: float, steps: int, step_s: float = 0.75) -> str:
    """One line: the first step where the state-loaded run differs from the continuous one, and how."""
    import libsumo

    from couplers.net.folder import load_net_folder
    from couplers.sumo_coupler import SumoScenario

    scen = SumoScenario(net=load_net_folder(net_dir), control=control, seed=seed, step_length=step_s,
                        duration_s=at_s + (steps + 1) * step_s)
    cmd = scen.sumo_options().command()
    with tempfile.TemporaryDirectory() as tmp:
        state = str(Path(tmp) / "state.xml.gz")
        libsumo.start(cmd + ["--save-state.rng", "true", "--save-state.precision", "17"])
        while libsumo.simulation.getTime() < at_s - 1e-9:
            libsumo.simulationStep()
        libsumo.simulation.saveState(state)
        a = _trace(libsumo, steps)
        libsumo.close()
        libsumo.start(cmd + ["--load-state", state])
        b = _trace(libsumo, steps)
        libsumo.close()
    for k, (x, y) in enumerate(zip(a, b)):
        if x == y:
            continue
        what = []
        if x[4] != y[4]:
            what.append("traffic-light phases")
        if x[1] != y[1]:
            what.append("vehicles present")
        else:
            for i, v in enumerate(x[1]):
                if x[2][i] != y[2][i] or x[3][i] != y[3][i]:
                    dx = max(abs(p - q) for p, q in zip(x[2][i], y[2][i]))
                    what.append(f"vehicle {v}: position {x[2][i]} vs {y[2][i]} ({dx:.3g} m), speed "
                                f"{x[3][i]:.4g} vs {y[3][i]:.4g} m/s")
                    break
        return f"differs from step {k + 1} after the load (t = {x[0]:g} s): " + "; ".join(what)
    return f"identical over {steps} steps after the load at t = {at_s:g} s"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("net_dir")
    ap.add_argument("--control", default="tlr")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--at", type=float, default=60.0, help="time of the saved state, s")
    ap.add_argument("--steps", type=int, default=80)
    args = ap.parse_args(argv)
    print(f"{args.net_dir} {args.control} seed {args.seed}: "
          + probe(args.net_dir, args.control, args.seed, args.at, args.steps))
    return 0


if __name__ == "__main__":
    sys.exit(main())
