"""Occlusion geometry of the realistic perception (:mod:`couplers.sensing.perception` uses it,
:mod:`couplers.sensing.v2x` too for the buildings' shadowing of V2V links): vehicle footprints, sight lines
against footprints and against the net folder's buildings.

* Vehicles: every SUMO vehicle on the road is a length x width rectangle behind its front bumper,
  along the heading (:func:`vehicle_footprints`). A sight line is tested against the footprints listed in
  x buckets of their bounding boxes (:func:`_occluder_buckets`, :class:`OccluderIndex`) by exact
  segment/rectangle tests (edges included), skipped for a footprint that lies wholly to one side of the
  line (:func:`_occluded_by_quads_bucketed`); :func:`_occluded_by_quads` is the plain loop over every
  footprint they are tested against.
* Buildings: the polygons of ``buildings.geojson``; a sight line walks the 4 m cells near a building
  (boxes listed per cell, :class:`couplers.net.buildings.BuildingBoxes`) and meets a building when it meets its
  widened box and, exactly, its footprint: a ring edge (closed segments) or, wholly inside, the polygon (even-odd),
  in numba (:func:`_building_hits`). Its reference, shapely 2's STRtree ``query(..., predicate="intersects")`` on
  the sight lines that meet a box (:func:`_needs_building_test`), is kept for the tests and for sight lines that
  are not finite.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from numba import njit

from couplers.net.buildings import Buildings


def unit_heading(heading: np.ndarray) -> np.ndarray:
    """(N, 2) unit vectors of headings in rad from +x, counter-clockwise."""
    heading = np.asarray(heading, dtype=float)
    return np.stack([np.cos(heading), np.sin(heading)], axis=-1)


def vehicle_footprints(xy: np.ndarray, heading: np.ndarray, length: np.ndarray, width: np.ndarray,
                       direction: np.ndarray | None = None) -> np.ndarray:
    """(N, 4, 2) corners of the vehicles' rectangles, counter-clockwise.

    ``xy``: the centres of the front bumpers (SUMO's position; the coupler moves a vehicle's centre
    forward first, couplers.sumo_coupler._front_bumpers); the body extends ``length`` behind it along
    the heading and ``width`` / 2 to each side. ``direction``: ``unit_heading(heading)`` when the caller has it."""
    return _footprints(np.ascontiguousarray(xy, dtype=np.float64),
                       unit_heading(heading) if direction is None else np.ascontiguousarray(direction),
                       np.asarray(length, dtype=float).reshape(-1), np.asarray(width, dtype=float).reshape(-1))


@njit(cache=True)
def _footprints(xy, u, length, width):
    """Corners xy -/+ (w/2) n, back +/- (w/2) n with back = xy - length u and n = (-u_y, u_x)."""
    k = xy.shape[0]
    out = np.empty((k, 4, 2))
    for i in range(k):
        half = 0.5 * width[i]
        nx, ny = -u[i, 1], u[i, 0]
        bx, by = xy[i, 0] - length[i] * u[i, 0], xy[i, 1] - length[i] * u[i, 1]
        out[i, 0, 0], out[i, 0, 1] = xy[i, 0] - half * nx, xy[i, 1] - half * ny
        out[i, 1, 0], out[i, 1, 1] = xy[i, 0] + half * nx, xy[i, 1] + half * ny
        out[i, 2, 0], out[i, 2, 1] = bx + half * nx, by + half * ny
        out[i, 3, 0], out[i, 3, 1] = bx - half * nx, by - half * ny
    return out


@njit(cache=True)
def _orient(ax, ay, bx, by, cx, cy):
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


@njit(cache=True)
def _on_segment(ax, ay, bx, by, cx, cy):
    # c collinear with a-b: inside its bounding box
    return min(ax, bx) <= cx <= max(ax, bx) and min(ay, by) <= cy <= max(ay, by)


@njit(cache=True)
def _segments_intersect(ax, ay, bx, by, cx, cy, dx, dy):
    """Closed segments a-b and c-d share a point (touching counts, as shapely's intersects)."""
    o1 = _orient(ax, ay, bx, by, cx, cy)
    o2 = _orient(ax, ay, bx, by, dx, dy)
    o3 = _orient(cx, cy, dx, dy, ax, ay)
    o4 = _orient(cx, cy, dx, dy, bx, by)
    if ((o1 > 0 and o2 < 0) or (o1 < 0 and o2 > 0)) and ((o3 > 0 and o4 < 0) or (o3 < 0 and o4 > 0)):
        return True
    if o1 == 0 and _on_segment(ax, ay, bx, by, cx, cy):
        return True
    if o2 == 0 and _on_segment(ax, ay, bx, by, dx, dy):
        return True
    if o3 == 0 and _on_segment(cx, cy, dx, dy, ax, ay):
        return True
    if o4 == 0 and _on_segment(cx, cy, dx, dy, bx, by):
        return True
    return False


@njit(cache=True)
def _inside_convex(quad, px, py):
    """Point inside or on a counter-clockwise convex quadrilateral."""
    for k in range(4):
        a = quad[k]
        b = quad[(k + 1) % 4]
        if _orient(a[0], a[1], b[0], b[1], px, py) < 0:
            return False
    return True


@njit(cache=True)
def _segment_hits_quad(quad, ax, ay, bx, by):
    if _inside_convex(quad, ax, ay) or _inside_convex(quad, bx, by):
        return True
    for k in range(4):
        c = quad[k]
        d = quad[(k + 1) % 4]
        if _segments_intersect(ax, ay, bx, by, c[0], c[1], d[0], d[1]):
            return True
    return False


@njit(cache=True)
def _occluded_by_quads(seg, skip_a, skip_b, quads):
    """For each segment (M, 4): does it hit a quad other than skip_a / skip_b? Every quad tested exactly
    (:func:`_segment_hits_quad`): the reference of :func:`_occluded_by_quads_bucketed`."""
    m = seg.shape[0]
    out = np.zeros(m, dtype=np.bool_)
    for i in range(m):
        ax, ay, bx, by = seg[i, 0], seg[i, 1], seg[i, 2], seg[i, 3]
        for q in range(quads.shape[0]):
            if q != skip_a[i] and q != skip_b[i] and _segment_hits_quad(quads[q], ax, ay, bx, by):
                out[i] = True
                break
    return out


#: A sight line passes a footprint for certain when all four corners lie on one side of its line, more than
#: SIDE_MARGIN_M from it (_quad_hides).
SIDE_MARGIN_M = 1e-6


@njit(cache=True)
def _segment_box(seg, i):
    """Segment i's end points, its x and y extents and its side margin (SIDE_MARGIN_M times its length)."""
    ax, ay, bx, by = seg[i, 0], seg[i, 1], seg[i, 2], seg[i, 3]
    dx, dy = bx - ax, by - ay
    return (ax, ay, bx, by, min(ax, bx), max(ax, bx), min(ay, by), max(ay, by),
            SIDE_MARGIN_M * math.sqrt(dx * dx + dy * dy))


@njit(cache=True)
def _quad_hides(quads, q, rectangle, ax, ay, bx, by, side_margin):
    """Segment a-b meets quad q (:func:`_segment_hits_quad`), decided without the exact test when q is a
    ``rectangle`` whose four corners lie on one side of the segment's line by more than ``side_margin``
    (SIDE_MARGIN_M times the segment's length): each corner's orientation, as :func:`_orient` computes it,
    beyond that margin plus 1e-12 of its two products, far above their rounding of ~1e-16. The quad then misses
    the segment, and so does the exact test: its proper crossing needs corners on both sides, and the segment's
    end points lie more than the margin outside a counter-clockwise rectangle, so none of its orientation tests
    or on-segment tests can tip (their rounding is ~1e-13 m at these coordinates)."""
    if rectangle:
        dx, dy = bx - ax, by - ay
        above = 0
        below = 0
        for k in range(4):
            p1 = dx * (quads[q, k, 1] - ay)
            p2 = dy * (quads[q, k, 0] - ax)
            o = p1 - p2  # _orient(ax, ay, bx, by, corner)
            bound = side_margin + 1e-12 * (abs(p1) + abs(p2))
            if o > bound:
                above += 1
            elif o < -bound:
                below += 1
        if above == 4 or below == 4:
            return False
    return _segment_hits_quad(quads[q], ax, ay, bx, by)


#: Width of the x buckets of :func:`_occluder_buckets` (m), widened so that there are at most 4 K + 16 buckets.
OCCLUDER_BUCKET_M = 8.0


@njit(cache=True)
def _occluder_buckets(corners, width):
    """The quads listed by the x bucket of their bounding box's xmin, buckets ``width`` wide (or wider: at most
    4 K + 16 buckets) from the smallest xmin, with the boxes (:func:`_quad_boxes`): (order (K,), bucket starts
    (B + 1,), x0, width, xmin, xmax, ymin, ymax (K,) each, the widest x extent). A counting sort: the order is
    stable within a bucket. :func:`_occluded_by_quads_bucketed` reads it."""
    k = corners.shape[0]
    xmin, xmax, ymin, ymax, max_wx = _quad_boxes(corners)
    x0 = xmin.min() if k else 0.0
    span = (xmin.max() - x0) if k else 0.0
    n_max = 4 * k + 16
    if not (span / width < n_max - 1):
        width = span / (n_max - 1) if span > 0.0 else width
    nb = min(int(span / width) + 1, n_max) if math.isfinite(span) else 1
    bucket = np.empty(k, dtype=np.int64)
    start = np.zeros(nb + 1, dtype=np.int64)
    for q in range(k):
        b = int((xmin[q] - x0) / width) if math.isfinite(xmin[q]) else 0
        bucket[q] = min(max(b, 0), nb - 1)
        start[bucket[q] + 1] += 1
    for b in range(nb):
        start[b + 1] += start[b]
    fill = start[:-1].copy()
    order = np.empty(k, dtype=np.int64)
    for q in range(k):
        order[fill[bucket[q]]] = q
        fill[bucket[q]] += 1
    return order, start, x0, width, xmin, xmax, ymin, ymax, max_wx


@njit(cache=True)
def _occluded_by_quads_bucketed(seg, skip_a, skip_b, quads, order, start, x0, width, xmin, xmax, ymin, ymax,
                                max_wx, rectangle):
    """:func:`_occluded_by_quads` (the same answers) over :func:`_occluder_buckets`: the candidates of a
    segment are the quads of the buckets its window [x_lo, x_hi] = [min x - max_wx, max x] covers, kept when
    their xmin lies in the window (the bucket of a value is monotone in it, so those buckets hold every quad
    of the window; a quad outside it cannot meet the segment), then those whose box meets the segment's box,
    each decided by :func:`_quad_hides` (a shortcut for a ``rectangle`` wholly on one side of the line, then
    the exact test). A segment with a coordinate that is not finite looks at every quad."""
    m = seg.shape[0]
    nb = start.size - 1
    out = np.zeros(m, dtype=np.bool_)
    for i in range(m):
        ax, ay, bx, by, sx0, sx1, sy0, sy1, side_margin = _segment_box(seg, i)
        x_lo = sx0 - max_wx
        f0 = math.floor((x_lo - x0) / width)
        f1 = math.floor((sx1 - x0) / width)
        if math.isfinite(f0) and math.isfinite(f1):
            if f1 < 0 or f0 > nb - 1:
                continue
            b0, b1 = int(max(f0, 0.0)), int(min(f1, nb - 1.0))
        else:
            b0, b1 = 0, nb - 1
        for r in range(start[b0], start[b1 + 1]):
            q = order[r]
            if q == skip_a[i] or q == skip_b[i] or xmin[q] < x_lo or xmin[q] > sx1:
                continue
            if xmax[q] < sx0 or ymax[q] < sy0 or ymin[q] > sy1:
                continue
            if _quad_hides(quads, q, rectangle[q], ax, ay, bx, by, side_margin):
                out[i] = True
                break
    return out


@njit(cache=True)
def _rectangles(corners):
    """(K,) bool: quad q is a counter-clockwise rectangle with sides longer than 0.1 m (corners as
    :func:`_footprints` writes them, right angles within 1e-6), the quads :func:`_quad_hides` may pass by
    their sides."""
    k = corners.shape[0]
    out = np.zeros(k, dtype=np.bool_)
    for q in range(k):
        ok = True
        for c in range(4):
            ex = corners[q, (c + 1) % 4, 0] - corners[q, c, 0]
            ey = corners[q, (c + 1) % 4, 1] - corners[q, c, 1]
            fx = corners[q, (c + 2) % 4, 0] - corners[q, (c + 1) % 4, 0]
            fy = corners[q, (c + 2) % 4, 1] - corners[q, (c + 1) % 4, 1]
            le, lf = math.sqrt(ex * ex + ey * ey), math.sqrt(fx * fx + fy * fy)
            if not (le > 0.1 and lf > 0.1 and abs(ex * fx + ey * fy) <= 1e-6 * le * lf
                    and ex * fy - ey * fx > 0.0):
                ok = False
                break
        out[q] = ok
    return out


@dataclass(frozen=True)
class OccluderIndex:
    """Vehicle footprints (K, 4, 2) listed by the x bucket of their bounding boxes (:func:`_occluder_buckets`,
    buckets OCCLUDER_BUCKET_M wide), built once per step; ``rectangle`` marks the footprints that are
    counter-clockwise rectangles (:func:`_rectangles`)."""

    corners: np.ndarray
    order: np.ndarray  # quad indices, bucket by bucket
    start: np.ndarray  # (B + 1,) where each bucket's quads begin in ``order``
    x0: float
    width: float
    xmin: np.ndarray  # bounding boxes (K,) each, in quad order
    xmax: np.ndarray
    ymin: np.ndarray
    ymax: np.ndarray
    max_wx: float
    rectangle: np.ndarray

    @classmethod
    def build(cls, corners: np.ndarray) -> "OccluderIndex":
        corners = np.ascontiguousarray(corners, dtype=np.float64).reshape(-1, 4, 2)
        order, start, x0, width, xmin, xmax, ymin, ymax, max_wx = _occluder_buckets(corners, OCCLUDER_BUCKET_M)
        return cls(corners=corners, order=order, start=start, x0=float(x0), width=float(width), xmin=xmin,
                   xmax=xmax, ymin=ymin, ymax=ymax, max_wx=float(max_wx), rectangle=_rectangles(corners))

    def buckets(self) -> tuple:
        """The arguments of :func:`_occluded_by_quads_bucketed` after the skips: quads .. rectangle."""
        return (self.corners, self.order, self.start, self.x0, self.width, self.xmin, self.xmax, self.ymin,
                self.ymax, self.max_wx, self.rectangle)


@njit(cache=True)
def _quad_boxes(corners):
    """The quads' bounding boxes (xmin, xmax, ymin, ymax (K,) each) and the widest x extent."""
    k = corners.shape[0]
    xmin = np.empty(k)
    xmax = np.empty(k)
    ymin = np.empty(k)
    ymax = np.empty(k)
    max_wx = 0.0
    for q in range(k):
        xmin[q], xmax[q] = corners[q, 0, 0], corners[q, 0, 0]
        ymin[q], ymax[q] = corners[q, 0, 1], corners[q, 0, 1]
        for c in range(1, 4):
            xmin[q] = min(xmin[q], corners[q, c, 0])
            xmax[q] = max(xmax[q], corners[q, c, 0])
            ymin[q] = min(ymin[q], corners[q, c, 1])
            ymax[q] = max(ymax[q], corners[q, c, 1])
        wx = xmax[q] - xmin[q]
        if q == 0 or wx > max_wx:
            max_wx = wx
    return xmin, xmax, ymin, ymax, max_wx


def occluded_by_vehicles(start: np.ndarray, end: np.ndarray, occluders: "OccluderIndex | np.ndarray",
                         observer: np.ndarray, target: np.ndarray | None = None) -> np.ndarray:
    """(M,) bool: the sight line start[i] -> end[i] crosses a vehicle footprint (``occluders``: an
    OccluderIndex or corners (K, 4, 2)) other than ``observer[i]`` and ``target[i]`` (-1 when the
    target is not a vehicle)."""
    idx = occluders if isinstance(occluders, OccluderIndex) else OccluderIndex.build(occluders)
    return _segments_occluded_by_vehicles(np.hstack([start, end]), idx, observer, target)


def _segments_occluded_by_vehicles(seg: np.ndarray, idx: OccluderIndex, observer: np.ndarray,
                                   target: np.ndarray | None = None) -> np.ndarray:
    """:func:`occluded_by_vehicles` of the segments ``seg`` (M, 4): start x, y, end x, y."""
    m = seg.shape[0]
    if m == 0 or idx.corners.shape[0] == 0:
        return np.zeros(m, dtype=bool)
    skip_b = np.full(m, -1, dtype=np.int64) if target is None else np.asarray(target, dtype=np.int64)
    return _occluded_by_quads_bucketed(np.ascontiguousarray(seg, dtype=np.float64),
                                       np.asarray(observer, dtype=np.int64), skip_b, *idx.buckets())


@njit(cache=True)
def _sampling(ax, ay, bx, by, x0, y0, cell):
    """The samples of segment a-b in grid units, less than a cell apart: sample k of 0..k_max lies at
    (gx + sx k, gy + sy k), i.e. at a + (b - a) k / k_max up to rounding (~1e-12 m). Returns
    (gx, gy, sx, sy, k_max), k_max = -1 for a segment whose length is not finite."""
    length = math.sqrt((bx - ax) * (bx - ax) + (by - ay) * (by - ay))
    if not math.isfinite(length):
        return 0.0, 0.0, 0.0, 0.0, -1
    k_max = int(length / cell) + 1
    return (ax - x0) / cell, (ay - y0) / cell, (bx - ax) / cell / k_max, (by - ay) / cell / k_max, k_max


@njit(cache=True)
def _clear_of_buildings(seg, x0, y0, cell, near):
    """(M,) bool: segment i certainly misses every building. Samples less than a cell apart along the
    segment (:func:`_sampling`): every point of it lies within half a cell of a sample (plus the samples'
    rounding, far below a cell), so in a cell next to the sample's cell as computed; a building point on the
    segment lies in its bounding box's cells, which ``near`` widens by one."""
    m = seg.shape[0]
    ny, nx = near.shape
    out = np.zeros(m, dtype=np.bool_)
    for i in range(m):
        gx, gy, sx, sy, k_max = _sampling(seg[i, 0], seg[i, 1], seg[i, 2], seg[i, 3], x0, y0, cell)
        if k_max < 0:
            continue
        clear = True
        for k in range(k_max + 1):
            fx = math.floor(gx + sx * k)
            fy = math.floor(gy + sy * k)
            if 0 <= fx < nx and 0 <= fy < ny and near[int(fy), int(fx)]:
                clear = False
                break
        out[i] = clear
    return out


@njit(cache=True)
def _segment_meets_box(ax, ay, bx, by, xmin, ymin, xmax, ymax):
    """The closed segment a-b meets the closed box (slab clipping of t in [0, 1])."""
    t0, t1 = 0.0, 1.0
    for axis in range(2):
        p0 = ax if axis == 0 else ay
        d = (bx - ax) if axis == 0 else (by - ay)
        lo = xmin if axis == 0 else ymin
        hi = xmax if axis == 0 else ymax
        if d == 0.0:
            if p0 < lo or p0 > hi:
                return False
            continue
        ta, tb = (lo - p0) / d, (hi - p0) / d
        if ta > tb:
            ta, tb = tb, ta
        t0, t1 = max(t0, ta), min(t1, tb)
        if t0 > t1:
            return False
    return True


@njit(cache=True)
def _needs_building_test(seg, x0, y0, cell, near, start, ids, boxes, margin):
    """(M,) bool: segment i may meet a building, i.e. one of its sample cells (:func:`_sampling`, those
    :func:`_clear_of_buildings` looks at) is ``near`` a building and lists a building whose bounding box,
    widened by ``margin``, the segment meets (or the segment is not finite). The others certainly miss every
    building (a polygon lies in its box, and a box the segment meets is listed in a sample cell:
    :func:`_clear_of_buildings`' argument), so only these go to the polygon test. One walk along the segment:
    the boxes of a sample cell are tested when the walk reaches it."""
    m = seg.shape[0]
    ny, nx = near.shape
    out = np.zeros(m, dtype=np.bool_)
    seen = np.full(boxes.shape[0], -1, dtype=np.int64)
    for i in range(m):
        ax, ay, bx, by = seg[i, 0], seg[i, 1], seg[i, 2], seg[i, 3]
        gx, gy, sx, sy, k_max = _sampling(ax, ay, bx, by, x0, y0, cell)
        if k_max < 0:
            out[i] = True
            continue
        for k in range(k_max + 1):
            fx = math.floor(gx + sx * k)
            fy = math.floor(gy + sy * k)
            if not (0 <= fx < nx and 0 <= fy < ny) or not near[int(fy), int(fx)]:
                continue
            c = int(fy) * nx + int(fx)
            for q in range(start[c], start[c + 1]):
                b = ids[q]
                if seen[b] == i:
                    continue
                seen[b] = i
                if _segment_meets_box(ax, ay, bx, by, boxes[b, 0] - margin, boxes[b, 1] - margin,
                                      boxes[b, 2] + margin, boxes[b, 3] + margin):
                    out[i] = True
                    break
            if out[i]:
                break
    return out


@njit(cache=True)
def _orient(ax, ay, bx, by, cx, cy):
    """Sign of the turn a -> b -> c: 1 left, -1 right, 0 collinear (the cross product's sign)."""
    v = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    return 1 if v > 0.0 else (-1 if v < 0.0 else 0)


@njit(cache=True)
def _on_segment(ax, ay, bx, by, px, py):
    """p, collinear with a-b, lies on the closed segment a-b (its bounding box)."""
    return min(ax, bx) <= px <= max(ax, bx) and min(ay, by) <= py <= max(ay, by)


@njit(cache=True)
def _segments_meet(ax, ay, bx, by, cx, cy, dx, dy):
    """The closed segments a-b and c-d share a point (crossing, touching or overlapping)."""
    o1, o2 = _orient(ax, ay, bx, by, cx, cy), _orient(ax, ay, bx, by, dx, dy)
    o3, o4 = _orient(cx, cy, dx, dy, ax, ay), _orient(cx, cy, dx, dy, bx, by)
    if o1 * o2 < 0 and o3 * o4 < 0:
        return True
    return ((o1 == 0 and _on_segment(ax, ay, bx, by, cx, cy)) or (o2 == 0 and _on_segment(ax, ay, bx, by, dx, dy))
            or (o3 == 0 and _on_segment(cx, cy, dx, dy, ax, ay)) or (o4 == 0 and _on_segment(cx, cy, dx, dy, bx, by)))


@njit(cache=True)
def _segment_meets_polygon(ax, ay, bx, by, edges, e0, e1):
    """The closed segment a-b meets the closed polygon whose ring edges are ``edges[e0:e1]`` (x0, y0, x1, y1;
    exterior and holes, of every part): it meets an edge, or else lies wholly inside, so a is inside (even-odd
    crossings of a horizontal ray from a over all rings)."""
    inside = False
    for q in range(e0, e1):
        x0, y0, x1, y1 = edges[q, 0], edges[q, 1], edges[q, 2], edges[q, 3]
        if _segments_meet(ax, ay, bx, by, x0, y0, x1, y1):
            return True
        if (y0 > ay) != (y1 > ay) and ax < (x1 - x0) * (ay - y0) / (y1 - y0) + x0:
            inside = not inside
    return inside


@njit(cache=True)
def _building_hits(seg, x0, y0, cell, near, start, ids, boxes, margin, edge_start, edges):
    """(M,) int8 per segment: 0 it misses every building, 1 it meets one, 2 not finite (left to shapely).
    The walk of :func:`_needs_building_test`; each building whose widened box a segment meets goes to the exact
    closed segment / polygon test (:func:`_segment_meets_polygon`, shapely's ``intersects``) at once."""
    m = seg.shape[0]
    ny, nx = near.shape
    out = np.zeros(m, dtype=np.int8)
    seen = np.full(boxes.shape[0], -1, dtype=np.int64)
    for i in range(m):
        ax, ay, bx, by = seg[i, 0], seg[i, 1], seg[i, 2], seg[i, 3]
        gx, gy, sx, sy, k_max = _sampling(ax, ay, bx, by, x0, y0, cell)
        if k_max < 0:
            out[i] = 2
            continue
        for k in range(k_max + 1):
            fx = math.floor(gx + sx * k)
            fy = math.floor(gy + sy * k)
            if not (0 <= fx < nx and 0 <= fy < ny) or not near[int(fy), int(fx)]:
                continue
            c = int(fy) * nx + int(fx)
            for q in range(start[c], start[c + 1]):
                b = ids[q]
                if seen[b] == i:
                    continue
                seen[b] = i
                if _segment_meets_box(ax, ay, bx, by, boxes[b, 0] - margin, boxes[b, 1] - margin,
                                      boxes[b, 2] + margin, boxes[b, 3] + margin) \
                        and _segment_meets_polygon(ax, ay, bx, by, edges, edge_start[b], edge_start[b + 1]):
                    out[i] = 1
                    break
            if out[i]:
                break
    return out


def building_edges(buildings: Buildings) -> tuple[np.ndarray, np.ndarray]:
    """(CSR start (B + 1,), ring edges (E, 4)) of the footprints, every ring of every part (built once per
    ``buildings``)."""
    cache = buildings.__dict__
    if "_ring_edges" not in cache:
        starts, edges = [0], []
        for poly in buildings.polygons:
            k = 0
            for part in shapely.get_parts(poly):
                rings = [shapely.get_exterior_ring(part)] + [shapely.get_interior_ring(part, j) for j in
                                                            range(shapely.get_num_interior_rings(part))]
                for ring in rings:
                    c = shapely.get_coordinates(ring)
                    if len(c) >= 2:
                        edges.append(np.hstack([c[:-1], c[1:]]))
                        k += len(c) - 1
            starts.append(starts[-1] + k)
        e = np.ascontiguousarray(np.vstack(edges) if edges else np.empty((0, 4)), dtype=np.float64)
        cache["_ring_edges"] = (np.asarray(starts, dtype=np.int64), e)
    return cache["_ring_edges"]


def occluded_by_buildings(start: np.ndarray, end: np.ndarray, buildings: Buildings | None) -> np.ndarray:
    """(M,) bool: the sight line start[i] -> end[i] intersects a building (one STRtree query for all
    sight lines that meet a building's bounding box: ``buildings.cells`` and ``buildings.boxes`` clear the
    others without shapely, :func:`_needs_building_test`)."""
    return _segments_occluded_by_buildings(np.hstack([start, end]), buildings)


def _segments_occluded_by_buildings(seg: np.ndarray, buildings: Buildings | None) -> np.ndarray:
    """:func:`occluded_by_buildings` of the segments ``seg`` (M, 4): start x, y, end x, y: the exact test in
    numba (:func:`_building_hits`), shapely for segments that are not finite."""
    m = seg.shape[0]
    if m == 0 or buildings is None or len(buildings) == 0:
        return np.zeros(m, dtype=bool)
    g, bb = buildings.cells, buildings.boxes
    edge_start, edges = building_edges(buildings)
    seg = np.ascontiguousarray(seg, dtype=np.float64)
    hits = _building_hits(seg, g.x0, g.y0, g.cell, g.values, bb.start, bb.ids, bb.boxes, bb.margin, edge_start, edges)
    out = hits == 1
    odd = np.flatnonzero(hits == 2)
    if odd.size:
        out[odd] = _segments_occluded_by_buildings_shapely(seg[odd], buildings)
    return out


def _segments_occluded_by_buildings_shapely(seg: np.ndarray, buildings: Buildings | None) -> np.ndarray:
    """:func:`_segments_occluded_by_buildings` with shapely 2's STRtree ``intersects`` for the segments that may
    meet a building (:func:`_needs_building_test`): the reference of the numba test."""
    m = seg.shape[0]
    out = np.zeros(m, dtype=bool)
    if m == 0 or buildings is None or len(buildings) == 0:
        return out
    g, bb = buildings.cells, buildings.boxes
    seg = np.ascontiguousarray(seg, dtype=np.float64)
    near = np.flatnonzero(_needs_building_test(seg, g.x0, g.y0, g.cell, g.values, bb.start, bb.ids, bb.boxes,
                                               bb.margin))
    if near.size:
        lines = shapely.linestrings(seg[near].reshape(-1, 2, 2))
        hit = buildings.tree.query(lines, predicate="intersects")
        out[near[hit[0]]] = True
    return out
