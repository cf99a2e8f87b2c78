"""Import a user's SUMO net, SUMO scenario or OpenStreetMap extract as a net folder (``coloc net import``).

From one ``.net.xml`` or ``.osm[.gz]`` file, or a ``.sumocfg`` (its net, route files, additional
files and clock: :mod:`couplers.net.importer.sumocfg`), this derives everything a net
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
  against the net; or the user's route files (plain or gzipped, several), checked the same way
  and copied as given; a ``.sumocfg``'s begin becomes the folder's ``[sumo] begin`` (the clock of
  its runs), and the departures before it, which SUMO drops, are counted and reported; its additional
  files' signal programs are loaded into every run (``signals.add.xml``, ``[files] additional``);
* features: traffic-light poles at the stop lines of signalised junctions,
  bus stops (OSM stop positions / ``busStop`` additionals), car parks (OSM
  ``amenity=parking`` / ``parkingArea`` additionals) and signs at the minor
  approaches of unsignalised junctions, as SUMO POIs beside the road;
* buildings: the extract's building footprints (polyconvert, OSM tags kept for the
  height: ``height``, else ``building:levels`` x 3 m) written to ``buildings.geojson`` in net
  x/y, for occlusion, NLOS GNSS episodes and the NLOS V2V curve; a footprint over a drivable
  lane (an OSM building passage) is left out and counted; an input without buildings says so;
* GNSS zones: from building density (polyconvert) when the extract has
  buildings, else a stated default layout (concentric rectangles, worst class
  in the centre), or the user's GeoJSON; analysis areas: a 3 x 2 grid or the
  user's GeoJSON. The user's GeoJSON is net x/y metres (crs
  ``urn:coloc:sumo-net-xy``) or WGS84 lon/lat (RFC 7946: no crs member, or
  CRS84 / EPSG:4326), converted with the net's own projection
  (:mod:`couplers.net.georef`); the folder always holds net x/y.

Everything is built in a temporary folder next to the output and renamed into
place only when complete; bad input raises :class:`InputError` naming the
file and field, and leaves nothing behind.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import shapely
from shapely.geometry import LineString

from couplers.errors import InputError, seed_problem
from couplers.net.georef import geojson_to_net_xy, read_georef
from couplers.net.folder import lane_shape_points, read_regions
from couplers.net.importer.demand import _user_routes, _write_demand, user_demand_trial
from couplers.net.importer.features import (
    FEATURE_KINDS,
    FEATURE_MIN_SPACING_M,
    _additional_stops,
    _candidate_features,
    _select_features,
    _write_features,
)
from couplers.net.importer.geometry import _drivable_edges, implausible_signal_programs
from couplers.net.importer.inputs import _check_net_xml, _netconvert, scan_osm
from couplers.net.importer.regions import (
    _default_areas,
    _default_zones,
    _read_user_geojson,
    _user_geojson,
    _write_buildings,
    _zones_from_buildings,
)
from couplers.net.importer.scenario import _write_scenario
from couplers.net.importer.tools import _binary, _run, _sumo_home
from couplers.publish import check_target, make_dirs, remove_created, staged_folder, write_file_atomic, write_file_keeping

SIGNAL_MODES = ("check", "rebuild", "keep")


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
    routes: Path | tuple[Path, ...] | None = None  # the user's route files (one or several, plain or gzipped)
    additional: Path | tuple[Path, ...] | None = None  # busStop / parkingArea elements for a .net.xml input
    # A SUMO configuration: its net, route files, additional files and clock (begin_s, end_s, step_length)
    sumocfg: Path | None = None
    begin_s: float | None = None  # the scenario's begin on its own clock (s); None: 0, the generated demand's
    end_s: float | None = None
    step_length: float | None = None
    ignored_options: tuple[str, ...] = ()  # options of the .sumocfg coloc does not apply
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
    # The user's route files not sorted by departure are refused (SUMO drops every vehicle departing before
    # one above it); True: the folder's copy holds them sorted, and the import says so.
    sort_routes: bool = False
    force: bool = False

    @property
    def source(self) -> Path:
        return self.osm if self.osm is not None else self.net  # type: ignore[return-value]

    @property
    def route_files(self) -> tuple[Path, ...]:
        return _paths(self.routes)

    @property
    def additional_files(self) -> tuple[Path, ...]:
        return _paths(self.additional)


def _paths(value) -> tuple[Path, ...]:
    if value is None:
        return ()
    if isinstance(value, (str, Path)):
        return (Path(value),)
    return tuple(Path(v) for v in value)


@dataclass(frozen=True)
class ImportResult:
    folder: Path
    summary: dict
    lines: tuple[str, ...]
    seconds: float
    track_area: str
    staged: Path | None = None  # where the folder is while ``finalize`` runs (it is renamed into place after)


@dataclass
class _Report:
    """What was derived and what was not (written to scenario.toml and printed)."""

    derived: dict = field(default_factory=dict)
    not_derived: list[str] = field(default_factory=list)
    lines: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------
# The import
# --------------------------------------------------------------------------

def _validate_options(opts: ImportOptions) -> None:
    from couplers.net.importer.sumocfg import is_sumocfg  # noqa: PLC0415

    if (opts.net is None) == (opts.osm is None):
        raise InputError(None, "--net/--osm/--sumocfg", "give exactly one of --net FILE.net.xml, --osm "
                                                        "FILE.osm[.gz] or --sumocfg FILE.sumocfg")
    for flag, paths in (("--net", _paths(opts.net)), ("--osm", _paths(opts.osm)), ("--routes", opts.route_files)):
        for p in paths:
            if p.is_file() and is_sumocfg(p):
                raise InputError(p, flag, "a SUMO configuration (.sumocfg): import it with --sumocfg FILE, which "
                                          "reads its net, route files, additional files and begin/end")
    if not re.fullmatch(r"[A-Za-z0-9_-]+", opts.name):
        raise InputError(None, "--name", f"{opts.name!r}: use letters, digits, '_' and '-' only")
    for key in ("net", "osm", "zones", "areas", "routes", "additional"):
        for p in _paths(getattr(opts, key)):
            if not p.is_file():
                raise InputError(p, None, "is a folder, not a file" if p.is_dir() else "file not found")
    if opts.begin_s is not None and not (opts.begin_s >= 0 and math.isfinite(opts.begin_s)):
        raise InputError(opts.sumocfg, "begin", "must be a finite time >= 0 s")
    if opts.feature_count < 1:  # a folder without features is refused by `coloc net check`
        raise InputError(None, "--features", f"must be >= 1 (a net folder needs features), got {opts.feature_count}")
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
    if opts.sumocfg is not None:
        if opts.net is not None or opts.osm is not None:
            raise InputError(None, "--net/--osm/--sumocfg", "give exactly one of --net FILE.net.xml, --osm "
                                                            "FILE.osm[.gz] or --sumocfg FILE.sumocfg")
        opts = _from_sumocfg(opts)
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
        # an existing --out is written into only with --force (a net folder is the user's, imported or
        # not); files coloc did not write are kept (couplers.publish)
        with staged_folder(opts.out, None, force=opts.force) as work:
            track_area = _build_folder(work, opts, report, osm_counts, user_geo, t0)
            seconds = time.perf_counter() - t0
            result = ImportResult(folder=opts.out,
                                  summary={"derived": report.derived, "not_derived": report.not_derived},
                                  lines=tuple(report.lines + [f"not derived: {x}" for x in report.not_derived]),
                                  seconds=seconds, track_area=track_area, staged=Path(work))
            for dest, text in (finalize(result) if finalize is not None else {}).items():
                dest = Path(dest)
                check_target(dest, (), force=opts.force, field=None, file=True)
                created += make_dirs(dest.parent)
                extra[dest] = text
        # the folder is in place; then the extra files
        for dest, text in extra.items():
            write_file_keeping(dest, text)
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
    heights: list = []
    parking_polys: list = []
    if opts.osm is not None and (osm_counts["buildings"] or osm_counts["parking"]):
        poly_path = work / ".poly.xml"
        typemap = _sumo_home() / "data" / "typemap" / "osmPolyconvert.typ.xml"
        _run([_binary("polyconvert"), "--osm-files", str(opts.osm.resolve()), "--net-file", net_path.name,
              "--type-file", str(typemap), "-o", poly_path.name, "--no-warnings", "true",
              "--all-attributes", "true", "--xml-validation", "never"], work, opts.osm, "polyconvert")
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
                heights.append(_osm_height({q.get("key"): q.get("value") for q in el.iter("param")}))
            elif typ == "parking" or typ.startswith("amenity.parking"):
                parking_polys.append((el.get("id", f"p{len(parking_polys)}"), poly))
        poly_path.unlink()

    if buildings:
        _write_buildings(work / "buildings.geojson", buildings, heights, lane_tree, report)
    elif opts.osm is not None:
        report.not_derived.append("buildings.geojson: the extract has no buildings (no occlusion by buildings; NLOS "
                                  "GNSS episodes by zone; every V2V link in line of sight)")
    else:
        report.not_derived.append("buildings.geojson: a SUMO net holds no buildings (import the OSM extract, or "
                                  "write buildings.geojson in net x/y yourself: docs/your-city.md)")

    # features
    stops: dict = {"bus_stop": [], "parking": []}
    if opts.osm is not None:
        stops = _additional_stops(work / ".stops.add.xml", net, opts.osm)
    for add in opts.additional_files:
        more = _additional_stops(add, net, add)
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
    whys = {"bus_stop": "no bus stops in the data" + (" (a .net.xml holds none: pass --additional "
                                                       "with busStop elements)" if opts.osm is None else ""),
            "parking": "no car parks in the data" + (" (pass --additional with parkingArea elements)"
                                                     if opts.osm is None else ""),
            "traffic_light": "no signalised junction approaches",
            "sign": "no unsignalised junction with a minor approach"}
    if not feats:  # a folder without features is refused by `coloc net check`: say why here instead
        raise InputError(opts.source, "--feature-kinds", "no place for a feature of the kinds asked ("
                         + "; ".join(f"{k}: {whys[k]}" for k in opts.feature_kinds) + "): add other kinds")
    for k in opts.feature_kinds:
        if not cands[k]:
            report.not_derived.append(f"features of kind {k}: {whys[k]}")
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
        _default_areas(work / "areas.geojson", lane_xy, report, lane_lines)
    areas = read_regions(work / "areas.geojson", "area", False)
    track_area = _busiest_area(areas, lane_lines)
    report.derived["track_area"] = track_area

    # demand
    route_names = ["demand.rou.xml"]
    if opts.routes is not None:
        route_names = _user_routes(opts, net, work, report)
    else:
        _write_demand(opts, net, net_path, work, lane_km, report)
    if opts.sumocfg is not None:
        _sumocfg_extras(opts, net, work, report)
    if opts.routes is not None:  # after the .sumocfg's signal programs, which the trial loads as the runs do
        user_demand_trial(opts, work, route_names, report)

    _write_scenario(work, opts, report, route_names)
    for leftover in work.glob(".*"):
        leftover.unlink()
    return track_area


def _from_sumocfg(opts: ImportOptions) -> ImportOptions:
    """The options with what the .sumocfg names: net, route files, additional files, clock."""
    from couplers.net.importer.sumocfg import read_sumocfg  # noqa: PLC0415

    if opts.routes is not None or opts.additional is not None:
        raise InputError(opts.sumocfg, "--routes/--additional", "not with --sumocfg: the configuration names the "
                                                                 "route and additional files")
    cfg = read_sumocfg(opts.sumocfg)
    return dataclasses.replace(opts, net=cfg.net, routes=cfg.routes, additional=cfg.additional or None,
                               begin_s=cfg.begin if cfg.begin is not None else 0.0, end_s=cfg.end,
                               step_length=cfg.step_length, ignored_options=cfg.ignored)


def _sumocfg_extras(opts: ImportOptions, net, work: Path, report: "_Report") -> None:
    """The .sumocfg's signal programs (``signals.add.xml``, loaded into the runs), what the import took from
    the configuration, and what it left out (never silently)."""
    from couplers.net.importer.sumocfg import SIGNAL_TAGS, clock, program_problems, signal_programs  # noqa: PLC0415

    begin = opts.begin_s or 0.0
    report.derived["sumocfg"] = {
        "file": opts.sumocfg.name, "net": opts.net.name, "route_files": [p.name for p in opts.route_files],
        "additional_files": [p.name for p in opts.additional_files], "begin_s": begin,
        **({"end_s": opts.end_s} if opts.end_s is not None else {}),
        **({"step_length_s": opts.step_length} if opts.step_length is not None else {}),
    }
    end = f" to {opts.end_s:g} s ({clock(opts.end_s)})" if opts.end_s is not None else " (no end given)"
    report.lines.append(f"scenario: {opts.sumocfg.name}: begin {begin:g} s ({clock(begin)}){end}"
                        + (f", step {opts.step_length:g} s" if opts.step_length is not None else "")
                        + "; runs simulate from this begin ([sumo] begin, [scenario] begin_s)")
    if opts.additional_files:
        names = ", ".join(p.name for p in opts.additional_files)
        text, programs, others = signal_programs(opts.additional_files, f"{opts.sumocfg.name} ({names})")
        if text is not None:
            bad = program_problems(net, opts.additional_files)
            if bad:
                raise InputError(opts.sumocfg, "additional-files", bad[0].split(": ", 1)[1]
                                 + (f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""))
            (work / "signals.add.xml").write_text(text, encoding="utf-8")
            report.derived["signal_programs"] = {"file": "signals.add.xml", "programs": programs}
            report.lines.append(f"signals: {len(programs)} signal program(s) of {names} loaded into every run "
                                f"(signals.add.xml; SUMO runs the last one loaded for each light, as with the "
                                f".sumocfg); VSR still switches every signal off")
        if others:
            what = ", ".join(f"{n} {tag}" for tag, n in sorted(others.items()))
            report.not_derived.append(
                f"additional elements in the runs: {what} of {names} are not loaded into coloc's runs (only "
                f"{', '.join(SIGNAL_TAGS)} are; busStop and parkingArea are feature places)")
    if opts.ignored_options:
        report.not_derived.append(f"options of {opts.sumocfg.name} coloc does not apply: "
                                  + ", ".join(opts.ignored_options))


_NUMBER = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*(m|metres|meters)?\s*$")


def _osm_height(tags: dict) -> float:
    """A building's height in metres from its OSM tags: ``height`` (plain metres, "12 m"), else
    ``building:levels`` x 3 m (the storey height commonly assumed for OSM levels); NaN if neither parses."""
    m = _NUMBER.match(tags.get("height") or "")
    if m and float(m.group(1)) > 0:
        return float(m.group(1))
    m = _NUMBER.match(tags.get("building:levels") or "")
    if m and float(m.group(1)) > 0:
        return 3.0 * float(m.group(1))
    return float("nan")


def _busiest_area(areas, lane_lines: list) -> str:
    """The analysis area holding the most drivable lane length (the report's along/cross-track area)."""
    lines = np.array(lane_lines, dtype=object)
    best, best_len = areas[0].name, -1.0
    for a in areas:
        length = float(shapely.length(shapely.intersection(lines, a.polygon)).sum())
        if length > best_len + 1e-9:
            best, best_len = a.name, length
    return best
