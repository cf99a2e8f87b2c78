"""Point-in-polygon lookups: GNSS class and analysis area of each vehicle.

:meth:`RegionIndex.locate` answers from a raster of the regions built once per index: a cell that
lies inside one region and touches no region listed before it has that region's label for every
point in it, a cell that touches no region is outside all, and only the points in cells that a
region's border crosses are tested against the polygons (:meth:`RegionIndex.locate_exact`, the
reference). Cells are closed boxes widened by a margin far above the rounding of the cell index,
so a point is always inside the box of the cell it is looked up in: the raster gives the labels of
the polygon test exactly (``tests/couplers/test_zones.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import shapely
from numba import njit

if TYPE_CHECKING:  # annotations only: the net folder imports this module through its buildings
    from couplers.net.folder import Region

RASTER_CELL_M = 5.0  # cell side; coarser when the regions' extent would need more than RASTER_MAX_CELLS
# A cell that a border crosses is split into REFINE x REFINE cells, classified when a point first falls in one
# of them (RegionIndex.locate): only points in the fine cells a border crosses go to the polygon test.
REFINE = 8
RASTER_MAX_CELLS = 1 << 20
_OUTSIDE, _BORDER = -1, -2  # raster labels besides region indices


@dataclass(frozen=True)
class CellGrid:
    """Values on a regular grid in net x/y: row i, column j covers [x0 + j cell, x0 + (j + 1) cell) x
    [y0 + i cell, y0 + (i + 1) cell) (a point's cell is floor((x - x0) / cell), floor((y - y0) / cell))."""

    x0: float
    y0: float
    cell: float
    values: np.ndarray  # (ny, nx)

    def at(self, xy: np.ndarray) -> np.ndarray:
        """(N,) float: the value of each point's cell, 0 outside the grid (and for non-finite points)."""
        return _grid_values(np.ascontiguousarray(np.asarray(xy, dtype=float).reshape(-1, 2)), self.x0, self.y0,
                            self.cell, self.values)


@njit(cache=True)
def _grid_values(xy, x0, y0, cell, values):
    """Value of the cell of each point, 0 outside the grid."""
    ny, nx = values.shape
    out = np.zeros(xy.shape[0])
    for k in range(xy.shape[0]):
        fx = math.floor((xy[k, 0] - x0) / cell)
        fy = math.floor((xy[k, 1] - y0) / cell)
        if 0 <= fx < nx and 0 <= fy < ny:
            out[k] = values[int(fy), int(fx)]
    return out


def _classify(regions: tuple[Region, ...], bx: np.ndarray, by: np.ndarray, size: float, margin: float,
              edges: list[np.ndarray] | None = None) -> np.ndarray:
    """Labels of the closed boxes [bx, bx + size] x [by, by + size] widened by ``margin`` (lower left corners
    on a lattice of spacing ``size``): a region's index where the box lies inside it and touches no region
    listed before, ``_BORDER`` where a region's border comes near the box, ``_OUTSIDE`` elsewhere.

    Without a geometry per box: a box that no edge of a region's rings comes within 4 ``margin`` of
    (:func:`_near_edges`, conservative) lies wholly inside or wholly outside that region, as its centre does
    (one vectorised point test). A box near an edge is ``_BORDER``, which only sends the points in it to the
    finer cells and the polygon test. :func:`_classify_boxes` is the per-box shapely classification this
    replaces (its reference in the tests: every label it gives that is not ``_BORDER`` is the same here).
    ``edges``: the regions' :func:`_region_edges`, when the caller has them."""
    labels = np.full(bx.size, _OUTSIDE, dtype=np.int16)
    if bx.size == 0:
        return labels
    x0, y0 = float(bx.min()), float(by.min())
    jx = np.rint((bx - x0) / size).astype(np.int64)
    jy = np.rint((by - y0) / size).astype(np.int64)
    nx, ny = int(jx.max()) + 1, int(jy.max()) + 1
    cx, cy = bx + 0.5 * size, by + 0.5 * size
    open_ = np.ones(bx.size, dtype=bool)  # no region listed so far touches the box
    for i, r in enumerate(regions):
        cand = np.flatnonzero(open_)
        if cand.size == 0:
            break
        e = _region_edges(r.polygon) if edges is None else edges[i]
        near = _near_edges(e, x0, y0, size, 4.0 * margin, nx, ny)[jy[cand], jx[cand]]
        inside = np.zeros(cand.size, dtype=bool)
        inside[~near] = shapely.intersects_xy(r.polygon, cx[cand[~near]], cy[cand[~near]])
        hit = near | inside
        labels[cand[hit]] = np.where(near[hit], _BORDER, i)
        open_[cand[hit]] = False
    return labels


def _region_edges(polygon) -> np.ndarray:
    """(E, 4) edges (ax, ay, bx, by) of every ring of a Polygon / MultiPolygon."""
    rings = shapely.get_rings(shapely.get_parts(polygon))
    xy, ring = shapely.get_coordinates(rings, return_index=True)
    same = ring[1:] == ring[:-1]
    return np.ascontiguousarray(np.hstack([xy[:-1][same], xy[1:][same]]), dtype=np.float64)


@njit(cache=True)
def _near_edges(edges, x0, y0, size, tol, nx, ny):
    """(ny, nx) bool: the boxes [x0 + j size, x0 + (j + 1) size] x [y0 + i size, ...] widened by ``tol`` that an
    edge may meet. Column by column of each edge: the y range of the edge over the column's widened x span,
    widened by ``tol`` (conservative: a box marked may miss the edge, a box the edge meets is marked)."""
    out = np.zeros((ny, nx), dtype=np.bool_)
    for e in range(edges.shape[0]):
        ax, ay, bx, by = edges[e, 0], edges[e, 1], edges[e, 2], edges[e, 3]
        if ax > bx:
            ax, ay, bx, by = bx, by, ax, ay
        c0 = max(int(math.floor((ax - tol - x0) / size)), 0)
        c1 = min(int(math.floor((bx + tol - x0) / size)), nx - 1)
        for c in range(c0, c1 + 1):
            xl = max(ax, x0 + c * size - tol)
            xr = min(bx, x0 + (c + 1) * size + tol)
            if bx > ax:
                ya = ay + (by - ay) * ((xl - ax) / (bx - ax))
                yb = ay + (by - ay) * ((xr - ax) / (bx - ax))
            else:
                ya, yb = ay, by
            lo, hi = min(ya, yb), max(ya, yb)
            r0 = max(int(math.floor((lo - tol - y0) / size)), 0)
            r1 = min(int(math.floor((hi + tol - y0) / size)), ny - 1)
            for row in range(r0, r1 + 1):
                out[row, c] = True
    return out


def _classify_boxes(regions: tuple[Region, ...], bx: np.ndarray, by: np.ndarray, size: float,
                    margin: float, edges=None) -> np.ndarray:
    """:func:`_classify` with a shapely box per cell (shapely's intersects / covers): its reference."""
    boxes = shapely.box(bx - margin, by - margin, bx + size + margin, by + size + margin)
    labels = np.full(boxes.size, _OUTSIDE, dtype=np.int16)
    open_ = np.ones(boxes.size, dtype=bool)  # no region listed so far touches the box
    for i, r in enumerate(regions):
        cand = np.flatnonzero(open_)
        if cand.size == 0:
            break
        hit = cand[shapely.intersects(r.polygon, boxes[cand])]
        labels[hit] = np.where(shapely.covers(r.polygon, boxes[hit]), i, _BORDER)
        open_[hit] = False
    return labels


def region_raster(regions: tuple[Region, ...], cell_m: float = RASTER_CELL_M,
                  max_cells: int = RASTER_MAX_CELLS, coarse: int = 8) -> CellGrid:
    """The raster of ``regions`` (first region listed wins, as in the polygon test): per cell a region
    index, ``_OUTSIDE`` or ``_BORDER`` (int16).

    Built coarse to fine: blocks of ``coarse`` x ``coarse`` cells are classified first, and only the
    blocks a border crosses are classified cell by cell."""
    xmin, ymin, xmax, ymax = shapely.total_bounds([r.polygon for r in regions])
    cell = max(float(cell_m), math.sqrt((xmax - xmin + 2 * cell_m) * (ymax - ymin + 2 * cell_m) / max_cells))
    x0, y0 = xmin - cell, ymin - cell  # padding: points beyond the grid are outside every region
    block = coarse * cell
    bnx = int(math.ceil((xmax + cell - x0) / block))
    bny = int(math.ceil((ymax + cell - y0) / block))
    # Margin: the lookup's floor((x - x0) / cell) may round a point across a cell edge by ~1e-16 of the
    # coordinates' magnitude; 1e-9 of it (and at least a micrometre) keeps every point inside its box.
    margin = max(1e-6, 1e-9 * max(abs(xmin), abs(xmax), abs(ymin), abs(ymax), cell))
    jx, jy = np.meshgrid(np.arange(bnx), np.arange(bny))
    edges = [_region_edges(r.polygon) for r in regions]
    coarse_labels = _classify(regions, x0 + jx.ravel() * block, y0 + jy.ravel() * block, block, margin, edges)
    labels = np.repeat(np.repeat(coarse_labels.reshape(bny, bnx), coarse, axis=0), coarse, axis=1)
    border = np.flatnonzero(coarse_labels == _BORDER)
    if border.size:
        sub = np.arange(coarse)
        ix = (jx.ravel()[border, None, None] * coarse + sub[None, None, :]).repeat(coarse, axis=1)
        iy = (jy.ravel()[border, None, None] * coarse + sub[None, :, None]).repeat(coarse, axis=2)
        labels[iy.ravel(), ix.ravel()] = _classify(regions, x0 + ix.ravel() * cell, y0 + iy.ravel() * cell, cell,
                                                   margin, edges)
    return CellGrid(x0=float(x0), y0=float(y0), cell=float(cell), values=labels)


@njit(cache=True)
def _raster_labels(xy, x0, y0, cell, labels):
    """Label of the cell of each point (``_OUTSIDE`` beyond the grid, ``_BORDER`` for non-finite points)."""
    n = xy.shape[0]
    ny, nx = labels.shape
    out = np.empty(n, dtype=np.int64)
    for k in range(n):
        fx = (xy[k, 0] - x0) / cell
        fy = (xy[k, 1] - y0) / cell
        if not (math.isfinite(fx) and math.isfinite(fy)):
            out[k] = _BORDER
            continue
        ix = math.floor(fx)
        iy = math.floor(fy)
        if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
            out[k] = _OUTSIDE
        else:
            out[k] = labels[iy, ix]
    return out


@dataclass(frozen=True)
class RegionIndex:
    """Look up which region contains each point; the first region listed wins on shared borders."""

    regions: tuple[Region, ...]

    @cached_property
    def names(self) -> np.ndarray:
        return np.array([r.name for r in self.regions], dtype=object)

    @cached_property
    def _names_outside(self) -> dict[str, np.ndarray]:
        return {}

    @cached_property
    def polygons(self) -> np.ndarray:
        return np.array([r.polygon for r in self.regions], dtype=object)

    @cached_property
    def sigmas(self) -> tuple[np.ndarray, np.ndarray, int]:
        """GNSS zones: (sigma_p (Z,), sigma_v (Z,), index of the zone of largest sigma_p)."""
        sp = np.array([r.sigma_p for r in self.regions])
        sv = np.array([r.sigma_v for r in self.regions])
        return sp, sv, int(np.argmax(sp))

    @cached_property
    def raster(self) -> CellGrid:
        return region_raster(self.regions)

    def locate_exact(self, xy: np.ndarray) -> np.ndarray:
        """:meth:`locate` by testing every point against the polygons (the raster's reference)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if xy.shape[0] == 0:
            return np.empty(0, dtype=np.int64)
        # (regions, points) in one vectorised call over the prepared polygons.
        hits = shapely.intersects_xy(self.polygons[:, None], xy[None, :, 0], xy[None, :, 1])
        first = np.argmax(hits, axis=0)
        return np.where(hits[first, np.arange(xy.shape[0])], first, -1).astype(np.int64)

    @cached_property
    def _edges(self) -> list[np.ndarray]:
        """The edges of each region's rings (:func:`_region_edges`), for the fine cells' classification."""
        return [_region_edges(r.polygon) for r in self.regions]

    @cached_property
    def _fine_blocks(self) -> dict:
        """Labels of the fine cells of the border cells met so far (:meth:`_refine`), by raster and block."""
        return {}

    @cached_property
    def _margin(self) -> float:
        """Widening of the fine cells' boxes: as :func:`region_raster`'s, far above the rounding of a cell index."""
        xmin, ymin, xmax, ymax = shapely.total_bounds(self.polygons)
        return max(1e-6, 1e-9 * max(abs(xmin), abs(xmax), abs(ymin), abs(ymax), self.raster.cell))

    def _refine(self, xy: np.ndarray, rows: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Labels of the points ``rows`` (in border cells of the raster) from the fine cells (cell / REFINE on
        the raster's origin, classified as the raster's cells are, a block of REFINE x REFINE at a time when a
        point first falls in it), written into ``idx``; returns the rows whose fine cell a border crosses too
        (and non-finite points), for the polygon test."""
        g = self.raster
        fine = g.cell / REFINE
        blocks = self._fine_blocks
        left = []
        for k in rows.tolist():
            fx, fy = (float(xy[k, 0]) - g.x0) / fine, (float(xy[k, 1]) - g.y0) / fine
            if not (math.isfinite(fx) and math.isfinite(fy)):
                left.append(k)
                continue
            jx, jy = math.floor(fx), math.floor(fy)
            key = (g.x0, g.y0, fine, jy // REFINE, jx // REFINE)
            block = blocks.get(key)
            if block is None:
                sub = np.arange(REFINE)
                ix = np.tile((jx // REFINE) * REFINE + sub, REFINE)
                iy = np.repeat((jy // REFINE) * REFINE + sub, REFINE)
                block = blocks[key] = _classify(self.regions, g.x0 + ix * fine, g.y0 + iy * fine, fine,
                                                self._margin, self._edges).reshape(REFINE, REFINE)
            label = block[jy % REFINE, jx % REFINE]
            if label == _BORDER:
                left.append(k)
            else:
                idx[k] = label
        return np.array(left, dtype=np.int64)

    def locate(self, xy: np.ndarray) -> np.ndarray:
        """Index of the containing region for each point (N,), -1 outside all regions."""
        xy = np.ascontiguousarray(np.asarray(xy, dtype=float).reshape(-1, 2))
        if xy.shape[0] == 0:
            return np.empty(0, dtype=np.int64)
        g = self.raster
        idx = _raster_labels(xy, g.x0, g.y0, g.cell, g.values)
        border = np.flatnonzero(idx == _BORDER)
        if border.size:
            left = self._refine(xy, border, idx)
            if left.size:
                idx[left] = self.locate_exact(xy[left])
        return idx

    def names_at(self, xy: np.ndarray, outside: str = "") -> np.ndarray:
        names = self._names_outside.get(outside)
        if names is None:
            names = self._names_outside[outside] = np.append(self.names, outside)
        return names[self.locate(xy)]


def gnss_sigma_for_zone(zones: RegionIndex, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zone-dependent GNSS accuracy (model (3), Brambilla Sec. VI-A): (zone names, sigma_p, sigma_v).

    Points outside every zone get the worst class of the layout (a conservative
    choice; ``coloc net check`` flags nets whose zones leave roads uncovered).
    """
    idx = zones.locate(xy)
    sp, sv, worst = zones.sigmas
    idx = np.where(idx < 0, worst, idx)
    return zones.names[idx], sp[idx], sv[idx]
