"""A net folder (docs/architecture.md "A net folder"): scenario.toml, the net, demand, zones, areas, features.

Parsing only; geometry lookups are in ``couplers.net.zones``.
"""

from __future__ import annotations

import json
import math
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import shape

from couplers.net import ranges
from couplers.errors import InputError, read_toml
from couplers.net.buildings import Buildings

REQUIRED_FILES = ("net", "routes", "zones", "areas", "features")
BUILDINGS_FILE = "buildings.geojson"  # optional
# The GeoJSON of a net folder is in SUMO net x/y metres, marked with this private crs name.
NET_CRS_NAME = "urn:coloc:sumo-net-xy"
NET_CRS = {"type": "name", "properties": {"name": NET_CRS_NAME}}


@dataclass(frozen=True)
class Region:
    """A named polygon with properties (a GNSS zone or an analysis area)."""

    name: str
    polygon: shapely.Geometry
    sigma_p: float = float("nan")
    sigma_v: float = float("nan")


@dataclass(frozen=True)
class Features:
    ids: np.ndarray  # (K,) str
    kinds: np.ndarray  # (K,) str
    xy: np.ndarray  # (K, 2)


@dataclass(frozen=True)
class NetFolder:
    root: Path
    name: str
    net: Path
    routes: Path
    zones: tuple[Region, ...]
    areas: tuple[Region, ...]
    features: Features
    tls_off: dict[str, bool]
    scenario: dict
    buildings: "Buildings | None" = None  # buildings.geojson, optional (occlusion, NLOS GNSS)
    # [files] persons: a SUMO route file of persons (walkers), optional; loaded beside the vehicle
    # routes, and what ``[features] pedestrians = true`` needs (couplers.sensing.pedestrians).
    persons: Path | None = None
    # [files] routes may list several route files (plain or gzipped): ``routes`` is the first, these the others
    more_routes: tuple[Path, ...] = ()
    # [files] additional: SUMO additional files loaded into every run (an imported .sumocfg's signal programs)
    additional: tuple[Path, ...] = ()
    clock: "SumoClock" = None  # type: ignore[assignment]  # [sumo]; set by load_net_folder

    @property
    def route_files(self) -> tuple[Path, ...]:
        """Every route file of the demand, in the order SUMO loads them."""
        return (self.routes, *self.more_routes)


@dataclass(frozen=True)
class SumoClock:
    """A net folder's ``[sumo]`` table: the scenario's own clock (s).

    ``begin`` (default 0): when its runs start (``--begin``; SUMO drops vehicles departing before it);
    ``end``: the scenario's end; ``step_length``: the step it was built for. A config's
    ``[scenario] begin_s``, ``[scenario] step_s`` and ``[run] duration_s`` (= end - begin) default to them."""

    begin: float = 0.0
    end: float | None = None
    step_length: float | None = None


SUMO_KEYS = ("begin", "end", "step_length")


def read_sumo_clock(scen: dict, path: Path) -> SumoClock:
    """The ``[sumo]`` table of a scenario.toml (``path`` names it in errors); unknown keys are refused."""
    table = scen.get("sumo", {})
    if not isinstance(table, dict):
        raise InputError(path, "sumo", "expected a table")
    unknown = sorted(set(table) - set(SUMO_KEYS))
    if unknown:
        raise InputError(path, f"sumo.{unknown[0]}", f"unknown key (known: {', '.join(SUMO_KEYS)})")
    vals = {}
    for key in SUMO_KEYS:
        v = table.get(key)
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise InputError(path, f"sumo.{key}", f"expected a finite number of seconds, got {v!r}")
        vals[key] = float(v)
    if vals.get("begin", 0.0) < 0:
        raise InputError(path, "sumo.begin", "must be >= 0")
    if "step_length" in vals and not vals["step_length"] > 0:
        raise InputError(path, "sumo.step_length", "must be positive")
    if "end" in vals and not vals["end"] > vals.get("begin", 0.0):
        raise InputError(path, "sumo.end", f"must be after begin ({vals.get('begin', 0.0):g} s)")
    return SumoClock(**vals)


def read_json(path: Path):
    """A JSON file parsed, or one line naming it: not found, or not valid JSON (and where)."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"not valid JSON ({exc})") from None


def _load_geojson(path: Path):
    """Parse a net folder's GeoJSON file and check its crs member (net x/y only)."""
    data = read_json(path)
    if isinstance(data, dict) and data.get("crs") is not None:
        crs = data["crs"]
        name = crs.get("properties", {}).get("name") if isinstance(crs, dict) and isinstance(
            crs.get("properties"), dict) else crs
        if name != NET_CRS_NAME:
            # a folder holds net x/y only (no crs member: read as net x/y, as before the marker existed)
            raise InputError(path, "crs", f"a net folder's GeoJSON is in net x/y metres (crs {NET_CRS_NAME}), got "
                                          f"{name!r}: give WGS84 polygons to coloc net import --zones/--areas, "
                                          "which converts them with the net's projection")
    return data


def _read_regions(path: Path, key: str, with_sigmas: bool) -> tuple[Region, ...]:
    return regions_from_doc(_load_geojson(path), path, key, with_sigmas)


def _polygon_of(feat, path: Path, i: int) -> shapely.Geometry:
    """The valid, non-empty (Multi)Polygon of GeoJSON feature ``i``, prepared; else an InputError."""
    # shapely warns (RuntimeWarning, its own validity notes) on degenerate input: the one error line says it all
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            poly = shape(feat["geometry"])
        except Exception as exc:  # shapely raises several types on malformed geometry
            raise InputError(path, f"features[{i}].geometry", f"not a valid geometry ({exc})") from None
        ranges.check_coordinates(shapely.get_coordinates(poly), path, f"features[{i}].geometry")
        if poly.geom_type not in ("Polygon", "MultiPolygon") or not poly.is_valid or poly.area <= 0:
            raise InputError(path, f"features[{i}].geometry", "expected a valid, non-empty Polygon or MultiPolygon")
    shapely.prepare(poly)
    return poly


def regions_from_doc(data, path: Path, key: str, with_sigmas: bool) -> tuple[Region, ...]:
    """The regions of a parsed GeoJSON document (``path`` names it in errors); the crs member is not looked at."""
    feats = data.get("features") if isinstance(data, dict) else None
    if not isinstance(feats, list) or not feats:
        raise InputError(path, "features", "expected a GeoJSON FeatureCollection with at least one polygon")
    regions = []
    for i, feat in enumerate(feats):
        if not isinstance(feat, dict):
            raise InputError(path, f"features[{i}]", "not a GeoJSON Feature object")
        props = feat.get("properties") or {}
        name = props.get(key) if isinstance(props, dict) else None
        if not isinstance(name, str) or not name:
            raise InputError(path, f"features[{i}].properties.{key}", "missing or not a string")
        poly = _polygon_of(feat, path, i)
        sp = sv = float("nan")
        if with_sigmas:
            for fld in ("sigma_p", "sigma_v"):
                val = props.get(fld)
                if not isinstance(val, (int, float)) or isinstance(val, bool) or not val > 0:
                    raise InputError(path, f"features[{i}].properties.{fld}", "missing or not a positive number")
                ranges.check_zone_sigma(val, path, f"features[{i}].properties.{fld}", fld)
            sp, sv = float(props["sigma_p"]), float(props["sigma_v"])
        regions.append(Region(name=name, polygon=poly, sigma_p=sp, sigma_v=sv))
    return tuple(regions)


def read_regions(path: Path, key: str, with_sigmas: bool) -> tuple[Region, ...]:
    """GNSS zones (``key="zone"``, with sigma_p/sigma_v) or analysis areas (``key="area"``) of a GeoJSON file."""
    return _read_regions(Path(path), key, with_sigmas)


def read_buildings(path: str | Path) -> Buildings:
    """``buildings.geojson``: net x/y (Multi)Polygons, optional ``height`` property (m, positive).

    An empty FeatureCollection is allowed (no buildings); bad JSON, a foreign crs, an invalid
    geometry or a bad height is an InputError naming the file and the feature's field."""
    path = Path(path)
    data = _load_geojson(path)
    feats = data.get("features") if isinstance(data, dict) else None
    if not isinstance(feats, list):
        raise InputError(path, "features", "expected a GeoJSON FeatureCollection of building polygons")
    polys, heights = [], []
    for i, feat in enumerate(feats):
        if not isinstance(feat, dict):
            raise InputError(path, f"features[{i}]", "not a GeoJSON Feature object")
        polys.append(_polygon_of(feat, path, i))
        props = feat.get("properties") or {}
        h = props.get("height") if isinstance(props, dict) else None
        if h is not None and (isinstance(h, bool) or not isinstance(h, (int, float)) or not 0 < h < float("inf")):
            raise InputError(path, f"features[{i}].properties.height", f"not a positive number: {h!r}")
        heights.append(float("nan") if h is None else float(h))
    return Buildings.from_polygons(polys, heights)


def _read_features(path: Path) -> Features:
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None
    except ET.ParseError as exc:
        raise InputError(path, None, f"not valid XML ({exc})") from None
    ids, kinds, xy = [], [], []
    for i, poi in enumerate(root.iter("poi")):
        try:
            x, y = float(poi.attrib["x"]), float(poi.attrib["y"])
        except (KeyError, ValueError):
            raise InputError(path, f"poi[{i}].x/y", "missing or not a number (lane-relative POIs are not supported)") from None
        ranges.check_coordinates(np.array([x, y]), path, f"poi[{i}].x/y")
        ids.append(poi.attrib.get("id", f"poi{i}"))
        kinds.append(poi.attrib.get("type", ""))
        xy.append((x, y))
    return Features(
        ids=np.array(ids, dtype=object),
        kinds=np.array(kinds, dtype=object),
        xy=np.array(xy, dtype=float).reshape(-1, 2),
    )


def has_buildings(root: str | Path) -> bool:
    """Whether the net folder ``root`` has buildings (its ``[files] buildings``, else ``buildings.geojson``),
    without loading the folder."""
    root = Path(root)
    toml = root / "scenario.toml"
    files = read_toml(toml).get("files", {}) if toml.is_file() else {}
    name = files.get("buildings") if isinstance(files, dict) else None
    return (root / (name if isinstance(name, str) else BUILDINGS_FILE)).is_file()


def load_net_folder(root: str | Path) -> NetFolder:
    """Read and validate a net folder; raises ``InputError`` naming the file and field."""
    root = Path(root)
    scen_path = root / "scenario.toml"
    if not root.is_dir():
        raise InputError(root, None, "is a file, not a net folder (a folder with a scenario.toml)"
                         if root.exists() else "net folder not found")
    if not scen_path.exists():
        raise InputError(root, None, "is not a net folder: it has no scenario.toml")
    scen = read_toml(scen_path)
    files = scen.get("files")
    if not isinstance(files, dict):
        raise InputError(scen_path, "files", "missing table")
    paths = {}
    more_routes = []
    for key in REQUIRED_FILES:
        val = files.get(key)
        if key == "routes" and isinstance(val, list) and val and all(isinstance(v, str) for v in val):
            val, *more = val  # several route files, loaded in this order
            for i, m in enumerate(more, 1):
                if not (root / m).is_file():
                    raise InputError(scen_path, f"files.routes[{i}]", f"file {root / m} not found")
                more_routes.append(root / m)
        if not isinstance(val, str):
            raise InputError(scen_path, f"files.{key}", "missing or not a string"
                             + (" or list of strings" if key == "routes" else ""))
        p = root / val
        if not p.is_file():
            raise InputError(scen_path, f"files.{key}", f"file {p} not found")
        paths[key] = p
    clock = read_sumo_clock(scen, scen_path)
    aval = files.get("additional", [])
    aval = [aval] if isinstance(aval, str) else aval
    if not isinstance(aval, list) or not all(isinstance(v, str) for v in aval):
        raise InputError(scen_path, "files.additional", "not a string or list of strings")
    additional = tuple(root / v for v in aval)
    for i, a in enumerate(additional):
        if not a.is_file():
            raise InputError(scen_path, f"files.additional[{i}]", f"file {a} not found")
    # buildings.geojson is optional: [files] buildings names it (it must then exist), else the
    # folder's buildings.geojson is read when present.
    bval = files.get("buildings")
    if bval is not None and not isinstance(bval, str):
        raise InputError(scen_path, "files.buildings", "not a string")
    bpath = root / (bval or BUILDINGS_FILE)
    if bval is not None and not bpath.is_file():
        raise InputError(scen_path, "files.buildings", f"file {bpath} not found")
    buildings = read_buildings(bpath) if bpath.is_file() else None
    pval = files.get("persons")
    if pval is not None and not isinstance(pval, str):
        raise InputError(scen_path, "files.persons", "not a string")
    persons = root / pval if pval is not None else None
    if persons is not None and not persons.is_file():
        raise InputError(scen_path, "files.persons", f"file {persons} not found")
    controls = scen.get("controls", {"tlr": {"tls_off": False}, "vsr": {"tls_off": True}})
    tls_off = {}
    for name, spec in controls.items():
        if not isinstance(spec, dict) or not isinstance(spec.get("tls_off"), bool):
            raise InputError(scen_path, f"controls.{name}.tls_off", "missing or not a boolean")
        tls_off[name] = spec["tls_off"]
    folder = NetFolder(
        root=root.resolve(),
        name=str(scen.get("name", root.name)),
        net=paths["net"],
        routes=paths["routes"],
        zones=_read_regions(paths["zones"], "zone", with_sigmas=True),
        areas=_read_regions(paths["areas"], "area", with_sigmas=False),
        features=_read_features(paths["features"]),
        tls_off=tls_off,
        scenario=scen,
        buildings=buildings,
        persons=persons.resolve() if persons is not None else None,
        more_routes=tuple(more_routes),
        additional=additional,
        clock=clock,
    )
    ranges.check_net_folder_numbers(folder, scen_path, files)  # near the net, finite demand (couplers.net.ranges)
    return folder


def lane_shape_points(net_path: Path) -> tuple[np.ndarray, list[str]]:
    """All lane shape points of a SUMO net (internal lanes included), and each point's lane id."""
    pts: list[tuple[float, float]] = []
    owners: list[str] = []
    try:
        for _event, elem in ET.iterparse(net_path, events=("end",)):
            if elem.tag == "lane":
                for pair in elem.attrib.get("shape", "").split():
                    x, y = pair.split(",")[:2]
                    pts.append((float(x), float(y)))
                    owners.append(elem.attrib.get("id", "?"))
            elif elem.tag == "edge":
                elem.clear()
    except ET.ParseError as exc:
        raise InputError(net_path, None, f"net file does not parse as XML ({exc})") from None
    if not pts:
        raise InputError(net_path, "lane", "the net has no lanes")
    return np.array(pts, dtype=float), owners
