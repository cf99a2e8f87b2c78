"""The fast kernel of the facade reflections (couplers.sensing.gnss_reflect) against the reference kernel of
couplers.sensing.gnss_sky: the same found sets, extra paths and rate coefficients, bit for bit, on random scenes
(rotated boxes and concave outlines, antennas inside footprints, axis-parallel azimuths), on a street canyon
whose blocks share walls, and on the arterial's buildings."""

import math
from pathlib import Path

import numpy as np
import pytest
import shapely
from numba import njit

from couplers.net.buildings import Buildings
from couplers.sensing.gnss_reflect import _argsort_into
from couplers.sensing.gnss_sky import BuildingEdges, clearance_radius, line_of_sight, reflections

ROOT = Path(__file__).resolve().parents[2]


def _random_scene(rng, k):
    polys, heights = [], []
    for _ in range(k):
        cx, cy = rng.uniform(-80, 80, 2)
        if rng.random() < 0.7:  # rotated rectangle
            w, h, a = rng.uniform(4, 30), rng.uniform(4, 30), rng.choice([0.0, rng.uniform(0, np.pi)])
            c = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
            r = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            poly = shapely.Polygon(c @ r.T + [cx, cy])
        else:  # a concave star-like outline
            m = int(rng.integers(5, 10))
            ang = np.sort(rng.uniform(0, 2 * np.pi, m))
            rad = rng.uniform(3, 15, m)
            poly = shapely.Polygon(np.c_[cx + rad * np.cos(ang), cy + rad * np.sin(ang)])
        if poly.is_valid:
            polys.append(poly)
            heights.append(rng.uniform(0.5, 35.0))
    return Buildings.from_polygons(polys, heights)


def _shared_wall_canyon():
    """Blocks of 20 m wall to wall (shared facades) on both sides of a 16 m street, heights 8-30 m."""
    blocks = [shapely.box(x, s * 8, x + 20, s * 8 + 25 * s) for x in range(-200, 200, 20) for s in (1, -1)]
    heights = [8.0 + (7 * i) % 23 for i in range(len(blocks))]
    return Buildings.from_polygons([shapely.box(*g.bounds) for g in blocks], heights)


def _same(edges, xy, az, el, h_ant, mask_deg):
    r = clearance_radius(edges.heights, h_ant, mask_deg)
    blocked, _ = line_of_sight(edges, xy, az, el, h_ant, r)
    fast = reflections(edges, xy, az, el, blocked, h_ant, r)
    ref = reflections(edges, xy, az, el, blocked, h_ant, r, reference=True)
    for a, b in zip(fast, ref):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert a.tobytes() == b.tobytes()
    return int(ref[0].sum()), int(blocked.sum())


def test_fast_reflections_equal_the_reference_on_random_scenes():
    rng = np.random.default_rng(21)
    found = blocked = 0
    for _ in range(8):
        edges = BuildingEdges.build(_random_scene(rng, 40))
        xy = rng.uniform(-100, 100, (50, 2))
        az = np.concatenate([rng.uniform(-np.pi, np.pi, 36), [0.0, np.pi / 2, np.pi, -np.pi / 2]])
        el = np.radians(rng.uniform(10, 80, az.size))
        f, b = _same(edges, xy, az, el, 1.5, 10.0)
        found, blocked = found + f, blocked + b
    assert 0 < found < blocked  # both outcomes are exercised


def test_fast_reflections_equal_the_reference_between_shared_walls():
    rng = np.random.default_rng(4)
    edges = BuildingEdges.build(_shared_wall_canyon())
    xy = np.c_[rng.uniform(-190, 190, 80), rng.uniform(-7, 7, 80)]
    xy[:5, 1] = 0.0
    az = rng.uniform(-np.pi, np.pi, 40)
    az[:4] = [0.0, np.pi / 2, np.pi, -np.pi / 2]
    el = np.radians(rng.uniform(10, 85, 40))
    f, b = _same(edges, xy, az, el, 1.5, 10.0)
    assert 0 < f < b


def test_fast_reflections_equal_the_reference_on_the_arterial():
    from couplers.net.folder import load_net_folder
    from experiments.config import load_config

    cfg = load_config(ROOT / "experiments" / "arterial_tlr_realistic.toml")
    b = load_net_folder(cfg.net_dir).buildings
    if b is None or not len(b):
        pytest.skip("the arterial has no buildings")
    edges = BuildingEdges.build(b)
    rng = np.random.default_rng(8)
    lo, hi = edges.boxes[:, :2].min(0), edges.boxes[:, 2:].max(0)
    xy = rng.uniform(lo, hi, (300, 2))
    az = rng.uniform(-np.pi, np.pi, 48)
    el = np.radians(rng.uniform(10, 88, 48))
    f, b = _same(edges, xy, az, el, 1.5, 10.0)
    assert 0 < f < b


@pytest.mark.parametrize("nlos", ["block", "delay", "reflect"])
def test_pseudorange_assembly_equals_its_numpy_reference(nlos):
    """SatelliteErrorProcess.pseudorange_errors (trigonometry once, the kernels called directly, one assembly
    kernel) against pseudorange_errors_reference: every array bit for bit, the reflections' rate coefficients
    too, receivers inside and outside the shared-wall canyon, and with no receiver."""
    from couplers.sensing.gnss_error import GnssErrorParams
    from couplers.sensing.gnss_satellites import SatelliteErrorProcess

    proc = SatelliteErrorProcess(GnssErrorParams(model="satellites", nlos=nlos), 3, 0.75, _shared_wall_canyon())
    rng = np.random.default_rng(6)
    for n in (60, 0):
        xy = np.c_[rng.uniform(-260, 260, n), rng.uniform(-12, 12, n)]
        u, white = rng.standard_normal((n, proc.sky.size)), rng.standard_normal((n, proc.sky.size))
        for t in (0.0, 1800.0):
            fast, slow = [], []
            a = proc.pseudorange_errors(t, xy, u, white, fast)
            b = proc.pseudorange_errors_reference(t, xy, u, white, slow)
            for x, y in zip(a, b):
                assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
            assert len(fast) == len(slow) and all(x.tobytes() == y.tobytes() for x, y in zip(fast, slow))
            if n:
                assert a[4].any()  # something is blocked


def test_receiver_kernels_equal_the_numpy_expressions_they_replaced():
    """The NLOS counts and the range-rate errors (sig w + einsum("nsk,nk->ns", rate, v), whose zeros may carry
    another sign than the kernel's: the sum with sig w is the same) bit for bit on random inputs with zeros."""
    from couplers.sensing.gnss_satellites import _nlos_counts, _range_rate_errors

    rng = np.random.default_rng(12)
    for n in (0, 1, 37, 150):
        s = 48
        blocked, usedm, above = rng.random((n, s)) < 0.3, rng.random((n, s)) < 0.6, rng.random(s) < 0.4
        got = _nlos_counts(blocked, above, usedm)
        want = ((blocked & above[None, :]).sum(axis=1), (blocked & usedm).sum(axis=1))
        for g, w in zip(got, want):
            assert g.dtype == w.dtype and g.tobytes() == w.tobytes()
        sig, w = rng.uniform(0.05, 0.2, s), rng.standard_normal((n, s))
        rate = rng.standard_normal((n, s, 2)) * (rng.random((n, s, 1)) < 0.2)
        v = rng.standard_normal((n, 2)) * 10 * (rng.random((n, 1)) < 0.8)
        assert _range_rate_errors(sig, w, np.zeros((0, s, 2)), v).tobytes() == (sig[None, :] * w).tobytes()
        want = sig[None, :] * w + np.einsum("nsk,nk->ns", rate, v)
        assert _range_rate_errors(sig, w, rate, v).tobytes() == want.tobytes()


def _fresh_candidates(edges, xy, r, h_ant):
    from couplers.sensing.gnss_sky import building_candidates

    none = np.full(len(xy), -1, dtype=np.int64)
    no_bits = np.empty((0, 2), dtype=np.int64)
    return building_candidates(xy, none, xy.view(np.int64), no_bits, np.zeros(1, dtype=np.int64), none[:0],
                               np.empty(0), *edges.grid(r), float(r), edges.boxes, edges.heights, h_ant)


def test_listed_line_of_sight_equals_the_grid_kernel():
    """los_listed over building_candidates' lists (the coarse grid's buildings in its order) against the
    line-of-sight kernel's own fine-grid search: blocked sets and distances bit for bit (an "or" and a minimum
    over the same buildings), on random scenes, the shared-wall canyon and antennas on cell borders."""
    from couplers.sensing.gnss_sky import los_listed

    rng = np.random.default_rng(31)
    scenes = [BuildingEdges.build(_random_scene(rng, 40)) for _ in range(5)]
    scenes.append(BuildingEdges.build(_shared_wall_canyon()))
    blocked_total = 0
    for edges in scenes:
        r = clearance_radius(edges.heights, 1.5, 10.0)
        xy = np.c_[rng.uniform(-150, 150, 60), rng.uniform(-100, 100, 60)]
        xy[:4] = edges.grid(r)[:2]  # on the grid's origin and cell corners
        xy[4:8] = np.asarray(edges.grid(r)[:2]) + edges.grid(r)[2]
        az = np.concatenate([rng.uniform(-np.pi, np.pi, 30), [0.0, np.pi / 2, np.pi, -np.pi / 2]])
        el = np.radians(rng.uniform(5, 85, az.size))
        want = line_of_sight(edges, xy, az, el, 1.5, r)
        got = los_listed(xy, *_fresh_candidates(edges, xy, r, 1.5), edges.edges, edges.start, edges.boxes,
                         edges.heights, np.sin(az), np.cos(az), np.tan(el), 1.5)
        for a, b in zip(got, want):
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
        blocked_total += int(want[0].sum())
    assert blocked_total > 0


def test_candidates_carried_for_standing_vehicles_equal_fresh_ones():
    """building_candidates with the previous step's lists: a vehicle that stops, moves, stops again (and one
    that moves by the last bit of x only, and rows whose previous row is another vehicle's) gets exactly the
    lists computed afresh; only a bitwise-equal position is carried."""
    from couplers.sensing.gnss_sky import building_candidates

    edges = BuildingEdges.build(_shared_wall_canyon())
    r = clearance_radius(edges.heights, 1.5, 10.0)
    rng = np.random.default_rng(5)
    xy = np.c_[rng.uniform(-190, 190, 6), rng.uniform(-7, 7, 6)]
    moves = [(0, 0, 1, 1, 0, 0, 1), (0, 1, 1, 0, 0, 1, 1)]  # per step: vehicles 0 and 1 stand (0) or move (1)
    prev_bits, prev = np.empty((0, 2), dtype=np.int64), (np.zeros(1, dtype=np.int64), np.empty(0, dtype=np.int64),
                                                          np.empty(0))
    carried = 0
    for step in range(len(moves[0])):
        xy = xy.copy()
        for v in (0, 1):
            if moves[v][step]:
                xy[v, 0] += 7.5
        xy[2, 0] = np.nextafter(xy[2, 0], np.inf)  # moves by one ulp: not carried
        xy[3:] += 0.5
        rows = np.arange(6, dtype=np.int64) if step else np.full(6, -1, dtype=np.int64)
        if step % 3 == 2:
            rows = rows[::-1].copy()  # the previous rows of other vehicles: positions differ, nothing carried
        got = building_candidates(xy, rows, xy.view(np.int64), prev_bits, *prev, *edges.grid(r), float(r),
                                  edges.boxes, edges.heights, 1.5)
        want = _fresh_candidates(edges, xy, r, 1.5)
        for a, b in zip(got, want):
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
        # the same call with every previous list replaced by building 0 at distance -1: exactly the rows whose
        # position is bitwise their previous row's take it
        m = prev[0].size - 1
        poison = (np.arange(m + 1, dtype=np.int64), np.zeros(m, dtype=np.int64), np.full(m, -1.0))
        marked = building_candidates(xy, rows, xy.view(np.int64), prev_bits, *poison, *edges.grid(r), float(r),
                                     edges.boxes, edges.heights, 1.5)
        same = np.array([0 <= q < len(prev_bits) and (xy.view(np.int64)[i] == prev_bits[q]).all()
                         for i, q in enumerate(rows)], dtype=bool)
        for i in range(6):
            row = marked[2][marked[0][i]:marked[0][i + 1]]
            assert (row.tolist() == [-1.0]) == bool(same[i])
        carried += int(same.sum())
        prev_bits, prev = xy.view(np.int64).copy(), got
    assert carried == 4 and np.diff(want[0]).min() > 0  # every antenna has candidates in the canyon


def test_the_receiver_with_its_carried_candidates_equals_one_without():
    """SatelliteErrorProcess.step with the candidate buildings carried for standing vehicles against the same
    process made to list every antenna's buildings afresh each step: fixes, reported covariances and Doppler
    velocities bit for bit, vehicles stopping, moving, stopping, entering and leaving."""
    from couplers.sensing.gnss_error import GnssErrorParams
    from couplers.sensing import gnss_satellites as gs

    params = GnssErrorParams(model="satellites", nlos="reflect", velocity="doppler", reported_covariance="residual")
    carry = gs.SatelliteErrorProcess(params, 4, 0.75, _shared_wall_canyon())
    fresh = gs.SatelliteErrorProcess(params, 4, 0.75, _shared_wall_canyon())
    rng = np.random.default_rng(9)
    n = 30
    ids = np.array([f"v{i}" for i in range(n)], dtype=object)
    xy = np.c_[rng.uniform(-190, 190, n), rng.uniform(-7, 7, n)]
    stand = rng.random(n) < 0.5
    for k in range(12):
        if k % 4 == 0:
            stand = rng.random(n) < 0.5
        xy = xy + np.where(stand[:, None], 0.0, [0.6, 0.0])
        keep = np.ones(n, dtype=bool)
        keep[(k * 3) % n] = False  # one vehicle missing this step (leaves, comes back as entered)
        fresh._cands = gs._NO_CANDIDATES
        entered = np.full(int(keep.sum()), k == 0)
        a = carry.step(k * 0.75, ids[keep], entered, None, None, None, xy[keep])
        b = fresh.step(k * 0.75, ids[keep], entered, None, None, None, xy[keep])
        assert a.tobytes() == b.tobytes() and carry.reported_cov.tobytes() == fresh.reported_cov.tobytes()
        v = np.tile([0.6 / 0.75, 0.0], (int(keep.sum()), 1))
        for x, y in zip(carry.velocity_error(v), fresh.velocity_error(v)):
            assert x.tobytes() == y.tobytes()


@njit
def _numba_argsort(a):
    return np.argsort(a)


def test_small_argsort_is_numbas_argsort():
    """The paths' order (couplers.sensing.gnss_reflect._argsort_into) is numba's np.argsort index for index:
    ties (numba's quicksort is not stable above its insertion-sort size), NaN, every length 0-40."""
    rng = np.random.default_rng(7)
    for n in range(41):
        for trial in range(30):
            a = rng.integers(0, 4, n).astype(float) if trial % 2 else rng.normal(size=n)
            if trial % 5 == 0 and n:
                a[rng.integers(0, n)] = np.nan
            buf = np.concatenate([a, rng.normal(size=3)])  # values past n are not read
            order = np.full(buf.size, -7, dtype=np.int64)
            _argsort_into(buf, n, order)
            assert order[:n].tolist() == _numba_argsort(a).tolist()
