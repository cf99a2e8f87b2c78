#!/usr/bin/env python3
"""Generate ``sumo_nets/arterial``: a Turin-like urban arterial (paper Sec. VI).

Deterministic: running it twice writes identical files. It writes the plain
netconvert sources, the netconvert configuration, the demand, zones, areas,
features and scenario description, then builds ``tlr.net.xml`` with
:func:`couplers.net.build.build_net`. The road net itself (geometry, signal
timing, plain sources, netconvert configuration) is ``tools/arterial_net.py``;
this module adds the demand, zones, areas, features, buildings, scenario
description and README.

Design (all coordinates plain Cartesian metres, arterial on y = 0):

* arterial x = 0 .. 2000 m, 2 lanes per direction, 50 km/h, priority 3;
* 3 primary crossings (2 lanes per direction, 50 km/h, priority 2) and
  6 secondary crossings (1 lane per direction, 40 km/h, priority 1), each
  running 250-400 m north and south to fringe nodes;
* 5 signalised junctions (the primaries P1-P3 and secondaries S2, S4), the
  other four are priority junctions with the arterial as major road;
* signal plans: netconvert's default phases re-timed to a 90 s cycle in which
  the arterial gets the longer green (see ``retime_tls``);
* VSR = the same net with all signals switched off at run time.

Usage: ``python tools/make_arterial.py [--out DIR] [--no-build]``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "tools"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from arterial_net import (  # noqa: E402  (tools/make_arterial_ped.py reads these as make_arterial.X)
    ARTERIAL_LENGTH,
    ARTERIAL_NODES,
    CLASSES,
    CROSSINGS,
    LANE_WIDTH,
    TLS_ALLRED,
    TLS_ARTERIAL_SHARE,
    TLS_CYCLE,
    TLS_OFFSET_FRACTIONS,
    TLS_YELLOW,
    arterial_edge,
    crossing,
    fmt,
    retime_tls,
    write_connections,
    write_edges,
    write_netccfg,
    write_nodes,
)
from couplers.net.build import NET_NAME, build_net  # noqa: E402
from couplers.net.folder import NET_CRS as CRS  # noqa: E402

# --------------------------------------------------------------------------
# Demand (veh/h at t = 0 and t = 3600 s; linear in between, per 5-min bin)
# --------------------------------------------------------------------------
DURATION = 3600.0
BIN = 300.0
TOTAL_START = 2800.0
TOTAL_END = 1800.0
# share of total demand per flow group (sum = 1)
SHARE_ARTERIAL = 0.60  # W<->E through traffic (both directions)
SHARE_PRIMARY_THROUGH = 0.14  # N<->S on the three primaries
SHARE_PRIMARY_TURN = 0.16  # arterial <-> primary turning traffic
SHARE_SECONDARY = 0.10  # everything touching a secondary road

VTYPE = {
    "id": "car",
    "vClass": "passenger",
    "carFollowModel": "Krauss",
    "accel": "2.6",
    "decel": "4.5",
    "emergencyDecel": "9",
    "sigma": "0.5",
    "tau": "1.0",
    "length": "4.5",
    "minGap": "2.5",
    "maxSpeed": "15",
    "speedFactor": "normc(1.0,0.1,0.8,1.2)",
    "jmTimegapMinor": "1.5",
    "impatience": "0.5",
    "color": "1,1,0",
}

# --------------------------------------------------------------------------
# Zones and areas: vertical strips across the whole net (x boundaries)
# --------------------------------------------------------------------------
MARGIN = 60.0
ZONE_STRIPS = [  # (zone, x_hi) in west-to-east order; last x_hi = +inf
    ("A", 300.0),
    ("B", 850.0),
    ("C", 1550.0),
    ("B", 1750.0),
    ("A", math.inf),
]
ZONE_PARAMS = {"A": (3.0, 0.1), "B": (8.0, 0.17), "C": (15.0, 0.45)}
AREA_STRIPS = [  # (area, x_hi)
    ("1", 300.0),
    ("2", 575.0),
    ("3", 850.0),
    ("4", 1250.0),
    ("5", 1750.0),
    ("6", math.inf),
]


# --------------------------------------------------------------------------
# Demand
# --------------------------------------------------------------------------

def node_index(end) -> int:
    """Index in ARTERIAL_NODES of an origin/destination ("W", "E" or (crossing, 'n'|'s'))."""
    if end == "W":
        return 0
    if end == "E":
        return len(ARTERIAL_NODES) - 1
    return ARTERIAL_NODES.index(f"J{end[0]}")


def end_id(end) -> str:
    return end if isinstance(end, str) else f"{end[0]}{end[1]}"


def route_edges(orig, dest) -> list[str]:
    p, q = node_index(orig), node_index(dest)
    edges = [] if isinstance(orig, str) else [f"{orig[0]}{orig[1]}_in"]
    if p < q:
        edges += [arterial_edge(i, True) for i in range(p, q)]
    elif p > q:
        edges += [arterial_edge(i, False) for i in range(p - 1, q - 1, -1)]
    if not isinstance(dest, str):
        edges.append(f"{dest[0]}{dest[1]}_out")
    return edges


def demand_groups() -> list[tuple[object, object, float]]:
    """(origin, destination, share of total demand); shares sum to 1."""
    groups: list[tuple[object, object, float]] = []
    groups += [("W", "E", SHARE_ARTERIAL / 2), ("E", "W", SHARE_ARTERIAL / 2)]
    prim = [c[0] for c in CROSSINGS if c[2] == "primary"]
    sec = [c for c in CROSSINGS if c[2] == "secondary"]
    for p in prim:
        groups += [((p, "n"), (p, "s"), SHARE_PRIMARY_THROUGH / (2 * len(prim))),
                   ((p, "s"), (p, "n"), SHARE_PRIMARY_THROUGH / (2 * len(prim)))]
    turns = []
    for p in prim:
        for side in ("n", "s"):
            for a in ("W", "E"):
                turns += [(a, (p, side)), ((p, side), a)]
    groups += [(o, d, SHARE_PRIMARY_TURN / len(turns)) for o, d in turns]
    # secondary roads: crossing + turning; signalised secondaries weigh 2x
    sec_flows = []
    for name, x, cls, tls, ln, ls in sec:
        w = 2.0 if tls else 1.0
        sec_flows += [((name, "n"), (name, "s"), w), ((name, "s"), (name, "n"), w)]
        for side in ("n", "s"):
            for a in ("W", "E"):
                sec_flows += [(a, (name, side), w), ((name, side), a, w)]
    wsum = sum(w for _, _, w in sec_flows)
    groups += [(o, d, SHARE_SECONDARY * w / wsum) for o, d, w in sec_flows]
    assert abs(sum(g[2] for g in groups) - 1.0) < 1e-9
    return groups


def total_rate(t_mid: float) -> float:
    """Total demand (veh/h) at time t (linear TOTAL_START -> TOTAL_END)."""
    return TOTAL_START + (TOTAL_END - TOTAL_START) * t_mid / DURATION


def write_demand(out: Path) -> dict:
    groups = demand_groups()
    n_bins = int(DURATION // BIN)
    golden = (math.sqrt(5) - 1) / 2
    flows = []
    routes = []
    totals = [0] * n_bins
    for r, (o, d, share) in enumerate(groups):
        rid = f"{end_id(o)}_{end_id(d)}"
        routes.append((rid, route_edges(o, d)))
        phase = (r * golden) % 1.0  # deterministic per-route arrival phase
        cum = 0.0  # expected vehicles before the bin
        for b in range(n_bins):
            t0, t1 = b * BIN, (b + 1) * BIN
            rate = share * total_rate((t0 + t1) / 2)  # veh/h in this bin
            expected = rate * BIN / 3600.0
            # vehicle n departs when the cumulative expectation reaches n + phase
            first = math.ceil(cum - phase - 1e-9)
            last = math.ceil(cum + expected - phase - 1e-9) - 1
            number = last - first + 1
            if number > 0:
                period = 3600.0 / rate
                begin = t0 + (first + phase - cum) * period
                begin = round(begin, 2)
                period = round(period, 2)
                # keep all departures inside the bin despite rounding
                while begin + (number - 1) * period >= t1:
                    period = round(period - 0.01, 2)
                flows.append((begin, f"{rid}.{b:02d}", rid, period, number, rate))
                totals[b] += number
            cum += expected
    flows.sort(key=lambda f: (f[0], f[1]))
    vt = " ".join(f'{k}="{v}"' for k, v in VTYPE.items())
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        "<!-- generated by tools/make_arterial.py.",
        f"     One hour (0-{fmt(DURATION)} s). Total demand falls linearly from {fmt(TOTAL_START)} to "
        f"{fmt(TOTAL_END)} veh/h (paper Fig. 13),",
        f"     one <flow> per route and {fmt(BIN)} s bin with evenly spaced departures: number vehicles at",
        "     begin + k * (end - begin) / number, k = 0 .. number-1 (end - begin = number * period);",
        "     each route has a fixed arrival phase so flows do not all depart together. Runs are",
        "     reproducible with sumo's seed (driver imperfection sigma, speed factors).",
        f"     Shares: arterial through {SHARE_ARTERIAL:.0%}, primary through {SHARE_PRIMARY_THROUGH:.0%}, "
        f"arterial<->primary turns {SHARE_PRIMARY_TURN:.0%},",
        f"     secondary roads {SHARE_SECONDARY:.0%}. Vehicles per bin: {totals} -->",
        "<routes>",
        "    <!-- Passenger car, Krauss car following:",
        "         accel 2.6 m/s2, decel 4.5 m/s2, emergencyDecel 9 m/s2, sigma 0.5 (driver imperfection),",
        "         tau 1.0 s (desired time headway), length 4.5 m, minGap 2.5 m, maxSpeed 15 m/s,",
        "         speedFactor normal(1.0, 0.1) clipped to [0.8, 1.2] (speed limit 13.89 m/s -> at most 15 m/s).",
        f"         Junction model: jmTimegapMinor {VTYPE['jmTimegapMinor']} s (minimum time gap a minor-road",
        f"         vehicle accepts in front of a priority vehicle), impatience {VTYPE['impatience']} (after waiting,",
        "         drivers increasingly force priority vehicles to brake; avoids deadlock under VSR). -->",
        f"    <vType {vt}/>",
    ]
    for rid, edges in routes:
        lines.append(f'    <route id="{rid}" edges="{" ".join(edges)}"/>')
    for begin, fid, rid, period, number, rate in flows:
        lines.append(
            f'    <flow id="{fid}" type="car" route="{rid}" begin="{fmt(begin)}" end="{fmt(begin + number * period)}" '
            f'number="{number}" departLane="best" departSpeed="max" departPos="base"/>')
    lines.append("</routes>")
    (out / "demand.rou.xml").write_text("\n".join(lines) + "\n")
    return {"routes": len(routes), "flows": len(flows), "vehicles_per_bin": totals,
            "vehicles": sum(totals)}


# --------------------------------------------------------------------------
# Zones, areas, features
# --------------------------------------------------------------------------

def net_bbox() -> tuple[float, float, float, float]:
    """Bounding box of all nodes plus MARGIN (lane shapes lie well inside)."""
    ymax = max(c[4] for c in CROSSINGS)
    ymin = -max(c[5] for c in CROSSINGS)
    return (-MARGIN, ymin - MARGIN, ARTERIAL_LENGTH + MARGIN, ymax + MARGIN)


def strips(spec, prop):
    x0, y0, x1, y1 = net_bbox()
    feats = []
    lo = x0
    for name, hi in spec:
        hi = min(hi, x1)
        ring = [[lo, y0], [hi, y0], [hi, y1], [lo, y1], [lo, y0]]
        feats.append((name, [[[round(a, 2), round(b, 2)] for a, b in ring]]))
        lo = hi
    return feats




def write_geojson(path: Path, features: list[dict], one_line_per_feature: bool = False) -> None:
    doc = {"type": "FeatureCollection", "crs": CRS, "features": features}
    if not one_line_per_feature:
        path.write_text(json.dumps(doc, indent=1) + "\n")
        return
    head = json.dumps({"type": "FeatureCollection", "crs": CRS})[:-1]
    body = ",\n".join(json.dumps(f, separators=(",", ":")) for f in features)
    path.write_text(f'{head}, "features": [\n{body}\n]}}\n')


def write_zones(out: Path) -> None:
    feats = []
    for name, coords in strips(ZONE_STRIPS, "zone"):
        sp, sv = ZONE_PARAMS[name]
        feats.append({"type": "Feature",
                      "properties": {"zone": name, "sigma_p": sp, "sigma_v": sv},
                      "geometry": {"type": "Polygon", "coordinates": coords}})
    write_geojson(out / "zones.geojson", feats)


def write_areas(out: Path) -> None:
    feats = [{"type": "Feature", "properties": {"area": name},
              "geometry": {"type": "Polygon", "coordinates": coords}}
             for name, coords in strips(AREA_STRIPS, "area")]
    write_geojson(out / "areas.geojson", feats)


ART_EDGE_Y = CLASSES["arterial"][0] * LANE_WIDTH  # outer lane edge |y| = 6.4 m
FEATURE_COLORS = {"bus_stop": "0,0,255", "traffic_light": "255,0,0",
                  "sign": "255,165,0", "parking": "0,160,0"}
BUS_STOP_X = [110.0, 530.0, 745.0, 925.0, 1125.0, 1320.0, 1525.0, 1920.0]
PARKING = [  # (crossing, side, distance from arterial, east/west)
    ("S2", "n", 120.0, 1), ("S3", "s", 90.0, -1), ("P2", "n", 110.0, 1), ("P2", "s", 150.0, -1),
    ("S4", "n", 100.0, -1), ("S4", "s", 130.0, 1), ("S5", "n", 80.0, 1), ("P3", "s", 140.0, -1),
]


def feature_list() -> list[tuple[str, str, float, float]]:
    feats: list[tuple[str, str, float, float]] = []
    # traffic lights: four corners of each signalised junction
    for name, x, cls, tls, ln, ls in CROSSINGS:
        if not tls:
            continue
        hw = CLASSES[cls][0] * LANE_WIDTH + 3.0
        for tag, sx, sy in (("ne", 1, 1), ("nw", -1, 1), ("sw", -1, -1), ("se", 1, -1)):
            feats.append((f"tl_{name}_{tag}", "traffic_light", x + sx * hw, sy * (ART_EDGE_Y + 3.0)))
    # bus stops: on the sidewalk both sides, 4 m from the outer lane edge
    for k, x in enumerate(BUS_STOP_X):
        feats.append((f"bus_{k + 1:02d}_s", "bus_stop", x, -(ART_EDGE_Y + 4.0)))
        feats.append((f"bus_{k + 1:02d}_n", "bus_stop", x + 15.0, ART_EDGE_Y + 4.0))
    # signs: give-way/stop signs on the minor approaches of priority junctions
    for name, x, cls, tls, ln, ls in CROSSINGS:
        if tls:
            continue
        hw = CLASSES[cls][0] * LANE_WIDTH + 2.0
        feats.append((f"sign_{name}_n", "sign", x - hw, ART_EDGE_Y + 10.0))
        feats.append((f"sign_{name}_s", "sign", x + hw, -(ART_EDGE_Y + 10.0)))
    # signs: "traffic light ahead" 60 m before each signalised junction on the arterial
    for name, x, cls, tls, ln, ls in CROSSINGS:
        if not tls:
            continue
        feats.append((f"sign_{name}_we", "sign", x - 60.0, -(ART_EDGE_Y + 2.5)))
        feats.append((f"sign_{name}_ew", "sign", x + 60.0, ART_EDGE_Y + 2.5))
    # signs: speed limit at both arterial entries
    feats.append(("sign_W_limit", "sign", 30.0, -(ART_EDGE_Y + 2.5)))
    feats.append(("sign_E_limit", "sign", ARTERIAL_LENGTH - 30.0, ART_EDGE_Y + 2.5))
    # car parks beside side roads near the centre
    for name, side, dist, ew in PARKING:
        c = crossing(name)
        off = CLASSES[c[2]][0] * LANE_WIDTH + 8.0
        y = dist if side == "n" else -dist
        feats.append((f"park_{name}{side}", "parking", c[1] + ew * off, y))
    assert len(feats) == 64, len(feats)
    assert len({f[0] for f in feats}) == 64
    return feats


def write_features(out: Path) -> dict:
    feats = feature_list()
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             "<!-- generated by tools/make_arterial.py: 64 static features (paper Sec. VI) as POIs in net x/y "
             "metres: traffic-light poles at the corners of the 5 signalised junctions, bus stops on the "
             "sidewalks, road signs at junction approaches, car parks beside side roads -->",
             "<additional>"]
    for fid, typ, x, y in feats:
        lines.append(f'    <poi id="{fid}" type="{typ}" x="{fmt(x)}" y="{fmt(y)}" '
                     f'color="{FEATURE_COLORS[typ]}" layer="5"/>')
    lines.append("</additional>")
    (out / "features.add.xml").write_text("\n".join(lines) + "\n")
    counts: dict[str, int] = {}
    for _, typ, _, _ in feats:
        counts[typ] = counts.get(typ, 0) + 1
    return counts


# --------------------------------------------------------------------------
# Buildings (the occluders of the realistic perception): street-fronting blocks, denser and taller where GNSS is class C
# --------------------------------------------------------------------------
# Urban blocks fill the land between the roads up to BUILDING_BAND_M from the arterial. Facades stand
# ARTERIAL_FACADE_M from the arterial's axis (a 40 m street: 2 x 6.4 m of lanes plus sidewalks, the
# bus stops and signs, as on a Turin corso) and SIDE_FACADE_M from a side road's axis. The style of a
# plot follows the GNSS zone class at its x (our choice, consistent with the zones: class C is the
# built-up centre whose urban canyon degrades GNSS):
#   C: closed perimeter blocks (Turin's "isolato"): a continuous street front 20 m deep on every
#      street, a courtyard inside, 6-8 storeys (21-27 m);
#   B: terraced rows 18 m wide with 10 m gaps, 14 m deep, on the streets only, 4-5 storeys (12-17 m);
#   A: detached houses 12 x 10 m every 40 m, set back 10 m, 2 storeys (6-8 m).
# Plots are trimmed off every lane (1.5 m clearance beyond the lane edge), off every feature (3 m) and
# off an open lot of 15 m radius around each car park. Heights are informational (occlusion is 2-D).
BUILDING_BAND_M = 180.0
ARTERIAL_FACADE_M = 20.0
SIDE_FACADE_M = {"primary": 16.0, "secondary": 12.0}
BUILDING_STYLE = {  # zone class: (plot width, gap, depth, setback, storeys lo, storeys hi, perimeter block)
    "C": (22.0, 0.0, 20.0, 0.0, 7, 9, True),
    "B": (18.0, 10.0, 14.0, 0.0, 4, 5, False),
    "A": (12.0, 28.0, 10.0, 10.0, 2, 2, False),
}
STOREY_M = 3.0  # storey height (a common convention for buildings without a height, e.g. OSM building:levels)
LANE_CLEARANCE_M = 1.5
FEATURE_CLEARANCE_M = 3.0
CAR_PARK_LOT_M = 15.0


def zone_class_at(x: float) -> str:
    for name, hi in ZONE_STRIPS:
        if x < hi:
            return name
    return ZONE_STRIPS[-1][0]


def _frontage_plots(lo: float, hi: float, width: float, gap: float) -> list[tuple[float, float]]:
    """Plots of ``width`` separated by ``gap`` along [lo, hi], centred so both ends get the same margin."""
    n = int((hi - lo + gap) // (width + gap))
    if n <= 0:
        return []
    used = n * width + (n - 1) * gap
    a = lo + (hi - lo - used) / 2
    return [(a + k * (width + gap), a + k * (width + gap) + width) for k in range(n)]


def building_plots() -> list[tuple[list[tuple[float, float]], str]]:
    """Rectangles (corner lists) and zone class of every plot before trimming, west to east."""
    x0, _, x1, _ = net_bbox()
    # street corridors across the arterial: (x of the side road's facade west, east)
    cuts = [(c[1] - SIDE_FACADE_M[c[2]], c[1] + SIDE_FACADE_M[c[2]]) for c in CROSSINGS]
    blocks = [(x0, cuts[0][0])] + [(cuts[k][1], cuts[k + 1][0]) for k in range(len(cuts) - 1)] + [(cuts[-1][1], x1)]
    plots = []
    for bx0, bx1 in blocks:
        for sign in (1.0, -1.0):
            front = ARTERIAL_FACADE_M
            back = BUILDING_BAND_M
            def rect(xa, xb, ya, yb):
                y0, y1 = sorted((sign * ya, sign * yb))
                return [(xa, y0), (xb, y0), (xb, y1), (xa, y1)]
            # the arterial front, plot by plot (the class may change along a block)
            for zone in ("A", "B", "C"):
                w, gap, depth, setback, *_ , perimeter = BUILDING_STYLE[zone]
                for a, b in _frontage_plots(bx0, bx1, w, gap):
                    if zone_class_at((a + b) / 2) == zone:
                        plots.append((rect(a, b, front + setback, front + setback + depth), zone))
            # the side-road fronts and, in a perimeter block, the back row closing the courtyard
            for xs, inward in ((bx0, 1.0), (bx1, -1.0)):
                if xs in (x0, x1):
                    continue  # the net's ends: no street there
                zone = zone_class_at(xs + inward * 10.0)
                w, gap, depth, setback, *_, perimeter = BUILDING_STYLE[zone]
                ya = front + (setback + depth if perimeter else setback + depth + gap)  # behind the front row
                for a, b in _frontage_plots(ya, back, w, gap):
                    xa, xb = sorted((xs + inward * setback, xs + inward * (setback + depth)))
                    plots.append((rect(xa, xb, a, b), zone))
            zone = zone_class_at((bx0 + bx1) / 2)
            w, gap, depth, setback, *_, perimeter = BUILDING_STYLE[zone]
            if perimeter and bx1 - bx0 > 2 * depth:
                plots.append((rect(bx0 + depth, bx1 - depth, back - depth, back), zone))
    return plots


def write_buildings(out: Path) -> dict:
    """``buildings.geojson`` (net x/y) from :func:`building_plots`, trimmed off the built net's lanes
    and the features; returns counts and plan areas per zone class for scenario.toml / README."""
    import numpy as np
    import shapely
    import sumolib

    net = sumolib.net.readNet(str(out / NET_NAME), withInternal=True)
    lanes = [shapely.LineString(l.getShape()).buffer(l.getWidth() / 2 + LANE_CLEARANCE_M, cap_style="flat")
             for e in net.getEdges(withInternal=True) for l in e.getLanes() if len(l.getShape()) >= 2]
    feats = feature_list()
    keep_out = [shapely.Point(x, y).buffer(FEATURE_CLEARANCE_M) for _, _, x, y in feats]
    keep_out += [shapely.Point(x, y).buffer(CAR_PARK_LOT_M) for _, typ, x, y in feats if typ == "parking"]
    obstacles = shapely.union_all(lanes + keep_out)
    placed = shapely.Polygon()  # plots already built: a later plot never overlaps an earlier one
    rng = np.random.default_rng(20261126)  # fixed: the storeys of each plot, reproducible
    out_feats, stats = [], {z: {"count": 0, "area_m2": 0.0} for z in ("A", "B", "C")}
    for k, (corners, zone) in enumerate(building_plots()):
        poly = shapely.make_valid(shapely.Polygon(corners).difference(obstacles).difference(placed))
        parts = [g for g in getattr(poly, "geoms", [poly]) if g.geom_type == "Polygon" and g.area >= 20.0]
        lo, hi = BUILDING_STYLE[zone][4], BUILDING_STYLE[zone][5]
        storeys = int(rng.integers(lo, hi + 1))
        if not parts:
            continue
        geom = parts[0] if len(parts) == 1 else shapely.MultiPolygon(parts)
        placed = shapely.union_all([placed, geom])
        coords = shapely.geometry.mapping(shapely.set_precision(geom, 0.01))
        coords = json.loads(json.dumps(coords), parse_float=lambda v: round(float(v), 2))
        out_feats.append({"type": "Feature",
                          "properties": {"id": f"b{k:04d}", "zone_class": zone, "storeys": storeys,
                                         "height": storeys * STOREY_M},
                          "geometry": coords})
        stats[zone]["count"] += 1
        stats[zone]["area_m2"] += float(geom.area)
    write_geojson(out / "buildings.geojson", out_feats, one_line_per_feature=True)
    return stats


# --------------------------------------------------------------------------
# scenario.toml and README
# --------------------------------------------------------------------------

def write_scenario(out: Path, demand: dict, fcounts: dict, bstats: dict) -> None:
    tls = [f"J{c[0]}" for c in CROSSINGS if c[3]]
    prio = [f"J{c[0]}" for c in CROSSINGS if not c[3]]
    zb = [fmt(hi) for _, hi in ZONE_STRIPS[:-1]]
    ab = [fmt(hi) for _, hi in AREA_STRIPS[:-1]]
    def tlist(xs):
        return "[" + ", ".join(f'"{x}"' for x in xs) + "]"
    def nlist(xs):
        return "[" + ", ".join(str(x) for x in xs) + "]"
    text = f"""# generated by tools/make_arterial.py
name = "arterial"
description = "Turin-like urban arterial (Brambilla et al., Sec. VI): 2 km, 2 lanes per direction, 3 primary and 6 secondary crossings, 5 signalised junctions; one hour of traffic falling from {fmt(TOTAL_START)} to {fmt(TOTAL_END)} veh/h"
units = "metres and seconds; coordinates are SUMO net x/y (no geo projection)"
sources = "written by this project (tools/make_arterial.py); no imported data"
licence = "EPL-2.0 OR GPL-2.0-or-later (same as the project); no third-party data"

[files]
net = "{NET_NAME}"
routes = "demand.rou.xml"
zones = "zones.geojson"
areas = "areas.geojson"
features = "features.add.xml"
buildings = "buildings.geojson"

[controls]
tlr = {{ tls_off = false }}
vsr = {{ tls_off = true }}

[sumo]
step_length = 0.75
end = {int(DURATION)}

[derived]  # free-form notes: what the generator decided
arterial_length_m = {fmt(ARTERIAL_LENGTH)}
arterial_lanes_per_direction = {CLASSES['arterial'][0]}
speed_limit_mps = {{ arterial = {fmt(CLASSES['arterial'][1])}, primary = {fmt(CLASSES['primary'][1])}, secondary = {fmt(CLASSES['secondary'][1])} }}
edge_priority = {{ arterial = {CLASSES['arterial'][2]}, primary = {CLASSES['primary'][2]}, secondary = {CLASSES['secondary'][2]} }}
primary_crossings = {tlist([f"J{c[0]}" for c in CROSSINGS if c[2] == "primary"])}
secondary_crossings = {tlist([f"J{c[0]}" for c in CROSSINGS if c[2] == "secondary"])}
traffic_lights = {tlist(tls)}
priority_junctions = {tlist(prio)}
tls_cycle_s = {fmt(TLS_CYCLE)}
tls_yellow_s = {fmt(TLS_YELLOW)}
tls_allred_s = {fmt(TLS_ALLRED)}
tls_offsets_s = {{ {", ".join(f"{k} = {fmt(v * TLS_CYCLE)}" for k, v in sorted(TLS_OFFSET_FRACTIONS.items()))} }}
tls_arterial_green_share = {TLS_ARTERIAL_SHARE}
demand_veh_per_h = {{ start = {fmt(TOTAL_START)}, end = {fmt(TOTAL_END)}, bin_s = {fmt(BIN)} }}
demand_shares = {{ arterial_through = {SHARE_ARTERIAL}, primary_through = {SHARE_PRIMARY_THROUGH}, primary_turns = {SHARE_PRIMARY_TURN}, secondary = {SHARE_SECONDARY} }}
demand_vehicles = {demand['vehicles']}
demand_vehicles_per_bin = {nlist(demand['vehicles_per_bin'])}
routes = {demand['routes']}
flows = {demand['flows']}
zone_x_boundaries_m = {nlist(zb)}  # west to east: A | B | C | B | A
area_x_boundaries_m = {nlist(ab)}  # west to east: 1 .. 6
features = {{ {", ".join(f"{k} = {v}" for k, v in sorted(fcounts.items()))} }}
buildings = {{ {", ".join(f"{z} = {bstats[z]['count']}" for z in sorted(bstats))} }}  # footprints per zone class
building_plan_area_m2 = {{ {", ".join(f"{z} = {round(bstats[z]['area_m2'])}" for z in sorted(bstats))} }}
building_band_m = {fmt(BUILDING_BAND_M)}  # blocks reach this far from the arterial
arterial_facade_m = {fmt(ARTERIAL_FACADE_M)}  # facades this far from the arterial's axis
"""
    (out / "scenario.toml").write_text(text)


README = """# sumo_nets/arterial — a Turin-like urban arterial

Written by this project (`tools/make_arterial.py`, deterministic; no imported
data) to imitate the Turin arterial of Brambilla et al., Sec. VI. Plain
Cartesian metres, arterial on y = 0; no geo projection.

Rebuild the net from its plain sources: `python -m couplers.net.build sumo_nets/arterial`
(`make net`); regenerate everything: `python tools/make_arterial.py`.

## Geometry
- Arterial x = 0 .. 2000 m, 2 lanes per direction, 50 km/h (13.89 m/s), edge priority 3.
- 3 primary crossings P1 (x = 420), P2 (1020), P3 (1620): 2 lanes per direction,
  50 km/h, priority 2; 6 secondary crossings S1 (200), S2 (640), S3 (820),
  S4 (1220), S5 (1420), S6 (1830): 1 lane per direction, 40 km/h, priority 1.
  Side roads run 250-400 m north and south to fringe nodes.
- 5 signalised junctions JP1, JS2, JP2, JS4, JP3 ({cycle} s cycle: arterial green
  {art_green} s, side-road green {side_green} s, yellow {yellow} s, all-red {allred} s;
  offsets {offsets}; no green wave). Left turns are permissive (yield to
  oncoming traffic), from the arterial's left lane. JS1, JS3, JS5, JS6 are
  priority junctions, arterial major.
- TLR and VSR share `tlr.net.xml`; VSR switches every signal off at run time
  (`sumo --tls.all-off true` or `trafficlight.setProgram(id, "off")`).

## Demand (`demand.rou.xml`)
One hour; total demand {d0} -> {d1} veh/h, linear, one `<flow>` per route and
5-min bin with evenly spaced departures ({nveh} vehicles, {nroutes} routes).
Shares: arterial through {sa:.0%}, primary through {sp:.0%}, arterial<->primary
turns {st:.0%}, secondary roads {ss:.0%}. One vType `car` (Krauss: accel 2.6,
decel 4.5, emergencyDecel 9, sigma 0.5, tau 1.0, length 4.5, minGap 2.5,
maxSpeed 15, speedFactor N(1, 0.1) in [0.8, 1.2]; jmTimegapMinor {tg} s,
impatience {imp}).

## Measured (sumo 1.28, step 0.75 s, seed 1, full hour)
| | TLR | VSR |
|---|---|---|
| mean vehicles in network | 121.9 | 81.2 |
| mean halting vehicles (speed < 0.1 m/s) | 29.5 (36 -> 25 over the hour) | 0.9 |
| stop time (waiting / distance) | 28.8 s/km | 0.9 s/km |
| teleports / collisions | 0 / 0 | 0 / 0 |
| exit flow, veh/h per 5-min bin | 1080, 2676, 2544, 2604, 2496, 2484, 2220, 2340, 2088, 2064, 1992, 1908 | 1524, 2796, 2568, 2580, 2388, 2448, 2292, 2196, 2136, 2004, 1980, 1896 |

The net starts empty: the first bin's exit flow lags the demand.

## Data
- `zones.geojson`: GNSS classes as strips across the net, west to east
  A | B | C | B | A at x = {zb} m (A: sigma_p 3 m, sigma_v 0.1 m/s;
  B: 8 m, 0.17 m/s; C: 15 m, 0.45 m/s).
- `areas.geojson`: analysis areas 1..6 as strips, boundaries x = {ab} m
  (1 and 6 in zone A, 4 and 5 in the built-up centre).
- `features.add.xml`: 64 POIs: {fc}.
- `buildings.geojson`: {nb} building footprints (zone class C {bz}), street-fronting
  blocks up to {band} m from the arterial, facades {facade} m from its axis ({sfp} / {sfs} m from a
  primary / secondary side road's). Denser and taller where GNSS is class C: closed perimeter
  blocks around courtyards, 7-9 storeys; B: terraced rows with gaps, 4-5 storeys; A: detached
  houses, 2 storeys (3 m a storey, `height` in metres). Plots keep 1.5 m off every lane, 3 m off
  every feature and an open lot of 15 m around each car park. Only the opt-in effects read them:
  occlusion (`[perception]`), NLOS GNSS episodes (`[gnss_error]`, rate from the plan-area
  fraction within 50 m) and the NLOS delivery curve (`[v2x]`); the paper configs do not.
- The zone, area and building GeoJSON files use net x/y metres (`crs` name
  `urn:coloc:sumo-net-xy`); zones and areas cover the net bounding box plus {margin} m.
"""


def write_readme(out: Path, demand: dict, fcounts: dict, bstats: dict) -> None:
    green_total = TLS_CYCLE - 2 * (TLS_YELLOW + TLS_ALLRED)
    art = round(green_total * TLS_ARTERIAL_SHARE)
    text = README.format(
        cycle=fmt(TLS_CYCLE), art_green=fmt(art), side_green=fmt(green_total - art),
        yellow=fmt(TLS_YELLOW), allred=fmt(TLS_ALLRED),
        offsets=", ".join(f"{k} {fmt(v * TLS_CYCLE)} s" for k, v in TLS_OFFSET_FRACTIONS.items()),
        d0=fmt(TOTAL_START), d1=fmt(TOTAL_END), nveh=demand["vehicles"], nroutes=demand["routes"],
        sa=SHARE_ARTERIAL, sp=SHARE_PRIMARY_THROUGH, st=SHARE_PRIMARY_TURN, ss=SHARE_SECONDARY,
        tg=VTYPE["jmTimegapMinor"], imp=VTYPE["impatience"],
        zb=", ".join(fmt(hi) for _, hi in ZONE_STRIPS[:-1]),
        ab=", ".join(fmt(hi) for _, hi in AREA_STRIPS[:-1]),
        fc=", ".join(f"{v} {k}" for k, v in sorted(fcounts.items())), margin=fmt(MARGIN),
        nb=sum(v["count"] for v in bstats.values()),
        bz=", ".join(f"{z} {bstats[z]['count']} ({bstats[z]['area_m2'] / 1e4:.1f} ha)" for z in ("C", "B", "A")),
        band=fmt(BUILDING_BAND_M), facade=fmt(ARTERIAL_FACADE_M),
        sfp=fmt(SIDE_FACADE_M["primary"]), sfs=fmt(SIDE_FACADE_M["secondary"]))
    (out / "README.md").write_text(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "sumo_nets" / "arterial")
    ap.add_argument("--no-build", action="store_true",
                    help="write sources only (keeps an existing arterial.tll.xml; the netccfg refers to it)")
    args = ap.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    write_nodes(out)
    write_edges(out)
    write_connections(out)
    if not args.no_build:
        # pass 1: netconvert's default signal programs, to learn phase states
        write_netccfg(out, with_tll=False)
        build_net(out)
        retime_tls(out)
    write_netccfg(out, with_tll=True)
    demand = write_demand(out)
    write_zones(out)
    write_areas(out)
    fcounts = write_features(out)
    if not args.no_build:
        build_net(out)  # pass 2: with the re-timed programs
    bstats = write_buildings(out)  # trimmed off the built net's lanes (--no-build: the existing net's)
    write_scenario(out, demand, fcounts, bstats)
    write_readme(out, demand, fcounts, bstats)
    print(f"wrote {out} ({demand['vehicles']} vehicles, {demand['flows']} flows)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
