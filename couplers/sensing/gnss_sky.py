"""The sky of the ``[gnss_error] model = "satellites"`` receivers: a GPS + Galileo constellation seen from the net,
and the line of sight of every (vehicle, satellite) pair past the net folder's buildings.

Constellation (:data:`CONSTELLATIONS`, synthetic, Walker-like, with the real planes and orbit sizes):

* GPS: 24 satellites in 6 planes (right ascensions 60 deg apart), inclination 55 deg, semi-major axis 26 560 km
  (period 11 h 58 min), 4 per plane, phased as a Walker 24/6/2 (assumption: the real GPS slots are not a
  Walker pattern, and ~31 satellites fly rather than the 24 of the baseline; fewer satellites than in reality,
  so the geometry is, if anything, pessimistic). Planes, inclination and radius: the GPS SPS Performance
  Standard's baseline 24-slot constellation (6 planes A-F, 55 deg, 26 560 km).
* Galileo: Walker 24/3/1, inclination 56 deg, semi-major axis 29 600 km (period 14 h 05 min): the nominal
  Galileo constellation (three planes, eight satellites each).
* Circular Kepler orbits, period 2 pi sqrt(a^3 / mu) with mu = 3.986004418e14 m^3/s^2 (WGS 84), propagated in
  an Earth-centred inertial frame and rotated into ECEF with the Earth's rate 7.2921151467e-5 rad/s (WGS 84).
  ``constellation_time_s`` is the time of the run's t = 0 after the constellation's epoch (at which each plane's
  right ascension and each satellite's argument of latitude take their Walker values).
* Seen from the net's geographic reference: the WGS 84 lon/lat of net x/y (0, 0) through the net's own
  projection (``<location projParameter>``, :mod:`couplers.net.georef`); a net without geo-reference is placed at
  :data:`DEFAULT_LAT_DEG` / :data:`DEFAULT_LON_DEG` (Turin, 45.07 N 7.69 E: the arterial is Turin-like). The few km
  of a net change a satellite's direction by hundredths of a degree: one direction per satellite for the whole
  net. Net x/y are taken as east / north (a projected net's grid convergence, a degree or two, is neglected).

Line of sight (:func:`line_of_sight`): from the antenna (``antenna_height_m`` above the ground, the ground at 0) a
ray in the satellite's azimuth rising at its elevation. It is blocked by a building when it enters the building's
extruded footprint below the roof: the 2-D ray crosses the footprint at horizontal distance d (its first
crossing) where d tan(el) + h_ant < h_building, or the antenna stands inside the footprint below the roof. Walls
are vertical and roofs flat (the footprint extruded to ``height``). The ray's height grows with d, so the first
crossing of a footprint is its lowest point there: one test per building. Candidate buildings per vehicle: those whose
bounding box lies within the distance at which a ray at the elevation mask clears the tallest roof, found through
a grid of square cells (a quarter of that size, :data:`LOS_GRID_DIVISIONS`) listing the buildings whose box meets each
cell (one numba kernel, no per-pair Python); per (vehicle, building) the satellites are visited by rising elevation and
the building is left at the first satellite whose ray its bounding box is already too close to the ground to block
(a box at distance b cannot block when b tan(el) + h_ant >= h, nor then at any higher elevation); a satellite whose
horizontal ray misses the box (grown by :data:`BOX_MARGIN_M`) is skipped: no edge can be crossed. Blocked sets and
distances are those of testing every satellite against every edge (``line_of_sight(..., box_test=False)``, tested).
The receiver (:meth:`couplers.sensing.gnss_satellites.SatelliteErrorProcess.pseudorange_errors`) lists each
antenna's candidate buildings once a step for the line of sight and the reflections (:func:`building_candidates`,
:func:`los_listed`, the same results, tested); the list depends on the position alone, so a vehicle at bitwise the
same position as at the last step takes its list over.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from numba import njit

from couplers.net.buildings import Buildings, _cell_lists

MU_EARTH = 3.986004418e14  # m^3/s^2, WGS 84
OMEGA_EARTH = 7.2921151467e-5  # rad/s, WGS 84
WGS84_A = 6378137.0  # m
WGS84_F = 1.0 / 298.257223563
DEFAULT_LAT_DEG = 45.07  # Turin (assumption for a net without geo-reference)
DEFAULT_LON_DEG = 7.69


@dataclass(frozen=True)
class Constellation:
    """A Walker T/P/F constellation: ``t`` satellites in ``p`` planes, phasing ``f``."""

    name: str
    t: int
    p: int
    f: int
    inclination_deg: float
    a_m: float

    @property
    def period_s(self) -> float:
        return 2.0 * math.pi * math.sqrt(self.a_m ** 3 / MU_EARTH)

    def elements(self) -> tuple[np.ndarray, np.ndarray]:
        """(raan0, u0) of each satellite (rad): plane k at RAAN 2 pi k / p, slot j at 2 pi j / s + 2 pi f k / t."""
        s = self.t // self.p
        k, j = np.divmod(np.arange(self.t), s)
        raan = 2.0 * np.pi * k / self.p
        u = 2.0 * np.pi * j / s + 2.0 * np.pi * self.f * k / self.t
        return raan, u


GPS = Constellation("GPS", 24, 6, 2, 55.0, 26_560e3)
GALILEO = Constellation("Galileo", 24, 3, 1, 56.0, 29_600e3)
CONSTELLATIONS = (GPS, GALILEO)


@dataclass(frozen=True)
class Sky:
    """Every satellite's orbital elements (arrays over the satellites of :data:`CONSTELLATIONS`, in order) and the
    receivers' geographic reference."""

    raan0: np.ndarray
    u0: np.ndarray
    inc: np.ndarray
    a: np.ndarray
    n: np.ndarray  # mean motion, rad/s
    system: np.ndarray  # index into CONSTELLATIONS
    lat_deg: float
    lon_deg: float

    @classmethod
    def build(cls, lat_deg: float = DEFAULT_LAT_DEG, lon_deg: float = DEFAULT_LON_DEG) -> "Sky":
        raan, u, inc, a, n, sys_ = [], [], [], [], [], []
        for k, c in enumerate(CONSTELLATIONS):
            r, uu = c.elements()
            raan.append(r)
            u.append(uu)
            inc.append(np.full(c.t, math.radians(c.inclination_deg)))
            a.append(np.full(c.t, c.a_m))
            n.append(np.full(c.t, 2.0 * math.pi / c.period_s))
            sys_.append(np.full(c.t, k))
        cat = np.concatenate
        return cls(cat(raan), cat(u), cat(inc), cat(a), cat(n), cat(sys_), float(lat_deg), float(lon_deg))

    @property
    def size(self) -> int:
        return int(self.raan0.size)

    def ecef(self, t: float) -> np.ndarray:
        """(S, 3) ECEF positions (m) at ``t`` s after the constellation's epoch: circular orbits, Earth rotation."""
        u = self.u0 + self.n * t
        raan = self.raan0 - OMEGA_EARTH * t  # the node's longitude in the rotating frame
        cu, su = np.cos(u), np.sin(u)
        ci, si = self._constants()[:2]
        cr, sr = np.cos(raan), np.sin(raan)
        x = self.a * (cr * cu - sr * su * ci)
        y = self.a * (sr * cu + cr * su * ci)
        z = self.a * (su * si)
        return np.stack([x, y, z], axis=1)

    def _constants(self) -> tuple:
        """(cos, sin of the inclinations, :meth:`receiver_ecef`, :meth:`enu_rotation` transposed): the same arrays
        every step, computed at the first call."""
        c = self.__dict__.get("_consts")
        if c is None:
            c = self.__dict__["_consts"] = (np.cos(self.inc), np.sin(self.inc), self.receiver_ecef(),
                                            self.enu_rotation().T)
        return c

    def receiver_ecef(self) -> np.ndarray:
        """The reference point on the WGS 84 ellipsoid (height 0)."""
        lat, lon = math.radians(self.lat_deg), math.radians(self.lon_deg)
        e2 = WGS84_F * (2.0 - WGS84_F)
        nr = WGS84_A / math.sqrt(1.0 - e2 * math.sin(lat) ** 2)
        return np.array([nr * math.cos(lat) * math.cos(lon), nr * math.cos(lat) * math.sin(lon),
                         nr * (1.0 - e2) * math.sin(lat)])

    def enu_rotation(self) -> np.ndarray:
        """(3, 3) rows: east, north, up unit vectors in ECEF at the reference point."""
        lat, lon = math.radians(self.lat_deg), math.radians(self.lon_deg)
        sl, cl, sp, cp = math.sin(lon), math.cos(lon), math.sin(lat), math.cos(lat)
        return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])

    def look(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(unit line-of-sight vectors (S, 3) in ENU, azimuth (S,) rad clockwise from north, elevation (S,) rad)."""
        d = (self.ecef(t) - self._constants()[2]) @ self._constants()[3]
        los = d / np.linalg.norm(d, axis=1)[:, None]
        az = np.arctan2(los[:, 0], los[:, 1])
        el = np.arcsin(np.clip(los[:, 2], -1.0, 1.0))
        return los, az, el

    def look_many(self, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`look` at each time of ``ts`` (K,): (K, S, 3), (K, S), (K, S), the same values (tested): every
        operation of :meth:`ecef` and :meth:`look` is elementwise (numpy's loops give each element the same
        value whatever the array's shape) except the rotation into ENU, a BLAS product, which runs one time at a
        time on the same (S, 3) operands as :meth:`look`'s."""
        t = np.asarray(ts, dtype=np.float64)[:, None]
        u = self.u0 + self.n * t
        raan = self.raan0 - OMEGA_EARTH * t
        cu, su = np.cos(u), np.sin(u)
        ci, si, rec, rot = self._constants()
        cr, sr = np.cos(raan), np.sin(raan)
        x = self.a * (cr * cu - sr * su * ci)
        y = self.a * (sr * cu + cr * su * ci)
        z = self.a * (su * si)
        e = np.stack([x, y, z], axis=2)
        d = np.empty_like(e)
        for k in range(e.shape[0]):
            d[k] = (e[k] - rec) @ rot
        los = d / np.linalg.norm(d, axis=2)[:, :, None]
        az = np.arctan2(los[:, :, 0], los[:, :, 1])
        el = np.arcsin(np.clip(los[:, :, 2], -1.0, 1.0))
        return los, az, el


def net_origin(net_path: Path | None) -> tuple[float, float, str]:
    """(lat, lon, how) of the net's x/y (0, 0): through its projection, else the default (module docstring)."""
    if net_path is not None:
        from couplers.net.georef import read_georef

        g = read_georef(Path(net_path))
        if g.has_proj:
            import pyproj

            lon, lat = pyproj.Proj(projparams=g.proj)(-g.net_offset[0], -g.net_offset[1], inverse=True)
            if math.isfinite(lat) and math.isfinite(lon):
                return float(lat), float(lon), f"the net's projection {g.proj!r}"
    return DEFAULT_LAT_DEG, DEFAULT_LON_DEG, "no geo-reference: the default (Turin)"


# --- line of sight ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BuildingEdges:
    """Every ring edge of the footprints (E, 4: x0, y0, x1, y1), listed per building (CSR ``start``), with the
    buildings' boxes (B, 4) and heights (B,)."""

    edges: np.ndarray
    start: np.ndarray
    boxes: np.ndarray
    heights: np.ndarray

    @classmethod
    def build(cls, buildings: Buildings) -> "BuildingEdges":
        rings_per_poly = []
        for poly in buildings.polygons:
            parts = shapely.get_parts(poly)
            rings = []
            for part in parts:
                rings.append(shapely.get_exterior_ring(part))
                rings.extend(shapely.get_interior_ring(part, i) for i in range(shapely.get_num_interior_rings(part)))
            rings_per_poly.append(rings)
        edges, start = [], [0]
        for rings in rings_per_poly:
            k = 0
            for ring in rings:
                c = shapely.get_coordinates(ring)
                if len(c) >= 2:
                    edges.append(np.hstack([c[:-1], c[1:]]))
                    k += len(c) - 1
            start.append(start[-1] + k)
        e = np.vstack(edges) if edges else np.empty((0, 4))
        return cls(edges=np.ascontiguousarray(e, dtype=np.float64), start=np.asarray(start, dtype=np.int64),
                   boxes=np.ascontiguousarray(shapely.bounds(buildings.polygons), dtype=np.float64),
                   heights=np.asarray(buildings.heights, dtype=np.float64))

    def grid(self, radius: float, divisions: int = 1) -> tuple[float, float, float, int, int, np.ndarray, np.ndarray]:
        """(x0, y0, cell, nx, ny, CSR start, building ids) of square cells of side ``radius / divisions`` (at least
        10 m) listing the buildings whose box meets each cell; cached per (radius, divisions)."""
        cache = self.__dict__.setdefault("_grids", {})
        key = (radius, divisions)
        if key not in cache:
            cell = max(float(radius) / divisions, 10.0)
            b = self.boxes
            x0, y0 = float(b[:, 0].min()), float(b[:, 1].min())
            nx = int((b[:, 2].max() - x0) // cell) + 1
            ny = int((b[:, 3].max() - y0) // cell) + 1
            ix0 = np.floor((b[:, 0] - x0) / cell).astype(np.int64)
            iy0 = np.floor((b[:, 1] - y0) / cell).astype(np.int64)
            ix1 = np.minimum(np.floor((b[:, 2] - x0) / cell).astype(np.int64), nx - 1)
            iy1 = np.minimum(np.floor((b[:, 3] - y0) / cell).astype(np.int64), ny - 1)
            start, ids = _cell_lists(ix0, iy0, ix1, iy1, nx, ny)
            cache[key] = (x0, y0, cell, nx, ny, start, ids)
        return cache[key]


def clearance_radius(heights: np.ndarray, antenna_height_m: float, elevation_mask_deg: float) -> float:
    """Horizontal distance beyond which no roof blocks a ray at or above the elevation mask."""
    h = float(np.max(heights, initial=0.0)) - antenna_height_m
    if h <= 0:
        return 0.0
    return h / math.tan(math.radians(max(elevation_mask_deg, 0.5)))


def line_of_sight(edges: BuildingEdges, xy: np.ndarray, az: np.ndarray, el: np.ndarray, antenna_height_m: float,
                  radius: float, box_test: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(blocked (N, S) bool, d (N, S): horizontal distance to the first blocking crossing, inf where clear) for
    antennas at ``xy`` and satellites at azimuth ``az`` / elevation ``el`` (rad) (module docstring). ``box_test``
    False: the reference of the speed-ups (every satellite in index order against every edge of every candidate
    building, on a grid of one cell per radius); True: the ray-box skip, satellites by rising elevation up to the
    first that clears the building's box, and a grid of :data:`LOS_GRID_DIVISIONS` cells per radius."""
    xy = np.ascontiguousarray(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
    if edges.heights.size == 0 or radius <= 0:
        return np.zeros((len(xy), az.size), dtype=bool), np.full((len(xy), az.size), np.inf)
    x0, y0, cell, nx, ny, start, ids = edges.grid(radius, LOS_GRID_DIVISIONS if box_test else 1)
    return _los_kernel(xy, x0, y0, cell, nx, ny, start, ids, float(radius), edges.edges, edges.start, edges.boxes,
                       edges.heights, np.sin(az), np.cos(az), np.tan(el), float(antenna_height_m), bool(box_test))


@njit(cache=True)
def _cell_span(px, py, radius, x0, y0, cell, nx, ny):
    """The grid cells (first and last column, first and last row) that a disc of ``radius`` about (px, py)
    touches, clipped to the grid."""
    return (max(int(math.floor((px - radius - x0) / cell)), 0), min(int(math.floor((px + radius - x0) / cell)), nx - 1),
            max(int(math.floor((py - radius - y0) / cell)), 0), min(int(math.floor((py + radius - y0) / cell)), ny - 1))


@njit(cache=True)
def _box_distance(px, py, box):
    dx = max(box[0] - px, 0.0, px - box[2])
    dy = max(box[1] - py, 0.0, py - box[3])
    return math.sqrt(dx * dx + dy * dy)


@njit(cache=True)
def _edge_crossings(px, py, dx, dy, edges, e0, e1):
    """How many of the edges ``e0:e1`` (one building's footprint) the horizontal ray from (px, py) along the unit
    vector (dx, dy) crosses, and the distance along the ray of the nearest crossing (inf without one); an edge's end
    point counts once (u in [0, 1))."""
    crossings = 0
    tmin = np.inf
    for e in range(e0, e1):
        ax, ay = edges[e, 0] - px, edges[e, 1] - py
        ex, ey = edges[e, 2] - edges[e, 0], edges[e, 3] - edges[e, 1]
        den = dx * ey - dy * ex  # cross(dir, edge)
        if den == 0.0:
            continue  # parallel
        t = (ax * ey - ay * ex) / den  # distance along the ray
        u = (ax * dy - ay * dx) / den  # fraction along the edge
        if t >= 0.0 and 0.0 <= u < 1.0:
            crossings += 1
            if t < tmin:
                tmin = t
    return crossings, tmin


@njit(cache=True)
def _los_kernel(xy, x0, y0, cell, nx, ny, gstart, gids, radius, edges, estart, boxes, heights, de, dn, tan_el,
                h_ant, box_test):
    """Every (vehicle, candidate building, satellite) (module docstring). Per (vehicle, building) the satellites
    are visited by rising elevation (``order``): once the box is cleared at one elevation it is at every higher
    one (b tan(el) + h_ant is monotone in tan(el), in floating point too), so the rest are skipped; each
    satellite's result does not depend on the order. ``box_test`` False: the reference (module docstring)."""
    n, s = xy.shape[0], de.size
    blocked = np.zeros((n, s), dtype=np.bool_)
    dist = np.full((n, s), np.inf)
    seen = np.full(heights.size, -1, dtype=np.int64)  # the vehicle that last looked at each building
    # satellites by rising elevation (finite: arcsin of a clipped cosine); the reference: in index order
    order = np.argsort(tan_el) if box_test else np.arange(tan_el.size)
    for i in range(n):
        px, py = xy[i, 0], xy[i, 1]
        cx0, cx1, cy0, cy1 = _cell_span(px, py, radius, x0, y0, cell, nx, ny)
        for cy in range(cy0, cy1 + 1):
            for cx in range(cx0, cx1 + 1):
                c = cy * nx + cx
                for g in range(gstart[c], gstart[c + 1]):
                    b = gids[g]
                    if seen[b] == i:
                        continue
                    seen[b] = i
                    hb = heights[b]
                    if not hb > h_ant:
                        continue
                    bd = _box_distance(px, py, boxes[b])
                    if bd > radius:
                        continue
                    _building_blocks(i, px, py, b, bd, hb, h_ant, boxes, order, tan_el, de, dn, edges, estart,
                                     box_test, blocked, dist)
    return blocked, dist


@njit(cache=True)
def _building_blocks(i, px, py, b, bd, hb, h_ant, boxes, order, tan_el, de, dn, edges, estart, box_test, blocked,
                     dist):
    """One antenna ``i`` at (px, py) against one candidate building ``b`` (box distance ``bd``, height ``hb``): every
    satellite, in ``order``, that the building blocks is marked in ``blocked[i]``, with the smallest crossing
    distance in ``dist[i]``. ``box_test``: skip the rays that miss the grown box, and stop at the first elevation
    that clears the box (``order`` rising); False: the reference, every satellite tested."""
    bx0, by0 = boxes[b, 0] - BOX_MARGIN_M, boxes[b, 1] - BOX_MARGIN_M
    bx1, by1 = boxes[b, 2] + BOX_MARGIN_M, boxes[b, 3] + BOX_MARGIN_M
    for kk in range(de.size):
        k = order[kk]
        if tan_el[k] <= 0.0:
            continue  # under the horizon (not used)
        if bd * tan_el[k] + h_ant >= hb:
            if box_test:
                break  # the box is already cleared at this elevation, and at every higher one
            continue
        dx, dy = de[k], dn[k]
        if box_test and not _ray_meets_box(px, py, dx, dy, bx0, by0, bx1, by1):
            continue  # no edge of the footprint can be crossed: every crossing lies in the box
        crossings, tmin = _edge_crossings(px, py, dx, dy, edges, estart[b], estart[b + 1])
        if crossings == 0:
            continue
        # an odd count: the antenna stands inside the footprint, below the roof
        if crossings % 2 == 1 or tmin * tan_el[k] + h_ant < hb:
            blocked[i, k] = True
            if tmin < dist[i, k]:
                dist[i, k] = tmin


@njit(cache=True)
def building_candidates(xy, prev, bits, prev_bits, prev_start, prev_ids, prev_bd, x0, y0, cell, nx, ny, gstart, gids,
                        radius, boxes, heights, h_ant):
    """(start (N+1,), ids, box distances): every antenna's candidate buildings as CSR rows, the buildings taller
    than the antenna whose box lies within ``radius`` (:func:`_candidates` on the grid ``x0 .. gids``, in its
    order) and their :func:`_box_distance`. Both depend on the antenna's position alone. ``prev`` (N,): each
    antenna's row among the previous call's antennas (-1: none), whose positions' bits are ``prev_bits`` and lists
    ``prev_*``; ``bits``: the bits of ``xy`` (``xy.view(np.int64)``). An antenna whose x and y are bitwise those
    of its previous row (a vehicle standing since the last step) takes that row's list: every row is the one
    computed afresh (tested)."""
    n, nb = xy.shape[0], heights.size
    carry = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        q = prev[i]
        if 0 <= q < prev_bits.shape[0] and bits[i, 0] == prev_bits[q, 0] and bits[i, 1] == prev_bits[q, 1]:
            carry[i] = q
    start = np.zeros(n + 1, dtype=np.int64)
    ids = np.empty(max(64, 16 * n), dtype=np.int64)
    bd = np.empty(ids.size)
    seen = np.full(nb, -1, dtype=np.int64)
    cand = np.empty(nb, dtype=np.int64)
    for i in range(n):
        q = carry[i]
        if q >= 0:
            a = prev_start[q]
            m = prev_start[q + 1] - a
        else:
            m = _candidates(xy[i, 0], xy[i, 1], x0, y0, cell, nx, ny, gstart, gids, radius, boxes, heights, h_ant,
                            seen, i, cand)
        o = start[i]
        if o + m > ids.size:  # grow by doubling
            k = max(2 * ids.size, o + m)
            ids2, bd2 = np.empty(k, dtype=np.int64), np.empty(k)
            ids2[:o], bd2[:o] = ids[:o], bd[:o]
            ids, bd = ids2, bd2
        if q >= 0:
            for j in range(m):
                ids[o + j], bd[o + j] = prev_ids[a + j], prev_bd[a + j]
        else:
            for j in range(m):
                b = cand[j]
                ids[o + j], bd[o + j] = b, _box_distance(xy[i, 0], xy[i, 1], boxes[b])
        start[i + 1] = o + m
    return start, ids[:start[n]].copy(), bd[:start[n]].copy()


@njit(cache=True)
def los_listed(xy, cstart, cids, cbd, edges, estart, boxes, heights, de, dn, tan_el, h_ant):
    """:func:`_los_kernel` with ``box_test`` over the candidate buildings of :func:`building_candidates` instead of
    its own grid search: the same set of buildings (the same test), visited in another order, and a satellite's
    result is an "or" (blocked) and a minimum (distance) over the buildings, which the order does not change
    (tested equal)."""
    n, s = xy.shape[0], de.size
    blocked = np.zeros((n, s), dtype=np.bool_)
    dist = np.full((n, s), np.inf)
    order = np.argsort(tan_el)
    for i in range(n):
        px, py = xy[i, 0], xy[i, 1]
        for q in range(cstart[i], cstart[i + 1]):
            b = cids[q]
            hb = heights[b]
            _building_blocks(i, px, py, b, cbd[q], hb, h_ant, boxes, order, tan_el, de, dn, edges, estart, True,
                             blocked, dist)
    return blocked, dist


#: Cells per clearance radius of the line-of-sight grid (speed only: a finer grid lists fewer buildings outside
#: a vehicle's disc; the buildings' results are combined by "or" and "min", whatever their order).
LOS_GRID_DIVISIONS = 4

#: Margin (m) by which a building's box is grown before a ray is tested against it: the ray-box test only skips
#: footprints whose edges the ray cannot cross, and a crossing computed in floating point lies within far less than
#: this of its edge (coordinates of a few km: rounding of order 1e-12 m).
BOX_MARGIN_M = 1e-3


@njit(cache=True)
def _ray_meets_box(px, py, dx, dy, bx0, by0, bx1, by1):
    """True when the horizontal ray (px, py) + t (dx, dy), t >= 0, meets the box [bx0, bx1] x [by0, by1] (slabs)."""
    t_lo, t_hi = 0.0, np.inf
    if dx == 0.0:
        if px < bx0 or px > bx1:
            return False
    else:
        t1, t2 = (bx0 - px) / dx, (bx1 - px) / dx
        t_lo, t_hi = max(t_lo, min(t1, t2)), min(t_hi, max(t1, t2))
    if dy == 0.0:
        if py < by0 or py > by1:
            return False
    else:
        t1, t2 = (by0 - py) / dy, (by1 - py) / dy
        t_lo, t_hi = max(t_lo, min(t1, t2)), min(t_hi, max(t1, t2))
    return t_lo <= t_hi


# --- single-bounce reflections (``nlos = "reflect"``) ------------------------------------------------------------


def reflections(edges: BuildingEdges, xy: np.ndarray, az: np.ndarray, el: np.ndarray, blocked: np.ndarray,
                antenna_height_m: float, radius: float,
                reference: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(found (N, S) bool, extra path (N, S) m, rate coefficient g (N, S, 2)) of the shortest single-bounce
    specular reflection off a building facade for every ``blocked`` (vehicle, satellite) pair.

    Geometry (image method, vertical walls): a facade at perpendicular distance d from the antenna, unit normal
    n pointing from the antenna to the wall, reflects a satellite of horizontal direction u_h (east, north) and
    elevation el when the wall faces it, cos(dphi) = -u_h . n > 0. The reflected ray reaches the antenna from
    the mirrored direction r = u_h + 2 cos(dphi) n at the same elevation, off the wall point at horizontal
    distance t = d / cos(dphi), height h_ant + t tan(el); the point must lie on the facade's edge and below its
    roof. The extra path over the direct one is 2 d cos(el) cos(dphi) (the antenna's image 2 d n behind the wall;
    L.-T. Hsu, GPS Solutions 22:7, 2018, eq. gamma = d sec(el) (1 + cos 2 el) for dphi = 0). Both legs must be
    clear: from the antenna to the wall point no other footprint is crossed below its roof, and the ray from the
    wall point to the satellite (the image's ray beyond t) clears every roof. Among the valid facades the
    shortest extra path is taken (the earliest replica, which a code tracking loop locks to when the direct
    signal is absent). ``g``: the extra path's rate for a receiver velocity v is g . v, g = -2 cos(el) cos(dphi)
    n (moving toward the wall shortens it): the Doppler error of the reflected signal. No valid facade: the
    signal is not received (multiple bounces and diffraction are not modelled).

    ``reference`` True: the kernel before its speed-ups (every facade's geometry per satellite, both legs tested
    against every edge of every candidate building), which :func:`couplers.sensing.gnss_reflect.reflect_kernel`
    reproduces exactly (tested)."""
    xy = np.ascontiguousarray(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
    n, s = len(xy), az.size
    if edges.heights.size == 0 or radius <= 0 or n == 0:
        return np.zeros((n, s), dtype=bool), np.zeros((n, s)), np.zeros((n, s, 2))
    x0, y0, cell, nx, ny, start, ids = edges.grid(radius)
    args = (xy, np.ascontiguousarray(blocked, dtype=np.bool_), x0, y0, cell, nx, ny, start, ids, float(radius),
            edges.edges, edges.start, edges.boxes, edges.heights, np.sin(az), np.cos(az), np.tan(el), np.cos(el),
            float(antenna_height_m))
    if reference:
        return _reflect_kernel_reference(*args)
    from couplers.sensing.gnss_reflect import facade_lines, reflect_kernel

    none = np.full(n, -1, dtype=np.int64)
    no_bits = np.empty((0, 2), dtype=np.int64)
    cand = building_candidates(xy, none, no_bits, no_bits, none[:1] * 0, none[:0], np.empty(0), x0, y0, cell, nx, ny,
                               start, ids, float(radius), edges.boxes, edges.heights, float(antenna_height_m))
    return reflect_kernel(args[0], args[1], *cand, *args[9:], facade_lines(edges),
                          *edges.grid(radius, LOS_GRID_DIVISIONS))


@njit(cache=True)
def _candidates(px, py, x0, y0, cell, nx, ny, gstart, gids, radius, boxes, heights, h_ant, seen, stamp, out):
    """Buildings taller than the antenna whose box is within ``radius`` of (px, py), into ``out``; their count."""
    cx0, cx1, cy0, cy1 = _cell_span(px, py, radius, x0, y0, cell, nx, ny)
    m = 0
    for cy in range(cy0, cy1 + 1):
        for cx in range(cx0, cx1 + 1):
            c = cy * nx + cx
            for g in range(gstart[c], gstart[c + 1]):
                b = gids[g]
                if seen[b] == stamp:
                    continue
                seen[b] = stamp
                if heights[b] > h_ant and _box_distance(px, py, boxes[b]) <= radius:
                    out[m] = b
                    m += 1
    return m


@njit(cache=True)
def _ray_hits(px, py, dx, dy, tan_el, h_ant, t_lo, t_hi, skip_edge, cand, m, edges, estart, heights):
    """True when the ray from (px, py, h_ant) in horizontal direction (dx, dy) rising at tan_el crosses a
    footprint edge (other than ``skip_edge``) at horizontal distance in (t_lo, t_hi) below that building's
    roof."""
    for q in range(m):
        b = cand[q]
        hb = heights[b]
        for e in range(estart[b], estart[b + 1]):
            if e == skip_edge:
                continue
            ax, ay = edges[e, 0] - px, edges[e, 1] - py
            ex, ey = edges[e, 2] - edges[e, 0], edges[e, 3] - edges[e, 1]
            den = dx * ey - dy * ex
            if den == 0.0:
                continue
            t = (ax * ey - ay * ex) / den
            u = (ax * dy - ay * dx) / den
            if t_lo < t < t_hi and 0.0 <= u <= 1.0 and t * tan_el + h_ant < hb:
                return True
    return False


@njit(cache=True)
def _reflect_kernel_reference(xy, blocked, x0, y0, cell, nx, ny, gstart, gids, radius, edges, estart, boxes, heights, de, dn,
                    tan_el, cos_el, h_ant):
    n, s = blocked.shape
    found = np.zeros((n, s), dtype=np.bool_)
    extra = np.zeros((n, s))
    rate = np.zeros((n, s, 2))
    nb = heights.size
    seen = np.full(nb, -1, dtype=np.int64)
    cand = np.empty(nb, dtype=np.int64)
    cand2 = np.empty(nb, dtype=np.int64)
    ne = edges.shape[0]
    c_ex = np.empty(ne)  # this pair's specular facades: extra path, edge, t, normal, cos(dphi)
    c_e = np.empty(ne, dtype=np.int64)
    c_t = np.empty(ne)
    c_n = np.empty((ne, 2))
    c_c = np.empty(ne)
    stamp = 0
    eps = 1e-6
    for i in range(n):
        px, py = xy[i, 0], xy[i, 1]
        any_blocked = False
        for k in range(s):
            if blocked[i, k]:
                any_blocked = True
                break
        if not any_blocked:
            continue
        m = _candidates(px, py, x0, y0, cell, nx, ny, gstart, gids, radius, boxes, heights, h_ant, seen, stamp,
                        cand)
        stamp += 1
        for k in range(s):
            if not blocked[i, k] or tan_el[k] <= 0.0:
                continue
            ux, uy = de[k], dn[k]
            nc = 0
            for q in range(m):  # every facade with a specular point on it, below its roof
                b = cand[q]
                hb = heights[b]
                if _box_distance(px, py, boxes[b]) * tan_el[k] + h_ant >= hb:
                    continue  # every point of this building's walls is above its roof on the reflected ray
                for e in range(estart[b], estart[b + 1]):
                    ax, ay = edges[e, 0], edges[e, 1]
                    ex, ey = edges[e, 2] - ax, edges[e, 3] - ay
                    ln = math.sqrt(ex * ex + ey * ey)
                    if ln == 0.0:
                        continue
                    nxw, nyw = ey / ln, -ex / ln
                    d = (ax - px) * nxw + (ay - py) * nyw
                    if d < 0.0:
                        nxw, nyw, d = -nxw, -nyw, -d
                    if d < eps:
                        continue  # the antenna on the wall's line
                    cphi = -(ux * nxw + uy * nyw)
                    if cphi <= eps:
                        continue  # the wall turns its back to the satellite
                    t = d / cphi
                    if t * tan_el[k] + h_ant >= hb:
                        continue  # the specular point is above the roof
                    qx, qy = px + t * (ux + 2.0 * cphi * nxw), py + t * (uy + 2.0 * cphi * nyw)
                    w = ((qx - ax) * ex + (qy - ay) * ey) / (ln * ln)
                    if w < 0.0 or w > 1.0:
                        continue  # ... or off the facade
                    c_ex[nc] = 2.0 * d * cos_el[k] * cphi
                    c_e[nc] = e
                    c_t[nc] = t
                    c_n[nc, 0], c_n[nc, 1] = nxw, nyw
                    c_c[nc] = cphi
                    nc += 1
            if nc == 0:
                continue
            order = np.argsort(c_ex[:nc])
            for j in order:  # the shortest path whose two legs are clear
                e, t, cphi = c_e[j], c_t[j], c_c[j]
                nxw, nyw = c_n[j, 0], c_n[j, 1]
                rx, ry = ux + 2.0 * cphi * nxw, uy + 2.0 * cphi * nyw
                if _ray_hits(px, py, rx, ry, tan_el[k], h_ant, eps, t - eps, e, cand, m, edges, estart, heights):
                    continue  # the leg from the antenna to the wall is blocked
                d = t * cphi
                ix, iy = px + 2.0 * d * nxw, py + 2.0 * d * nyw  # the antenna's image behind the wall
                m2 = _candidates(ix, iy, x0, y0, cell, nx, ny, gstart, gids, radius, boxes, heights, h_ant, seen,
                                 stamp, cand2)
                stamp += 1
                if _ray_hits(ix, iy, ux, uy, tan_el[k], h_ant, t + eps, np.inf, e, cand2, m2, edges, estart,
                             heights):
                    continue  # the leg from the wall to the satellite is blocked
                found[i, k] = True
                extra[i, k] = c_ex[j]
                rate[i, k, 0] = -2.0 * cos_el[k] * cphi * nxw
                rate[i, k, 1] = -2.0 * cos_el[k] * cphi * nyw
                break
    return found, extra, rate

