"""Net geometry helpers of ``coloc net import``: implausible signal programs, drivable edges, roadside points."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

from shapely.geometry import LineString

FEATURE_SIDE_M = 2.5  # POI distance from the outer lane edge (sidewalk)
# A signal program is implausible for urban traffic when its cycle is longer than this or when
# some of its links are never green. Urban fixed-time cycles are 60-120 s and rarely above 150-180 s
# (FHWA Signal Timing Manual, 2nd ed., 2015, ch. 6); netconvert's own default is 90 s
# (--tls.cycle.time). 300 s leaves a wide margin: the programs this catches are games' and test
# nets' placeholders (the eclipse-sumo wheel's tools/game/bs3d/bs.net.xml: 1000 s phases).
MAX_PLAUSIBLE_CYCLE_S = 300.0


# --------------------------------------------------------------------------
# Net geometry helpers
# --------------------------------------------------------------------------

def implausible_signal_programs(net_path: Path) -> list[str]:
    """Signal programs (``tlLogic`` of a SUMO net) no urban signal would run: cycle above
    :data:`MAX_PLAUSIBLE_CYCLE_S`, or links that no phase ever serves (green ``G``/``g``, or ``o``/``O``:
    signal off, priority rules apply).

    One description per program: ``tlLogic 'ID' program 'P': ...``.
    """
    out = []
    for _event, el in ET.iterparse(net_path, events=("end",)):
        if el.tag != "tlLogic":
            if el.tag == "edge":
                el.clear()
            continue
        phases = [(float(p.get("duration", "0")), p.get("state", "")) for p in el.iter("phase")]
        if not phases:
            continue
        cycle = sum(d for d, _ in phases)
        n_links = max(len(st) for _, st in phases)
        unserved = sum(not any(i < len(st) and st[i] in "GgOo" for _, st in phases) for i in range(n_links))
        why = []
        if cycle > MAX_PLAUSIBLE_CYCLE_S:
            why.append(f"cycle {cycle:g} s (longest phase {max(d for d, _ in phases):g} s; "
                       f"more than {MAX_PLAUSIBLE_CYCLE_S:g} s)")
        if unserved:
            why.append(f"{unserved} of {n_links} links never green")
        if why:
            out.append(f"tlLogic {el.get('id')!r} program {el.get('programID')!r}: " + ", ".join(why))
    return out


def _drivable_edges(net) -> list:
    return [e for e in net.getEdges(withInternal=False) if e.getFunction() == "" and e.allows("passenger")]


def _roadside(lane, from_end_m: float, side_m: float | None = None) -> tuple[float, float]:
    """A point ``from_end_m`` before the end of ``lane``, on the right, beside the lane's outer edge."""
    line = LineString(lane.getShape())
    s = max(0.0, line.length - from_end_m)
    p = line.interpolate(s)
    a = line.interpolate(max(0.0, s - 0.5))
    b = line.interpolate(min(line.length, s + 0.5))
    dx, dy = b.x - a.x, b.y - a.y
    norm = math.hypot(dx, dy) or 1.0
    off = lane.getWidth() / 2.0 + (FEATURE_SIDE_M if side_m is None else side_m)
    return (p.x + dy / norm * off, p.y - dx / norm * off)


def _fmt(v: float) -> str:
    s = f"{v:.2f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s
