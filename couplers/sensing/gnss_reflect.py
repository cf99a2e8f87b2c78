"""The fast kernel of ``[gnss_error] nlos = "reflect"``: :func:`couplers.sensing.gnss_sky.reflections`' single-bounce
facade reflections, with exactly the results of its reference kernel
(:func:`couplers.sensing.gnss_sky._reflect_kernel_reference`, the geometry is described there).

What makes it faster, none of which changes a result (``tests/couplers/test_gnss_reflect.py`` compares the two
array for array on random scenes and on the arterial's buildings):

* Each facade's length and unit normal are computed once for the net (:func:`facade_lines`), and its distance from
  the antenna once per vehicle and building, when a satellite first needs that building, instead of once per
  satellite. The values are the reference's: the same operations on the same numbers.
* The facades of a (vehicle, satellite) pair are collected in the reference's order (the candidate buildings of the
  coarse grid, their edges in order), so the shortest path's tie-break (the sort of the extra paths) is the same.
* Both legs of a reflected path (antenna to wall, wall to satellite) are tested only against the buildings whose box
  meets the leg's bounding box (grown by :data:`couplers.sensing.gnss_sky.BOX_MARGIN_M`), listed from the fine
  line-of-sight grid, and kept only when they pass the reference's own candidate test about the leg's start (taller
  than the antenna, box within the clearance radius). A leg's answer is an "or" over its buildings, so their order
  does not matter, and every building the reference finds a crossing in lies on the leg, hence in a listed cell.
  Each listed building is skipped when the leg misses its grown box or meets it only above its roof
  (:func:`_ray_hits_boxed`).
* The candidate paths are ordered by numba's own argsort's insertion sort when there are at most
  :data:`SMALL_SORT` of them (almost always: 1.8 a (vehicle, satellite) pair on average in the TLR realistic preset,
  seed 1), without the quicksort's allocations (``_argsort_into``, tested index for index against ``np.argsort``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from couplers.sensing.gnss_sky import BOX_MARGIN_M, BuildingEdges, _box_distance


def facade_lines(edges: BuildingEdges) -> np.ndarray:
    """:func:`_facade_lines` of ``edges``, computed once per :class:`BuildingEdges`."""
    lines = edges.__dict__.get("_lines")
    if lines is None:
        lines = edges.__dict__["_lines"] = _facade_lines(edges.edges)
    return lines


@njit(cache=True)
def _facade_lines(edges):
    """(E, 5): ex, ey, length and unit normal (ey, -ex) / length of every edge, with the reference's operations
    (length 0: the normal stays 0 and is never read)."""
    out = np.zeros((edges.shape[0], 5))
    for e in range(edges.shape[0]):
        ax, ay = edges[e, 0], edges[e, 1]
        ex, ey = edges[e, 2] - ax, edges[e, 3] - ay
        ln = math.sqrt(ex * ex + ey * ey)
        out[e, 0], out[e, 1], out[e, 2] = ex, ey, ln
        if ln != 0.0:
            out[e, 3], out[e, 4] = ey / ln, -ex / ln
    return out


@njit(cache=True)
def _ray_box_span(px, py, dx, dy, bx0, by0, bx1, by1):
    """(t_in, t_out) of the line (px, py) + t (dx, dy) inside the box [bx0, bx1] x [by0, by1] (slabs); t_in > t_out
    when it misses."""
    t_lo, t_hi = -np.inf, np.inf
    if dx == 0.0:
        if px < bx0 or px > bx1:
            return np.inf, -np.inf
    else:
        t1, t2 = (bx0 - px) / dx, (bx1 - px) / dx
        t_lo, t_hi = max(t_lo, min(t1, t2)), min(t_hi, max(t1, t2))
    if dy == 0.0:
        if py < by0 or py > by1:
            return np.inf, -np.inf
    else:
        t1, t2 = (by0 - py) / dy, (by1 - py) / dy
        t_lo, t_hi = max(t_lo, min(t1, t2)), min(t_hi, max(t1, t2))
    return t_lo, t_hi


@njit(cache=True)
def _ray_hits_boxed(px, py, dx, dy, tan_el, h_ant, t_lo, t_hi, skip_edge, cand, m, edges, estart, boxes, heights):
    """The reference's ``_ray_hits`` (a crossing of an edge other than ``skip_edge`` at t in (t_lo, t_hi) below
    the roof) over the buildings ``cand[:m]``, skipping a building when the stretch misses its box grown by
    BOX_MARGIN_M (every crossing lies in the box) or meets it only where the ray is at or above the roof (the ray
    rises with t, and the grown box is entered a millimetre before any crossing: the crossing's rounding, ~1e-12 m,
    cannot tip the test). ``dx, dy``: a unit vector."""
    for q in range(m):
        b = cand[q]
        hb = heights[b]
        t_in, t_out = _ray_box_span(px, py, dx, dy, boxes[b, 0] - BOX_MARGIN_M, boxes[b, 1] - BOX_MARGIN_M,
                                    boxes[b, 2] + BOX_MARGIN_M, boxes[b, 3] + BOX_MARGIN_M)
        t_in, t_out = max(t_in, t_lo), min(t_out, t_hi)
        if t_in > t_out or t_in * tan_el + h_ant >= hb:
            continue
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
def _cell_index(v, origin, cell, count):
    """The grid column (row) of coordinate ``v``, clamped to [-1, count] before the floor (v may be infinite)."""
    f = (v - origin) / cell
    f = min(max(f, -1.0), float(count))
    return int(math.floor(f))


@njit(cache=True)
def _leg_candidates(sx, sy, dx, dy, t0, t1, x0, y0, cell, nx, ny, gstart, gids, cx, cy, radius, boxes, heights,
                    h_ant, seen, stamp, out):
    """Into ``out``: the buildings listed in the grid cells met by the bounding box (grown by BOX_MARGIN_M) of
    the leg (sx, sy) + t (dx, dy), t in [t0, t1], that pass the reference's candidate test about (cx, cy) (taller
    than the antenna, box within ``radius``); their count."""
    ax, ay = sx + t0 * dx, sy + t0 * dy
    bx, by = sx + t1 * dx, sy + t1 * dy
    cx0 = max(_cell_index(min(ax, bx) - BOX_MARGIN_M, x0, cell, nx), 0)
    cx1 = min(_cell_index(max(ax, bx) + BOX_MARGIN_M, x0, cell, nx), nx - 1)
    cy0 = max(_cell_index(min(ay, by) - BOX_MARGIN_M, y0, cell, ny), 0)
    cy1 = min(_cell_index(max(ay, by) + BOX_MARGIN_M, y0, cell, ny), ny - 1)
    m = 0
    for gy in range(cy0, cy1 + 1):
        for gx in range(cx0, cx1 + 1):
            c = gy * nx + gx
            for g in range(gstart[c], gstart[c + 1]):
                b = gids[g]
                if seen[b] == stamp:
                    continue
                seen[b] = stamp
                if heights[b] > h_ant and _box_distance(cx, cy, boxes[b]) <= radius:
                    out[m] = b
                    m += 1
    return m


#: numba's ``np.argsort`` (its quicksort, numba/misc/quicksort.py) sorts at most this many values by its insertion
#: sort alone (``SMALL_QUICKSORT`` = 15: partitions while high - low >= 15).
SMALL_SORT = 15


@njit(cache=True)
def _float_lt(a, b):
    """numba's order of floats in its sorts (``numba.np.numpy_support.lt_floats``: NaN last)."""
    return a < b or (np.isnan(b) and not np.isnan(a))


@njit(cache=True)
def _argsort_into(a, n, order):
    """``order[:n]`` = ``np.argsort(a[:n])`` as numba computes it: for n <= :data:`SMALL_SORT` its insertion sort,
    the same comparisons and moves (without the quicksort's allocations, about 1 us a call here), else numba's
    argsort itself."""
    if n > SMALL_SORT:
        order[:n] = np.argsort(a[:n])
        return
    for i in range(n):
        order[i] = i
    for i in range(1, n):
        k = order[i]
        v = a[k]
        j = i
        while j > 0 and _float_lt(v, a[order[j - 1]]):
            order[j] = order[j - 1]
            j -= 1
        order[j] = k


@njit(cache=True)
def reflect_kernel(xy, blocked, cstart, cids, cbd, radius, edges, estart, boxes, heights, de, dn, tan_el, cos_el,
                   h_ant, lines, fx0, fy0, fcell, fnx, fny, fstart, fids):
    """(found, extra, rate) as the reference kernel (module docstring): ``cstart, cids, cbd`` each antenna's
    candidate buildings and their box distances (:func:`couplers.sensing.gnss_sky.building_candidates` on the
    coarse grid, one cell per clearance radius: the reference's buildings in the reference's order), ``lines``
    :func:`facade_lines`, ``fx0 .. fids`` the fine grid."""
    n, s = blocked.shape
    found = np.zeros((n, s), dtype=np.bool_)
    extra = np.zeros((n, s))
    rate = np.zeros((n, s, 2))
    nb = heights.size
    seen = np.full(nb, -1, dtype=np.int64)
    cand2 = np.empty(nb, dtype=np.int64)
    geo_of = np.full(nb, -1, dtype=np.int64)  # the vehicle whose facade distances a building holds
    ne = edges.shape[0]
    c_ex = np.empty(ne)  # this pair's specular facades: extra path, edge, t, normal, cos(dphi)
    c_e = np.empty(ne, dtype=np.int64)
    c_t = np.empty(ne)
    c_n = np.empty((ne, 2))
    c_c = np.empty(ne)
    c_order = np.empty(ne, dtype=np.int64)
    f_d = np.empty(ne)  # this vehicle's distance to each facade's line (-1: not a candidate facade)
    f_s = np.empty(ne)  # and the sign that turns the facade's normal toward the wall
    h_max = 0.0
    for b in range(nb):
        h_max = max(h_max, heights[b])
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
        c0 = cstart[i]
        m = cstart[i + 1] - c0
        cand, bdist = cids[c0:c0 + m], cbd[c0:c0 + m]
        for k in range(s):
            if not blocked[i, k] or tan_el[k] <= 0.0:
                continue
            ux, uy = de[k], dn[k]
            nc = 0
            for q in range(m):  # every facade with a specular point on it, below its roof
                b = cand[q]
                hb = heights[b]
                if bdist[q] * tan_el[k] + h_ant >= hb:
                    continue  # every point of this building's walls is above its roof on the reflected ray
                if geo_of[b] != i:  # this vehicle's distances to the building's facades
                    geo_of[b] = i
                    for e in range(estart[b], estart[b + 1]):
                        f_d[e] = -1.0
                        if lines[e, 2] == 0.0:
                            continue
                        d = (edges[e, 0] - px) * lines[e, 3] + (edges[e, 1] - py) * lines[e, 4]
                        sg = 1.0
                        if d < 0.0:
                            sg, d = -1.0, -d
                        if d < eps:
                            continue  # the antenna on the wall's line
                        f_d[e], f_s[e] = d, sg
                for e in range(estart[b], estart[b + 1]):
                    d = f_d[e]
                    if d < 0.0:
                        continue
                    nxw, nyw = f_s[e] * lines[e, 3], f_s[e] * lines[e, 4]  # exact negation or copy
                    cphi = -(ux * nxw + uy * nyw)
                    if cphi <= eps:
                        continue  # the wall turns its back to the satellite
                    t = d / cphi
                    if t * tan_el[k] + h_ant >= hb:
                        continue  # the specular point is above the roof
                    ax, ay, ex, ey, ln = edges[e, 0], edges[e, 1], lines[e, 0], lines[e, 1], lines[e, 2]
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
            _argsort_into(c_ex, nc, c_order)
            # beyond this distance from its start no ray rising at this elevation is under any roof
            t_top = (h_max - h_ant) / tan_el[k] * (1.0 + 1e-9) + BOX_MARGIN_M
            for jj in range(nc):  # the shortest path whose two legs are clear
                j = c_order[jj]
                e, t, cphi = c_e[j], c_t[j], c_c[j]
                nxw, nyw = c_n[j, 0], c_n[j, 1]
                rx, ry = ux + 2.0 * cphi * nxw, uy + 2.0 * cphi * nyw
                m1 = _leg_candidates(px, py, rx, ry, 0.0, t, fx0, fy0, fcell, fnx, fny, fstart, fids, px, py, radius,
                                     boxes, heights, h_ant, seen, stamp, cand2)
                stamp += 1
                if _ray_hits_boxed(px, py, rx, ry, tan_el[k], h_ant, eps, t - eps, e, cand2, m1, edges, estart, boxes,
                                   heights):
                    continue  # the leg from the antenna to the wall is blocked
                d = t * cphi
                ix, iy = px + 2.0 * d * nxw, py + 2.0 * d * nyw  # the antenna's image behind the wall
                m2 = _leg_candidates(ix, iy, ux, uy, t, max(t, t_top), fx0, fy0, fcell, fnx, fny, fstart, fids, ix,
                                     iy, radius, boxes, heights, h_ant, seen, stamp, cand2)
                stamp += 1
                if _ray_hits_boxed(ix, iy, ux, uy, tan_el[k], h_ant, t + eps, np.inf, e, cand2, m2, edges, estart,
                                   boxes, heights):
                    continue  # the leg from the wall to the satellite is blocked
                found[i, k] = True
                extra[i, k] = c_ex[j]
                rate[i, k, 0] = -2.0 * cos_el[k] * cphi * nxw
                rate[i, k, 1] = -2.0 * cos_el[k] * cphi * nyw
                break
    return found, extra, rate
