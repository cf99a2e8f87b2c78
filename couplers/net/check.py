"""``coloc net check DIR``: validate a net folder, one line per problem.

Checks: scenario.toml and the files it names load (:func:`load_net_folder`);
the net parses and has edges open to passenger cars and traffic lights (else
TLR and VSR are the same); the GNSS zones and the analysis areas are in net
x/y (a folder never holds lon/lat: ``coloc net import`` converts it) and cover
every lane shape point of the net; every feature lies within a given distance of a
drivable lane; the optional ``buildings.geojson`` covers no lane shape point of a drivable
lane and holds no feature (a feature inside a building could never be seen); every
vehicle, flow or trip of the demand has a route whose edges exist in the net and follow
each other; the folder's ``[sumo] begin`` (its clock, :class:`couplers.net.folder.SumoClock`) is not after the
demand's last departure (vehicles departing before it are counted: SUMO drops them).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import LineString

from couplers.errors import InputError
from couplers.net.folder import lane_shape_points, load_net_folder
from couplers.net.importer.demand import routes_problems


def check_net_folder(root: Path, max_feature_distance_m: float = 30.0) -> tuple[list[str], str]:
    """(problems, one-line description of what was checked); no problems means the folder is usable."""
    import sumolib  # noqa: PLC0415

    root = Path(root)
    try:
        folder = load_net_folder(root)
    except InputError as exc:
        return [exc.describe()], ""
    problems: list[str] = []
    net_name = folder.net.name
    try:
        net = sumolib.net.readNet(str(folder.net))
    except Exception as exc:  # noqa: BLE001 - sumolib raises several types
        return [f"{folder.net}: the net does not parse ({exc})"], ""
    drivable = [e for e in net.getEdges(withInternal=False) if e.getFunction() == "" and e.allows("passenger")]
    if not drivable:
        problems.append(f"{folder.net}: no edge open to passenger cars")
    if not net.getTrafficLights() and any(not off for off in folder.tls_off.values()):
        problems.append(f"{folder.net}: no traffic lights: TLR and VSR are the same "
                        "(re-import with --guess-signals)")

    try:
        xy, owners = lane_shape_points(folder.net)
    except InputError as exc:
        problems.append(exc.describe())
        xy, owners = np.empty((0, 2)), []
    files = folder.scenario["files"]
    for regions, key in ((folder.zones, "zones"), (folder.areas, "areas")):
        if not len(xy):
            break
        union = shapely.union_all([r.polygon for r in regions])
        inside = shapely.intersects_xy(union, xy[:, 0], xy[:, 1])
        if not inside.all():
            bad = np.flatnonzero(~inside)
            i = int(bad[0])
            problems.append(f"{root / files[key]}: leaves {bad.size} of {len(inside)} lane shape points of "
                            f"{net_name} uncovered (first: lane {owners[i]} at x={xy[i, 0]:.1f}, y={xy[i, 1]:.1f})")

    feats = folder.features
    if len(feats.ids) == 0:
        problems.append(f"{root / files['features']}: no features (POIs)")
    elif drivable:
        lines = [LineString(l.getShape()) for e in drivable for l in e.getLanes()]
        tree = shapely.STRtree(lines)
        pts = shapely.points(feats.xy)
        _, dist = tree.query_nearest(pts, return_distance=True, all_matches=False)
        # query_nearest returns one match per point in input order when all_matches=False
        far = np.flatnonzero(dist > max_feature_distance_m)
        for i in far[:10]:
            problems.append(f"{root / files['features']}: poi {feats.ids[i]!r} ({feats.kinds[i]}) is "
                            f"{dist[i]:.1f} m from the nearest drivable lane (more than {max_feature_distance_m:g} m)")
        if far.size > 10:
            problems.append(f"{root / files['features']}: ... and {far.size - 10} more features far from roads")

    problems += _building_problems(folder, root, xy, owners, drivable)

    rproblems, n = routes_problems(net, folder.route_files)
    from couplers.net.importer.sumocfg import first_unsorted  # noqa: PLC0415

    for path in folder.route_files:
        try:
            why = first_unsorted(path)
        except InputError as exc:
            why, rproblems = None, rproblems + [exc.describe()]
        if why is not None:
            rproblems.append(f"{path}: depart: not sorted by departure: {why} (sort it, or re-import with "
                             "--sort-routes)")
    problems += [f"{folder.routes.parent / p}" if not p.startswith(str(folder.routes.parent)) else p for p in rproblems]
    clock_info, clock_problem = _clock_check(folder, root)
    if folder.additional:
        from couplers.net.importer.sumocfg import program_problems  # noqa: PLC0415

        problems += program_problems(net, folder.additional)
    problems += clock_problem
    persons = ""
    if folder.persons is not None:
        pproblems, npf = person_problems(net, folder.persons)
        problems += pproblems
        persons = f", {npf} person flows/persons"
    info = (f"{len(net.getNodes())} junctions, {len(drivable)} drivable edges, {len(net.getTrafficLights())} "
            f"traffic lights, {len(feats.ids)} features, {n} vehicles/flows/trips, {len(folder.zones)} zones, "
            f"{len(folder.areas)} areas{persons}")
    if folder.buildings is not None:
        info += f", {len(folder.buildings)} buildings"
    return problems, info + clock_info


def _clock_check(folder, root: Path) -> tuple[str, list[str]]:
    """(info clause, problems) of the folder's begin against the demand's departures; shipped folders
    (begin 0, [sumo] without begin) are not read for it."""
    from couplers.net.importer.sumocfg import clock, demand_departures  # noqa: PLC0415

    begin = folder.clock.begin
    if "begin" not in folder.scenario.get("sumo", {}):
        return "", []
    try:
        dep = demand_departures(folder.route_files)
    except InputError as exc:
        return "", [exc.describe()]
    where = root / "scenario.toml"
    info = f"; begin {begin:g} s ({clock(begin)})"
    if dep.first is None:
        return info, []
    info += f", departures {dep.first:g} s ({clock(dep.first)}) to {dep.last:g} s ({clock(dep.last)})"
    if begin > dep.last:
        return info, [f"{where}: sumo.begin: {begin:g} s ({clock(begin)}) is after the demand's last departure "
                      f"({dep.last:g} s, {clock(dep.last)}): a run from it would have no vehicle"]
    early = dep.describe_before(begin)
    return info + (f"; {early}" if early else ""), []


def _building_problems(folder, root: Path, xy: np.ndarray, owners: list[str], drivable) -> list[str]:
    """Lane shape points of drivable lanes and features that lie inside a building footprint."""
    if folder.buildings is None or len(folder.buildings) == 0:
        return []
    path = root / folder.scenario["files"].get("buildings", "buildings.geojson")
    out = []
    lane_ids = {l.getID() for e in drivable for l in e.getLanes()}
    on_lane = np.fromiter((o in lane_ids for o in owners), dtype=bool, count=len(owners))
    pts = xy[on_lane]
    if len(pts):
        hit_pt, hit_b = folder.buildings.tree.query(shapely.points(pts), predicate="within")
        if hit_pt.size:
            i, b = int(hit_pt[0]), int(hit_b[0])
            lane = np.asarray(owners, dtype=object)[on_lane][i]
            out.append(f"{path}: {np.unique(hit_pt).size} lane shape points of drivable lanes lie inside buildings "
                       f"(first: lane {lane} at x={pts[i, 0]:.1f}, y={pts[i, 1]:.1f}, building features[{b}])")
    feats = folder.features
    if len(feats.ids):
        hit_f, hit_b = folder.buildings.tree.query(shapely.points(feats.xy), predicate="within")
        for i, b in list(zip(hit_f, hit_b))[:10]:
            out.append(f"{path}: poi {feats.ids[i]!r} ({feats.kinds[i]}) lies inside building features[{b}]: "
                       "its sight lines are always blocked")
    return out


def person_problems(net, path: Path) -> tuple[list[str], int]:
    """Walks of a persons file whose edges are missing or closed to pedestrians; (problems, persons)."""
    import xml.etree.ElementTree as ET  # noqa: PLC0415

    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        return [f"{path}: does not parse ({exc})"], 0
    problems, n = [], 0
    for person in root:
        if person.tag not in ("person", "personFlow"):
            continue
        n += 1
        for walk in person.iter("walk"):
            edges = walk.get("edges", "").split() or [walk.get("from"), walk.get("to")]
            for e in edges:
                if e is None or not net.hasEdge(e) or not net.getEdge(e).allows("pedestrian"):
                    problems.append(f"{path}: {person.tag} {person.get('id')!r} walks on edge {e!r}, "
                                    "which is missing or has no sidewalk")
    return problems[:10], n


def require_usable_net_folder(root: Path, max_feature_distance_m: float = 30.0) -> None:
    """Raise :class:`InputError` with the first problem :func:`check_net_folder` finds (``coloc run`` calls
    this before SUMO starts, so a run accepts exactly the folders ``coloc net check`` accepts)."""
    root = Path(root).resolve()
    stamp = tuple((p.name, p.stat().st_mtime_ns, p.stat().st_size) for p in sorted(root.iterdir()) if p.is_file())
    problems = _problems(root, max_feature_distance_m, stamp)
    if problems:
        more = f" (and {len(problems) - 1} more: coloc net check {root})" if len(problems) > 1 else ""
        raise InputError(None, None, problems[0] + more)


@functools.lru_cache(maxsize=8)
def _problems(root: Path, max_feature_distance_m: float, stamp: tuple) -> tuple[str, ...]:
    # ``stamp`` (names, times and sizes of the folder's files) keys the cache: a sweep worker checks a
    # folder once, and again only when a file changed.
    return tuple(check_net_folder(root, max_feature_distance_m)[0])
