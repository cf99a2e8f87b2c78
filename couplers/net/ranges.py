"""Physical ranges of the numbers a net folder's files hold, checked when the folder is loaded.

:func:`couplers.net.folder.load_net_folder` (and with it ``coloc net check`` and ``coloc run``)
refuses, with one line naming the file and the field:

* a GNSS zone's ``sigma_p`` / ``sigma_v`` outside :data:`ZONE_SIGMA` (NaN and infinities included:
  Python's JSON reader accepts ``NaN`` and ``Infinity``);
* a non-finite coordinate in a GeoJSON geometry (zones, areas, buildings) or a POI of the features
  file, and one farther than :data:`REGION_MARGIN_M` / :data:`FEATURE_MARGIN_M` from the net's
  boundary (``<location convBoundary>`` of the net file);
* a time, rate, count, position or speed of the demand (routes file) or of the persons file that is
  not a finite number in its range (:data:`DEMAND_RANGES`), naming that file, not the net; values
  SUMO reads as words or expressions (``depart="triggered"``, ``departPos="random"``, ``period="exp(0.1)"``,
  ``1:00:00``) are left to SUMO;
* a NaN or infinite number anywhere in ``scenario.toml`` (TOML has ``nan`` and ``inf``).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from couplers.errors import InputError

#: zones.geojson properties: (low, high, unit, why); low exclusive, high inclusive.
ZONE_SIGMA = {
    "sigma_p": (0.0, 1e3, "m", "a GNSS position error beyond 1 km locates nothing"),
    "sigma_v": (0.0, 100.0, "m/s", "a GNSS velocity error beyond 100 m/s exceeds any road speed"),
}
#: A feature (POI) or person lies at most this far outside the net's boundary (``coloc net check``
#: then asks for 30 m from a drivable lane; 10 km catches a wrong projection or unit).
FEATURE_MARGIN_M = 1e4
#: A zone, area or building vertex lies at most this far outside the net's boundary (zones may be drawn
#: generously around the net; 100 km is beyond any city).
REGION_MARGIN_M = 1e5
#: Any coordinate of a net folder: SUMO net x/y of a projected map stay within 10,000 km.
COORD_MAX_M = 1e7

_DAY_S = 86400.0
TIME_MAX_S = 365 * _DAY_S  # a simulation time beyond a year is a typo
#: Numeric attributes of the demand and persons files: name -> (low, high, unit, why), both inclusive.
DEMAND_RANGES: dict[str, tuple[float, float, str, str]] = {
    "depart": (0.0, TIME_MAX_S, "s", "a simulation time, at most a year"),
    "begin": (0.0, TIME_MAX_S, "s", "a simulation time, at most a year"),
    "end": (0.0, TIME_MAX_S, "s", "a simulation time, at most a year"),
    "until": (0.0, TIME_MAX_S, "s", "a simulation time, at most a year"),
    "period": (0.0, TIME_MAX_S, "s", "a simulation time, at most a year"),
    "duration": (0.0, TIME_MAX_S, "s", "a simulation time, at most a year"),
    "vehsPerHour": (0.0, 1e5, "1/h", "beyond the capacity of any road"),
    "perHour": (0.0, 1e5, "1/h", "beyond the capacity of any road"),
    "personsPerHour": (0.0, 1e5, "1/h", "beyond the capacity of any sidewalk"),
    "probability": (0.0, 1.0, "1", "a probability per second"),
    "number": (0.0, 1e7, "1", "ten million vehicles or persons"),
    "departPos": (-1e5, 1e5, "m", "a position on a lane of at most 100 km"),
    "arrivalPos": (-1e5, 1e5, "m", "a position on a lane of at most 100 km"),
    "departSpeed": (0.0, 150.0, "m/s", "above any road speed"),
    "arrivalSpeed": (0.0, 150.0, "m/s", "above any road speed"),
    "speed": (0.0, 150.0, "m/s", "above any road speed"),
    "maxSpeed": (0.0, 150.0, "m/s", "above any road speed"),
    "accel": (0.0, 50.0, "m/s^2", "5 g"),
    "decel": (0.0, 50.0, "m/s^2", "5 g"),
    "emergencyDecel": (0.0, 100.0, "m/s^2", "10 g"),
    "apparentDecel": (0.0, 100.0, "m/s^2", "10 g"),
    "sigma": (0.0, 1.0, "1", "SUMO's driver imperfection"),
    "tau": (0.0, 60.0, "s", "a reaction time of a minute"),
    "length": (0.0, 1e3, "m", "a vehicle or train of 1 km"),
    "width": (0.0, 100.0, "m", "a vehicle of 100 m width"),
    "height": (0.0, 100.0, "m", "a vehicle of 100 m height"),
    "minGap": (0.0, 1e3, "m", "a standstill gap of 1 km"),
    "speedFactor": (0.0, 100.0, "1", "a factor of the speed limit"),
    "speedDev": (0.0, 100.0, "1", "a spread of the speed factor"),
}


def _in(value: float, low: float, high: float, low_open: bool = False) -> bool:
    return (value > low if low_open else value >= low) and value <= high


def check_zone_sigma(value, path: Path, where: str, name: str) -> None:
    """A GNSS zone's ``sigma_p`` / ``sigma_v`` (already known to be a number): finite and in its range."""
    low, high, unit, why = ZONE_SIGMA[name]
    if not _in(float(value), low, high, low_open=True):
        raise InputError(path, where, f"{value:g} {unit} is outside ({low:g}, {high:g}] {unit} ({why})")


def check_coordinates(coords: np.ndarray, path: Path, where: str) -> None:
    """Every coordinate finite and within :data:`COORD_MAX_M` of the origin."""
    coords = np.asarray(coords, dtype=float)
    bad = ~np.isfinite(coords) | (np.abs(coords) > COORD_MAX_M)
    if bad.any():
        v = coords.ravel()[np.flatnonzero(bad.ravel())[0]]
        raise InputError(path, where, f"coordinate {v:g} m is not finite or beyond {COORD_MAX_M:g} m "
                                      "(a folder holds SUMO net x/y metres)")


def net_boundary(net_path: Path) -> tuple[float, float, float, float] | None:
    """``convBoundary`` of the net's ``<location>`` (xmin, ymin, xmax, ymax), or None when the net has none
    (or it does not parse: the net's own checks report that)."""
    try:
        for _event, elem in ET.iterparse(net_path, events=("start",)):
            if elem.tag == "location":
                parts = [float(v) for v in elem.attrib.get("convBoundary", "").split(",")]
                return tuple(parts) if len(parts) == 4 and all(map(math.isfinite, parts)) else None
            if elem.tag in ("edge", "junction"):
                return None  # <location> comes first in a SUMO net
    except (ET.ParseError, ValueError, OSError):
        return None
    return None


def check_within(xy: np.ndarray, box, margin: float, path: Path, where, what) -> None:
    """Points ``xy`` (N, 2) within ``margin`` of the net boundary ``box``; ``where(i)`` names point i's field,
    ``what(i)`` the point."""
    if box is None or len(xy) == 0:
        return
    xmin, ymin, xmax, ymax = box
    d = np.maximum.reduce([xmin - xy[:, 0], xy[:, 0] - xmax, ymin - xy[:, 1], xy[:, 1] - ymax])
    far = np.flatnonzero(~(d <= margin))
    if far.size:
        i = int(far[0])
        raise InputError(path, where(i), f"{what(i)} at x={xy[i, 0]:g}, y={xy[i, 1]:g} lies {d[i]:g} m outside "
                                         f"the net's boundary (more than {margin:g} m; convBoundary of the net)")


def _number(text: str) -> float | None:
    """The value of a numeric attribute, None for SUMO's words, expressions and h:m:s times."""
    try:
        return float(text)
    except ValueError:
        return None


def check_demand_numbers(path: Path) -> None:
    """Every numeric attribute of :data:`DEMAND_RANGES` in a routes or persons file: finite and in range.

    Errors name ``path`` and the field ``tag[i].attribute`` (i counts the elements of that tag)."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError):
        return  # the route checks (coloc net check) report an unreadable file
    counts: dict[str, int] = {}
    for el in root.iter():
        i = counts.get(el.tag, 0)
        counts[el.tag] = i + 1
        for name, text in el.attrib.items():
            spec = DEMAND_RANGES.get(name)
            if spec is None:
                continue
            value = _number(text)
            if value is None:
                continue
            low, high, unit, why = spec
            if not _in(value, low, high):
                ident = f" ({el.tag} {el.get('id')!r})" if el.get("id") is not None else ""
                unit_t = "" if unit == "1" else f" {unit}"
                raise InputError(path, f"{el.tag}[{i}].{name}",
                                 f"{text}{unit_t} is outside [{low:g}, {high:g}]{unit_t} ({why}){ident}")


def check_toml_finite(data, path: Path, prefix: str = "") -> None:
    """No NaN or infinity anywhere in a parsed TOML document (scenario.toml)."""
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, list) else ()
    for key, value in items:
        where = f"{prefix}[{key}]" if isinstance(data, list) else (f"{prefix}.{key}" if prefix else str(key))
        if isinstance(value, float) and not math.isfinite(value):
            raise InputError(path, where, f"{value} is not a finite number")
        if isinstance(value, (dict, list)):
            check_toml_finite(value, path, where)


def check_net_folder_numbers(folder, scen_path: Path, files: dict) -> None:
    """The numbers of a loaded :class:`couplers.net.folder.NetFolder` that need the net or other files:
    features, zones, areas and buildings near the net's boundary, the demand's and persons' numbers and
    scenario.toml's."""
    import shapely  # noqa: PLC0415

    check_toml_finite(folder.scenario, scen_path)
    box = net_boundary(folder.net)
    feats = folder.features
    check_within(feats.xy, box, FEATURE_MARGIN_M, folder.root / files["features"], lambda i: f"poi[{i}].x/y",
                 lambda i: f"poi {feats.ids[i]!r}")
    layers = [(files["zones"], [r.polygon for r in folder.zones]), (files["areas"], [r.polygon for r in folder.areas])]
    if folder.buildings is not None:
        layers.append((files.get("buildings", "buildings.geojson"), list(folder.buildings.polygons)))
    for name, polygons in layers:
        for i, poly in enumerate(polygons):
            check_within(shapely.get_coordinates(poly), box, REGION_MARGIN_M, folder.root / name,
                         lambda _k, i=i: f"features[{i}].geometry", lambda _k: "a vertex")
    check_demand_numbers(folder.routes)
    if folder.persons is not None:
        check_demand_numbers(folder.persons)
