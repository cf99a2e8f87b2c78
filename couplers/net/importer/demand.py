"""Demand of ``coloc net import``.

The arterial's falling profile matched to the net's density, routes from randomTrips/duarouter, the
gridlock calibration under VSR and TLR, or the user's route file checked against the net.
"""

from __future__ import annotations

import math
import shutil
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from couplers.errors import InputError
from couplers.net import gridlock as jam
from couplers.net.importer.geometry import _fmt
from couplers.net.importer.tools import _run, _sumo_home

if TYPE_CHECKING:
    from couplers.net.importer import ImportOptions, _Report

# The shipped arterial (sumo_nets/arterial), measured from its files; a test
# checks these against the folder. Demand is scaled so that an imported net
# carries the arterial's density: rate x mean route length / lane-km equal.
ARTERIAL_LANE_KM = 22.666  # drivable lane length without internal lanes, km
ARTERIAL_MEAN_ROUTE_M = 1527.1  # mean route length over the hour's vehicles, m

# Passenger car of the arterial's demand (sumo_nets/arterial/demand.rou.xml).
VTYPE = {
    "id": "car", "vClass": "passenger", "carFollowModel": "Krauss", "accel": "2.6", "decel": "4.5",
    "emergencyDecel": "9", "sigma": "0.5", "tau": "1.0", "length": "4.5", "minGap": "2.5",
    "maxSpeed": "15", "speedFactor": "normc(1.0,0.1,0.8,1.2)", "jmTimegapMinor": "1.5",
    "impatience": "0.5", "color": "1,1,0",
}

BIN_S = 300.0
# Demand calibration (see gridlock_trial): the density-matched demand is simulated
# (by default for its whole duration, ImportOptions.calibration_s) and scaled down by
# CALIB_FACTOR until neither control shows gridlock. Measured on a Berlin extract: a
# demand clean over the first 10 min still jammed VSR after 25 min, so the default
# checks the whole hour; a jammed trial stops at the first sign, so failures are cheap.
# The trials stay microscopic: SUMO's mesoscopic model (--mesosim, --meso-junction-control)
# ran the 2000-junction synthetic hour in 5.7 s against 107 s, but on the Berlin extract it
# passed x 0.864 of the arterial's demand, where the microscopic VSR hour jams at t = 1110 s
# (the microscopic calibration ends at x 0.311), so it cannot stand in for the runs it calibrates.
# The rule's numbers live in couplers.net.gridlock (a run line judges a run by the same rule).
CALIB_WARMUP_S = jam.WARMUP_S
CALIB_WINDOW = jam.WINDOW  # checks (30 s apart) averaged for the halting share
CALIB_HALTING_SHARE = jam.HALTING_SHARE
CALIB_BACKLOG = jam.BACKLOG
CALIB_BACKLOG_MIN = jam.BACKLOG_MIN
CALIB_TELEPORTS = jam.TELEPORTS
CALIB_TELEPORTS_MIN = jam.TELEPORTS_MIN
CALIB_FACTOR = 0.6
CALIB_MAX_TRIALS = 8


# --------------------------------------------------------------------------
# Demand
# --------------------------------------------------------------------------

def falling_profile_bins(start_vph: float, end_vph: float, duration_s: float) -> list[float]:
    """Vehicles per 5-min bin of a demand linear in time from ``start_vph`` to ``end_vph`` (bin midpoints)."""
    nbins = max(1, int(round(duration_s / BIN_S)))
    out = []
    for b in range(nbins):
        tmid = (b + 0.5) * BIN_S
        rate = start_vph + (end_vph - start_vph) * min(tmid / duration_s, 1.0)
        out.append(rate * BIN_S / 3600.0)
    return out


def route_problems(net, routes_path: Path, limit: int = 20,
                   named: dict[str, list[str]] | None = None) -> tuple[list[str], int]:
    """Problems of a route file (plain or gzipped) against a net (unknown edges, disconnected routes,
    unroutable trips). ``named``: the named routes of route files loaded before this one (SUMO's ids are
    shared by all route files of a run); this file's are added to it.

    Returns (problems, number of vehicles/flows/trips checked).
    """
    from couplers.net.importer.sumocfg import _open  # noqa: PLC0415

    problems: list[str] = []
    try:
        with _open(routes_path) as fh:
            root = ET.parse(fh).getroot()
    except FileNotFoundError:
        return [f"{routes_path}: file not found"], 0
    except (ET.ParseError, EOFError, OSError) as exc:
        return [f"{routes_path}: not valid XML ({exc})"], 0
    if root.tag in ("configuration", "sumoConfiguration"):
        return [f"{routes_path}: a SUMO configuration, not a route file: import it with --sumocfg"], 0
    named = {} if named is None else named
    for r in root.findall("route"):
        named[r.get("id", "")] = r.get("edges", "").split()
    for dist in root.findall("routeDistribution"):  # a vehicle's route="dist": checked on its first route
        inner = [r.get("edges", "").split() for r in dist.findall("route") if r.get("edges")]
        if inner:
            named[dist.get("id", "")] = inner[0]
    checked_routes: dict[tuple[str, ...], str | None] = {}
    checked_pairs: dict[tuple[str, str], bool] = {}

    def route_problem(edges: list[str]) -> str | None:
        key = tuple(edges)
        if key in checked_routes:
            return checked_routes[key]
        msg = None
        if not edges:
            msg = "empty route"
        for e in edges:
            if not net.hasEdge(e):
                msg = f"edge {e!r} is not in the net"
                break
        else:
            for a, b in zip(edges, edges[1:]):
                if net.getEdge(b) not in net.getEdge(a).getOutgoing():
                    msg = f"edges {a!r} -> {b!r} are not connected"
                    break
        checked_routes[key] = msg
        return msg

    n = 0
    for el in root:
        if el.tag not in ("vehicle", "flow", "trip"):
            continue
        n += 1
        vid = el.get("id", f"#{n}")
        rid = el.get("route")
        inner = el.find("route")
        if inner is not None:
            msg = route_problem(inner.get("edges", "").split())
        elif rid is not None:
            msg = f"route {rid!r} is not defined" if rid not in named else route_problem(named[rid])
        elif el.get("from") and el.get("to"):
            a, b = el.get("from"), el.get("to")
            if not (net.hasEdge(a) and net.hasEdge(b)):
                msg = f"edge {a if not net.hasEdge(a) else b!r} is not in the net"
            else:
                if (a, b) not in checked_pairs:
                    path, _ = net.getShortestPath(net.getEdge(a), net.getEdge(b), vClass="passenger")
                    checked_pairs[(a, b)] = path is not None
                msg = None if checked_pairs[(a, b)] else f"no path from {a!r} to {b!r} for passenger cars"
        else:
            msg = "no route (neither route, <route> nor from/to)"
        if msg:
            problems.append(f"{routes_path.name}: {el.tag} {vid!r}: {msg}")
            if len(problems) >= limit:
                problems.append(f"{routes_path.name}: ... (stopped after {limit} problems)")
                break
    if n == 0:
        problems.append(f"{routes_path.name}: no vehicles, flows or trips")
    return problems, n


def _random_routes(opts: ImportOptions, net, net_path: Path, work: Path) -> list[list[str]]:
    """A pool of routable passenger-car routes: randomTrips (seeded) with its duarouter validation.

    randomTrips draws trips (fringe factor, minimum distance), routes them with
    duarouter (fastest path, deterministic) and keeps only routable ones, drawing
    more until the pool is full.
    """
    tool = _sumo_home() / "tools" / "randomTrips.py"
    xs, ys = zip(*[n.getCoord() for n in net.getNodes()])
    diag = math.hypot(max(xs) - min(xs), max(ys) - min(ys))
    min_dist = round(min(300.0, 0.25 * diag), 1)
    trips, routed = work / ".trips.xml", work / ".routes.xml"
    period = opts.duration_s / opts.route_pool
    _run([sys.executable, str(tool), "-n", net_path.name, "-o", trips.name, "--seed", str(opts.seed),
          "-b", "0", "-e", repr(opts.duration_s), "--period", repr(period),
          "--fringe-factor", repr(opts.fringe_factor), "--min-distance", repr(min_dist),
          "--vehicle-class", "passenger", "--vclass", "passenger", "--remove-loops",
          "--validate", "-r", routed.name],
         work, opts.source, "randomTrips.py")
    pool = []
    for veh in ET.parse(routed).getroot().iter("vehicle"):
        r = veh.find("route")
        if r is not None and r.get("edges"):
            pool.append(r.get("edges").split())
    for leftover in work.glob(".*.xml"):
        if leftover.name.startswith((".trips", ".routes")):
            leftover.unlink()
    return pool


def _demand_text(opts: ImportOptions, pool: list[list[str]], counts: list[int], note: list[str]) -> str:
    """demand.rou.xml: vehicles per bin evenly spaced, each drawing a route from the pool (seeded)."""
    rng = np.random.default_rng([opts.seed, 1])
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f"<!-- generated by coloc net import (seed {opts.seed}) from {opts.source.name}."]
    lines += [f"     {x}" for x in note]
    lines += [f"     Vehicles per {int(BIN_S)} s bin, evenly spaced departures: {counts}.",
              f"     Routes: {len(pool)} randomTrips trips (fringe factor {_fmt(opts.fringe_factor)}) routed by "
              "duarouter; each vehicle draws one at random (seeded). -->",
              "<routes>",
              "    " + "<vType " + " ".join(f'{k}="{v}"' for k, v in VTYPE.items()) + "/>"]
    choice = rng.integers(0, len(pool), size=sum(counts))
    for i in sorted(set(int(i) for i in choice)):
        lines.append(f'    <route id="r{i}" edges="{" ".join(pool[i])}"/>')
    k = 0
    for b, n in enumerate(counts):
        for j in range(n):
            depart = b * BIN_S + (j + 0.5) * BIN_S / n
            lines.append(f'    <vehicle id="v{k}" type="car" route="r{int(choice[k])}" depart="{depart:.2f}" '
                         'departLane="best" departSpeed="max" departPos="base"/>')
            k += 1
    lines.append("</routes>")
    return "\n".join(lines) + "\n"


def gridlock_trial(net_path: Path, routes_path: Path, tls_off: bool, seed: int, end: float,
                   vehicles: int, begin: float = 0.0, extra_routes: tuple = (), additional: tuple = ()) -> dict:
    """Run the demand with libsumo (the options of ``coloc run``) until ``end``; stop at the first sign of gridlock.

    Gridlock signs, checked every 30 simulated seconds: teleports (vehicles stuck for
    SUMO's 300 s) of more than CALIB_TELEPORTS of the ``vehicles`` due before ``end``
    (a few happen at odd junctions of real nets at any demand), more than CALIB_HALTING_SHARE of the
    vehicles in the net halting over the last CALIB_WINDOW checks after the first CALIB_WARMUP_S, or an insertion backlog above CALIB_BACKLOG of
    the vehicles departed (entries blocked). ``begin``, ``extra_routes``, ``additional``: a user's scenario's
    clock (the warm-up counts from ``begin``), further route files and signal programs, as its runs load them.
    """
    from couplers.traffic.sumo import SumoOptions, libsumo  # noqa: PLC0415

    options = SumoOptions(net=net_path, routes=routes_path, seed=seed, end=end, tls_off=tls_off, begin=begin,
                          extra_routes=tuple(extra_routes), additional=tuple(additional))
    libsumo.start(options.command())
    sim = libsumo.simulation
    try:
        edges = [e for e in libsumo.edge.getIDList() if not e.startswith(":")]
        every = max(1, int(round(30.0 / options.step_length)))
        teleports = departed = steps = 0
        window: list[tuple[int, int]] = []  # (halting, vehicles) at the last checks
        worst_share, worst_backlog, verdict = 0.0, 0, ""
        while sim.getTime() < end - 1e-9:
            libsumo.simulationStep()
            steps += 1
            teleports += sim.getStartingTeleportNumber()
            departed += sim.getDepartedNumber()
            t = sim.getTime()
            if teleports > max(CALIB_TELEPORTS_MIN, CALIB_TELEPORTS * vehicles):
                verdict = f"{teleports} teleports by t = {t:.0f} s"
                break
            if steps % every:
                continue
            n = libsumo.vehicle.getIDCount()
            halting = sum(libsumo.edge.getLastStepHaltingNumber(e) for e in edges)
            window.append((halting, n))
            del window[:-CALIB_WINDOW]
            share = sum(h for h, _ in window) / max(1, sum(m for _, m in window))
            backlog = len(sim.getPendingVehicles())
            if t - begin >= CALIB_WARMUP_S:
                worst_share = max(worst_share, share)
            worst_backlog = max(worst_backlog, backlog)
            if t - begin >= CALIB_WARMUP_S and share > CALIB_HALTING_SHARE:
                verdict = f"{share:.0%} of {n} vehicles halting over the {CALIB_WINDOW * 30 // 60} min to t = {t:.0f} s"
                break
            if backlog > max(CALIB_BACKLOG_MIN, CALIB_BACKLOG * departed):
                verdict = f"{backlog} vehicles waiting to enter at t = {t:.0f} s"
                break
        return {"ok": not verdict, "verdict": verdict or f"no gridlock ({teleports} teleports)",
                "teleports": teleports, "simulated_s": round(sim.getTime(), 2),
                "max_halting_share": round(worst_share, 3), "max_backlog": worst_backlog}
    finally:
        libsumo.close()


def _gridlock_trial_job(args: tuple) -> dict:
    return gridlock_trial(*args)


def gridlock_trials_vsr_tlr(net_path: Path, routes_path: Path, seed: int, end: float, vehicles: int,
                            *more) -> dict:
    """The VSR and the TLR gridlock trial of one demand, side by side in two processes (libsumo is one
    simulation per process).

    Recorded as if run one after the other: VSR first; a VSR failure ends the trial (the TLR process is
    stopped and not recorded), otherwise the TLR result is added. So the record, and the files written
    from it, do not depend on which process finishes first.
    """
    import multiprocessing  # noqa: PLC0415
    import threading  # noqa: PLC0415

    jobs = {"vsr": (net_path, routes_path, True, seed, end, vehicles, *more),
            "tlr": (net_path, routes_path, False, seed, end, vehicles, *more)}
    # "fork": the children need nothing re-imported (spawn would re-run a caller's unguarded
    # script); libsumo is only started inside them. Without fork, one after the other; likewise in a
    # process that runs other threads (an embedding program, a test session with a Dask or tqdm thread):
    # a fork copies the locks those threads hold, and a pool worker then waits on them forever.
    if "fork" not in multiprocessing.get_all_start_methods() or threading.active_count() > 1:
        out = {"vsr": gridlock_trial(*jobs["vsr"])}
        if out["vsr"]["ok"]:
            out["tlr"] = gridlock_trial(*jobs["tlr"])
        return out
    with multiprocessing.get_context("fork").Pool(2) as pool:
        pending = {c: pool.apply_async(_gridlock_trial_job, (a,)) for c, a in jobs.items()}
        out = {"vsr": pending["vsr"].get()}
        if out["vsr"]["ok"]:
            out["tlr"] = pending["tlr"].get()
        pool.terminate()
    return out


def _write_demand(opts: ImportOptions, net, net_path: Path, work: Path, lane_km: float, report: _Report) -> None:
    t0 = time.perf_counter()
    pool = _random_routes(opts, net, net_path, work)
    t_pool = time.perf_counter() - t0
    if not pool:
        raise InputError(opts.source, None, "randomTrips/duarouter found no route for passenger cars between "
                                            "distinct edges: is the road network connected?")
    bad, _ = route_problems_for_pool(net, pool)
    if bad:
        raise InputError(opts.source, None, f"internal check: duarouter returned an unusable route ({bad})")
    lengths = np.array([sum(net.getEdge(e).getLength() for e in r) for r in pool])
    mean_len = float(lengths.mean())
    density_scale = (lane_km / ARTERIAL_LANE_KM) * (ARTERIAL_MEAN_ROUTE_M / mean_len)
    capped = min(density_scale, opts.max_density_scale)
    scale = opts.demand_scale * capped
    if capped < density_scale:
        report.not_derived.append(
            f"the full density-matched demand (x {density_scale:.2f} the arterial's): capped at x "
            f"{opts.max_density_scale:g} so that runs stay tractable (--max-density-scale)")
    path = work / "demand.rou.xml"
    trials: list[dict] = []

    def counts_for(sc: float) -> list[int]:
        bins = falling_profile_bins(opts.demand_start_vph * sc, opts.demand_end_vph * sc, opts.duration_s)
        return [int(round(b)) for b in bins]

    def note_for(sc: float) -> list[str]:
        return [f"Falling profile: {_fmt(opts.demand_start_vph)} -> {_fmt(opts.demand_end_vph)} veh/h on the arterial, "
                f"linear, times {sc:.4f} for this net:",
                f"density match {density_scale:.4f} (lane-km {lane_km:.2f} / {ARTERIAL_LANE_KM}, "
                f"mean route {ARTERIAL_MEAN_ROUTE_M:.0f} m / {mean_len:.0f} m)"
                + (f", capped at {opts.max_density_scale:g}" if capped < density_scale else "")
                + f", x demand scale {_fmt(opts.demand_scale)}"
                + (f" x {CALIB_FACTOR}^{len(trials) - 1} (gridlock calibration, scenario.toml [derived.demand])"
                   if len(trials) > 1 else "") + "."]

    calibrate = opts.calibrate
    if calibrate:
        from couplers.traffic.sumo import libsumo  # noqa: PLC0415

        if libsumo is None:
            calibrate = False
            report.not_derived.append("demand calibration against gridlock: libsumo is not installed")
    while True:
        counts = counts_for(scale)
        if not sum(counts):  # a folder without vehicles is refused by `coloc net check`: say why here instead
            raise InputError(None, "--demand/--demand-scale/--duration",
                             f"the generated demand has no vehicle ({_fmt(opts.demand_start_vph)} -> "
                             f"{_fmt(opts.demand_end_vph)} veh/h x {scale:.4g} over {_fmt(opts.duration_s)} s rounds "
                             "to none" + (f" after {len(trials)} gridlock trial(s)" if trials else "")
                             + "): raise them")
        path.write_text(_demand_text(opts, pool, counts, note_for(scale)))
        if not calibrate:
            break
        end = min(opts.calibration_s or opts.duration_s, opts.duration_s)
        trial = {"scale": round(scale, 4)}
        due = int(sum(n for b, n in enumerate(counts) if b * BIN_S < end))
        trial.update(gridlock_trials_vsr_tlr(work / "tlr.net.xml", path, opts.seed, end, due))
        trials.append(trial)
        if all(trial.get(c, {}).get("ok") for c in ("vsr", "tlr")):
            break
        if len(trials) >= CALIB_MAX_TRIALS:
            cause = ("the signal programs are implausible (see above): import with --rebuild-signals"
                     if report.derived.get("implausible_signal_programs") else "lower --demand-scale")
            report.not_derived.append(f"a gridlock-free demand: still gridlocked after {len(trials)} trials "
                                      f"(last scale {scale:.4f}); {cause}")
            break
        scale *= CALIB_FACTOR
    # the comment names the number of trials: rewrite once they are known
    path.write_text(_demand_text(opts, pool, counts, note_for(scale)))
    peak = counts[0] * 3600.0 / BIN_S if counts else 0.0
    report.derived["demand"] = {
        "profile_veh_per_h": [opts.demand_start_vph, opts.demand_end_vph],
        "scale": round(scale, 4), "density_scale": round(density_scale, 4),
        "max_density_scale": opts.max_density_scale, "demand_scale": opts.demand_scale,
        "lane_km": round(lane_km, 2), "mean_route_m": round(mean_len, 1), "route_pool": len(pool),
        "vehicles": int(sum(counts)), "vehicles_per_bin": counts, "fringe_factor": opts.fringe_factor,
    }
    if trials:
        report.derived["demand_calibration"] = {
            "rule": (f"first {_fmt(min(opts.calibration_s or opts.duration_s, opts.duration_s))} s under VSR then "
                     "TLR: teleports at most "
                     f"{CALIB_TELEPORTS:.0%} of the vehicles (min {CALIB_TELEPORTS_MIN}), at most "
                     f"{CALIB_HALTING_SHARE:.0%} of vehicles halting after {_fmt(CALIB_WARMUP_S)} s, insertion backlog "
                     f"at most {CALIB_BACKLOG:.0%} of departures; else scale x {CALIB_FACTOR}"),
            "trials": [f"scale {t['scale']}: " + "; ".join(f"{c} {t[c]['verdict']}" for c in ("vsr", "tlr") if c in t)
                       for t in trials],
        }
    t_all = time.perf_counter() - t0
    calib = (f", calibrated in {len(trials)} trial(s)" if trials else "")
    report.lines.append(f"demand: {sum(counts)} vehicles over {_fmt(opts.duration_s)} s, "
                        f"{peak:.0f} -> {counts[-1] * 3600.0 / BIN_S:.0f} veh/h (arterial profile x {scale:.2f}: "
                        f"density match x {density_scale:.2f}{calib}), {len(pool)} routable routes; "
                        f"routes {t_pool:.1f} s, calibration {t_all - t_pool:.1f} s")
    for t in trials:
        report.lines.append("  gridlock trial, scale " + str(t["scale"]) + ": "
                            + "; ".join(f"{c.upper()} {t[c]['verdict']}" for c in ("vsr", "tlr") if c in t))


def route_problems_for_pool(net, pool: list[list[str]]) -> tuple[str | None, int]:
    for r in pool:
        for a, b in zip(r, r[1:]):
            if net.getEdge(b) not in net.getEdge(a).getOutgoing():
                return f"{a} -> {b} not connected", 0
    return None, len(pool)


def routes_problems(net, paths, limit: int = 20) -> tuple[list[str], int]:
    """:func:`route_problems` of several route files loaded together (named routes shared, in order)."""
    problems: list[str] = []
    named: dict[str, list[str]] = {}
    total = 0
    for path in paths:
        more, n = route_problems(net, Path(path), limit, named)
        problems += more
        total += n
    return problems, total


def folder_route_names(paths) -> list[str]:
    """The names of the user's route files in the net folder: one plain file is ``demand.rou.xml`` (as
    always); several, or a gzipped one, ``demand_1.rou.xml[.gz]``, ... in the order SUMO loads them."""
    from couplers.net.importer.sumocfg import is_gzip  # noqa: PLC0415

    paths = [Path(p) for p in paths]
    if len(paths) == 1 and not is_gzip(paths[0]):
        return ["demand.rou.xml"]
    return [f"demand_{i}.rou.xml" + (".gz" if is_gzip(p) else "") for i, p in enumerate(paths, 1)]


def _user_routes(opts: ImportOptions, net, work: Path, report: _Report) -> list[str]:
    """Check and copy the user's route files (byte for byte) into the folder; returns their names there."""
    from couplers.net.importer.sumocfg import (  # noqa: PLC0415
        clock,
        demand_departures,
        first_unsorted,
        sorted_routes_text,
    )

    srcs = list(opts.route_files)
    unsorted = {}
    for src in srcs:
        why = first_unsorted(src)
        if why is not None and not opts.sort_routes:
            raise InputError(src, "depart", f"not sorted by departure: {why} (pass --sort-routes to import a copy "
                                            "sorted by departure)")
        if why is not None:
            unsorted[src] = why
    per_file = []
    named: dict[str, list[str]] = {}
    for src in srcs:
        problems, n = route_problems(net, src, named=named)
        if problems:
            first = problems[0].split(": ", 1)[1] if ": " in problems[0] else problems[0]
            more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
            raise InputError(src, None, first + more)
        per_file.append(n)
    names = folder_route_names(srcs)
    for src, name in zip(srcs, names):
        if src in unsorted:
            text, moved = sorted_routes_text(src)
            data = text.encode("utf-8")
            if name.endswith(".gz"):
                import gzip  # noqa: PLC0415

                data = gzip.compress(data, mtime=0)  # mtime 0: the same input gives the same bytes
            (work / name).write_bytes(data)
            report.derived.setdefault("routes_sorted", {})[name] = (f"{src.name} sorted by departure (--sort-routes): "
                                                                    f"{moved} elements moved; was: {unsorted[src]}")
            report.lines.append(f"  {src.name}: not sorted by departure; the folder's {name} holds it sorted "
                                f"({moved} vehicles/trips/flows moved, --sort-routes)")
        else:
            shutil.copyfile(src, work / name)
    n = sum(per_file)
    label = srcs[0].name if len(srcs) == 1 else ", ".join(s.name for s in srcs)
    report.derived["demand"] = {"source": label, "vehicles_flows_trips": n}
    if len(srcs) > 1:
        report.derived["demand"]["files"] = {name: src.name for src, name in zip(srcs, names)}
    report.not_derived.append("demand from the falling profile: the user's route file"
                              + ("s are" if len(srcs) > 1 else " is") + " used as given")
    report.lines.append(f"demand: user's route file{'s' if len(srcs) > 1 else ''} {label} ({n} vehicles/flows/trips, "
                        "all routable)")
    begin = opts.begin_s
    if begin is not None:
        dep = demand_departures(srcs)
        if dep.last is not None and begin > dep.last:
            raise InputError(opts.sumocfg or srcs[0], "begin",
                             f"{begin:g} s ({clock(begin)}) is after the last departure of the demand "
                             f"({dep.last:g} s, {clock(dep.last)}): nothing would drive")
        nv, nf = dep.before(begin)
        report.derived["demand"].update(
            first_departure_s=dep.first, last_departure_s=dep.last,
            before_begin={"vehicles_trips": nv, "flows": nf,
                          "handled": "dropped by SUMO when it loads the routes (depart < begin), as with the "
                                     "scenario's own configuration; the folder keeps the files as given"})
        if dep.first is not None:
            report.lines.append(f"  departures {dep.first:g} s ({clock(dep.first)}) to {dep.last:g} s "
                                f"({clock(dep.last)}); begin {begin:g} s ({clock(begin)})")
        if nv or nf:
            report.lines.append(f"  before begin: {dep.describe_before(begin)}")
    return names


def user_demand_trial(opts: ImportOptions, work: Path, names: list[str], report: _Report) -> None:
    """The gridlock trial of the user's demand under VSR and TLR (the rule of :func:`gridlock_trial`), from
    the scenario's begin over ``calibration_s`` (default: ``duration_s``, what a run simulates by default),
    reported in the output lines and ``[derived.demand_gridlock_trial]``. A user's demand is never rescaled:
    it is the researcher's scenario; a jammed demand is reported (and its runs flagged by the run line).
    ``--no-calibrate`` skips the trial."""
    from couplers.net.importer.sumocfg import demand_departures  # noqa: PLC0415
    from couplers.traffic.sumo import libsumo  # noqa: PLC0415

    if not opts.calibrate:
        report.not_derived.append("gridlock trial of the user's demand: skipped (--no-calibrate)")
        return
    if libsumo is None:
        report.not_derived.append("gridlock trial of the user's demand: libsumo is not installed")
        return
    begin = opts.begin_s or 0.0
    span = min(opts.calibration_s or opts.duration_s, opts.duration_s)
    end = begin + span if opts.end_s is None else min(begin + span, opts.end_s)
    dep = demand_departures([work / n for n in names])
    due = dep.before(end)[0] - dep.before(begin)[0]
    paths = [work / n for n in names]
    additional = (work / "signals.add.xml",) if (work / "signals.add.xml").is_file() else ()
    out = gridlock_trials_vsr_tlr(work / "tlr.net.xml", paths[0], opts.seed, end, due, begin, tuple(paths[1:]),
                                  additional)
    ok = all(out.get(c, {}).get("ok") for c in ("vsr", "tlr"))
    verdicts = "; ".join(f"{c.upper()} {out[c]['verdict']}" for c in ("vsr", "tlr") if c in out)
    report.derived["demand_gridlock_trial"] = {
        "rule": f"{_fmt(begin)} s to {_fmt(end)} s under VSR then TLR: {jam.rule_text()}",
        "ok": ok, "rescaled": False,
        **{c: {k: out[c][k] for k in ("verdict", "teleports", "simulated_s", "max_halting_share", "max_backlog")}
           for c in ("vsr", "tlr") if c in out},
    }
    report.lines.append(f"  gridlock trial of the demand ({_fmt(end - begin)} s from begin): {verdicts}; "
                        + ("no gridlock" if ok else "JAMMED") + " (a user's demand is never rescaled)")
    if not ok:
        report.not_derived.append(f"a gridlock-free demand: the user's demand jams in the trial ({verdicts}); it "
                                  "is kept as given, and runs of it are flagged JAMMED in their run line")
