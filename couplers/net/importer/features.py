"""Static features of ``coloc net import``: candidate places per kind, the seeded selection, the POI file."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import shapely
import shapely.ops

from couplers.errors import InputError
from couplers.net.importer.geometry import FEATURE_SIDE_M, _fmt, _roadside

FEATURE_KINDS = ("traffic_light", "bus_stop", "parking", "sign")
FEATURE_COLORS = {"bus_stop": "0,0,255", "traffic_light": "255,0,0", "sign": "255,165,0", "parking": "0,160,0"}
FEATURE_MIN_SPACING_M = 4.0


# --------------------------------------------------------------------------
# Features
# --------------------------------------------------------------------------

def _additional_stops(path: Path, net, report_path: Path) -> dict[str, list[tuple[str, float, float]]]:
    """busStop / parkingArea elements on lanes of the net -> (id, x, y) beside the lane."""
    out: dict[str, list[tuple[str, float, float]]] = {"bus_stop": [], "parking": []}
    if not path.is_file():
        return out
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise InputError(report_path, None, f"not valid XML ({exc})") from None
    for tag, kind in (("busStop", "bus_stop"), ("parkingArea", "parking")):
        for i, el in enumerate(root.iter(tag)):
            lane_id = el.get("lane", "")
            try:
                lane = net.getLane(lane_id)
            except KeyError:
                continue  # on an edge netconvert removed (e.g. a tram-only stop)
            if not lane.getEdge().allows("passenger"):
                continue
            length = lane.getLength()
            try:
                start = float(el.get("startPos", 0.0))
                end = float(el.get("endPos", length))
            except ValueError:
                raise InputError(report_path, f"{tag}[{i}].startPos/endPos", "not a number") from None
            start = start + length if start < 0 else start
            end = end + length if end < 0 else end
            mid = min(max(0.5 * (start + end), 0.0), length)
            x, y = _roadside(lane, length - mid, side_m=(3.0 if kind == "parking" else FEATURE_SIDE_M))
            out[kind].append((el.get("id", f"{tag}{i}"), x, y))
    return out


def _candidate_features(net, stops: dict, parking_polys: list, lane_tree) -> dict[str, list[tuple[str, float, float]]]:
    cands: dict[str, list[tuple[str, float, float]]] = {k: [] for k in FEATURE_KINDS}
    # traffic-light poles: at the stop line of each approach, right side
    for node in net.getNodes():
        typ = node.getType()
        incoming = [e for e in node.getIncoming() if e.getFunction() == "" and e.allows("passenger")]
        if not incoming:
            continue
        if typ.startswith("traffic_light"):
            for e in incoming:
                x, y = _roadside(e.getLane(0), 2.0)
                cands["traffic_light"].append((f"tl_{node.getID()}_{e.getID()}", x, y))
                if e.getLength() > 100.0:  # "signal ahead" sign
                    x, y = _roadside(e.getLane(0), 60.0)
                    cands["sign"].append((f"sign_tls_{e.getID()}", x, y))
        elif typ in ("priority", "priority_stop", "right_before_left", "left_before_right", "allway_stop"):
            if len(incoming) < 3 and typ.startswith("priority"):
                continue  # a bend or a plain road split: no sign
            top = max(e.getPriority() for e in incoming)
            for e in incoming:
                if typ.startswith("priority") and e.getPriority() >= top:
                    continue  # major road: no give-way sign
                if e.getLength() < 15.0:
                    continue
                x, y = _roadside(e.getLane(0), 10.0)
                cands["sign"].append((f"sign_{node.getID()}_{e.getID()}", x, y))
    cands["bus_stop"] = list(stops.get("bus_stop", []))
    cands["parking"] = list(stops.get("parking", []))
    # car parks from OSM polygons: the point of the polygon nearest to a road
    for pid, poly in parking_polys:
        idx = lane_tree.nearest(poly)
        road = lane_tree.geometries[idx]
        p = shapely.ops.nearest_points(poly, road)[0]
        cands["parking"].append((f"park_{pid}", p.x, p.y))
    return cands


def _select_features(cands: dict, count: int, kinds: tuple[str, ...], rng: np.random.Generator
                     ) -> list[tuple[str, str, float, float]]:
    """``count`` features with an equal share per kind where available, drawn at random."""
    pools = {}
    for k in kinds:
        items = cands.get(k, [])
        order = rng.permutation(len(items)) if items else np.empty(0, dtype=int)
        pools[k] = [items[i] for i in order]
    chosen: list[tuple[str, str, float, float]] = []
    xy: list[tuple[float, float]] = []

    def far_enough(x, y):
        return all((x - a) ** 2 + (y - b) ** 2 >= FEATURE_MIN_SPACING_M ** 2 for a, b in xy)

    # round robin over kinds: equal shares, a kind that runs out leaves its share to the others
    active = [k for k in kinds if pools[k]]
    pos = {k: 0 for k in kinds}
    while len(chosen) < count and active:
        for k in list(active):
            if len(chosen) >= count:
                break
            pool = pools[k]
            while pos[k] < len(pool):
                fid, x, y = pool[pos[k]]
                pos[k] += 1
                if far_enough(x, y):
                    chosen.append((fid, k, x, y))
                    xy.append((x, y))
                    break
            if pos[k] >= len(pool):
                active.remove(k)
    return chosen


def _write_features(path: Path, feats: list, source: str) -> None:
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f"<!-- generated by coloc net import from {source}: static features as POIs in net x/y metres "
             "(traffic-light poles at stop lines, bus stops, car parks, signs at junction approaches) -->",
             "<additional>"]
    used: set[str] = set()
    for fid, kind, x, y in sorted(feats, key=lambda f: (FEATURE_KINDS.index(f[1]), f[0])):
        pid = re.sub(r"[^A-Za-z0-9_.#:-]", "_", fid)
        while pid in used:
            pid += "_"
        used.add(pid)
        lines.append(f'    <poi id="{pid}" type="{kind}" x="{_fmt(x)}" y="{_fmt(y)}" color="{FEATURE_COLORS[kind]}" layer="5"/>')
    lines.append("</additional>")
    path.write_text("\n".join(lines) + "\n")
