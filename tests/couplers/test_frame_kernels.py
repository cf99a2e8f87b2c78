"""The numba fast paths of frame synthesis against numpy / shapely references: identical outputs.

(Zone lookup: test_zones.py; V2V graph and V2F pairs: test_sensors.py; id rows: test_rows.py.)
"""

import math
from pathlib import Path

import numpy as np
import pytest
import shapely

from couplers.net.zones import CellGrid
from couplers.sensing.gnss_error import (
    GnssErrorParams,
    GnssErrorProcess,
    episode_start_probability,
    gauss_markov_step,
)
from couplers.sensing.inertial import (
    InertialParams,
    InertialProcess,
    gauss_markov_bias,
    true_body_motion,
    turn_on_bias,
    white_noise,
)
from couplers.net.folder import load_net_folder
from couplers.sensing.occlusion import occluded_by_buildings
from couplers.sensing.perception import _merge_detections
from couplers.sensing.rows import shuffle_within_owner

ARTERIAL = Path(__file__).resolve().parents[2] / "sumo_nets" / "arterial"


def test_shuffle_within_owner_is_lexsort_of_the_same_draws():
    rng = np.random.default_rng(1)
    for size, owners in [(0, 1), (1, 1), (50, 3), (400, 120), (300, 2)]:  # (300, 2): groups past 32 rows
        owner = rng.integers(0, owners, size)
        if size == 400:
            owner = np.sort(owner)
        got = shuffle_within_owner(owner, np.random.default_rng(size))
        want = np.lexsort((np.random.default_rng(size).random(size), owner))
        np.testing.assert_array_equal(got, want)
    keys = np.array([0.5, 0.5, 0.1, 0.5, 0.1])  # equal keys keep their order, as lexsort's
    got = shuffle_within_owner(np.zeros(5, dtype=np.int64), type("R", (), {"random": lambda self, n: keys})())
    np.testing.assert_array_equal(got, np.lexsort((keys, np.zeros(5))))


def test_merge_detections_equals_the_lexsort_reference():
    rng = np.random.default_rng(2)
    range_m, pd_near, pd_far = np.array([80.0, 30.0, 50.0]), np.array([0.95, 0.9, 1.0]), np.array([0.7, 0.6, 0.5])
    sigma_p, growth = np.array([0.1, 0.1, 0.2]), np.array([3.0, 3.0, 0.0])
    for _ in range(50):
        n_pairs, c = 60, 150
        pair = rng.integers(0, n_pairs, c)
        sensor = rng.integers(0, 3, c)
        dist = np.where(rng.random(c) < 0.2, 0.0, rng.uniform(0, 90, c))  # ties in sigma_p at d = 0
        u, visible = rng.random(c), rng.random(c) < 0.8
        detected = np.empty(c, dtype=bool)
        sig, first = _merge_detections(pair, dist, sensor, detected, n_pairs, range_m, pd_near, pd_far, sigma_p,
                                       growth, u, visible)
        frac = np.clip(dist / range_m[sensor], 0.0, 1.0)
        sig_ref = sigma_p[sensor] * (1.0 + growth[sensor] * frac)
        hit = np.flatnonzero(visible & (u < pd_near[sensor] + (pd_far[sensor] - pd_near[sensor]) * frac))
        order = hit[np.lexsort((sensor[hit], sig_ref[hit], pair[hit]))]
        np.testing.assert_array_equal(sig, sig_ref)
        np.testing.assert_array_equal(first, order[np.unique(pair[order], return_index=True)[1]])
        np.testing.assert_array_equal(np.flatnonzero(detected), hit)


def test_buildings_prefilter_gives_the_strtree_answer():
    blds = load_net_folder(ARTERIAL).buildings
    rng = np.random.default_rng(3)
    xmin, ymin, xmax, ymax = shapely.total_bounds(blds.polygons)
    start = np.column_stack([rng.uniform(xmin - 30, xmax + 30, 20000), rng.uniform(ymin - 30, ymax + 30, 20000)])
    ang, length = rng.uniform(-np.pi, np.pi, 20000), rng.uniform(0, 90, 20000)
    end = start + length[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    # segments ending on building corners and edges, or running along an edge
    corners = shapely.get_coordinates(shapely.get_exterior_ring(shapely.get_parts(blds.polygons)))
    pick = corners[rng.integers(0, len(corners), 3000)]
    start = np.vstack([start, pick + rng.normal(0, 20, pick.shape), pick[:-1]])
    end = np.vstack([end, pick, pick[1:]])
    got = occluded_by_buildings(start, end, blds)
    lines = shapely.linestrings(np.stack([start, end], axis=1))
    want = np.zeros(len(start), dtype=bool)
    want[blds.tree.query(lines, predicate="intersects")[0]] = True
    np.testing.assert_array_equal(got, want)
    assert 0.01 < want.mean() < 0.9


def test_density_grid_lookup_equals_the_floor_reference():
    rng = np.random.default_rng(4)
    grid = CellGrid(x0=-3.3, y0=7.1, cell=5.0, values=rng.random((20, 30)))
    xy = np.vstack([rng.uniform(-20, 170, (5000, 2)) + [0, 10],
                    np.column_stack([-3.3 + 5.0 * rng.integers(-1, 32, 500), 7.1 + 5.0 * rng.integers(-1, 22, 500)])])
    ix = np.floor((xy[:, 0] - grid.x0) / grid.cell).astype(np.int64)
    iy = np.floor((xy[:, 1] - grid.y0) / grid.cell).astype(np.int64)
    ok = (ix >= 0) & (iy >= 0) & (ix < 30) & (iy < 20)
    want = np.zeros(len(xy))
    want[ok] = grid.values[iy[ok], ix[ok]]
    np.testing.assert_array_equal(grid.at(xy), want)


def _fleet(rng, steps=60, pool=40):
    """Per step: ids (vehicles entering and leaving), entered flags, headings and positions."""
    out, present = [], rng.random(pool) < 0.5
    for _ in range(steps):
        present ^= rng.random(pool) < 0.08
        ids = np.array([f"v{i}" for i in np.flatnonzero(present)], dtype=object)
        rng.shuffle(ids)
        out.append((ids, rng.random(ids.size) < 0.05, rng.uniform(-np.pi, np.pi, ids.size),
                    rng.uniform(0, 400, (ids.size, 2))))
    return out


@pytest.mark.parametrize("tau_s, buildings", [(0.0, False), (30.0, False), (30.0, True)])
def test_gnss_error_step_equals_the_array_reference(tau_s, buildings):
    params = GnssErrorParams(tau_s=tau_s, nlos_rate_per_min=(3.0, 12.0), nlos_rate_per_density_per_min=30.0)
    blds = load_net_folder(ARTERIAL).buildings if buildings else None
    dt, proc = 0.75, GnssErrorProcess(params, seed=5, dt=0.75, buildings=blds)
    ref = GnssErrorProcess(params, seed=5, dt=0.75, buildings=blds)  # its streams drive the reference below
    state = dict(ids=np.empty(0, dtype=object), u=np.empty((0, 2)), bias=np.empty((0, 2)), end=np.empty(0))
    rng = np.random.default_rng(6)
    lo = np.array(shapely.total_bounds(blds.polygons)[:2]) if buildings else np.zeros(2)
    for k, (ids, entered, _, xy) in enumerate(_fleet(rng)):
        xy = xy + lo  # over the buildings (their density) when the net has them
        n, t = ids.size, (k + 1) * dt
        w, sp = rng.standard_normal((n, 2)), rng.choice([3.0, 8.0, 15.0], n)
        zone = np.where(sp == 3.0, "A", np.where(sp == 8.0, "B", "C")).astype(object)
        got = proc.step(t, ids, entered, w, sp, zone, xy)
        # the previous implementation, step by step
        prev = {v: i for i, v in enumerate(state["ids"])}
        idx = np.array([prev.get(v, -1) for v in ids], dtype=np.int64)
        cont = (idx >= 0) & ~entered
        u = w.copy()
        u[cont] = gauss_markov_step(state["u"][idx[cont]], w[cont], ref.a)
        bias, end = np.zeros((n, 2)), np.full(n, -np.inf)
        bias[cont], end[cont] = state["bias"][idx[cont]], state["end"][idx[cont]]
        active = end > t + 1e-9
        bias[~active] = 0.0
        start = (ref.nlos_start.random(n) < episode_start_probability(ref.start_rates(zone, xy), dt)) & ~active
        dur = ref.nlos_duration.exponential(params.nlos_mean_duration_s, size=n)
        mag = ref.nlos_bias.exponential(params.nlos_bias_mean_m, size=n)
        ang = ref.nlos_bias.uniform(-np.pi, np.pi, size=n)
        bias[start] = mag[start, None] * np.stack([np.cos(ang[start]), np.sin(ang[start])], axis=1)
        end[start] = t + dur[start]
        end[~active & ~start] = -np.inf
        state = dict(ids=ids, u=u, bias=bias, end=end)
        np.testing.assert_array_equal(got, sp[:, None] * u + bias)
        np.testing.assert_array_equal(proc.in_episode, np.any(bias != 0.0, axis=1))


def test_inertial_step_equals_the_array_reference():
    p, dt = InertialParams(), 0.75
    proc, ref = InertialProcess(p, seed=7, dt=dt), InertialProcess(p, seed=7, dt=dt)
    rad = math.pi / 180.0
    st = dict(ids=np.empty(0, dtype=object), heading=np.empty(0), a_on=np.empty((0, 2)), a_dr=np.empty((0, 2)),
              g_on=np.empty(0), g_dr=np.empty(0))
    rng = np.random.default_rng(8)
    for ids, entered, heading, _ in _fleet(rng):
        n = ids.size
        accel_net = rng.normal(0, 1, (n, 2))
        got = proc.step(ids, entered, heading, accel_net)
        prev = {v: i for i, v in enumerate(st["ids"])}
        idx = np.array([prev.get(v, -1) for v in ids], dtype=np.int64)
        fresh = (idx < 0) | entered
        cont = ~fresh

        def carried(arr, fill=0.0):
            out = np.full((n,) + arr.shape[1:], fill)
            out[cont] = arr[idx[cont]]
            return out

        body, yaw = true_body_motion(accel_net, heading, carried(st["heading"], np.nan), dt)
        a_on = np.where(fresh[:, None], turn_on_bias(ref.accel_turn_on_rng, (n, 2), p.accel_turn_on_sigma),
                        carried(st["a_on"]))
        g_on = np.where(fresh, turn_on_bias(ref.gyro_turn_on_rng, (n,), p.gyro_turn_on_sigma * rad), carried(st["g_on"]))
        a_dr = gauss_markov_bias(carried(st["a_dr"]), ref.accel_drift_rng.standard_normal((n, 2)), fresh,
                                 p.accel_bias_sigma, ref.a_accel)
        g_dr = gauss_markov_bias(carried(st["g_dr"]), ref.gyro_drift_rng.standard_normal(n), fresh,
                                 p.gyro_bias_sigma * rad, ref.a_gyro)
        accel = body + a_on + a_dr + white_noise(ref.accel_noise_rng, (n, 2), p.accel_noise_density, dt)
        yaw_rate = yaw + g_on + g_dr + white_noise(ref.gyro_noise_rng, (n,), p.gyro_noise_density * rad, dt)
        st = dict(ids=ids, heading=heading, a_on=a_on, a_dr=a_dr, g_on=g_on, g_dr=g_dr)
        np.testing.assert_array_equal(got.accel_body, accel)
        np.testing.assert_array_equal(got.yaw_rate, yaw_rate)
        np.testing.assert_array_equal(proc.accel_bias, a_on + a_dr)
        np.testing.assert_array_equal(proc.gyro_bias, g_on + g_dr)


def test_footprints_and_occluder_boxes_equal_the_array_reference():
    from couplers.sensing.occlusion import OccluderIndex, unit_heading, vehicle_footprints

    rng = np.random.default_rng(9)
    xy, heading = rng.uniform(-500, 500, (300, 2)), rng.uniform(-4, 4, 300)
    length, width = rng.uniform(3, 15, 300), rng.uniform(1.5, 2.6, 300)
    u = unit_heading(heading)
    n = np.stack([-u[:, 1], u[:, 0]], axis=1)
    half, back = 0.5 * width[:, None], xy - length[:, None] * u
    want = np.stack([xy - half * n, xy + half * n, back + half * n, back - half * n], axis=1)
    corners = vehicle_footprints(xy, heading, length, width)
    np.testing.assert_array_equal(corners, want)
    corners[:50] = np.round(corners[:50])  # ties in the x minimum: the order stays stable
    idx = OccluderIndex.build(corners)
    xmin, xmax = corners[:, :, 0].min(axis=1), corners[:, :, 0].max(axis=1)
    np.testing.assert_array_equal(idx.xmin, xmin)
    np.testing.assert_array_equal(idx.xmax, xmax)
    np.testing.assert_array_equal(idx.ymin, corners[:, :, 1].min(axis=1))
    np.testing.assert_array_equal(idx.ymax, corners[:, :, 1].max(axis=1))
    assert idx.max_wx == float((xmax - xmin).max())
    # the buckets: a stable counting sort by the bucket of each xmin
    bucket = np.minimum(((xmin - idx.x0) / idx.width).astype(np.int64), idx.start.size - 2)
    assert idx.x0 == xmin.min() and idx.start[0] == 0 and idx.start[-1] == len(corners)
    np.testing.assert_array_equal(idx.order, np.argsort(bucket, kind="stable"))
    np.testing.assert_array_equal(np.diff(idx.start), np.bincount(bucket, minlength=idx.start.size - 1))
    assert OccluderIndex.build(np.empty((0, 4, 2))).max_wx == 0.0


# --- second pass (per-step overhead): fused kernels against the numpy they replace -----------------


def test_inertial_step_equals_its_numpy_reference_with_and_without_rows():
    from coloc.core.vehicles import match_ids

    p, dt = InertialParams(), 0.75
    fused, fused_rows, ref = (InertialProcess(p, seed=3, dt=dt) for _ in range(3))
    rng = np.random.default_rng(10)
    prev = np.empty(0, dtype=object)
    for k, (ids, entered, heading, _) in enumerate(_fleet(rng, steps=80)):
        # headings on and around the wrap (+-pi, signed zeros, a turn across the cut) as well as random ones
        special = np.array([np.pi, -np.pi, 0.0, -0.0, np.pi - 1e-12, -np.pi + 1e-12, 3.0, -3.0])
        heading = np.where(rng.random(ids.size) < 0.3, special[rng.integers(0, 8, ids.size)], heading)
        accel_net = rng.normal(0, 1, (ids.size, 2))
        got = fused.step(ids, entered, heading, accel_net)
        got_rows = fused_rows.step(ids, entered, heading, accel_net, idx=match_ids(prev, ids))
        want = ref.step_reference(ids, entered, heading, accel_net)
        prev = ids
        for g in (got, got_rows):
            np.testing.assert_array_equal(g.accel_body, want.accel_body)
            np.testing.assert_array_equal(g.yaw_rate, want.yaw_rate)
        for proc in (fused, fused_rows):
            np.testing.assert_array_equal(proc.accel_bias, ref.accel_bias)
            np.testing.assert_array_equal(proc.gyro_bias, ref.gyro_bias)
    for name in InertialProcess.STREAMS:  # the kernels' draws left every stream where numpy's leave it
        want = getattr(ref, f"{name}_rng").random()
        assert getattr(fused, f"{name}_rng").random() == want == getattr(fused_rows, f"{name}_rng").random()


def test_gnss_start_probability_lookup_equals_rate_then_expm1():
    blds = load_net_folder(ARTERIAL).buildings
    proc = GnssErrorProcess(GnssErrorParams(), seed=1, dt=0.75, buildings=blds)
    g = proc.density
    rng = np.random.default_rng(11)
    xy = np.vstack([rng.uniform([g.x0 - 50, g.y0 - 50], [g.x0 + g.cell * g.values.shape[1] + 50,
                                                          g.y0 + g.cell * g.values.shape[0] + 50], (20000, 2)),
                    [[np.nan, 0.0], [np.inf, 1.0]]])
    zone = np.full(len(xy), "B", dtype=object)
    want = episode_start_probability(proc.start_rates(zone, xy), proc.dt)
    np.testing.assert_array_equal(proc.start_probabilities(zone, xy), want)
    assert (want > 0).mean() > 0.1


def test_fov_with_the_heading_vectors_equals_fov_all():
    from couplers.sensing.perception import PerceptionParams, SensorSpec, _fov_all, _fov_params, unit_heading

    rng = np.random.default_rng(12)
    params = PerceptionParams(sensors=(SensorSpec(), SensorSpec(name="s", fov_deg=360.0, range_m=30.0),
                                       SensorSpec(name="rear", fov_deg=90.0, yaw_deg=180.0, mount_x_m=-4.0)))
    n, m = 150, 3000
    heading = np.where(rng.random(n) < 0.1, rng.choice([0.0, -0.0, np.pi, -np.pi], n), rng.uniform(-4, 4, n))
    xy = rng.uniform(0, 300, (n, 2))
    u = unit_heading(heading)
    origins = xy[None] + params.arrays["mount_x_m"][:, None, None] * u[None]
    owner, target = rng.integers(0, n, m), rng.uniform(-50, 350, (m, 2))
    got = _fov_params(origins, heading, u, owner, target, params)
    want = _fov_all(origins, heading, owner, target, params.sensors)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    assert got[0].size > 100


@pytest.mark.parametrize("rates", [(1.0, 1.0), (0.3, 2.0), (0.0, 0.0), (12.0, 12.0)])
def test_clutter_draws_equal_the_broadcast_poisson(rates):
    from couplers.sensing.perception import PerceptionParams, SensorSpec, _clutter_polar

    params = PerceptionParams(sensors=(SensorSpec(clutter_per_scan=rates[0]),
                                       SensorSpec(name="s", fov_deg=360.0, range_m=30.0, clutter_per_scan=rates[1])))
    heading = np.random.default_rng(13).uniform(-4, 4, 130)
    for n in (0, 1, 130):
        got = _clutter_polar(n, heading[:n], params, np.random.default_rng(n))
        rng = np.random.default_rng(n)  # the previous draws: Poisson counts of a broadcast rate array
        counts = rng.poisson(np.broadcast_to(params.arrays["clutter_per_scan"], (n, 2))).ravel()
        owner, sensor = np.repeat(np.arange(n), 2)[np.repeat(np.arange(2 * n), counts)], \
            np.tile([0, 1], n)[np.repeat(np.arange(2 * n), counts)]
        a = params.arrays
        r = a["range_m"][sensor] * np.sqrt(rng.random(owner.size))
        ang = heading[owner] + np.radians(a["yaw_deg"][sensor] + a["fov_deg"][sensor] * (rng.random(owner.size) - 0.5))
        for g, w in zip(got, (owner, sensor, r, ang)):
            np.testing.assert_array_equal(g, w)


def test_shuffled_rows_and_pair_counts_equal_the_concatenate_reference():
    from coloc.core.models import gnss_cov
    from couplers.sensing.perception import _pair_counts, _shuffled_rows

    rng = np.random.default_rng(14)
    for d, c in [(0, 0), (0, 5), (7, 0), (300, 120)]:
        t_owner, c_owner = np.sort(rng.integers(0, 90, d)), np.sort(rng.integers(0, 90, c))
        t_feat, t_sensor, c_sensor = rng.integers(0, 60, d), rng.integers(0, 2, d), rng.integers(0, 2, c)
        t_z, c_z = rng.normal(size=(d, 4)), rng.normal(size=(c, 4))
        t_sig, c_sig, t_sv, c_sv = rng.random(d), rng.random(c), rng.random(d), rng.random(c)
        t_klass = rng.integers(0, 2, d).astype(np.int8)
        owner = np.concatenate([t_owner, c_owner])
        perm = shuffle_within_owner(owner, np.random.default_rng(d))
        z, own, R, feat, sens, klass = _shuffled_rows(perm, t_z, c_z, t_owner, c_owner, t_feat, t_sensor, c_sensor,
                                                      t_sig, c_sig, t_sv, c_sv, t_klass)
        np.testing.assert_array_equal(z, np.concatenate([t_z, c_z])[perm])
        np.testing.assert_array_equal(own, owner[perm])
        np.testing.assert_array_equal(R, gnss_cov(np.concatenate([t_sig, c_sig])[perm],
                                                  np.concatenate([t_sv, c_sv])[perm]))
        np.testing.assert_array_equal(feat, np.concatenate([t_feat, np.full(c, -1, dtype=np.int64)])[perm])
        np.testing.assert_array_equal(sens, np.concatenate([t_sensor, c_sensor])[perm])
        np.testing.assert_array_equal(klass, np.concatenate([t_klass, np.zeros(c, dtype=np.int8)])[perm])
        assert (z.dtype, own.dtype, R.dtype, feat.dtype, sens.dtype, klass.dtype) == \
            (np.float64, np.int64, np.float64, np.int64, np.int64, np.int8)
    for n_pairs, m in [(0, 0), (10, 0), (50, 400)]:
        pair, visible = rng.integers(0, max(n_pairs, 1), m), rng.random(m) < 0.5
        want = (int(np.count_nonzero(np.bincount(pair, minlength=n_pairs))),
                int(np.count_nonzero(np.bincount(pair[visible], minlength=n_pairs))))
        assert _pair_counts(pair, visible, n_pairs) == want


def test_prior_gnss_and_v2f_rows_equal_their_numpy_references():
    from couplers.sensing.sensors import (_gnss_rows, _gnss_rows_reference, _prior_rows, _prior_rows_reference, _v2f_rows,
                                  _v2f_rows_reference)

    rng = np.random.default_rng(15)
    for n, o in [(0, 0), (1, 0), (5, 3), (150, 600)]:
        x = rng.normal(0, 300, (n, 4))
        entered = rng.random(n) < 0.3
        sig = np.array([2.0, 2.0, 0.1, 0.1])
        w = rng.standard_normal((int(entered.sum()), 4))
        for g, r in zip(_prior_rows(entered, x, w, sig), _prior_rows_reference(entered, x, w, sig)):
            np.testing.assert_array_equal(g, r)
        sp, sv, w = rng.choice([3.0, 8.0, 15.0], n), rng.choice([0.1, 0.17, 0.45], n), rng.standard_normal((n, 4))
        for g, r in zip(_gnss_rows(x, w, sp, sv), _gnss_rows_reference(x, w, sp, sv)):
            np.testing.assert_array_equal(g, r)
        feats = rng.normal(0, 300, (40, 4))
        owner, feat = np.sort(rng.integers(0, max(n, 1), o)), rng.integers(0, 40, o)
        perm, w = shuffle_within_owner(owner, rng), rng.standard_normal((o, 4))
        sig = np.array([0.1, 0.1, 0.1, 0.1])
        for g, r in zip(_v2f_rows(perm, owner, feat, feats, x if n else np.empty((1, 4)), w, sig),
                        _v2f_rows_reference(perm, owner, feat, feats, x if n else np.empty((1, 4)), w, sig)):
            assert g.dtype == r.dtype
            np.testing.assert_array_equal(g, r)


def test_building_box_filter_keeps_every_hit_and_drops_most_near_misses():
    from couplers.sensing.occlusion import _clear_of_buildings, _needs_building_test

    blds = load_net_folder(ARTERIAL).buildings
    g, bb = blds.cells, blds.boxes
    rng = np.random.default_rng(16)
    xmin, ymin, xmax, ymax = shapely.total_bounds(blds.polygons)
    start = np.column_stack([rng.uniform(xmin - 30, xmax + 30, 20000), rng.uniform(ymin - 30, ymax + 30, 20000)])
    ang, length = rng.uniform(-np.pi, np.pi, 20000), rng.uniform(0, 90, 20000)
    end = start + length[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    # segments through the boxes' corners and along their edges, and zero-length ones on them
    b = bb.boxes[rng.integers(0, len(bb.boxes), 3000)]
    corner = np.column_stack([np.where(rng.random(3000) < 0.5, b[:, 0], b[:, 2]),
                              np.where(rng.random(3000) < 0.5, b[:, 1], b[:, 3])])
    seg = np.vstack([np.hstack([start, end]), np.hstack([corner + rng.normal(0, 20, corner.shape), corner]),
                     np.hstack([corner, corner]), np.hstack([b[:, [0, 1]], b[:, [2, 1]]]),
                     [[np.nan, 0.0, 1.0, 1.0]]])
    lines = shapely.linestrings(seg[:-1].reshape(-1, 2, 2))
    hit = np.zeros(len(seg), dtype=bool)
    hit[blds.tree.query(lines, predicate="intersects")[0]] = True
    meets_box = np.zeros(len(seg), dtype=bool)
    meets_box[blds.tree.query(lines)[0][shapely.intersects(
        lines[blds.tree.query(lines)[0]], shapely.box(*bb.boxes[blds.tree.query(lines)[1]].T))]] = True
    need = _needs_building_test(seg, g.x0, g.y0, g.cell, g.values, bb.start, bb.ids, bb.boxes, bb.margin)
    near = ~_clear_of_buildings(seg, g.x0, g.y0, g.cell, g.values)
    assert need[-1] and np.all(need[hit]) and np.all(need[meets_box]) and not np.any(need & ~near)
    assert need.sum() < 0.9 * near.sum() and hit.sum() > 1000


def test_continuity_equals_its_numpy_reference():
    from couplers.traffic.sumo import _continuity, _continuity_reference

    rng = np.random.default_rng(17)
    for n, m in [(0, 0), (0, 5), (4, 0), (150, 140)]:
        idx = np.where(rng.random(n) < 0.1, -1, rng.integers(0, max(m, 1), n)) if m else np.full(n, -1)
        back = rng.random(n) < 0.05
        prev_xy, prev_vel = rng.uniform(0, 500, (m, 2)), rng.normal(0, 10, (m, 2))
        xy = rng.uniform(0, 500, (n, 2))
        near = idx >= 0
        xy[near] = prev_xy[idx[near]] + rng.normal(0, 20, (int(near.sum()), 2))  # steps around the 30 m jump
        vel = rng.normal(0, 10, (n, 2))
        for g, w in zip(_continuity(idx, back, xy, prev_xy, vel, prev_vel, 0.75, 30.0),
                        _continuity_reference(idx, back, xy, prev_xy, vel, prev_vel, 0.75, 30.0)):
            assert g.dtype == w.dtype
            np.testing.assert_array_equal(g, w)


def test_occlusion_side_shortcut_gives_the_exact_answers():
    """Footprints (rectangles) and other quads against sight lines in general position and through corners,
    along edges, starting on edges or inside, touching at one point, of zero length: every answer of the
    x buckets and the side shortcut as the plain exact loop's, with one skip or two."""
    from couplers.sensing.occlusion import (OccluderIndex, _occluded_by_quads, _occluded_by_quads_bucketed,
                                    _occluder_buckets, occluded_by_vehicles, unit_heading, vehicle_footprints)

    rng = np.random.default_rng(18)
    for offset in (0.0, 4.0e4):  # coordinates of a small net, and of a large one (more rounding)
        xy = rng.uniform(0, 300, (200, 2)) + offset
        heading = np.where(rng.random(200) < 0.2, rng.choice([0.0, np.pi / 2, -np.pi, np.pi / 4], 200),
                           rng.uniform(-4, 4, 200))
        corners = vehicle_footprints(xy, heading, rng.uniform(3, 15, 200), rng.uniform(1.5, 2.6, 200))
        odd = corners[:20].copy()
        odd[:, 2] += rng.normal(0, 0.5, (20, 2))  # not rectangles: the exact test only
        odd[:5] = odd[:5, ::-1]  # clockwise
        quads = np.vstack([corners, odd])
        idx = OccluderIndex.build(quads)
        assert idx.rectangle[:200].all() and not idx.rectangle[200:].any()
        c = quads[rng.integers(0, len(quads), 4000)]
        k = rng.integers(0, 4, 4000)
        pick = c[np.arange(4000), k]
        nxt = c[np.arange(4000), (k + 1) % 4]
        t = rng.random((4000, 1))
        on_edge = pick + t * (nxt - pick)
        far = pick + rng.normal(0, 30, pick.shape)
        seg = np.vstack([
            np.hstack([rng.uniform(0, 300, (20000, 2)) + offset, rng.uniform(0, 300, (20000, 2)) + offset]),
            np.hstack([far, pick]), np.hstack([pick, far]),  # ending or starting on a corner
            np.hstack([pick + 3 * (nxt - pick), pick - 2 * (nxt - pick)]),  # along an edge's line
            np.hstack([on_edge, far]), np.hstack([far, on_edge]),  # from / to a point of an edge
            np.hstack([on_edge, on_edge]), np.hstack([pick, pick]),  # zero length on the boundary
            np.hstack([far, far + 1e-9]),
            np.hstack([pick + 1e-7 * (far - pick), far]), np.hstack([far, pick - 1e-7 * (far - pick)]),
        ])
        skip_a = rng.integers(-1, len(quads), len(seg))
        no_b = np.full(len(seg), -1, dtype=np.int64)
        skip_b = rng.integers(-1, len(quads), len(seg))
        for b_skip in (no_b, skip_b):
            want = _occluded_by_quads(seg, skip_a, b_skip, quads)
            # every bucket width, including one that the cap on the number of buckets widens (1e-3 m)
            for width in (1e-3, 0.7, 8.0, 50.0, 1e4):
                b = _occluder_buckets(idx.corners, width)
                np.testing.assert_array_equal(
                    _occluded_by_quads_bucketed(seg, skip_a, b_skip, idx.corners, *b, idx.rectangle), want)
            np.testing.assert_array_equal(occluded_by_vehicles(seg[:, :2], seg[:, 2:], idx, skip_a, b_skip), want)
            assert 0.05 < want.mean() < 0.95
        # quads far apart (huge spans)
        far_quads = quads.copy()
        far_quads[:3] += np.array([1e7, -1e7])
        b = _occluder_buckets(far_quads, 8.0)
        assert b[1].size <= 4 * len(far_quads) + 17
        np.testing.assert_array_equal(
            _occluded_by_quads_bucketed(seg, skip_a, skip_b, far_quads, *b, OccluderIndex.build(far_quads).rectangle),
            _occluded_by_quads(seg, skip_a, skip_b, far_quads))


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_perceive_stages_equal_the_separate_kernels(seed):
    """The fused stages of perceive against perceive_reference (the separate kernels): every array and
    count, and each random stream left in the same state; with and without occluders, buildings, classes,
    the heading vectors, one clutter rate or several, sensors off the heading and behind the bumper."""
    from couplers.sensing.occlusion import unit_heading, vehicle_footprints
    from couplers.sensing.perception import PerceptionNoise, PerceptionParams, SensorSpec, perceive, perceive_reference
    from couplers.sensing.sensors import features_in_range
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    blds = load_net_folder(ARTERIAL).buildings
    xmin, ymin, xmax, ymax = shapely.total_bounds(blds.polygons)
    n, k = (0, 30) if seed == 4 else (120, 80)
    xy = np.column_stack([rng.uniform(xmin, xmax, n), rng.uniform(ymin, ymax, n)])
    heading = rng.uniform(-np.pi, np.pi, n)
    x_true = np.hstack([xy, rng.normal(0, 8, (n, 2))])
    feats = np.hstack([np.column_stack([rng.uniform(xmin, xmax, k), rng.uniform(ymin, ymax, k)]), np.zeros((k, 2))])
    corners = vehicle_footprints(xy, heading, rng.uniform(4, 12, n), rng.uniform(1.6, 2.5, n))
    sensors = (SensorSpec(), SensorSpec(name="s", fov_deg=360.0, range_m=30.0),
               SensorSpec(name="rear", fov_deg=90.0, range_m=40.0, yaw_deg=135.0, mount_x_m=-3.0,
                          clutter_per_scan=1.0 if seed % 2 else 2.5))
    for params in (PerceptionParams(sensors=sensors), PerceptionParams(sensors=sensors[:2], occlusion_buildings=False),
                   PerceptionParams(sensors=sensors[:2], occlusion_vehicles=False)):
        owner, feat = features_in_range(xy, cKDTree(feats[:, :2]) if k else None, params.max_reach_m)
        klass = (rng.random(k) < 0.3).astype(np.int8) if seed % 2 else None
        kw = dict(x_true=x_true, heading=heading, features_true=feats, pair_owner=owner, pair_feature=feat,
                  params=params, occluder_corners=corners, observer_occluder=np.arange(n), buildings=blds,
                  feature_class=klass)
        for direction in (None, unit_heading(heading)):
            na, nb = PerceptionNoise(seed), PerceptionNoise(seed)
            got = perceive(noise=na, direction=direction, **kw)
            want = perceive_reference(noise=nb, **kw)
            for name in ("z", "owner", "R", "feature", "sensor", "klass"):
                g, w = getattr(got, name), getattr(want, name)
                assert g.dtype == w.dtype and g.shape == w.shape, name
                np.testing.assert_array_equal(g, w, err_msg=name)
            assert got.stats == want.stats
            for stream in PerceptionNoise.STREAMS:
                assert getattr(na, stream).random() == getattr(nb, stream).random()
        if n and params.occlusion_vehicles and params.occlusion_buildings:
            assert want.stats["occluded"] > 0 and want.stats["detected"] > 0 and want.stats["clutter"] > 0


def test_fov_select_at_the_range_equals_the_square_root_test():
    """Targets at the range to the last bits (where the squared-distance shortcut must not decide): the
    candidates of _fov_select are those of the distance test d = sqrt(dx^2 + dy^2) <= range."""
    from couplers.sensing.perception import _fov_select

    rng = np.random.default_rng(20)
    n, m = 50, 20000
    origin = rng.uniform(-1e4, 1e4, (2, n, 2))
    bore = np.stack([np.cos(rng.uniform(-4, 4, (2, n))), np.sin(rng.uniform(-4, 4, (2, n)))], axis=-1)
    owner = rng.integers(0, n, m)
    range_m = np.array([80.0, 30.0])
    ang = rng.uniform(-np.pi, np.pi, m)
    r = range_m[rng.integers(0, 2, m)] * (1.0 + rng.integers(-40, 40, m) * 2.0 ** -52)
    s0 = rng.integers(0, 2, m)
    target = origin[s0, owner] + r[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    rows, dist, sensor = _fov_select(origin, bore, owner, target, range_m, np.array([0.5, -1.0]),
                                     np.array([False, True]))
    want = []
    for s in range(2):
        d = np.sqrt(((target - origin[s, owner]) ** 2).sum(axis=1))
        dot = ((target - origin[s, owner]) * bore[s, owner]).sum(axis=1)
        ok = (d <= range_m[s]) & ((s == 1) | (dot >= d * 0.5))
        want.append(np.flatnonzero(ok))
    np.testing.assert_array_equal(rows, np.concatenate(want))
    np.testing.assert_array_equal(sensor, np.repeat([0, 1], [len(w) for w in want]))
    assert 0.2 < np.mean(np.sqrt(((target - origin[s0, owner]) ** 2).sum(axis=1)) <= range_m[s0]) < 0.8
