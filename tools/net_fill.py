#!/usr/bin/env python3
"""How long a SUMO net takes to fill from empty: vehicles in the net and exits per minute, SUMO alone.

    python tools/net_fill.py sumo_nets/arterial --control tlr --seed 1 --minutes 20

The realistic presets' ``[analysis] warmup_s`` comes from this measure (docs/validation/realistic_sensing.md).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np


def fill(net_dir: str, control: str, seed: int, minutes: int, step_s: float = 0.75) -> list[tuple[int, float, int]]:
    """(minute, mean vehicles in the net over that minute, vehicles that left the net in it)."""
    from experiments.runner import folder_scenario
    from couplers.traffic.sumo import SumoTraffic

    # every route and additional file of the folder, from its begin, as `coloc run` starts SUMO
    scen = dataclasses.replace(folder_scenario(net_dir, control, seed, 60.0 * minutes), step_length=step_s)
    rows = []
    with SumoTraffic(scen.sumo_options()) as traffic:
        n, arrived = np.zeros(minutes), np.zeros(minutes, dtype=int)
        steps = np.zeros(minutes, dtype=int)
        import libsumo

        while not traffic.done():
            s = traffic.step()
            k = min(int((s.t - scen.begin_s - 1e-9) // 60.0), minutes - 1)  # minutes from the begin
            n[k] += len(s.ids)
            steps[k] += 1
            arrived[k] += libsumo.simulation.getArrivedNumber()
    for k in range(minutes):
        rows.append((k + 1, n[k] / max(steps[k], 1), int(arrived[k])))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("net_dir")
    ap.add_argument("--control", default="tlr")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--minutes", type=int, default=20)
    args = ap.parse_args(argv)
    print("minute  vehicles_in_net  exits")
    for minute, veh, exits in fill(args.net_dir, args.control, args.seed, args.minutes):
        print(f"{minute:6d}  {veh:15.1f}  {exits:5d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
