"""Import a user's SUMO net or OpenStreetMap extract as a net folder (``coloc net import``).

From one ``.net.xml`` or ``.osm[.gz]`` file this derives everything a net
folder holds (docs/architecture.md "A net folder"), and says what it could not derive:

* the net: netconvert with the options SUMO recommends for OSM imports (the
  docs/architecture.md "SUMO notes") and osmWebWizard's urban typemaps, cars only, or the
  user's net re-written by netconvert; the
  dated netconvert header is replaced by a fixed comment so that the same
  inputs give identical bytes. TLR is the net as built; VSR switches every
  signal off at run time (``[controls] vsr = { tls_off = true }``). A net
  without traffic lights is refused unless ``guess_signals`` lets netconvert
  place signals at major junctions (``--tls.guess``);
* demand: the paper's falling profile (2800 -> 1800 veh/h over the hour on the
  arterial, linear, per 5-min bin) scaled to the network so that the mean
  vehicle density (vehicles per lane-km) is the arterial's, then scaled down
  until the hour runs without gridlock under VSR and TLR
  (:func:`gridlock_trial`; real city nets jam long before the arterial's
  density because of their many unsignalised junctions); routes from
  randomTrips (fringe factor, seeded) routed by duarouter, every route checked
  against the net; or the user's route file, checked the same way;
* features: traffic-light poles at the stop lines of signalised junctions,
  bus stops (OSM stop positions / ``busStop`` additionals), car parks (OSM
  ``amenity=parking`` / ``parkingArea`` additionals) and signs at the minor
  approaches of unsignalised junctions, as SUMO POIs beside the road;
* GNSS zones: from building density (polyconvert) when the extract has
  buildings, else a stated default layout (concentric rectangles, worst class
  in the centre), or the user's GeoJSON; analysis areas: a 3 x 2 grid or the
  user's GeoJSON. The user's GeoJSON is net x/y metres (crs
  ``urn:coloc:sumo-net-xy``) or WGS84 lon/lat (RFC 7946: no crs member, or
  CRS84 / EPSG:4326), converted with the net's own projection
  (:mod:`couplers.georef`); the folder always holds net x/y.

Everything is built in a temporary folder next to the output and renamed into
place only when complete; bad input raises :class:`InputError` naming the
file and field, and leaves nothing behind.
"""

from __future__ import annotations

import dataclasses
import gzip
import hashlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import shapely
import shapely.ops
from shapely.geometry import LineString, box, mapping

from couplers.errors import InputError, seed_problem
from couplers.georef import GeoRef, check_lonlat, conversion_note, crs_kind, geojson_to_net_xy, read_georef
from couplers.netfolder import NET_CRS as CRS
from couplers.netfolder import NET_CRS_NAME, lane_shape_points, read_regions, regions_from_doc
from couplers.publish import check_target, make_dirs, remove_created, staged_folder, write_file_atomic

FEATURE_KINDS = ("traffic_light", "bus_stop", "parking", "sign")
FEATURE_COLORS = {"bus_stop": "0,0,255", "traffic_light": "255,0,0", "sign": "255,165,0", "parking": "0,160,0"}
# OSM highway values netconvert's osmNetconvert typemap opens to passenger cars.
CAR_HIGHWAYS = frozenset({
    "motorway", "motorway_link", "trunk", "trunk_link", "primary", "primary_link", "secondary",
    "secondary_link", "tertiary", "tertiary_link", "unclassified", "residential", "living_street",
    "service", "road",
})

# GNSS classes (docs/architecture.md "Models and default parameters", Brambilla Sec. VI): zone -> (sigma_p m, sigma_v m/s).
ZONE_PARAMS = {"A": (3.0, 0.1), "B": (8.0, 0.17), "C": (15.0, 0.45)}
# Built-up fraction of a zone cell (building footprint area / cell area) from
# which the cell gets the worse class: >= 0.30 dense urban canyon (C),
# >= 0.12 built-up (B), else open sky (A).
BUILT_FRACTION_C = 0.30
BUILT_FRACTION_B = 0.12

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
CALIB_WARMUP_S = 300.0
CALIB_WINDOW = 4  # checks (30 s apart) averaged for the halting share
CALIB_HALTING_SHARE = 0.5
CALIB_BACKLOG = 0.05
CALIB_BACKLOG_MIN = 20
CALIB_TELEPORTS = 0.01
CALIB_TELEPORTS_MIN = 3
CALIB_FACTOR = 0.6
CALIB_MAX_TRIALS = 8
ZONE_MARGIN_M = 60.0
FEATURE_MIN_SPACING_M = 4.0
FEATURE_SIDE_M = 2.5  # POI distance from the outer lane edge (sidewalk)
# A signal program is implausible for urban traffic when its cycle is longer than this or when
# some of its links are never green. Urban fixed-time cycles are 60-120 s and rarely above 150-180 s
# (FHWA Signal Timing Manual, 2nd ed., 2015, ch. 6); netconvert's own default is 90 s
# (--tls.cycle.time). 300 s leaves a wide margin: the programs this catches are games' and test
# nets' placeholders (the eclipse-sumo wheel's tools/game/bs3d/bs.net.xml: 1000 s phases).
MAX_PLAUSIBLE_CYCLE_S = 300.0
SIGNAL_MODES = ("check", "rebuild", "keep")

_HEADER_COMMENT = re.compile(r"\A(<\?xml[^>]*\?>\s*)<!--.*?-->\s*", re.DOTALL)


@dataclass(frozen=True)
class ImportOptions:
    """What ``coloc net import`` was asked for (command-line options)."""

    name: str
    out: Path
    net: Path | None = None
    osm: Path | None = None
    seed: int = 1
    feature_count: int = 64
    feature_kinds: tuple[str, ...] = FEATURE_KINDS
    guess_signals: bool = False
    zones: Path | None = None
    areas: Path | None = None
    routes: Path | None = None
    additional: Path | None = None  # busStop / parkingArea elements for a .net.xml input
    demand_start_vph: float = 2800.0
    demand_end_vph: float = 1800.0
    demand_scale: float = 1.0  # multiplies the density-matching scale
    fringe_factor: float = 10.0
    duration_s: float = 3600.0
    zone_cell_m: float = 200.0
    route_pool: int = 600  # randomTrips trips routed by duarouter; vehicles draw routes from them
    calibrate: bool = True  # scale the demand down until it runs without gridlock under VSR and TLR
    calibration_s: float | None = None  # simulated span of each gridlock trial; None = duration_s
    # The density match is capped at this multiple of the arterial's demand (about this
    # multiple of its ~120 vehicles in the net): a city-wide net at the arterial's density
    # would carry thousands of vehicles, beyond what a coupled run can evaluate in useful time.
    max_density_scale: float = 4.0
    # Implausible signal programs (implausible_signal_programs): "check" refuses the import and
    # names them, "rebuild" has netconvert rebuild every program (--tls.rebuild), "keep" imports them.
    signals: str = "check"
    force: bool = False

    @property
    def source(self) -> Path:
        return self.osm if self.osm is not None else self.net  # type: ignore[return-value]


@dataclass(frozen=True)
class ImportResult:
    folder: Path
    summary: dict
    lines: tuple[str, ...]
    seconds: float
    track_area: str


@dataclass
class _Report:
    """What was derived and what was not (written to scenario.toml and printed)."""

    derived: dict = field(default_factory=dict)
    not_derived: list[str] = field(default_factory=list)
    lines: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------
# SUMO tools from the eclipse-sumo wheel
# --------------------------------------------------------------------------

def _wheel_home() -> str:
    """SUMO_HOME of the eclipse-sumo wheel (bin/, tools/, data/typemap); else the environment's."""
    try:
        import sumo  # noqa: PLC0415  (the eclipse-sumo wheel)

        return sumo.SUMO_HOME
    except ImportError:  # pragma: no cover - environment problem
        return os.environ.get("SUMO_HOME", "")


def _sumo_env() -> dict[str, str]:
    """Environment of the SUMO tools: the wheel's SUMO_HOME (libsumo may point it at its data-only
    package) and its PROJ data (polyconvert needs proj.db)."""
    env = dict(os.environ)
    home = _wheel_home()
    if home:
        env["SUMO_HOME"] = home
        proj = os.path.join(home, "data", "proj")
        if os.path.isdir(proj):
            env["PROJ_LIB"] = env["PROJ_DATA"] = proj
    return env


def _sumo_home() -> Path:
    home = _wheel_home()
    if not home or not (Path(home) / "tools" / "randomTrips.py").is_file():
        raise InputError(None, "SUMO_HOME", f"SUMO tools not found in {home!r}: install the eclipse-sumo package")
    return Path(home)


def _binary(name: str) -> str:
    import sumolib  # noqa: PLC0415

    binary = sumolib.checkBinary(name)
    if not (os.path.isfile(binary) or shutil.which(binary)):
        raise InputError(None, name, f"{name} not found (install the eclipse-sumo package)")
    return binary


def _run(cmd: list[str], cwd: Path, path: Path, what: str) -> None:
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=_sumo_env())
    if proc.returncode != 0:
        lines = [ln for ln in (proc.stderr or proc.stdout).splitlines() if ln.strip() and "Warning" not in ln]
        msg = "; ".join(lines[:3]) or f"exit {proc.returncode}"
        raise InputError(path, None, f"{what} failed: {msg}")


def normalise_header(text: str, note: str) -> str:
    """Replace a SUMO tool's header comment (date, paths) by ``note``, so that outputs are reproducible."""
    m = _HEADER_COMMENT.match(text)
    fixed = f"<!-- {note} (tool header with date and paths removed for reproducibility) -->\n\n"
    if not m:
        return text
    return m.group(1) + fixed + text[m.end():]


# --------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------

def _open_xml(path: Path):
    if path.suffix == ".gz":
        return gzip.open(path, "rb")
    return open(path, "rb")


def scan_osm(path: Path) -> dict:
    """Count car roads, signals, buildings, bus stops and car parks of an OSM extract.

    Raises :class:`InputError` when the file is missing, not XML, not OSM, or has
    no road open to cars.
    """
    counts = {"car_roads": 0, "signals": 0, "buildings": 0, "bus_stops": 0, "parking": 0}
    try:
        with _open_xml(path) as fh:
            it = ET.iterparse(fh, events=("start", "end"))
            _, root = next(it)
            if root.tag != "osm":
                raise InputError(path, None, f"not an OpenStreetMap file (root element <{root.tag}>, expected <osm>)")
            for event, elem in it:
                if event != "end" or elem.tag not in ("node", "way", "relation"):
                    continue
                tags = {t.get("k"): t.get("v") for t in elem.iter("tag")}
                if elem.tag == "way":
                    if tags.get("highway") in CAR_HIGHWAYS:
                        counts["car_roads"] += 1
                    if "building" in tags:
                        counts["buildings"] += 1
                if tags.get("highway") == "traffic_signals":
                    counts["signals"] += 1
                if tags.get("highway") == "bus_stop" or (tags.get("public_transport") == "stop_position" and tags.get("bus") == "yes"):
                    counts["bus_stops"] += 1
                if tags.get("amenity") == "parking":
                    counts["parking"] += 1
                elem.clear()
                root.clear()
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None
    except (ET.ParseError, EOFError, OSError, StopIteration) as exc:
        raise InputError(path, None, f"not valid XML ({exc or 'empty file'})") from None
    if counts["car_roads"] == 0:
        raise InputError(path, "way[highway]",
                         "the extract has no road open to cars (no way tagged highway="
                         "motorway/trunk/primary/secondary/tertiary/unclassified/residential/service/...)")
    return counts


def _check_net_xml(path: Path) -> None:
    try:
        with _open_xml(path) as fh:
            for _event, elem in ET.iterparse(fh, events=("start",)):
                if elem.tag != "net":
                    raise InputError(path, None, f"not a SUMO net (root element <{elem.tag}>, expected <net>)")
                break
            else:
                raise InputError(path, None, "not valid XML (empty file)")
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None
    except (ET.ParseError, EOFError, OSError) as exc:
        raise InputError(path, None, f"not valid XML ({exc})") from None


def _netconvert(opts: ImportOptions, work: Path, report: _Report) -> Path:
    """Write ``work/tlr.net.xml`` (and ``work/.stops.add.xml`` from OSM)."""
    src = opts.source.resolve()
    out = work / "tlr.net.xml"
    cmd = [_binary("netconvert")]
    if opts.osm is not None:
        typemaps = _sumo_home() / "data" / "typemap"
        cmd += [
            # osmWebWizard's "urban" typemaps: roads without a maxspeed tag get urban speeds
            # (primary/secondary/tertiary 50 km/h instead of the rural 100/100/80 km/h)
            "--osm-files", str(src), "--type-files",
            f"{typemaps / 'osmNetconvert.typ.xml'},{typemaps / 'osmNetconvertUrbanDe.typ.xml'}",
            # SUMO's recommended OSM import (docs/architecture.md "SUMO notes")
            "--geometry.remove", "true", "--ramps.guess", "true", "--junctions.join", "true",
            "--tls.guess-signals", "true", "--tls.discard-simple", "true", "--tls.join", "true",
            "--roundabouts.guess", "true",
            # cars only: coloc simulates passenger cars
            "--keep-edges.by-vclass", "passenger", "--remove-edges.isolated", "true",
            "--output.street-names", "true", "--ptstop-output", ".stops.add.xml",
        ]
    else:
        cmd += ["--sumo-net-file", str(src), "--offset.disable-normalization", "true"]
    if opts.guess_signals:
        cmd += ["--tls.guess", "true"]
    if opts.signals == "rebuild":  # netconvert's static programs: 90 s cycle, every approach served
        cmd += ["--tls.rebuild", "true", "--tls.default-type", "static"]
    cmd += ["--output-file", out.name, "--no-warnings", "true", "--xml-validation", "never"]
    _run(cmd, work, opts.source, "netconvert")
    if not out.is_file() or out.stat().st_size == 0:
        raise InputError(opts.source, None, "netconvert wrote no net")
    text = out.read_text(encoding="utf-8")
    out.write_text(normalise_header(text, f"built by coloc net import from {opts.source.name}"),
                   encoding="utf-8", newline="\n")
    home = str(_sumo_home())
    report.derived["netconvert"] = " ".join(
        opts.source.name if a == str(src) else ",".join(Path(x).name for x in a.split(",")) if a.startswith(home)
        else "stops.add.xml(read,not-kept)" if a.startswith(".stops") else a for a in cmd[1:])
    return out


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


# --------------------------------------------------------------------------
# Zones and areas
# --------------------------------------------------------------------------

def _write_geojson(path: Path, features: list[dict]) -> None:
    doc = {"type": "FeatureCollection", "crs": CRS, "features": features}
    path.write_text(json.dumps(doc, indent=1) + "\n")


def _round_geom(geom):
    return shapely.set_precision(geom, 0.01)


def _grid_bbox(lane_xy: np.ndarray, cell: float) -> tuple[float, float, float, float, int, int]:
    x0, y0 = np.floor(lane_xy.min(axis=0) - ZONE_MARGIN_M)
    x1, y1 = np.ceil(lane_xy.max(axis=0) + ZONE_MARGIN_M)
    nx = max(1, int(math.ceil((x1 - x0) / cell)))
    ny = max(1, int(math.ceil((y1 - y0) / cell)))
    return float(x0), float(y0), float(x0 + nx * cell), float(y0 + ny * cell), nx, ny


def _zones_from_buildings(path: Path, lane_xy: np.ndarray, buildings: list, cell: float, report: _Report) -> None:
    x0, y0, x1, y1, nx, ny = _grid_bbox(lane_xy, cell)
    cells = [box(x0 + i * cell, y0 + j * cell, x0 + (i + 1) * cell, y0 + (j + 1) * cell)
             for j in range(ny) for i in range(nx)]
    built = shapely.union_all(buildings)
    frac = shapely.area(shapely.intersection(np.array(cells, dtype=object), built)) / (cell * cell)
    classes = np.where(frac >= BUILT_FRACTION_C, "C", np.where(frac >= BUILT_FRACTION_B, "B", "A"))
    feats = []
    for z in ("A", "B", "C"):
        sel = [c for c, k in zip(cells, classes) if k == z]
        if not sel:
            continue
        geom = _round_geom(shapely.union_all(sel))
        sp, sv = ZONE_PARAMS[z]
        feats.append({"type": "Feature", "properties": {"zone": z, "sigma_p": sp, "sigma_v": sv,
                                                        "cells": len(sel)},
                      "geometry": mapping(geom)})
    _write_geojson(path, feats)
    counts = {z: int(np.count_nonzero(classes == z)) for z in ("A", "B", "C")}
    report.derived["zones"] = (f"from building density: {len(buildings)} buildings, {nx} x {ny} cells of {_fmt(cell)} m; "
                               f"built-up fraction >= {BUILT_FRACTION_C} -> C, >= {BUILT_FRACTION_B} -> B, else A")
    report.derived["zone_cells"] = counts
    report.lines.append(f"zones: from building density ({len(buildings)} buildings): "
                        f"{counts['A']} A, {counts['B']} B, {counts['C']} C cells of {_fmt(cell)} m")


def _default_zones(path: Path, lane_xy: np.ndarray, report: _Report) -> None:
    x0, y0, x1, y1, _, _ = _grid_bbox(lane_xy, 1.0)
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    hx, hy = 0.5 * (x1 - x0), 0.5 * (y1 - y0)

    def rect(f):
        return box(round(cx - f * hx, 2), round(cy - f * hy, 2), round(cx + f * hx, 2), round(cy + f * hy, 2))

    inner, middle, outer = rect(1 / 3), rect(2 / 3), rect(1.0)
    geoms = {"C": inner, "B": middle.difference(inner), "A": outer.difference(middle)}
    feats = []
    for z in ("A", "B", "C"):
        sp, sv = ZONE_PARAMS[z]
        feats.append({"type": "Feature", "properties": {"zone": z, "sigma_p": sp, "sigma_v": sv},
                      "geometry": mapping(_round_geom(geoms[z]))})
    _write_geojson(path, feats)
    report.derived["zones"] = ("default layout (no buildings in the data): concentric rectangles about the net's "
                               "centre, C (15 m) in the inner third, B (8 m) in the middle ring, A (3 m) outside")
    report.not_derived.append("GNSS zones from building density: the input has no buildings (default layout used)")
    report.lines.append("zones: default layout (no buildings): C centre, B ring, A outskirts")


def _default_areas(path: Path, lane_xy: np.ndarray, report: _Report) -> None:
    x0, y0, x1, y1, _, _ = _grid_bbox(lane_xy, 1.0)
    wide = (x1 - x0) >= (y1 - y0)
    ncol, nrow = (3, 2) if wide else (2, 3)
    xs = np.linspace(x0, x1, ncol + 1).round(2)
    ys = np.linspace(y0, y1, nrow + 1).round(2)
    feats = []
    k = 1
    for j in range(nrow):
        for i in range(ncol):
            feats.append({"type": "Feature", "properties": {"area": str(k)},
                          "geometry": mapping(box(xs[i], ys[j], xs[i + 1], ys[j + 1]))})
            k += 1
    _write_geojson(path, feats)
    report.derived["areas"] = f"default partition: {ncol} x {nrow} grid over the net, numbered from the south-west"
    report.lines.append(f"areas: default {ncol} x {nrow} grid (1..{ncol * nrow})")


@dataclass(frozen=True)
class _UserGeoJSON:
    """The user's --zones/--areas file, read and checked before the net exists."""

    src: Path
    key: str  # "zone" | "area"
    with_sigmas: bool
    doc: dict
    crs: str  # "net" (net x/y metres) | "wgs84" (lon/lat, converted with the net's projection)
    how: str  # how the file says which (for messages)


def _read_user_geojson(src: Path, key: str, with_sigmas: bool) -> _UserGeoJSON:
    """The user's zones/areas GeoJSON: a known CRS, valid polygons, plausible lon/lat (before any conversion)."""
    try:
        doc = json.loads(src.read_text())
    except FileNotFoundError:
        raise InputError(src, None, "file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(src, None, f"not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise InputError(src, None, "expected a GeoJSON FeatureCollection (a JSON object)")
    crs, how = crs_kind(doc, src)
    regions_from_doc(doc, src, key, with_sigmas)
    if crs == "wgs84":
        check_lonlat(doc, src, how)
        try:
            import pyproj  # noqa: F401, PLC0415
        except ImportError:  # pragma: no cover - pyproj is a dependency
            raise InputError(src, "crs", "WGS84 lon/lat needs pyproj to convert to net x/y "
                                         "(pip install pyproj)") from None
    return _UserGeoJSON(src, key, with_sigmas, doc, crs, how)


def _user_geojson(user: _UserGeoJSON, dest: Path, georef: GeoRef, lane_xy: np.ndarray,
                  net_name: str, report: _Report) -> None:
    """Write the user's zones/areas in net x/y (converted from lon/lat if need be) once they cover the net."""
    src, key = user.src, user.key
    doc = geojson_to_net_xy(user.doc, georef, src, user.how) if user.crs == "wgs84" else user.doc
    regions = regions_from_doc(doc, src, key, user.with_sigmas)
    union = shapely.union_all([r.polygon for r in regions])
    inside = shapely.intersects_xy(union, lane_xy[:, 0], lane_xy[:, 1])
    if not inside.any():
        lo, hi = lane_xy.min(axis=0), lane_xy.max(axis=0)
        ux0, uy0, ux1, uy1 = union.bounds
        hint = ""
        if user.crs == "wgs84":
            hint = (f"; the file was read as WGS84 [lon, lat] ({user.how}) and converted with the net's projection: "
                    "check the coordinate order, or add the net x/y crs marker if the coordinates are metres")
        raise InputError(src, "features", f"the polygons lie outside the net (polygons x {ux0:.0f}..{ux1:.0f}, "
                                          f"y {uy0:.0f}..{uy1:.0f}; net x {lo[0]:.0f}..{hi[0]:.0f}, "
                                          f"y {lo[1]:.0f}..{hi[1]:.0f} in {net_name}){hint}")
    if not inside.all():
        i = int(np.flatnonzero(~inside)[0])
        raise InputError(src, "features", f"the polygons leave {int((~inside).sum())} of {len(inside)} lane shape "
                                          f"points of the net uncovered (first at x={lane_xy[i, 0]:.1f}, "
                                          f"y={lane_xy[i, 1]:.1f}" + (" in net x/y after conversion from lon/lat"
                                                                      if user.crs == "wgs84" else "") + ")")
    if user.crs == "wgs84":
        dest.write_text(json.dumps(doc, indent=1) + "\n")
        note = conversion_note(georef, user.how)
        report.derived[key + "s"] = (f"user's GeoJSON {src.name} ({len(regions)} polygons), converted from WGS84 "
                                     f"lon/lat ({user.how}) to net x/y with the net's projection")
        report.derived[key + "s_conversion"] = note
        report.lines.append(f"{key}s: from {src.name} ({len(regions)} polygons), converted from WGS84 lon/lat to "
                            f"net x/y with the net's projection {georef.proj} and netOffset "
                            f"{georef.net_offset[0]:.2f},{georef.net_offset[1]:.2f}")
    else:
        shutil.copyfile(src, dest)
        report.derived[key + "s"] = f"user's GeoJSON {src.name} ({len(regions)} polygons)"
        report.lines.append(f"{key}s: from {src.name} ({len(regions)} polygons)")


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


def route_problems(net, routes_path: Path, limit: int = 20) -> tuple[list[str], int]:
    """Problems of a route file against a net (unknown edges, disconnected routes, unroutable trips).

    Returns (problems, number of vehicles/flows/trips checked).
    """
    problems: list[str] = []
    try:
        root = ET.parse(routes_path).getroot()
    except FileNotFoundError:
        return [f"{routes_path}: file not found"], 0
    except ET.ParseError as exc:
        return [f"{routes_path}: not valid XML ({exc})"], 0
    named: dict[str, list[str]] = {}
    for r in root.findall("route"):
        named[r.get("id", "")] = r.get("edges", "").split()
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
                   vehicles: int) -> dict:
    """Run the demand with libsumo (the options of ``coloc run``) until ``end``; stop at the first sign of gridlock.

    Gridlock signs, checked every 30 simulated seconds: teleports (vehicles stuck for
    SUMO's 300 s) of more than CALIB_TELEPORTS of the ``vehicles`` due before ``end``
    (a few happen at odd junctions of real nets at any demand), more than CALIB_HALTING_SHARE of the
    vehicles in the net halting over the last CALIB_WINDOW checks after the first CALIB_WARMUP_S, or an insertion backlog above CALIB_BACKLOG of
    the vehicles departed (entries blocked).
    """
    from couplers.sumo_traffic import SumoOptions, libsumo  # noqa: PLC0415

    options = SumoOptions(net=net_path, routes=routes_path, seed=seed, end=end, tls_off=tls_off)
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
            if t >= CALIB_WARMUP_S:
                worst_share = max(worst_share, share)
            worst_backlog = max(worst_backlog, backlog)
            if t >= CALIB_WARMUP_S and share > CALIB_HALTING_SHARE:
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


def gridlock_trials_vsr_tlr(net_path: Path, routes_path: Path, seed: int, end: float, vehicles: int) -> dict:
    """The VSR and the TLR gridlock trial of one demand, side by side in two processes (libsumo is one
    simulation per process).

    Recorded as if run one after the other: VSR first; a VSR failure ends the trial (the TLR process is
    stopped and not recorded), otherwise the TLR result is added. So the record, and the files written
    from it, do not depend on which process finishes first.
    """
    import multiprocessing  # noqa: PLC0415

    jobs = {"vsr": (net_path, routes_path, True, seed, end, vehicles),
            "tlr": (net_path, routes_path, False, seed, end, vehicles)}
    # "fork": the children need nothing re-imported (spawn would re-run a caller's unguarded
    # script); libsumo is only started inside them. Without fork, one after the other.
    if "fork" not in multiprocessing.get_all_start_methods():
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
        from couplers.sumo_traffic import libsumo  # noqa: PLC0415

        if libsumo is None:
            calibrate = False
            report.not_derived.append("demand calibration against gridlock: libsumo is not installed")
    while True:
        counts = counts_for(scale)
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


def _user_routes(opts: ImportOptions, net, work: Path, report: _Report) -> None:
    src = opts.routes
    problems, n = route_problems(net, src)
    if problems:
        first = problems[0].split(": ", 1)[1] if ": " in problems[0] else problems[0]
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise InputError(src, None, first + more)
    shutil.copyfile(src, work / "demand.rou.xml")
    report.derived["demand"] = {"source": src.name, "vehicles_flows_trips": n}
    report.not_derived.append("demand from the falling profile: the user's route file is used as given")
    report.lines.append(f"demand: user's route file {src.name} ({n} vehicles/flows/trips, all routable)")


# --------------------------------------------------------------------------
# scenario.toml
# --------------------------------------------------------------------------

def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_toml(x)}" for k, x in v.items()) + " }"
    raise TypeError(v)


def _key(k: str) -> str:
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _write_scenario(work: Path, opts: ImportOptions, report: _Report) -> None:
    src = opts.source
    if opts.osm is not None:
        licence = ("OpenStreetMap data (c) OpenStreetMap contributors, ODbL 1.0 "
                   "(https://www.openstreetmap.org/copyright): keep this notice when sharing the folder")
        kind = "OpenStreetMap extract"
    else:
        licence = "as the source net's licence (unknown to coloc): check it before sharing this folder"
        kind = "SUMO net"
    digest = _sha256(src)
    inputs = {"source": src.name, "source_sha256": digest}
    for key in ("zones", "areas", "routes", "additional"):
        p = getattr(opts, key)
        if p is not None:
            inputs[key] = p.name
            inputs[key + "_sha256"] = _sha256(p)
    lines = [
        "# generated by coloc net import; what was derived and what was not is listed below",
        f"name = {_toml(opts.name)}",
        f"description = {_toml(f'imported from the {kind} {src.name}')}",
        f'units = "metres and seconds; coordinates are SUMO net x/y (GeoJSON crs {NET_CRS_NAME})"',
        f"sources = {_toml(f'{kind} {src.name} (sha256 {digest}) via coloc net import')}",
        f"licence = {_toml(licence)}",
        "",
        "[files]",
        'net = "tlr.net.xml"',
        'routes = "demand.rou.xml"',
        'zones = "zones.geojson"',
        'areas = "areas.geojson"',
        'features = "features.add.xml"',
        "",
        "[controls]",
        "tlr = { tls_off = false }",
        "vsr = { tls_off = true }",
        "",
        "[sumo]",
        "step_length = 0.75",
        f"end = {_toml(float(opts.duration_s))}",
        "",
        "[import]  # the options of the import (same inputs + seed -> identical files)",
        f"seed = {opts.seed}",
        f"feature_count = {opts.feature_count}",
        f"feature_kinds = {_toml(list(opts.feature_kinds))}",
        f"guess_signals = {_toml(opts.guess_signals)}",
        f"signals = {_toml(opts.signals)}",
        f"demand_veh_per_h = {_toml([opts.demand_start_vph, opts.demand_end_vph])}",
        f"demand_scale = {_toml(float(opts.demand_scale))}",
        f"fringe_factor = {_toml(float(opts.fringe_factor))}",
        f"zone_cell_m = {_toml(float(opts.zone_cell_m))}",
        f"route_pool = {opts.route_pool}",
        f"calibrate = {_toml(opts.calibrate)}",
        f"calibration_s = {_toml(float(opts.calibration_s or opts.duration_s))}",
        f"max_density_scale = {_toml(float(opts.max_density_scale))}",
        f"inputs = {_toml(inputs)}",
        "",
        "[derived]",
    ]
    for k, v in report.derived.items():
        lines.append(f"{_key(k)} = {_toml(v)}")
    lines += ["", "[not_derived]", f"items = {_toml(report.not_derived)}", ""]
    (work / "scenario.toml").write_text("\n".join(lines))


# --------------------------------------------------------------------------
# The import
# --------------------------------------------------------------------------

def _validate_options(opts: ImportOptions) -> None:
    if (opts.net is None) == (opts.osm is None):
        raise InputError(None, "--net/--osm", "give exactly one of --net FILE.net.xml or --osm FILE.osm[.gz]")
    if not re.fullmatch(r"[A-Za-z0-9_-]+", opts.name):
        raise InputError(None, "--name", f"{opts.name!r}: use letters, digits, '_' and '-' only")
    for key in ("net", "osm", "zones", "areas", "routes", "additional"):
        p = getattr(opts, key)
        if p is not None and not Path(p).is_file():
            raise InputError(p, None, "file not found")
    if opts.feature_count < 0:
        raise InputError(None, "--features", "must be >= 0")
    bad = [k for k in opts.feature_kinds if k not in FEATURE_KINDS]
    if bad or not opts.feature_kinds:
        what = f"unknown kind {bad[0]!r}" if bad else "at least one kind is needed"
        raise InputError(None, "--feature-kinds", f"{what} (available: {', '.join(FEATURE_KINDS)})")
    for key in ("demand_start_vph", "demand_end_vph"):
        if not getattr(opts, key) >= 0:
            raise InputError(None, "--demand", "rates must be >= 0 veh/h")
    for key, flag in (("demand_scale", "--demand-scale"), ("duration_s", "--duration"), ("zone_cell_m", "--zone-cell"),
                      ("fringe_factor", "--fringe-factor"),
                      ("max_density_scale", "--max-density-scale")):
        val = getattr(opts, key)
        if not (val > 0 and math.isfinite(val)):
            raise InputError(None, flag, "must be a positive number")
    if (why := seed_problem(opts.seed)) is not None:
        raise InputError(None, "--seed", why)
    if opts.calibration_s is not None and not opts.calibration_s > 0:
        raise InputError(None, "--calibration-s", "must be a positive number of seconds")
    if opts.route_pool < 1:
        raise InputError(None, "--route-pool", "must be >= 1")
    if opts.signals not in SIGNAL_MODES:
        raise InputError(None, "signals", f"must be one of {', '.join(SIGNAL_MODES)}")
    check_target(opts.out, (), force=opts.force, field=None)  # before the (possibly long) import


def import_net(opts: ImportOptions,
               finalize: Callable[[ImportResult], dict[Path, str]] | None = None) -> ImportResult:
    """Build the net folder ``opts.out``; ``finalize`` may return more files to write (experiment configs).

    Those files and the folder appear only when everything succeeded.
    """
    t0 = time.perf_counter()
    opts = dataclasses.replace(opts, out=Path(opts.out))
    _validate_options(opts)
    report = _Report()
    osm_counts = scan_osm(opts.osm) if opts.osm is not None else None
    if opts.net is not None:
        _check_net_xml(opts.net)
    user_geo = {key: _read_user_geojson(path, key, sig)
                for key, path, sig in (("zone", opts.zones, True), ("area", opts.areas, False)) if path is not None}
    if opts.net is not None and any(u.crs == "wgs84" for u in user_geo.values()):
        # lon/lat polygons need a geo-referenced net: say so before the (possibly long) import
        # (the folder's polygons are converted with the re-written net's <location>, the same one)
        src_georef = read_georef(opts.net)
        for user in user_geo.values():
            if user.crs == "wgs84":
                geojson_to_net_xy(user.doc, src_georef, user.src, user.how)
    extra: dict[Path, str] = {}
    created: list[Path] = []
    try:
        # an existing --out is replaced only with --force (a net folder is the user's, imported or not)
        with staged_folder(opts.out, None, force=opts.force) as work:
            track_area = _build_folder(work, opts, report, osm_counts, user_geo, t0)
            seconds = time.perf_counter() - t0
            result = ImportResult(folder=opts.out,
                                  summary={"derived": report.derived, "not_derived": report.not_derived},
                                  lines=tuple(report.lines + [f"not derived: {x}" for x in report.not_derived]),
                                  seconds=seconds, track_area=track_area)
            for dest, text in (finalize(result) if finalize is not None else {}).items():
                dest = Path(dest)
                check_target(dest, (), force=opts.force, field=None, file=True)
                created += make_dirs(dest.parent)
                extra[dest] = text
        # the folder is in place; then the extra files
        for dest, text in extra.items():
            write_file_atomic(dest, text)
        return result
    except BaseException:
        remove_created(created)
        raise


def _build_folder(work: Path, opts: ImportOptions, report: "_Report", osm_counts: dict | None,
                  user_geo: dict, t0: float) -> str:
    """Write the net folder's files into ``work``; returns the track area (the report's along/cross-track area)."""
    import sumolib  # noqa: PLC0415

    net_path = _netconvert(opts, work, report)
    t_net = time.perf_counter() - t0
    try:
        net = sumolib.net.readNet(str(net_path))
    except Exception as exc:  # sumolib raises several types on a broken net
        raise InputError(opts.source, None, f"the converted net does not load ({exc})") from None
    drivable = _drivable_edges(net)
    if not drivable:
        raise InputError(opts.source, "edge", "the net has no edge open to passenger cars "
                                              "(no drivable edges: nothing to simulate)")
    tls_nodes = [n for n in net.getNodes() if n.getType().startswith("traffic_light")]
    if not net.getTrafficLights():
        hint = (" even with --guess-signals (netconvert's tls.guess found no major junction)"
                if opts.guess_signals else
                "; pass --guess-signals to let netconvert place signals at major junctions (tls.guess)")
        raise InputError(opts.source, "traffic lights",
                         "the net has no traffic lights, so TLR and VSR would be the same" + hint)
    lane_km = sum(e.getLength() * e.getLaneNumber() for e in drivable) / 1000.0
    report.derived["net"] = {
        "junctions": len(net.getNodes()), "drivable_edges": len(drivable), "lane_km": round(lane_km, 2),
        "traffic_lights": len(net.getTrafficLights()), "signalised_junctions": len(tls_nodes),
    }
    if osm_counts is not None:
        report.derived["osm"] = osm_counts
    report.lines.append(f"net: {len(net.getNodes())} junctions, {len(drivable)} drivable edges, "
                        f"{lane_km:.1f} lane-km, {len(net.getTrafficLights())} traffic lights "
                        f"({'guessed by netconvert' if opts.guess_signals else 'from the data'}); "
                        f"netconvert {t_net:.1f} s")
    if opts.guess_signals:
        report.derived["signals"] = "guessed by netconvert (tls.guess) at major junctions"
    implausible = implausible_signal_programs(net_path)
    if implausible and opts.signals == "check":
        raise InputError(opts.source, "tlLogic",
                         f"{len(implausible)} implausible signal program(s), first: {implausible[0]}: approaches "
                         "would stay red for good and read as gridlock; pass --rebuild-signals to let netconvert "
                         "rebuild every program (--tls.rebuild), or --keep-signals to import them as they are")
    if opts.signals == "rebuild":
        report.derived["signals_rebuilt"] = "every program rebuilt by netconvert (--tls.rebuild, static)"
        report.lines.append("signals: every program rebuilt by netconvert (--tls.rebuild, static)")
    if implausible:
        report.derived["implausible_signal_programs"] = implausible
        report.not_derived.append(f"plausible signal programs: {len(implausible)} kept as they are "
                                  f"(--keep-signals), first: {implausible[0]}")

    lane_xy, _ = lane_shape_points(net_path)
    lane_lines = [LineString(l.getShape()) for e in drivable for l in e.getLanes()]
    lane_tree = shapely.STRtree(lane_lines)

    # buildings and car parks (OSM only): polyconvert in the net's projection
    buildings: list = []
    parking_polys: list = []
    if opts.osm is not None and (osm_counts["buildings"] or osm_counts["parking"]):
        poly_path = work / ".poly.xml"
        typemap = _sumo_home() / "data" / "typemap" / "osmPolyconvert.typ.xml"
        _run([_binary("polyconvert"), "--osm-files", str(opts.osm.resolve()), "--net-file", net_path.name,
              "--type-file", str(typemap), "-o", poly_path.name, "--no-warnings", "true",
              "--xml-validation", "never"], work, opts.osm, "polyconvert")
        for el in ET.parse(poly_path).getroot().iter("poly"):
            typ = el.get("type", "")
            try:
                pts = [tuple(map(float, p.split(",")[:2])) for p in el.get("shape", "").split()]
                poly = shapely.Polygon(pts)
            except (ValueError, shapely.errors.GEOSException):
                continue
            if len(pts) < 3 or not poly.is_valid or poly.area <= 0:
                poly = poly.buffer(0) if len(pts) >= 3 else None
                if poly is None or poly.is_empty:
                    continue
            if typ.startswith("building"):
                buildings.append(poly)
            elif typ == "parking" or typ.startswith("amenity.parking"):
                parking_polys.append((el.get("id", f"p{len(parking_polys)}"), poly))
        poly_path.unlink()

    # features
    stops: dict = {"bus_stop": [], "parking": []}
    if opts.osm is not None:
        stops = _additional_stops(work / ".stops.add.xml", net, opts.osm)
    if opts.additional is not None:
        more = _additional_stops(opts.additional, net, opts.additional)
        for k in stops:
            stops[k] += more[k]
    (work / ".stops.add.xml").unlink(missing_ok=True)
    cands = _candidate_features(net, stops, parking_polys, lane_tree)
    rng = np.random.default_rng(opts.seed)
    feats = _select_features(cands, opts.feature_count, opts.feature_kinds, rng)
    _write_features(work / "features.add.xml", feats, opts.source.name)
    fcounts = {k: sum(1 for f in feats if f[1] == k) for k in FEATURE_KINDS if k in opts.feature_kinds}
    report.derived["features"] = fcounts
    report.derived["feature_candidates"] = {k: len(v) for k, v in cands.items()}
    for k in opts.feature_kinds:
        if not cands[k]:
            why = {"bus_stop": "no bus stops in the data" + (" (a .net.xml holds none: pass --additional "
                                                              "with busStop elements)" if opts.osm is None else ""),
                   "parking": "no car parks in the data" + (" (pass --additional with parkingArea elements)"
                                                            if opts.osm is None else ""),
                   "traffic_light": "no signalised junction approaches",
                   "sign": "no unsignalised junction with a minor approach"}[k]
            report.not_derived.append(f"features of kind {k}: {why}")
    if len(feats) < opts.feature_count:
        report.not_derived.append(f"{opts.feature_count} features: only {len(feats)} candidate places "
                                  f"{FEATURE_MIN_SPACING_M:.0f} m apart in the net")
    report.lines.append(f"features: {len(feats)} of {opts.feature_count} requested ("
                        + ", ".join(f"{v} {k}" for k, v in fcounts.items()) + ")")

    # zones and areas
    georef = dataclasses.replace(read_georef(net_path), net=opts.source)  # messages name the user's file
    if "zone" in user_geo:
        _user_geojson(user_geo["zone"], work / "zones.geojson", georef, lane_xy, opts.source.name, report)
    elif buildings:
        _zones_from_buildings(work / "zones.geojson", lane_xy, buildings, opts.zone_cell_m, report)
    else:
        _default_zones(work / "zones.geojson", lane_xy, report)
    if "area" in user_geo:
        _user_geojson(user_geo["area"], work / "areas.geojson", georef, lane_xy, opts.source.name, report)
    else:
        _default_areas(work / "areas.geojson", lane_xy, report)
    areas = read_regions(work / "areas.geojson", "area", False)
    track_area = _busiest_area(areas, lane_lines)
    report.derived["track_area"] = track_area

    # demand
    if opts.routes is not None:
        _user_routes(opts, net, work, report)
    else:
        _write_demand(opts, net, net_path, work, lane_km, report)

    _write_scenario(work, opts, report)
    for leftover in work.glob(".*"):
        leftover.unlink()
    return track_area


def _busiest_area(areas, lane_lines: list) -> str:
    """The analysis area holding the most drivable lane length (the report's along/cross-track area)."""
    lines = np.array(lane_lines, dtype=object)
    best, best_len = areas[0].name, -1.0
    for a in areas:
        length = float(shapely.length(shapely.intersection(lines, a.polygon)).sum())
        if length > best_len + 1e-9:
            best, best_len = a.name, length
    return best
