"""Benchmark: per-vehicle-step cost of frames and estimators on a city, from 100 to about 2700 vehicles.

Builds, deterministically and from files this project ships or generates:

1. the doubled Berlin net (``bench/berlin_twice.py``: the eclipse-sumo wheel's Berlin OSM net twice,
   2066 junctions, 185 lane-km, 42 traffic lights);
2. static features: bus-stop places every ``--feature-spacing`` m (default 50 m) along every
   drivable edge longer than 40 m, handed to ``coloc net import --additional`` so the import's own
   feature selection (4 m apart, seeded) picks up to ``--features`` of them (default 1500; it finds
   972 places on this net, about 11 per km of road, near the arterial's ~13);
3. a demand ramp: ``randomTrips.py`` trips (seeded, validated by duarouter, at least 1.5 km long)
   inserted at ``--insertion-rate`` veh/h (default 14000) for the first ``--insert-s`` seconds (900),
   so that the number of vehicles in the net climbs from 0 past 3000 in one run;
4. ``coloc net import --net ... --routes ... --additional ... --no-calibrate`` writes the net folder
   and its TLR config (default zones: C centre, B ring, A outskirts).

Then one coupled run (libsumo, ``SumoCoupler``, the generated TLR config's sensing; every estimator on
every frame, as ``bench/coupled_vs_sumo.py`` does) records per step the vehicles in the net, the V2V
links, the V2F rows and the wall time of the frame and of each method. Printed: per bin of vehicles in
the net, the cost per vehicle-step (microseconds) of frames, gnss, icp_known_da and icp_da_lc, with the
mean V2V degree and V2F rows per vehicle beside them (the jam packs the net, so the degree grows with
N: a change in cost can be read against it); the ratio of icp_da_lc's cost per
vehicle-step at ~3000 vehicles to its cost at ~300 (target: at most 1.5, i.e. the per-vehicle cost
stays nearly flat as the city fills); and the `sumo` binary
alone on the same net and routes against the coupled run with gnss + icp_da_lc (target: at most 10x).

    python bench/city_scale.py [--work /tmp/coloc_city] [--duration 900] [--seed 1]

With ``--realistic`` it measures instead icp_da_lc's cost per vehicle-step with the realistic tables
(the import's ``city_tlr_realistic.toml``, i.e. the arterial's realistic preset on the city) against
the arterial's own (``experiments/arterial_tlr_realistic.toml``), over the steps after ``--warmup``
seconds of the same ``--duration`` and seed (target: the city within 1.5x the arterial). For a city
of about 300 vehicles in the net build it with a lower rate, e.g.
``--work /tmp/coloc_city300 --insertion-rate 2500 --insert-s 1800``.

To time two revisions of icp_da_lc on the same inputs, record the frames once and replay them from each
checkout with ``bench/lc_replay.py``; the measurements of both kinds are in docs/performance.md
("City scale with realistic sensing").

Every SUMO run here is started as `coloc run` starts it (:func:`experiments.runner.sumo_scenario`:
every route file, additional file and the begin of the net folder).

The net folder is cached in ``--work`` (rebuilt when absent). Not a test: it asserts nothing and
prints numbers measured in one run (6 minutes on an idle 2-core machine, plus about 1 minute to
build the net folder the first time). The simulation jams as the demand exceeds the net's capacity,
which is what puts 2733 vehicles in it at once by t = 900 s.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import sumo  # the eclipse-sumo wheel
import sumolib

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from couplers.net.folder import load_net_folder  # noqa: E402
from couplers.sumo_coupler import SumoCoupler, SumoScenario  # noqa: E402
from experiments.config import load_config  # noqa: E402
from coloc.methods.registry import GNSS, ICP_DA_LC, ICP_KNOWN_DA, METHODS  # noqa: E402
from experiments.runner import build_estimators, sumo_scenario  # noqa: E402
from bench.coupled_vs_sumo import time_sumo_binary  # noqa: E402

BINS = (100, 200, 300, 500, 750, 1000, 1500, 2000, 2500, 3000, 3500)
METHOD_NAMES = (GNSS.name, ICP_KNOWN_DA.name, ICP_DA_LC.name)


def bus_stop_places(net_file: Path, spacing: float) -> str:
    """busStop additionals every ``spacing`` m along lane 0 of every drivable edge longer than 40 m."""
    net = sumolib.net.readNet(str(net_file))
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f"<!-- bench/city_scale.py: feature places every {spacing:g} m along drivable edges -->",
             "<additional>"]
    for e in sorted(net.getEdges(), key=lambda e: e.getID()):
        if e.getFunction() != "" or not e.allows("passenger") or e.getLength() <= 40.0:
            continue
        lane = e.getLane(0)
        for k, pos in enumerate(np.arange(20.0, lane.getLength() - 20.0, spacing)):
            lines.append(f'    <busStop id="cs_{e.getID()}_{k}" lane="{lane.getID()}" '
                         f'startPos="{pos:.1f}" endPos="{pos + 10.0:.1f}"/>')
    lines.append("</additional>")
    return "\n".join(lines) + "\n"


def build_city(work: Path, seed: int, features: int, spacing: float, rate: float, insert_s: float) -> Path:
    """The net folder and its TLR config under ``work`` (built once; returns the config path)."""
    config = work / "experiments" / "city_tlr.toml"
    if config.exists():
        return config
    work.mkdir(parents=True, exist_ok=True)
    net = work / "berlin2.net.xml"
    if not net.exists():
        subprocess.run([sys.executable, str(ROOT / "bench" / "berlin_twice.py"), "--out", str(net)], check=True)
    stops = work / "places.add.xml"
    stops.write_text(bus_stop_places(net, spacing))
    trips = work / "trips.rou.xml"
    subprocess.run([sys.executable, str(Path(sumo.SUMO_HOME) / "tools" / "randomTrips.py"), "-n", str(net),
                    "-e", f"{insert_s:g}", "--insertion-rate", f"{rate:g}", "--seed", str(seed),
                    "--min-distance", "1500", "--fringe-factor", "2", "--validate",
                    "--vehicle-class", "passenger", "-o", str(trips), "-r", str(work / "routes.rou.xml")],
                   check=True, capture_output=True, cwd=work)  # randomTrips writes its helper files to cwd
    subprocess.run([sys.executable, "-m", "experiments.cli", "net", "import", "--net", str(net), "--name", "city",
                    "--out", str(work / "net"), "--experiments-dir", str(work / "experiments"),
                    "--routes", str(trips), "--additional", str(stops), "--features", str(features),
                    "--seed", str(seed), "--no-calibrate"], check=True, cwd=ROOT)
    return config


def coupled_steps(scenario: SumoScenario, cfg, methods, clock=time.perf_counter) -> dict[str, np.ndarray]:
    """Per step: vehicles, V2V links, V2F rows, frame seconds and each method's seconds (``clock``: wall,
    or ``time.process_time`` for CPU seconds, steadier on a shared machine)."""
    estimators = build_estimators(cfg)
    estimators = [e for e in estimators if e.name in methods]
    rec = {k: [] for k in ("t", "n", "links", "rows", "frame", *[e.name for e in estimators])}
    with SumoCoupler(scenario, cfg.sensors) as coupler:
        frames = coupler.frames()
        while True:
            t0 = clock()
            frame = next(frames, None)
            if frame is None:
                break
            rec["frame"].append(clock() - t0)
            rec["t"].append(frame.t)
            rec["n"].append(frame.vehicle_ids.size)
            rec["links"].append(frame.neighbors.nnz // 2)
            rec["rows"].append(frame.v2f_owner.size)
            blind = frame.without_truth()
            for est in estimators:
                s = clock()
                if METHODS[est.name].known_association:  # the bound is told the association
                    est.step_with_association(blind, frame.truth.v2f_feature)
                else:
                    est.step(blind)
                rec[est.name].append(clock() - s)
    return {k: np.asarray(v, dtype=float) for k, v in rec.items()}


def per_vehicle_table(rec: dict[str, np.ndarray], names: list[str]) -> dict[int, float]:
    """Print the per-vehicle-step cost by bin of vehicles in the net; return icp_da_lc's by bin start."""
    n = rec["n"]
    head = f"  {'vehicles':>11} {'steps':>6} {'degree':>7} {'rows/veh':>8} {'frames':>8}" + "".join(
        f" {m:>13}" for m in names)
    print(head + "   (microseconds per vehicle-step)")
    lc = {}
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        sel = (n >= lo) & (n < hi)
        if sel.sum() < 5:
            continue
        veh_steps = n[sel].sum()
        row = (f"  {lo:>5}-{hi:<5} {int(sel.sum()):>6} {2 * rec['links'][sel].sum() / veh_steps:7.1f} "
               f"{rec['rows'][sel].sum() / veh_steps:8.2f} {1e6 * rec['frame'][sel].sum() / veh_steps:8.1f}")
        for m in names:
            cost = 1e6 * rec[m][sel].sum() / veh_steps
            row += f" {cost:13.1f}"
            if m == ICP_DA_LC.name:
                lc[lo] = cost
        print(row)
    return lc


def lc_per_vehicle_step(rec: dict[str, np.ndarray], warmup_s: float, vehicles: tuple[float, float] | None = None,
                        ) -> tuple[float, float, float, float]:
    """icp_da_lc's cost per vehicle-step (microseconds), the mean vehicles in the net, the V2F rows per
    vehicle-step and the frames' cost per vehicle-step, over the steps from ``warmup_s`` after the first
    (and with ``vehicles`` = (lo, hi) vehicles in the net, when given)."""
    sel = rec["t"] >= rec["t"][0] + warmup_s
    if vehicles is not None:
        sel &= (rec["n"] >= vehicles[0]) & (rec["n"] < vehicles[1])
    veh_steps = rec["n"][sel].sum()
    return (1e6 * rec[ICP_DA_LC.name][sel].sum() / veh_steps, float(rec["n"][sel].mean()),
            rec["rows"][sel].sum() / veh_steps, 1e6 * rec["frame"][sel].sum() / veh_steps)


def realistic_against_arterial(city_config: Path, args) -> None:
    """icp_da_lc per vehicle-step with the realistic tables on the city (its import's
    ``city_tlr_realistic.toml``) against the arterial's (``arterial_tlr_realistic.toml``), same duration, seed
    and warm-up; each SUMO run as `coloc run` starts it (:func:`experiments.runner.sumo_scenario`)."""
    over = {"run.duration_s": args.duration, "run.methods": [GNSS.name, ICP_DA_LC.name], "run.seed": args.seed}
    out = {}
    for label, path in (("arterial", ROOT / "experiments" / "arterial_tlr_realistic.toml"),
                        ("city", city_config.with_name("city_tlr_realistic.toml"))):
        cfg = load_config(path, over)
        t0 = time.perf_counter()
        rec = coupled_steps(sumo_scenario(cfg), cfg, over["run.methods"], time.process_time)
        cost, n, rows, frames = lc_per_vehicle_step(rec, args.warmup, args.vehicles if label == "city" else None)
        out[label] = cost
        print(f"  {label:<9} realistic: mean {n:6.1f} vehicles in the net, {rows:5.2f} V2F rows per vehicle-step, "
              f"frames {frames:7.1f} us, icp_da_lc {cost:7.1f} us CPU per vehicle-step "
              f"(t >= {args.warmup:g} s of {args.duration:g} s, seed {args.seed}; "
              f"{time.perf_counter() - t0:.0f} s wall)")
    print(f"  icp_da_lc per vehicle-step, city against arterial, realistic sensing: "
          f"{out['city'] / out['arterial']:.2f}x (target at most 1.5x)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path("/tmp/coloc_city"))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--duration", type=float, default=900.0, help="simulated seconds of the coupled run")
    ap.add_argument("--features", type=int, default=1500)
    ap.add_argument("--feature-spacing", type=float, default=50.0)
    ap.add_argument("--insertion-rate", type=float, default=14000.0, help="veh/h while inserting")
    ap.add_argument("--insert-s", type=float, default=900.0, help="seconds of insertion")
    ap.add_argument("--methods", default=",".join(METHOD_NAMES))
    ap.add_argument("--realistic", action="store_true",
                    help="instead: icp_da_lc per vehicle-step with the realistic tables, city against arterial")
    ap.add_argument("--warmup", type=float, default=300.0, help="with --realistic: seconds not counted at the start")
    ap.add_argument("--vehicles", type=lambda v: tuple(float(x) for x in v.split(",")), default=None,
                    help="with --realistic: count only the city's steps with LO,HI vehicles in the net")
    args = ap.parse_args()

    t0 = time.perf_counter()
    config = build_city(args.work, args.seed, args.features, args.feature_spacing, args.insertion_rate, args.insert_s)
    build_s = time.perf_counter() - t0
    if args.realistic:
        realistic_against_arterial(config, args)
        return
    methods = args.methods.split(",")
    cfg = load_config(config, {"run.duration_s": args.duration, "run.methods": methods, "run.seed": args.seed})
    net = load_net_folder(cfg.net_dir)
    scenario = sumo_scenario(cfg, net)  # as `coloc run` starts SUMO
    feats = net.features.ids.size
    sumo_alone = time_sumo_binary(scenario)
    rec = coupled_steps(scenario, cfg, methods)
    names = [m for m in methods if m in rec]

    print(f"city: doubled Berlin, {feats} features, seed {args.seed}, {args.duration:.0f} s simulated, "
          f"{rec['n'].size} steps, up to {int(rec['n'].max())} vehicles at once (net folder built in {build_s:.0f} s)")
    lc = per_vehicle_table(rec, names)
    if lc:
        near = lambda target: min(lc, key=lambda lo: abs(lo - target))  # noqa: E731
        a, b = near(300), near(3000)
        print(f"  icp_da_lc per vehicle-step, bin {b}+ against bin {a}+: {lc[b] / lc[a]:.2f}x (target at most 1.5x)")
    frames_s = rec["frame"].sum()
    print(f"  sumo binary alone          {sumo_alone:8.1f} s")
    print(f"  frames (libsumo + coupler) {frames_s:8.1f} s   ratio to sumo {frames_s / sumo_alone:5.2f}")
    for m in names:
        print(f"  estimator {m:<16} {rec[m].sum():8.1f} s")
    if ICP_DA_LC.name in names and GNSS.name in names:
        run = frames_s + rec[GNSS.name].sum() + rec[ICP_DA_LC.name].sum()
        print(f"  coupled gnss + icp_da_lc   {run:8.1f} s   ratio to sumo {run / sumo_alone:5.2f} (target at most 10)")


if __name__ == "__main__":
    main()
