"""WGS84 lon/lat GeoJSON to SUMO net x/y, with the net's own geo-reference.

A SUMO net records how netconvert projected it in ``<location netOffset="dx,dy"
projParameter="PROJ string">``: net x/y = projection(lon, lat) + netOffset, a
bare PROJ projection without datum shift (SUMO's GeoConvHelper). sumolib's
``net.convertLonLat2XY`` computes the same with ``pyproj.Proj(projParameter)``
one point at a time; :func:`lonlat_to_xy` builds that very Proj (a pyproj
Transformer from the projection pipeline) once and applies it to all points in
one vectorised call. ``projParameter="!"`` means the net has no geo-reference
(netgenerate, plain XML nodes/edges): lon/lat cannot be placed in it.
"""

from __future__ import annotations

import copy
import gzip
import json
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from couplers.errors import InputError
from couplers.net.folder import NET_CRS, NET_CRS_NAME

# crs names read as WGS84 lon/lat; a document without a crs member is lon/lat too (RFC 7946)
WGS84_CRS_NAMES = ("urn:ogc:def:crs:OGC:1.3:CRS84", "EPSG:4326", "urn:ogc:def:crs:EPSG::4326")
NO_GEOREF = "!"


@dataclass(frozen=True)
class GeoRef:
    """The ``<location>`` of a SUMO net."""

    net: Path
    net_offset: tuple[float, float]
    proj: str  # projParameter; "!" = no geo-reference

    @property
    def has_proj(self) -> bool:
        return self.proj != NO_GEOREF


def read_georef(net_path: Path) -> GeoRef:
    """``<location netOffset projParameter>`` of a net (no ``<location>``: no geo-reference)."""
    net_path = Path(net_path)
    try:
        with (gzip.open(net_path, "rb") if net_path.suffix == ".gz" else open(net_path, "rb")) as fh:
            for _event, elem in ET.iterparse(fh, events=("start",)):
                if elem.tag == "location":
                    try:
                        dx, dy = (float(v) for v in elem.get("netOffset", "0,0").split(","))
                    except ValueError:
                        raise InputError(net_path, "location.netOffset",
                                         f"not two numbers ({elem.get('netOffset')!r})") from None
                    return GeoRef(net_path, (dx, dy), elem.get("projParameter", NO_GEOREF).strip() or NO_GEOREF)
                if elem.tag in ("edge", "junction", "type", "tlLogic"):
                    break  # <location> comes first in a SUMO net
    except (ET.ParseError, OSError, EOFError) as exc:
        raise InputError(net_path, None, f"not valid XML ({exc})") from None
    return GeoRef(net_path, (0.0, 0.0), NO_GEOREF)


def lonlat_to_xy(georef: GeoRef, lon, lat) -> tuple[np.ndarray, np.ndarray]:
    """Net x/y of WGS84 lon/lat (arrays), as sumolib's ``net.convertLonLat2XY`` computes them."""
    import pyproj  # noqa: PLC0415

    try:
        proj = pyproj.Proj(projparams=georef.proj)
    except (pyproj.exceptions.CRSError, RuntimeError) as exc:
        raise InputError(georef.net, "location.projParameter",
                         f"projection {georef.proj!r} is not one pyproj can use ({exc})") from None
    x, y = proj.transform(np.asarray(lon, dtype=float), np.asarray(lat, dtype=float))
    return np.asarray(x) + georef.net_offset[0], np.asarray(y) + georef.net_offset[1]


def crs_kind(doc: dict, src: Path) -> tuple[str, str]:
    """("net" | "wgs84", how the file says so) for a GeoJSON document; other CRSs are an InputError."""
    accepted = (f"accepted: no crs member (RFC 7946) or {', '.join(WGS84_CRS_NAMES)} for WGS84 lon/lat, "
                f"or {json.dumps(NET_CRS)} for net x/y metres")
    crs = doc.get("crs")
    if crs is None:
        return "wgs84", "no crs member, RFC 7946"
    props = crs.get("properties") if isinstance(crs, dict) else None
    name = props.get("name") if isinstance(props, dict) else None
    if not isinstance(name, str) or crs.get("type", "name") != "name":
        raise InputError(src, "crs", f"not a named crs ({json.dumps(crs)[:80]}); {accepted}")
    if name == NET_CRS_NAME:
        return "net", f"crs {NET_CRS_NAME}"
    if name.strip().upper() in {n.upper() for n in WGS84_CRS_NAMES}:
        return "wgs84", f"crs {name}"
    raise InputError(src, "crs", f"{name!r} is not supported; {accepted}; reproject other CRSs to WGS84 first "
                                 "(e.g. QGIS Export > Save Features As, CRS EPSG:4326)")


def _positions(coords) -> list:
    """Every position ([x, y, ...] list) of a GeoJSON coordinates array, in order (same objects)."""
    out: list = []
    stack = [coords]
    while stack:
        c = stack.pop()
        if isinstance(c, list) and c and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in c):
            out.append(c)
        elif isinstance(c, list):
            stack.extend(reversed(c))
    return out


def check_lonlat(doc: dict, src: Path, how: str) -> None:
    """Every position of a lon/lat document is a plausible lon/lat (|lon| <= 180, |lat| <= 90)."""
    for i, feat in enumerate(doc["features"]):
        for pos in _positions(feat["geometry"]["coordinates"]):
            lon, lat = float(pos[0]), float(pos[1])
            if not (math.isfinite(lon) and math.isfinite(lat) and abs(lon) <= 180.0 and abs(lat) <= 90.0):
                raise InputError(src, f"features[{i}].geometry.coordinates",
                                 f"[{pos[0]}, {pos[1]}] is not a lon/lat (|lon| <= 180, |lat| <= 90) but the file "
                                 f"is read as WGS84 lon/lat ({how}); if the coordinates are net x/y metres, add "
                                 f"\"crs\": {json.dumps(NET_CRS)} to the FeatureCollection")


def geojson_to_net_xy(doc: dict, georef: GeoRef, src: Path, how: str, decimals: int = 3) -> dict:
    """A copy of a lon/lat FeatureCollection in net x/y metres (rounded to ``decimals``) with the net crs marker."""
    if not georef.has_proj:
        raise InputError(src, "crs", f"the polygons are WGS84 lon/lat ({how}) but the net {georef.net} has no "
                                     "geo-reference (<location projParameter=\"!\">: built by netgenerate or from "
                                     "plain XML nodes/edges), so lon/lat cannot be placed in it; give the polygons "
                                     f"in net x/y metres with \"crs\": {json.dumps(NET_CRS)}")
    out = copy.deepcopy(doc)
    positions = [p for feat in out["features"] for p in _positions(feat["geometry"]["coordinates"])]
    lon = np.array([p[0] for p in positions], dtype=float)
    lat = np.array([p[1] for p in positions], dtype=float)
    x, y = lonlat_to_xy(georef, lon, lat)
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        k = int(np.flatnonzero(~(np.isfinite(x) & np.isfinite(y)))[0])
        raise InputError(src, "features", f"[{lon[k]}, {lat[k]}] cannot be projected with the net's projection "
                                          f"{georef.proj!r}")
    x, y = np.round(x, decimals), np.round(y, decimals)
    for p, xi, yi in zip(positions, x.tolist(), y.tolist()):
        p[:] = [xi, yi]  # z, if any, is dropped: net x/y only
    out.pop("crs", None)
    out.pop("bbox", None)  # RFC 7946 bounding boxes are lon/lat: dropped rather than left stale
    for feat in out["features"]:
        feat.pop("bbox", None)
        feat["geometry"].pop("bbox", None)
    ordered = {"type": out.pop("type", "FeatureCollection"), "crs": NET_CRS}
    ordered.update(out)
    return ordered


def conversion_note(georef: GeoRef, how: str) -> dict:
    """What the conversion used (for scenario.toml)."""
    return {"from": f"WGS84 lon/lat ({how})", "projection": georef.proj,
            "net_offset": [georef.net_offset[0], georef.net_offset[1]],
            "rule": "net x/y = projection(lon, lat) + netOffset (the net's <location>, as sumolib convertLonLat2XY)"}
