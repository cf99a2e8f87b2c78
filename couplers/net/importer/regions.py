"""GNSS zones and analysis areas of ``coloc net import``.

From building density (polyconvert), the stated default layouts, or the user's GeoJSON (net x/y, or
WGS84 lon/lat converted with the net's projection).
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import shapely
from shapely.geometry import box, mapping

from couplers.errors import InputError
from couplers.net.georef import GeoRef, check_lonlat, conversion_note, crs_kind, geojson_to_net_xy
from couplers.net.folder import NET_CRS as CRS
from couplers.net.folder import read_json, regions_from_doc
from couplers.net.importer.geometry import _fmt

if TYPE_CHECKING:
    from couplers.net.importer import _Report

# GNSS classes (docs/architecture.md "Models and default parameters", Brambilla Sec. VI): zone -> (sigma_p m, sigma_v m/s).
ZONE_PARAMS = {"A": (3.0, 0.1), "B": (8.0, 0.17), "C": (15.0, 0.45)}
# Built-up fraction of a zone cell (building footprint area / cell area) from
# which the cell gets the worse class: >= 0.30 dense urban canyon (C),
# >= 0.12 built-up (B), else open sky (A).
BUILT_FRACTION_C = 0.30
BUILT_FRACTION_B = 0.12
ZONE_MARGIN_M = 60.0
# At most this many building-density cells over a net: each is a shapely intersection with the buildings
# (1 m cells over the test grid of tests/osmfixture.py, about 5e5 cells, took minutes); a --zone-cell giving
# more is refused, naming the count.
ZONE_CELLS_MAX = 100_000


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


def _write_buildings(path: Path, buildings: list, heights: list, lane_tree, report: _Report) -> None:
    """``buildings.geojson`` in net x/y: every footprint not crossed by a drivable lane (an OSM building
    passage over a street would block every sight line along it), ``height`` where the tags give one."""
    polys = np.empty(len(buildings), dtype=object)
    polys[:] = buildings
    hit = np.unique(lane_tree.query(polys, predicate="intersects")[0])
    keep = np.ones(len(polys), dtype=bool)
    keep[hit] = False
    feats = []
    for i in np.flatnonzero(keep):
        geom = _round_geom(polys[i])
        if geom.is_empty or not geom.is_valid or geom.area <= 0:  # a sliver lost to the 1 cm grid
            keep[i] = False
            continue
        props = {} if not np.isfinite(heights[i]) else {"height": round(float(heights[i]), 2)}
        feats.append({"type": "Feature", "properties": props, "geometry": mapping(geom)})
    doc = {"type": "FeatureCollection", "crs": CRS, "features": feats}
    path.write_text(json.dumps(doc, separators=(",", ":")) + "\n")
    n_h = int(np.isfinite(np.asarray(heights, dtype=float)[keep]).sum())
    report.derived["buildings"] = {"footprints": int(keep.sum()), "with_height": n_h, "over_lanes_left_out": int(hit.size)}
    report.lines.append(f"buildings: {int(keep.sum())} footprints ({n_h} with a height from OSM tags) in buildings.geojson"
                        + (f"; {hit.size} over drivable lanes left out" if hit.size else ""))


def _zones_from_buildings(path: Path, lane_xy: np.ndarray, buildings: list, cell: float, report: _Report) -> None:
    x0, y0, x1, y1, nx, ny = _grid_bbox(lane_xy, cell)
    if nx * ny > ZONE_CELLS_MAX:
        raise InputError(None, "--zone-cell", f"{_fmt(cell)} m gives {nx} x {ny} = {nx * ny} cells over this net, "
                                              f"more than {ZONE_CELLS_MAX}: choose a larger cell")
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


def _default_areas(path: Path, lane_xy: np.ndarray, report: _Report, lane_lines: list | None = None) -> None:
    """A 3 x 2 (or 2 x 3) grid over the lanes' bounding box, numbered from the south-west; cells no drivable
    lane crosses (``lane_lines``) and that hold no lane shape point (``lane_xy``: every lane of the net,
    footpaths and rails too, which ``coloc net check`` wants covered) are dropped and listed as not derived
    (the others keep their numbers)."""
    x0, y0, x1, y1, _, _ = _grid_bbox(lane_xy, 1.0)
    wide = (x1 - x0) >= (y1 - y0)
    ncol, nrow = (3, 2) if wide else (2, 3)
    xs = np.linspace(x0, x1, ncol + 1).round(2)
    ys = np.linspace(y0, y1, nrow + 1).round(2)
    feats = []
    empty = []
    k = 1
    for j in range(nrow):
        for i in range(ncol):
            cell = box(xs[i], ys[j], xs[i + 1], ys[j + 1])
            if (lane_lines is not None and not any(cell.intersects(line) for line in lane_lines)
                    and not shapely.intersects_xy(cell, lane_xy[:, 0], lane_xy[:, 1]).any()):
                empty.append(str(k))
            else:
                feats.append({"type": "Feature", "properties": {"area": str(k)}, "geometry": mapping(cell)})
            k += 1
    _write_geojson(path, feats)
    kept = ", ".join(f["properties"]["area"] for f in feats)
    report.derived["areas"] = (f"default partition: {ncol} x {nrow} grid over the net, numbered from the south-west"
                               + (f"; cells without a road dropped: {', '.join(empty)}" if empty else ""))
    report.not_derived.append(f"analysis areas from data: a default {ncol} x {nrow} grid over the net's bounding box "
                              "(pass --areas with your own GeoJSON)")
    if empty:
        report.not_derived.append(f"areas {', '.join(empty)} of the default grid: no road crosses them (dropped)")
    report.lines.append(f"areas: default {ncol} x {nrow} grid ({kept})"
                        + (f"; {', '.join(empty)} dropped (no road)" if empty else ""))


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
    doc = read_json(src)
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
