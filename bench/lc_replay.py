"""Benchmark: icp_da_lc's CPU cost per vehicle-step on recorded frames, so that two revisions are timed on
the same inputs.

``record`` runs a config's coupled simulation once and pickles every frame without its truth (the
estimator's input); ``run`` steps icp_da_lc (the config's ``[lc]``, ``[estimator_sensors]``, ``[fusion]``)
through them and prints its CPU seconds (``time.process_time``, steadier than wall time on a shared
machine) per vehicle-step over the frames from ``--warmup`` to ``--until`` seconds after the first, the
mean vehicles in the net, V2F rows per vehicle-step, the tracks at the end and a hash of every estimate
(vehicle means and covariances, row assignments, feature tracks): equal hashes, equal estimates.

    python bench/lc_replay.py record CONFIG FRAMES.pkl --duration 420 [--seed 1]
    python bench/lc_replay.py run CONFIG FRAMES.pkl --warmup 300 [--until 420] [--profile OUT.txt]

Run ``run`` from each checkout to compare (it imports the checkout it is run from). The frames of a
300-vehicle city take about 0.5 MB each. Not a test.

Measured (seed 1, CPU per vehicle-step of the steps from t = 300 to 420 s, warm-up 300 s on both nets, docs/performance.md
"Cities within 1.5x the arterial"): the arterial's realistic preset (152.5 vehicles) 326.9 us before, 320.8 / 333.6 after (two runs); the
doubled Berlin at 5000 trips per hour with its import's ``city_tlr_realistic.toml`` (363.9 vehicles) 517.0 us before, 452.3 / 470.8 after;
city / arterial 1.58x before, 1.41x after (both runs), with the same estimate hashes before and after. The
same Berlin at 2500 trips per hour (174 vehicles, 20 tracks per vehicle): 634.0 us after, 1.90-1.98x. With the gate
bound per block as well (one later run of each, load 4-8): arterial 285.4 us, the 364-vehicle city 299.8 us (1.05x),
the 174-vehicle city 413.8 us (1.45x); a second run (load 1-3): arterial 222.9 us, the 174-vehicle city 343.7 us
(1.54x), the 364-vehicle city 268.8 us (1.21x); same hashes.
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import pstats
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.methods.registry import ICP_DA_LC  # noqa: E402
from couplers.sumo_coupler import SumoCoupler  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.runner import build_estimators, sumo_scenario  # noqa: E402
from tools.frame_recording import read_frames as frames, write_frames  # noqa: E402


def record(cfg, path: Path) -> None:
    """Every frame of the config's coupled run, without truth, pickled one after the other."""
    with SumoCoupler(sumo_scenario(cfg), cfg.sensors) as coupler:
        write_frames((frame.without_truth() for frame in coupler.frames()), path)


def replay(cfg, path: Path, warmup: float, until: float, prof: cProfile.Profile | None) -> dict:
    est = build_estimators(cfg)[0]
    h = hashlib.sha256()
    cpu = veh_steps = steps = rows = 0
    t_first = None
    for fr in frames(path):
        t_first = fr.t if t_first is None else t_first
        if fr.t >= t_first + until:
            break
        counted = fr.t >= t_first + warmup
        if counted and prof is not None:
            prof.enable()
        t0 = time.process_time()
        e = est.step(fr)
        dt = time.process_time() - t0
        if counted and prof is not None:
            prof.disable()
        if counted:
            cpu, veh_steps, steps, rows = cpu + dt, veh_steps + fr.vehicle_ids.size, steps + 1, rows + fr.v2f_owner.size
        for arr in (e.mean, e.cov, e.v2f_assignment, e.feature_mean, e.feature_track_ids):
            if arr is not None:
                h.update(np.ascontiguousarray(arr).tobytes())
    return {"steps": steps, "vehicles": veh_steps / max(steps, 1), "rows": rows / max(veh_steps, 1),
            "us": 1e6 * cpu / max(veh_steps, 1), "tracks": est.state.features.size, "hash": h.hexdigest()[:16]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("record", "run"))
    ap.add_argument("config", type=Path)
    ap.add_argument("frames", type=Path)
    ap.add_argument("--duration", type=float, default=420.0, help="record: simulated seconds")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--warmup", type=float, default=300.0, help="run: seconds not counted at the start")
    ap.add_argument("--until", type=float, default=float("inf"), help="run: stop this many seconds after the first")
    ap.add_argument("--profile", type=Path, help="run: cProfile of the counted steps, written here")
    args = ap.parse_args()
    cfg = load_config(args.config, {"run.duration_s": args.duration, "run.methods": [ICP_DA_LC.name],
                                    "run.seed": args.seed})
    if args.mode == "record":
        record(cfg, args.frames)
        return
    prof = cProfile.Profile() if args.profile else None
    r = replay(cfg, args.frames, args.warmup, args.until, prof)
    print(f"{args.frames}: {r['steps']} steps from t0 + {args.warmup:g} s, mean {r['vehicles']:.1f} vehicles, "
          f"{r['rows']:.2f} V2F rows per vehicle-step, icp_da_lc {r['us']:.1f} us CPU per vehicle-step; "
          f"{r['tracks']} tracks at the end; estimates hash {r['hash']}")
    if prof is not None:
        with open(args.profile, "w") as out:
            pstats.Stats(prof, stream=out).sort_stats("tottime").print_stats(40)


if __name__ == "__main__":
    main()
