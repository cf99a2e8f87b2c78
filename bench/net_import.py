"""Benchmark: import a net with ``coloc net import`` and run its first hour under TLR and VSR.

Prints the import's wall time, then for each control the traffic of the
simulated hour from the ``sumo`` binary run with exactly the options a
``coloc run`` uses (:func:`experiments.runner.folder_scenario`: every route and
additional file of the folder, its begin, step 0.75 s, ballistic update, seed,
``--tls.all-off`` for VSR) plus SUMO's own statistics output: vehicles loaded /
inserted / arrived, still running or waiting to enter at the end, teleports (jam, yield, wrong lane), mean vehicles running and halting, and
the mean speed and arrivals of the last 5 minutes (near 0 = gridlock).

    python bench/net_import.py (--net FILE.net.xml | --osm FILE.osm) [--seed 1] [--demand-scale 1]
    python bench/net_import.py --folder sumo_nets/NAME     # an existing net folder, no import

Not a test: it asserts nothing and prints numbers (noisy on a shared machine).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import sumolib

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from couplers.net.importer import ImportOptions, import_net  # noqa: E402
from experiments.runner import folder_scenario  # noqa: E402


def run_hour(folder: Path, control: str, seed: int, end: float) -> dict:
    # every route and additional file of the folder, from its begin, as `coloc run` starts SUMO
    opts = folder_scenario(folder, control, seed, end).sumo_options()
    with tempfile.TemporaryDirectory() as tmp:
        stats, summary = Path(tmp) / "stats.xml", Path(tmp) / "summary.xml"
        cmd = opts.command()
        cmd[0] = sumolib.checkBinary("sumo")
        cmd += ["--statistic-output", str(stats), "--summary-output", str(summary)]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        wall = time.perf_counter() - t0
        root = ET.parse(stats).getroot()
        steps = [s.attrib for s in ET.parse(summary).getroot().iter("step")]
    veh = root.find("vehicles").attrib
    tele = root.find("teleports").attrib
    t = np.array([float(s["time"]) for s in steps])
    running = np.array([int(s["running"]) for s in steps])
    halting = np.array([int(s["halting"]) for s in steps])
    arrived = np.array([int(s["arrived"]) for s in steps])
    speed = np.array([float(s["meanSpeed"]) for s in steps])
    last = t > t[-1] - 300.0
    return {
        "control": control, "wall_s": round(wall, 1),
        "loaded": int(veh["loaded"]), "inserted": int(veh["inserted"]), "arrived": int(arrived[-1]),
        "running_at_end": int(veh["running"]), "waiting_to_enter_at_end": int(veh["waiting"]),
        "teleports": int(tele["total"]), "teleports_jam": int(tele["jam"]), "teleports_yield": int(tele["yield"]),
        "teleports_wrong_lane": int(tele["wrongLane"]),
        "mean_running": round(float(running.mean()), 1), "mean_halting": round(float(halting.mean()), 1),
        "last_5min_mean_speed_mps": round(float(speed[last & (speed >= 0)].mean()), 2),
        "last_5min_arrivals": int(arrived[-1] - arrived[~last][-1]) if (~last).any() else int(arrived[-1]),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--net")
    src.add_argument("--osm")
    src.add_argument("--folder")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--demand-scale", type=float, default=1.0)
    ap.add_argument("--guess-signals", action="store_true")
    ap.add_argument("--end", type=float, default=3600.0, help="simulated seconds from the folder's begin")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        if args.folder:
            folder = Path(args.folder)
        else:
            folder = Path(tmp) / "net"
            opts = ImportOptions(name="bench", out=folder, net=Path(args.net) if args.net else None,
                                 osm=Path(args.osm) if args.osm else None, seed=args.seed,
                                 demand_scale=args.demand_scale, guess_signals=args.guess_signals)
            t0 = time.perf_counter()
            res = import_net(opts)
            print(f"import: {time.perf_counter() - t0:.1f} s wall")
            for line in res.lines:
                print("  " + line)
        for control in ("tlr", "vsr"):
            print(run_hour(folder, control, args.seed, args.end))
    return 0


if __name__ == "__main__":
    sys.exit(main())
