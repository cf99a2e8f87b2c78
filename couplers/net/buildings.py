"""The net folder's building footprints as arrays: the polygons of ``buildings.geojson`` (read by
:func:`couplers.net.folder.read_buildings`) with their STRtree, the cells near a building and the
bounding boxes listed per cell, which the sight-line tests of :mod:`couplers.sensing.occlusion` read."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import shapely
from numba import njit

from couplers.net.zones import CellGrid


@dataclass(frozen=True)
class Buildings:
    """Building footprints of a net folder (net x/y) with their STRtree, for sight-line queries."""

    polygons: np.ndarray  # (B,) shapely Polygons / MultiPolygons
    heights: np.ndarray  # (B,) m, NaN where the file gives none
    tree: shapely.STRtree

    @classmethod
    def from_polygons(cls, polygons, heights=None) -> "Buildings":
        polys = np.empty(len(polygons), dtype=object)
        polys[:] = list(polygons)
        h = np.full(polys.size, np.nan) if heights is None else np.asarray(heights, dtype=float)
        return cls(polygons=polys, heights=h, tree=shapely.STRtree(polys))

    def __len__(self) -> int:
        return int(self.polygons.size)

    @cached_property
    def cells(self):
        """Cells near these footprints (:func:`building_cells`, built on first use)."""
        return building_cells(self)

    @cached_property
    def boxes(self):
        """Bounding boxes listed per cell of :attr:`cells` (:class:`BuildingBoxes`)."""
        return BuildingBoxes.build(self)



BUILDING_CELL_M = 4.0


def building_cells(buildings: Buildings, cell_m: float = BUILDING_CELL_M) -> CellGrid:
    """Cells near a building: ``values`` (bool) marks the cells within one cell of a building's bounding box."""
    b = shapely.bounds(buildings.polygons)
    x0, y0 = float(b[:, 0].min()) - 2 * cell_m, float(b[:, 1].min()) - 2 * cell_m  # two free cells around
    nx = int(math.floor((b[:, 2].max() - x0) / cell_m)) + 3
    ny = int(math.floor((b[:, 3].max() - y0) / cell_m)) + 3
    # the lookup's floor((x - x0) / cell), on the boxes' corners, widened by one cell each side
    ix0 = np.floor((b[:, 0] - x0) / cell_m).astype(np.int64) - 1
    iy0 = np.floor((b[:, 1] - y0) / cell_m).astype(np.int64) - 1
    ix1 = np.floor((b[:, 2] - x0) / cell_m).astype(np.int64) + 1
    iy1 = np.floor((b[:, 3] - y0) / cell_m).astype(np.int64) + 1
    mark = np.zeros((ny + 1, nx + 1), dtype=np.int64)  # 2-D difference array of the boxes
    np.add.at(mark, (iy0, ix0), 1)
    np.add.at(mark, (iy0, ix1 + 1), -1)
    np.add.at(mark, (iy1 + 1, ix0), -1)
    np.add.at(mark, (iy1 + 1, ix1 + 1), 1)
    near = mark.cumsum(axis=0).cumsum(axis=1)[:ny, :nx] > 0
    return CellGrid(x0=x0, y0=y0, cell=float(cell_m), values=near)


@dataclass(frozen=True)
class BuildingBoxes:
    """The buildings' bounding boxes (B, 4: xmin, ymin, xmax, ymax) and, per cell of ``buildings.cells`` (ny * nx,
    CSR ``start`` / ``ids``), the buildings whose box widened by one cell covers it: the candidates of the
    sight lines sampled in that cell (:func:`_needs_building_test`)."""

    boxes: np.ndarray
    start: np.ndarray
    ids: np.ndarray
    margin: float  # widening of the boxes in the segment test, far above its rounding

    @classmethod
    def build(cls, buildings: Buildings) -> "BuildingBoxes":
        g = buildings.cells
        ny, nx = g.values.shape
        b = np.ascontiguousarray(shapely.bounds(buildings.polygons), dtype=np.float64)
        # the cells of building_cells' difference array: floor((x - x0) / cell) of the corners, widened by one
        ix0 = np.clip(np.floor((b[:, 0] - g.x0) / g.cell).astype(np.int64) - 1, 0, nx - 1)
        iy0 = np.clip(np.floor((b[:, 1] - g.y0) / g.cell).astype(np.int64) - 1, 0, ny - 1)
        ix1 = np.clip(np.floor((b[:, 2] - g.x0) / g.cell).astype(np.int64) + 1, 0, nx - 1)
        iy1 = np.clip(np.floor((b[:, 3] - g.y0) / g.cell).astype(np.int64) + 1, 0, ny - 1)
        start, ids = _cell_lists(ix0, iy0, ix1, iy1, nx, ny)
        margin = max(1e-6, 1e-9 * float(np.abs(b).max(initial=0.0)))
        return cls(boxes=b, start=start, ids=ids, margin=margin)


@njit(cache=True)
def _cell_lists(ix0, iy0, ix1, iy1, nx, ny):
    """CSR of the boxes [ix0, ix1] x [iy0, iy1] (cells, inclusive) covering each cell iy * nx + ix."""
    count = np.zeros(nx * ny + 1, dtype=np.int64)
    for k in range(ix0.size):
        for iy in range(iy0[k], iy1[k] + 1):
            for ix in range(ix0[k], ix1[k] + 1):
                count[iy * nx + ix + 1] += 1
    for c in range(nx * ny):
        count[c + 1] += count[c]
    ids = np.empty(count[nx * ny], dtype=np.int64)
    fill = count[:-1].copy()
    for k in range(ix0.size):
        for iy in range(iy0[k], iy1[k] + 1):
            for ix in range(ix0[k], ix1[k] + 1):
                ids[fill[iy * nx + ix]] = k
                fill[iy * nx + ix] += 1
    return count, ids
