"""Zone and area lookup: the raster (RegionIndex.locate) gives the labels of the polygon test
(RegionIndex.locate_exact) exactly, on random points and on points on and near the borders."""

from pathlib import Path

import numpy as np
import pytest
import shapely
from shapely.geometry import MultiPolygon, Polygon

from couplers.net.folder import Region, load_net_folder
from couplers.net.zones import RegionIndex, gnss_sigma_for_zone, region_raster

ARTERIAL = Path(__file__).resolve().parents[2] / "sumo_nets" / "arterial"


def _prepared(geom):
    shapely.prepare(geom)
    return geom


def _synthetic_regions() -> tuple[Region, ...]:
    """Overlapping regions (the first listed wins), a hole, a MultiPolygon, slanted and curved borders."""
    square = Polygon([(0, 0), (100, 0), (100, 100), (0, 100)], holes=[[(40, 40), (60, 40), (60, 60), (40, 60)]])
    slanted = Polygon([(50, -20), (170, 30), (120, 140), (30, 90)])
    disc = shapely.Point(130.3, 60.7).buffer(33.3, quad_segs=16)
    islands = MultiPolygon([Polygon([(-50, -50), (-10, -50), (-10, -10)]),
                            Polygon([(180, 150), (220.5, 150), (220.5, 190.25), (180, 190.25)])])
    big = Polygon([(-60, -60), (230, -60), (230, 200), (-60, 200)])
    return tuple(Region(name=n, polygon=_prepared(p), sigma_p=s, sigma_v=s / 10)
                 for n, p, s in [("sq", square, 3.0), ("slant", slanted, 8.0), ("disc", disc, 5.0),
                                 ("isl", islands, 9.0), ("big", big, 15.0)])


def _border_points(regions, rng, per_vertex=6) -> np.ndarray:
    """Vertices, points along every edge, and the same nudged by 1e-12 .. 1e-3 m in random directions."""
    pts = []
    for r in regions:
        for ring in shapely.get_rings(shapely.get_parts(r.polygon)):
            xy = shapely.get_coordinates(ring)
            pts.append(xy)
            a, b = xy[:-1], xy[1:]
            t = rng.random((a.shape[0], per_vertex))
            pts.append((a[:, None] + t[..., None] * (b - a)[:, None]).reshape(-1, 2))
    pts = np.vstack(pts)
    nudged = [pts + rng.normal(size=pts.shape) * eps for eps in (1e-12, 1e-9, 1e-6, 1e-3)]
    return np.vstack([pts, *nudged])


def _cell_edge_points(raster, rng, n=3000) -> np.ndarray:
    """Points on the raster's cell edges and corners (where the cell index rounds either way)."""
    ny, nx = raster.values.shape
    ix = rng.integers(0, nx + 1, n)
    iy = rng.integers(0, ny + 1, n)
    x = raster.x0 + ix * raster.cell
    y = raster.y0 + iy * raster.cell
    free = rng.random(n)
    xs = np.where(free < 0.33, raster.x0 + rng.random(n) * nx * raster.cell, x)
    ys = np.where(free > 0.66, raster.y0 + rng.random(n) * ny * raster.cell, y)
    return np.stack([xs, ys], axis=1)


@pytest.mark.parametrize("cell_m", [0.7, 5.0, 23.0])
def test_raster_labels_equal_the_polygon_test_synthetic(cell_m):
    rng = np.random.default_rng(7)
    regions = _synthetic_regions()
    index = RegionIndex(regions)
    index.__dict__["raster"] = region_raster(regions, cell_m=cell_m)  # this cell size instead of the default
    pts = np.vstack([rng.uniform(-80, 250, (20000, 2)), _border_points(regions, rng),
                     _cell_edge_points(index.raster, rng)])
    got, want = index.locate(pts), index.locate_exact(pts)
    np.testing.assert_array_equal(got, want)
    assert set(np.unique(want)) == {-1, 0, 1, 2, 3, 4}  # every label (and outside) is exercised


def test_raster_labels_equal_the_polygon_test_on_the_arterial():
    net = load_net_folder(ARTERIAL)
    rng = np.random.default_rng(11)
    for regions in (net.zones, net.areas):
        index = RegionIndex(regions)
        xmin, ymin, xmax, ymax = shapely.total_bounds(index.polygons)
        pts = np.vstack([np.column_stack([rng.uniform(xmin - 50, xmax + 50, 30000),
                                          rng.uniform(ymin - 50, ymax + 50, 30000)]),
                         _border_points(regions, rng), _cell_edge_points(index.raster, rng)])
        np.testing.assert_array_equal(index.locate(pts), index.locate_exact(pts))


def test_raster_cap_on_cells_and_odd_inputs():
    regions = _synthetic_regions()
    raster = region_raster(regions, cell_m=0.01, max_cells=5000)
    assert raster.values.size <= 2 * 5000 * 64 and raster.cell > 0.01  # the cap coarsens the cells
    index = RegionIndex(regions)
    assert index.locate(np.empty((0, 2))).shape == (0,)
    odd = np.array([[np.nan, 1.0], [np.inf, 0.0], [1e12, -1e12], [10.0, 10.0]])
    np.testing.assert_array_equal(index.locate(odd), index.locate_exact(odd))


def test_names_and_sigmas_follow_the_labels():
    regions = _synthetic_regions()
    index = RegionIndex(regions)
    pts = np.array([[10.0, 10.0], [50.0, 50.0], [-100.0, -100.0], [200.0, 170.0]])
    assert index.names_at(pts, outside="out").tolist() == ["sq", "slant", "out", "isl"]
    assert index.names_at(pts).tolist() == ["sq", "slant", "", "isl"]
    names, sp, sv = gnss_sigma_for_zone(index, pts)
    assert names.tolist() == ["sq", "slant", "big", "isl"]  # outside every zone: the worst (largest sigma_p)
    np.testing.assert_array_equal(sp, [3.0, 8.0, 15.0, 9.0])
    np.testing.assert_array_equal(sv, [0.3, 0.8, 1.5, 0.9])


def test_fine_cells_of_the_border_cells_give_the_polygon_test():
    """Points on the edges of the fine cells (REFINE per raster cell) and near the borders: same labels."""
    from couplers.net.zones import REFINE

    rng = np.random.default_rng(12)
    net = load_net_folder(ARTERIAL)
    for regions in (_synthetic_regions(), net.zones, net.areas):
        index = RegionIndex(regions)
        g = index.raster
        near = _border_points(regions, rng)
        fine = g.cell / REFINE
        jx, jy = np.floor((near[:, 0] - g.x0) / fine), np.floor((near[:, 1] - g.y0) / fine)
        edges = np.vstack([np.column_stack([g.x0 + jx * fine, near[:, 1]]), np.column_stack([near[:, 0], g.y0 + jy * fine]),
                           np.column_stack([g.x0 + (jx + 1) * fine, g.y0 + (jy + 1) * fine])])
        pts = np.vstack([near, edges, np.nextafter(edges, np.inf), np.nextafter(edges, -np.inf)])
        np.testing.assert_array_equal(index.locate(pts), index.locate_exact(pts))
        assert index._fine_blocks  # the fine cells were used


@pytest.mark.parametrize("which", ["synthetic", "arterial_zones", "arterial_areas"])
def test_raster_labels_agree_with_shapely_boxes(which, monkeypatch):
    """The raster classified without a geometry per cell (zones._classify) gives every cell the label of the
    shapely classification with a box per cell (zones._classify_boxes) or _BORDER, and marks few more
    cells _BORDER than it."""
    from couplers.net import zones

    if which == "synthetic":
        regions = _synthetic_regions()
    else:
        net = load_net_folder(ARTERIAL)
        regions = net.zones if which == "arterial_zones" else net.areas
    new = region_raster(regions, cell_m=2.0)
    monkeypatch.setattr(zones, "_classify", zones._classify_boxes)
    ref = region_raster(regions, cell_m=2.0)
    assert new.values.shape == ref.values.shape and (new.x0, new.y0, new.cell) == (ref.x0, ref.y0, ref.cell)
    border = new.values == zones._BORDER
    np.testing.assert_array_equal(new.values[~border], ref.values[~border])
    n_ref = int((ref.values == zones._BORDER).sum())
    assert n_ref > 0 and border.sum() <= 1.2 * n_ref + 10, (int(border.sum()), n_ref)
