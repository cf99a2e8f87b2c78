"""The numba passes of the realistic frames against their numpy references, bit for bit on seeded scenes:
the noise-free relative states of the sensor-frame rows and the merge of the perception's rows with the other
road users' (couplers.sensing.sensor_frame, couplers.sensing.road_users)."""

from dataclasses import replace

import numpy as np
import pytest

from couplers.sensing.perception import Detections
from couplers.sensing.road_users import KIND_PEDESTRIAN, KIND_VEHICLE, RoadUserNoise, merged_rows, merged_rows_reference
from couplers.sensing.sensor_frame import relative_states, relative_states_reference, sensor_frame_rows


def _det(rng, o, n, k, with_kind=True):
    feature = np.where(rng.random(o) < 0.5, rng.integers(0, k, o), -1)
    kind = rng.integers(0, 5, o).astype(np.int8) if with_kind else None
    return Detections(z=rng.normal(0, 30, (o, 4)), owner=np.sort(rng.integers(0, n, o)),
                      R=rng.normal(0, 1, (o, 4, 4)), feature=feature, sensor=rng.integers(0, 3, o),
                      klass=rng.integers(0, 3, o).astype(np.int8), kind=kind)


@pytest.mark.parametrize("with_kind", [True, False])
def test_relative_states_equal_the_numpy_reference(with_kind):
    rng = np.random.default_rng(21)
    for o in (0, 1, 57, 400):
        n, k = 12, 30
        det = _det(rng, o, n, k, with_kind)
        x_true, feats = rng.normal(0, 100, (n, 4)), rng.normal(0, 100, (k, 4))
        new, ref = relative_states(det, x_true, feats), relative_states_reference(det, x_true, feats)
        assert new.shape == ref.shape == (o, 4)
        assert new.tobytes() == ref.tobytes()
    if with_kind:  # the moving road users keep their row's velocity, the rest the vehicle's negated one
        moving = (det.feature < 0) & np.isin(det.kind, (KIND_VEHICLE, KIND_PEDESTRIAN))
        assert moving.any() and np.array_equal(new[moving, 2:], det.z[moving, 2:])


def test_range_bearing_rows_with_cos_sin_per_vehicle_equal_per_row():
    """cos / sin of each vehicle's heading gathered to its rows (couplers.sensing.sensor_frame.SensorFrameRows)
    give the rows of cos / sin taken per row, bit for bit, with and without the lever arm's yaw rate."""
    rng = np.random.default_rng(13)
    n, o = 37, 900
    heading = rng.uniform(-4, 4, n)
    heading[:3] = (0.0, np.pi, -np.pi / 2)
    owner = np.sort(rng.integers(0, n, o))
    args = (rng.normal(0, 40, (o, 4)), heading[owner], rng.choice([0.0, 2.25, -1.0], o),
            rng.choice([0.0, np.pi / 2, np.pi], o), rng.standard_normal((o, 3)), rng.uniform(0.1, 0.4, o),
            rng.uniform(0.001, 0.02, o), rng.uniform(0.01, 0.1, o))
    for yaw_rate in (None, rng.normal(0, 0.3, o)):
        per_row = sensor_frame_rows(*args, yaw_rate)
        gathered = sensor_frame_rows(*args, yaw_rate, cos_sin=(np.cos(heading)[owner], np.sin(heading)[owner]))
        for a, b in zip(per_row, gathered):
            assert a.tobytes() == b.tobytes()


@pytest.mark.parametrize("class_error", [0.0, 0.2])
def test_merged_rows_equal_the_numpy_reference(class_error):
    """Same rows, order, covariances, dtypes and random streams as the numpy merge, with none, one and two extra
    blocks of rows."""
    rng = np.random.default_rng(5)
    for o, sizes in ((0, []), (40, []), (40, [25]), (0, [7]), (60, [10, 15])):
        n = 9
        det = _det(rng, o, n, 30)
        extra = [(rng.integers(0, n, m), rng.normal(0, 20, (m, 4)), rng.uniform(0.1, 2, m), rng.uniform(0.1, 1, m),
                  rng.integers(0, 3, m), rng.integers(0, 3, m).astype(np.int8), rng.integers(1, 5, m).astype(np.int8))
                 for m in sizes]
        new = merged_rows(det, extra, RoadUserNoise(3), class_error)
        ref = merged_rows_reference(det, extra, RoadUserNoise(3), class_error)
        # the kinds handed over instead of carried (the SUMO coupler's call)
        handed = merged_rows(replace(det, kind=None), extra, RoadUserNoise(3), class_error, kind=det.kind)
        for name in ("z", "owner", "R", "feature", "sensor", "klass", "kind"):
            a, b, c = getattr(new, name), getattr(ref, name), getattr(handed, name)
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), name
            assert c.dtype == b.dtype and c.tobytes() == b.tobytes(), name
        if sizes:
            assert (new.feature == -1).sum() >= sum(sizes)


def test_satellite_receiver_kernels_equal_the_numpy_expressions():
    """The receivers' multipath update and pseudorange sum (couplers.sensing.gnss_satellites) against the numpy
    expressions they replace, bit for bit."""
    from couplers.sensing.gnss_satellites import _carried_multipath, _pseudorange_sum

    rng = np.random.default_rng(8)
    n, s = 40, 48
    z, u_prev, white = rng.standard_normal((n, s)), rng.standard_normal((n + 5, s)), rng.standard_normal((n, s))
    carried = rng.random(n) < 0.7
    prev = rng.permutation(n + 5)[:n][carried]
    a = np.exp(-rng.uniform(0, 30, carried.sum()) / 5.0)
    ref = z.copy()
    ref[carried] = a[:, None] * u_prev[prev] + np.sqrt(1.0 - a[:, None] * a[:, None]) * z[carried]
    u = _carried_multipath(np.flatnonzero(carried), prev, a, u_prev, z)
    assert u.tobytes() == ref.tobytes()
    common, sig_n, mp = rng.normal(0, 3, s), rng.uniform(0.2, 2, s), rng.uniform(0.3, 6, s)
    ref_eps = common[None, :] + sig_n[None, :] * white + mp[None, :] * u
    assert _pseudorange_sum(common, sig_n, white, mp, u).tobytes() == ref_eps.tobytes()


def test_building_sight_lines_in_numba_equal_shapely():
    """The numba segment / footprint test (couplers.sensing.occlusion._building_hits) gives shapely's
    ``intersects`` on every segment: random segments over random rectangles, L shapes with holes and
    multi-polygons, with segments ending inside footprints, on their corners and along their edges (segments
    that are not finite go to shapely as before)."""
    import shapely
    from shapely import affinity

    from couplers.net.buildings import Buildings
    from couplers.sensing.occlusion import _segments_occluded_by_buildings, _segments_occluded_by_buildings_shapely

    rng = np.random.default_rng(3)
    polys = []
    for _ in range(40):
        x, y = rng.uniform(0, 300, 2)
        w, h = rng.uniform(3, 30, 2)
        kind = rng.integers(3)
        if kind == 0:
            p = shapely.box(x, y, x + w, y + h)
        elif kind == 1:  # an L shape with a courtyard
            p = shapely.difference(shapely.union(shapely.box(x, y, x + w, y + h / 3), shapely.box(x, y, x + w / 3, y + h)),
                                   shapely.box(x + 0.3, y + 0.3, x + w / 6, y + h / 6))
        else:  # two parts
            p = shapely.MultiPolygon([shapely.box(x, y, x + w / 3, y + h), shapely.box(x + 2 * w / 3, y, x + w, y + h)])
        polys.append(affinity.rotate(p, float(rng.uniform(0, 90)), origin="centroid"))
    b = Buildings.from_polygons(polys, np.full(len(polys), 10.0))
    corners = np.vstack([shapely.get_coordinates(p) for p in polys])
    a = rng.uniform(-20, 320, (3000, 2))
    e = np.vstack([rng.uniform(-20, 320, (1500, 2)), a[1500:2500] + rng.normal(0, 5, (1000, 2)),
                   corners[rng.integers(len(corners), size=500)]])
    seg = np.hstack([a, e])
    seg[:200, 2:] = seg[:200, :2] + [25.0, 0.0]  # axis-parallel, like the rectangles' edges before rotation
    got, ref = _segments_occluded_by_buildings(seg, b), _segments_occluded_by_buildings_shapely(seg, b)
    assert got.dtype == bool and (got == ref).all()
    assert 0.2 < got.mean() < 0.9  # both kinds of segment are tested


@pytest.mark.parametrize("kernel_draws", [True, False])
@pytest.mark.parametrize("lever_arm", [False, True])
def test_range_bearing_kernels_equal_sensor_frame_rows(lever_arm, kernel_draws, monkeypatch):
    """SensorFrameRows.detections (two kernels around numpy's hypot and arctan2, the noise drawn in the second
    where numba's draws are numpy's, else by numpy) gives sensor_frame_rows of relative_states, with the per-row
    gathers of the numpy path, bit for bit, the stream's state after included: rows on the mount point (range 0),
    bearings at +-pi, with and without kinds and the lever arm's yaw rate."""
    from couplers.sensing import streams
    from couplers.sensing.perception import PerceptionParams, SensorSpec
    from couplers.sensing.sensor_frame import SensorFrameRows

    if not kernel_draws:
        monkeypatch.setattr(streams, "available", lambda: False)
    elif not streams.available():
        pytest.skip("numba's draws are not numpy's on this installation")

    sensors = (SensorSpec(name="front", mount_x_m=2.25, sigma_b_deg=0.5), SensorSpec(name="rear", yaw_deg=180.0,
               mount_x_m=-1.0, sigma_r_m=0.3), SensorSpec(name="surround", fov_deg=360.0, range_m=30.0))
    params = PerceptionParams(sensors=sensors, detections="range_bearing", lever_arm_range_rate=lever_arm)
    rng = np.random.default_rng(17)
    n_s = len(params.sensors)
    for o, with_kind in ((0, True), (1, False), (300, True), (900, False)):
        n, k = 25, 40
        det = replace(_det(rng, o, n, k, with_kind), sensor=rng.integers(0, n_s, o))
        x_true, feats = rng.normal(0, 60, (n, 4)), rng.normal(0, 60, (k, 4))
        heading = rng.uniform(-4, 4, n)
        heading[:4] = (0.0, np.pi, -np.pi, np.pi / 2)
        if o >= 300:  # a target on the mount point, and targets straight behind (bearing wraps at +-pi)
            det.feature[:3] = -1
            det.z[0, :2] = [params.sensors[det.sensor[0]].mount_x_m * np.cos(heading[det.owner[0]]),
                            params.sensors[det.sensor[0]].mount_x_m * np.sin(heading[det.owner[0]])]
            det.z[1:3, :2] = -5.0 * np.stack([np.cos(heading[det.owner[1:3]]), np.sin(heading[det.owner[1:3]])], 1)
        yaw_rate = rng.normal(0, 0.3, n) if lever_arm else None
        rows = SensorFrameRows(params, 4)
        got = rows.detections(det, x_true, heading, feats, yaw_rate)
        ref_rng = SensorFrameRows(params, 4).rng
        w = ref_rng.standard_normal((o, 3))
        s = det.sensor
        mount = np.array([x.mount_x_m for x in params.sensors])[s]
        yaw = np.deg2rad([x.yaw_deg for x in params.sensors])[s]
        sr = np.array([x.sigma_r_m for x in params.sensors])[s]
        sb = np.deg2rad([x.sigma_b_deg for x in params.sensors])[s]
        srd = np.array([x.sigma_rdot_mps for x in params.sensors])[s]
        ref = sensor_frame_rows(relative_states_reference(det, x_true, feats), heading[det.owner], mount, yaw, w, sr,
                                sb, srd, None if yaw_rate is None else yaw_rate[det.owner])
        for a, b in zip((got.range, got.bearing, got.range_rate), ref):
            assert a.dtype == b.dtype and a.shape == b.shape == (o,) and a.tobytes() == b.tobytes()
        for a, b in zip((got.mount_x, got.yaw, got.sigma_range, got.sigma_bearing, got.sigma_range_rate),
                        (mount, yaw, sr, sb, srd)):
            assert a.tobytes() == b.tobytes()
        assert rows.rng.bit_generator.state == ref_rng.bit_generator.state


def test_receiver_rows_equal_the_numpy_assignments():
    """The receiver's fix, reported covariance and range-rate solution written into model (3)'s rows
    (couplers.sensing.sensors._receiver_rows) as the numpy assignments, bit for bit, with each part off."""
    from couplers.sensing.sensors import _NO_COV, _NO_VELOCITY, _receiver_rows, _receiver_rows_reference

    rng = np.random.default_rng(23)
    for n in (0, 1, 60):
        x = rng.normal(0, 500, (n, 4))
        err, cov = rng.normal(0, 5, (n, 2)), rng.normal(0, 3, (n, 2, 2))
        verr, vcov, solved = rng.normal(0, 0.1, (n, 2)), rng.normal(0, 0.01, (n, 2, 2)), rng.random(n) < 0.8
        for has_cov, doppler in ((False, False), (True, False), (True, True)):
            z0, R0 = rng.normal(0, 500, (n, 4)), rng.normal(0, 1, (n, 4, 4))
            z1, R1, z2, R2 = z0.copy(), R0.copy(), z0.copy(), R0.copy()
            _receiver_rows(z1, R1, x, err, cov if has_cov else _NO_COV, has_cov,
                           *((verr, vcov, solved) if doppler else _NO_VELOCITY), doppler)
            _receiver_rows_reference(z2, R2, x, err, cov if has_cov else None, verr if doppler else None, vcov, solved)
            assert z1.tobytes() == z2.tobytes() and R1.tobytes() == R2.tobytes()


def test_carried_receiver_rows_equal_the_numpy_mask_and_gathers():
    """The receivers carried from the previous step (couplers.sensing.gnss_satellites._carried_rows): rows,
    previous rows, moves and last fixes as numpy's mask, flatnonzero and gathers, bit for bit, on strided
    positions (the coupler's x_true[:, :2])."""
    from couplers.sensing.gnss_satellites import _carried_rows

    rng = np.random.default_rng(29)
    for n, n_prev in ((0, 0), (5, 0), (40, 35), (80, 90)):
        x = rng.normal(0, 300, (n, 4))
        xy, xy_prev = x[:, :2], rng.normal(0, 300, (n_prev, 4))[:, :2]
        fix = rng.normal(0, 300, (n_prev, 2))
        fix[::7] = np.nan
        idx = np.where(rng.random(n) < 0.8, rng.integers(0, max(n_prev, 1), n), -1) if n_prev else np.full(n, -1)
        entered = rng.random(n) < 0.1
        rows, prev, moved, fix_prev = _carried_rows(idx, entered, xy, xy_prev, fix)
        carried = (idx >= 0) & ~entered
        ref_rows = np.flatnonzero(carried)
        ref_fix = np.full((n, 2), np.nan)
        ref_fix[ref_rows] = fix[idx[ref_rows]]
        assert rows.tobytes() == ref_rows.tobytes() and prev.tobytes() == idx[ref_rows].tobytes()
        assert moved.tobytes() == (xy[ref_rows] - xy_prev[idx[ref_rows]]).tobytes()
        assert fix_prev.tobytes() == ref_fix.tobytes()


def test_road_user_kernels_equal_the_numpy_expressions():
    """The road-user part's glue in numba (couplers.sensing.road_users): the perception rows' kinds, the vehicles'
    body centres and velocities, the pairs without the observer itself, bit for bit as the numpy expressions."""
    from couplers.sensing.road_users import body_centre_states, other_pairs, row_kinds, row_kinds_reference

    rng = np.random.default_rng(31)
    for n in (0, 1, 50):
        feature = np.where(rng.random(n * 3) < 0.6, rng.integers(0, 20, n * 3), -1)
        for klass in (None, rng.integers(0, 3, 20).astype(np.int8)):
            got, ref = row_kinds(feature, klass), row_kinds_reference(feature, klass)
            assert got.dtype == ref.dtype and got.shape == ref.shape and got.tobytes() == ref.tobytes()
        front, dims = rng.normal(0, 300, (n, 4))[:, 1:3], rng.uniform(3, 12, (n, 2))
        heading = rng.uniform(-4, 4, n)
        direction, velocity = np.stack([np.cos(heading), np.sin(heading)], 1), rng.normal(0, 10, (n, 2))
        ref = np.hstack([front - 0.5 * dims[:, :1] * direction, velocity])
        assert body_centre_states(front, dims, direction, velocity).tobytes() == ref.tobytes()
        owner, tgt = np.sort(rng.integers(0, 9, 4 * n)), rng.integers(0, 9, 4 * n)
        keep = tgt != owner
        o, t = other_pairs(owner, tgt)
        assert o.tobytes() == owner[keep].tobytes() and t.tobytes() == tgt[keep].tobytes()


def test_target_columns_equal_the_numpy_columns():
    """The road-user targets' P_D, footprint row, class and kind columns (couplers.sensing.road_users.target_columns)
    equal the numpy construction, dtypes included, for every order and size of the parts."""
    from couplers.sensing.road_users import target_columns, target_columns_reference

    for key in ((("vehicle", 0),), (("vehicle", 12), ("persistent", 5)), (("vehicle", 3), ("person", 4),
                                                                         ("persistent", 2)), (("persistent", 7),)):
        key = tuple((size, what) for what, size in key)
        got, ref = target_columns(key, 0.85), target_columns_reference(key, 0.85)
        for a, b in zip(got, ref):
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
