"""The "satellites" GNSS model (couplers.sensing.gnss_sky, couplers.sensing.gnss_satellites): the constellation's
geometry, the line of sight past extruded footprints against an exact check with shapely, the receiver's WLS fix
against the covariance it reports, no NLOS without buildings, same seed same bytes."""

import math

import numpy as np
import pytest
import shapely
from scipy.stats import chi2

from couplers.errors import InputError
from couplers.net.buildings import Buildings
from couplers.sensing.gnss_error import GnssErrorParams, gnss_error_process
from couplers.sensing.gnss_satellites import SatelliteErrorProcess, check_building_heights, open_sky_common_share
from couplers.sensing.gnss_sky import GALILEO, GPS, BuildingEdges, Sky, clearance_radius, line_of_sight, reflections

SAT = dict(model="satellites")


def _ids(n):
    return np.array([f"v{i}" for i in range(n)], dtype=object)


def test_periods_are_the_real_ones_and_orbits_close_after_one_period():
    assert abs(GPS.period_s - (11 * 3600 + 58 * 60)) < 60  # 11 h 58 min
    assert abs(GALILEO.period_s - (14 * 3600 + 5 * 60)) < 60  # 14 h 05 min
    sky = Sky.build()
    # in the inertial frame (Earth rotation taken back out) a satellite is where it was one period earlier
    for c, sel in ((GPS, sky.system == 0), (GALILEO, sky.system == 1)):
        t = c.period_s
        rot = 7.2921151467e-5 * t
        r = np.array([[math.cos(rot), -math.sin(rot), 0], [math.sin(rot), math.cos(rot), 0], [0, 0, 1]])
        np.testing.assert_allclose(sky.ecef(t)[sel] @ r.T, sky.ecef(0.0)[sel], atol=1e-3)
        assert np.allclose(np.linalg.norm(sky.ecef(123.0)[sel], axis=1), c.a_m)


@pytest.mark.parametrize("lat", [45.07, 0.0, 60.0])
def test_satellites_above_ten_degrees_number_eight_to_twenty(lat):
    """Typically 8-20 GPS + Galileo satellites above a 10 deg mask: the 5th to 95th percentile over a day."""
    sky = Sky.build(lat, 7.69)
    counts = np.array([(sky.look(t)[2] > math.radians(10)).sum() for t in np.arange(0.0, 86400.0, 600.0)])
    assert 8 <= np.percentile(counts, 5) and np.percentile(counts, 95) <= 20
    assert counts.min() >= 6
    assert 10 <= counts.mean() <= 18


def _random_scene(rng, k=25):
    polys, heights = [], []
    for _ in range(k):
        cx, cy = rng.uniform(-80, 80, 2)
        if rng.random() < 0.7:  # rotated rectangle
            w, h, a = rng.uniform(4, 30), rng.uniform(4, 30), rng.uniform(0, np.pi)
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


def _brute_force(b: Buildings, p, az, el, h_ant):
    """Exact 3-D check on the extruded footprints: the ray's horizontal trace clipped by each footprint (GEOS);
    the 3-D ray (rising with distance) enters the prism iff it is below the roof at the trace's first point inside."""
    out = np.zeros(az.size, dtype=bool)
    for k in range(az.size):
        far = 500.0
        end = (p[0] + far * math.sin(az[k]), p[1] + far * math.cos(az[k]))
        ray = shapely.LineString([tuple(p), end])
        for poly, h in zip(b.polygons, b.heights):
            inter = poly.intersection(ray)
            if inter.is_empty:
                continue
            pts = shapely.get_coordinates(inter)
            d = np.min(np.hypot(pts[:, 0] - p[0], pts[:, 1] - p[1]))
            if d * math.tan(el[k]) + h_ant < h:
                out[k] = True
                break
    return out


def test_line_of_sight_equals_an_exact_3d_check_on_random_scenes():
    rng = np.random.default_rng(7)
    checked = blocked_total = 0
    for _ in range(6):
        b = _random_scene(rng)
        edges = BuildingEdges.build(b)
        xy = rng.uniform(-90, 90, (25, 2))  # some antennas stand inside footprints
        az = rng.uniform(-np.pi, np.pi, 30)
        el = np.radians(rng.uniform(5, 85, 30))
        h_ant = 1.5
        blocked, dist = line_of_sight(edges, xy, az, el, h_ant, radius=1000.0)
        for i in range(len(xy)):
            ref = _brute_force(b, xy[i], az, el, h_ant)
            np.testing.assert_array_equal(blocked[i], ref)
            checked += ref.size
            blocked_total += ref.sum()
        assert np.all(np.isfinite(dist[blocked])) and np.all(np.isinf(dist[~blocked]))
    assert 0.1 * checked < blocked_total < 0.9 * checked  # both outcomes are exercised


def test_the_line_of_sight_speed_ups_give_exactly_the_full_edge_test():
    """The line-of-sight kernel's speed-ups (ray-box skip, satellites by rising elevation up to the first cleared
    one, a finer grid) change nothing: blocked sets and distances equal bit for bit those of testing every
    satellite against every edge, on random scenes with axis-parallel rays (azimuths 0, 90, 180, -90 deg) and
    repeated elevations among them."""
    rng = np.random.default_rng(11)
    for _ in range(6):
        edges = BuildingEdges.build(_random_scene(rng, 40))
        xy = rng.uniform(-90, 90, (40, 2))
        az = np.concatenate([rng.uniform(-np.pi, np.pi, 36), [0.0, np.pi / 2, np.pi, -np.pi / 2]])
        el = np.radians(rng.uniform(5, 85, az.size))
        el[:4] = el[4]  # ties in the elevation order
        fast = line_of_sight(edges, xy, az, el, 1.5, 500.0)
        full = line_of_sight(edges, xy, az, el, 1.5, 500.0, box_test=False)
        assert fast[0].any()
        np.testing.assert_array_equal(fast[0], full[0])
        np.testing.assert_array_equal(fast[1], full[1])


def test_the_clearance_radius_loses_no_blocked_ray():
    rng = np.random.default_rng(3)
    b = _random_scene(rng, 40)
    edges = BuildingEdges.build(b)
    xy = rng.uniform(-90, 90, (30, 2))
    az = rng.uniform(-np.pi, np.pi, 40)
    el = np.radians(rng.uniform(10, 85, 40))
    from couplers.sensing.gnss_sky import clearance_radius

    r = clearance_radius(edges.heights, 1.5, 10.0)
    np.testing.assert_array_equal(line_of_sight(edges, xy, az, el, 1.5, r)[0],
                                  line_of_sight(edges, xy, az, el, 1.5, 1e4)[0])


def _run(proc, n, steps, rng, speed=8.0, dt=0.75):
    xy = rng.uniform(0, 1500, (n, 2))
    errs, covs = [], []
    for k in range(steps):
        xy = xy + rng.normal(0, speed * dt, (n, 2))
        e = proc.step(k * dt, _ids(n), np.full(n, k == 0), None, None, None, xy)
        errs.append(e)
        covs.append(proc.reported_cov.copy())
    return np.array(errs), np.array(covs)


def test_fix_error_is_consistent_with_the_reported_covariance_in_the_open():
    """World errors exactly the receiver's budget (white code noise of the same elevation model, no common part,
    no multipath, open sky): NEES of the 2-D fix is chi-square with 2 degrees of freedom. 20 receivers x 1500
    epochs; the mean NEES of 30000 fixes within the two-sided 0.1 % band of chi2(60000) / 30000, and the share
    above the 95 % point within 3.3 sigma of 5 %. RAIM on at 1e-3 (its rare exclusions hardly move the mean)."""
    p = GnssErrorParams(model="satellites", sv_clock_orbit_m=0.0, iono_vertical_m=0.0, tropo_zenith_m=0.0,
                        multipath_m=0.0, code_noise_a_m=0.8, code_noise_b_m=0.6, rx_ure_m=0.0, rx_iono_m=0.0,
                        rx_tropo_m=0.0, rx_code_a_m=0.8, rx_code_b_m=0.6)
    proc = SatelliteErrorProcess(p, 11, 0.75)
    e, c = _run(proc, 20, 1500, np.random.default_rng(5))
    nees = np.einsum("kni,knij,knj->kn", e, np.linalg.inv(c), e).ravel()
    n = nees.size
    lo, hi = chi2.ppf([0.0005, 0.9995], 2 * n) / n
    assert lo < nees.mean() < hi, nees.mean()
    share = (nees > chi2.ppf(0.95, 2)).mean()
    assert abs(share - 0.05) < 3.3 * math.sqrt(0.05 * 0.95 / n)
    assert (c[:, :, 0, 1] != 0).any()  # the receiver reports the east-north correlation of its geometry


def test_open_sky_defaults_give_metre_level_errors_shared_between_receivers():
    proc = SatelliteErrorProcess(GnssErrorParams(**SAT), 2, 0.75)
    e, c = _run(proc, 10, 800, np.random.default_rng(1))
    rms = math.sqrt((e ** 2).sum(-1).mean())
    assert 0.7 < rms < 3.0  # open-sky single-frequency horizontal error (docs/validation/realistic_sensing.md)
    assert proc.last["fix"].all() and (proc.last["nlos"] == 0).all()


def test_common_mode_errors_alone_are_the_same_for_every_receiver_in_the_open():
    """Without receiver noise and multipath, every receiver of the net sees the same satellites with the same
    errors (clock/orbit, ionosphere, troposphere): identical fixes' errors, metre-level and changing slowly."""
    proc = SatelliteErrorProcess(GnssErrorParams(**SAT, code_noise_a_m=0.0, code_noise_b_m=0.0, multipath_m=0.0),
                                 2, 0.75)
    e, _ = _run(proc, 10, 100, np.random.default_rng(1))
    np.testing.assert_allclose(e, np.broadcast_to(e[:, :1], e.shape), atol=1e-9)
    assert 0.1 < np.abs(e).max() < 10.0
    assert np.abs(np.diff(e[:, 0], axis=0)).max() < 0.2  # Gauss-Markov over sv_tau_s = 1800 s


def test_no_buildings_no_nlos_and_low_buildings_none_either():
    low = Buildings.from_polygons([shapely.box(x, 10, x + 20, 30) for x in range(0, 400, 40)], [1.0] * 10)
    for b in (None, Buildings.from_polygons([], []), low):
        proc = SatelliteErrorProcess(GnssErrorParams(**SAT, nlos="block"), 4, 0.75, b)
        rng = np.random.default_rng(0)
        xy = np.c_[rng.uniform(0, 400, 30), np.zeros(30)]
        for k in range(20):
            proc.step(k * 0.75, _ids(30), np.full(30, k == 0), None, None, None, xy)
            assert (proc.last["nlos"] == 0).all()
            assert (proc.last["used"] == proc.last["above"] - proc.last["excluded"]).all()


def test_a_street_canyon_blocks_satellites_and_delay_biases_the_fix():
    """A 20 m wide east-west canyon of 25 m high blocks, receivers on its axis. "block": the satellites across the
    street are lost, the fix is poor across the street (north) and the receiver says so; "delay": they come in
    late, the receiver excludes some and is overconfident about the rest (NLOS is not in its budget)."""
    blocks = [shapely.box(x, s * 10, x + 45, s * 10 + 30 * s) for x in range(-300, 300, 50) for s in (1, -1)]
    b = Buildings.from_polygons([shapely.box(*g.bounds) for g in blocks], [25.0] * len(blocks))
    xy = np.c_[np.linspace(-250, 100, 40), np.zeros(40)]
    out = {}
    for mode in ("block", "delay"):
        proc = SatelliteErrorProcess(GnssErrorParams(**SAT, nlos=mode), 9, 0.75, b)
        errs, covs, excl = [], [], 0
        for k in range(200):
            errs.append(proc.step(k * 0.75, _ids(40), np.full(40, k == 0), None, None, None, xy + [k * 0.5, 0]))
            covs.append(proc.reported_cov.copy())
            assert (proc.last["nlos"] > 0).all() and proc.last["fix"].all()
            excl += proc.last["excluded"].sum()
        e, c = np.array(errs), np.array(covs)
        out[mode] = (e, np.einsum("kni,knij,knj->kn", e, np.linalg.inv(c), e).mean(), excl, proc.last)
    e, nees, _, last = out["block"]
    assert (last["used"] < last["above"]).all()
    assert np.sqrt((e[..., 1] ** 2).mean()) > 2 * np.sqrt((e[..., 0] ** 2).mean())
    assert nees < 4.0  # the poor geometry is in the reported covariance
    e, nees, excl, last = out["delay"]
    assert excl > 0 and nees > 4.0


def test_same_seed_same_bytes_and_another_seed_differs():
    b = Buildings.from_polygons([shapely.box(0, 8, 200, 40), shapely.box(0, -40, 200, -8)], [20.0, 30.0])

    def run(seed):
        proc = gnss_error_process(GnssErrorParams(**SAT), seed, 0.75, b)
        e, c = _run(proc, 12, 60, np.random.default_rng(0))
        return e.tobytes() + c.tobytes()

    assert run(3) == run(3)
    assert run(3) != run(4)


def test_elevation_mask_outside_0_90_and_unknown_nlos_are_refused():
    for bad in (-1.0, 90.0, 120.0, float("nan")):
        with pytest.raises(InputError) as exc:
            GnssErrorParams(**SAT, elevation_mask_deg=bad)
        assert exc.value.field == "elevation_mask_deg"
    with pytest.raises(InputError) as exc:
        GnssErrorParams(**SAT, nlos="mirror")
    assert exc.value.field == "nlos"
    with pytest.raises(InputError) as exc:
        GnssErrorParams(**SAT, velocity="radar")
    assert exc.value.field == "velocity"
    for bad in (0.0, -0.1, float("inf")):
        with pytest.raises(InputError) as exc:
            GnssErrorParams(**SAT, rx_doppler_mps=bad)
        assert exc.value.field == "rx_doppler_mps"
    with pytest.raises(InputError) as exc:
        GnssErrorParams(**SAT, doppler_noise_mps=-1.0)
    assert exc.value.field == "doppler_noise_mps"
    for bad in ("RAIM", "", 1):
        with pytest.raises(InputError) as exc:
            GnssErrorParams(**SAT, reported_covariance=bad)
        assert exc.value.field == "reported_covariance"


def test_a_building_without_height_is_refused_with_its_file_and_field(tmp_path):
    import json
    import shutil
    from pathlib import Path

    src = Path(__file__).resolve().parents[2] / "sumo_nets" / "arterial"
    net = tmp_path / "net"
    shutil.copytree(src, net)
    doc = json.loads((net / "buildings.geojson").read_text())
    del doc["features"][3]["properties"]["height"]
    (net / "buildings.geojson").write_text(json.dumps(doc))
    with pytest.raises(InputError) as exc:
        check_building_heights(net)
    assert exc.value.field == "features[3].properties.height"
    assert str(exc.value.path).endswith("buildings.geojson")
    check_building_heights(src)  # every building of the arterial has its height


def test_the_frame_carries_the_receivers_fix_and_reported_covariance_and_gnss_world_scores_it():
    from couplers.sensing.sensors import SensorNoise, SensorParams, synthesize_frame
    from experiments.gnss_world import GnssWorldTally

    n = 8
    rng = np.random.default_rng(2)
    x_true = np.c_[rng.uniform(0, 300, (n, 2)), rng.normal(0, 5, (n, 2))]
    proc = SatelliteErrorProcess(GnssErrorParams(**SAT), 1, 0.75)
    twin = SatelliteErrorProcess(GnssErrorParams(**SAT), 1, 0.75)
    entered = np.ones(n, bool)
    frame = synthesize_frame(
        t=0.0, dt=0.75, vehicle_ids=_ids(n), entered=entered, x_true=x_true, accel_true=np.zeros((n, 2)),
        heading=np.zeros(n), gnss_sigma_p=np.full(n, 8.0), gnss_sigma_v=np.full(n, 0.5),
        features_true=np.empty((0, 4)), feature_tree=None, params=SensorParams(), noise=SensorNoise(1),
        zone=np.full(n, "B", dtype=object), area=np.full(n, "1", dtype=object), gnss_error=proc, start="gnss_fix")
    err = twin.step(0.0, _ids(n), entered, None, None, None, x_true[:, :2])
    np.testing.assert_allclose(frame.gnss_z[:, :2] - x_true[:, :2], err, atol=1e-9)
    np.testing.assert_array_equal(frame.gnss_R[:, :2, :2], twin.reported_cov)
    assert np.allclose(frame.gnss_R[:, 2, 2], 0.25)  # the velocity keeps the zone's Doppler sigma
    np.testing.assert_array_equal(frame.prior_R[entered], frame.gnss_R[entered])  # entry from the receiver's fix
    tally = GnssWorldTally()
    tally.add(frame)
    block = tally.summary()["receiver_error_by_zone"]["B"]
    assert block["n"] == n and block["rms_2d_m"] == pytest.approx(math.sqrt((err ** 2).sum(1).mean()))


def test_with_doppler_the_frame_carries_the_range_rate_velocity_and_its_covariance():
    from couplers.sensing.sensors import SensorNoise, SensorParams, synthesize_frame

    n = 8
    rng = np.random.default_rng(2)
    x_true = np.c_[rng.uniform(0, 300, (n, 2)), rng.normal(0, 5, (n, 2))]
    params = GnssErrorParams(**SAT, velocity="doppler")
    proc, twin = SatelliteErrorProcess(params, 1, 0.75), SatelliteErrorProcess(params, 1, 0.75)
    entered = np.ones(n, bool)
    frame = synthesize_frame(
        t=0.0, dt=0.75, vehicle_ids=_ids(n), entered=entered, x_true=x_true, accel_true=np.zeros((n, 2)),
        heading=np.zeros(n), gnss_sigma_p=np.full(n, 8.0), gnss_sigma_v=np.full(n, 0.5),
        features_true=np.empty((0, 4)), feature_tree=None, params=SensorParams(), noise=SensorNoise(1),
        zone=np.full(n, "B", dtype=object), area=np.full(n, "1", dtype=object), gnss_error=proc, start="gnss_fix")
    twin.step(0.0, _ids(n), entered, None, None, None, x_true[:, :2])
    verr, vcov, ok = twin.velocity_error(x_true[:, 2:])
    assert ok.all()
    np.testing.assert_allclose(frame.gnss_z[:, 2:] - x_true[:, 2:], verr, atol=1e-12)
    np.testing.assert_array_equal(frame.gnss_R[:, 2:, 2:], vcov)
    assert (frame.gnss_R[:, 2, 2] < 0.05).all()  # the range rates' covariance, not the zone's 0.5 m/s
    np.testing.assert_array_equal(frame.prior_R[entered], frame.gnss_R[entered])


def test_two_receivers_correlate_in_the_open_as_the_common_errors_derive():
    """Open sky: two receivers 1 km apart correlate by the common errors' share of the horizontal variance
    (:func:`open_sky_common_share`, 0.6-0.75 with the defaults). Common processes white here (sv_tau_s = 0)
    so that 4000 epochs are ~4000 samples; RAIM off; the correlation about zero within 0.06 of the derived
    value averaged over the epochs (standard error ~0.02)."""
    p = GnssErrorParams(**SAT, sv_tau_s=0.0, raim_pfa=0.0)
    proc = SatelliteErrorProcess(p, 21, 0.75)
    rng = np.random.default_rng(4)
    xy = np.array([[0.0, 0.0], [1000.0, 0.0]])
    e, derived = [], []
    for k in range(4000):
        xy = xy + rng.normal(0, 6.0, (2, 2))
        e.append(proc.step(k * 0.75, _ids(2), np.full(2, k == 0), None, None, None, xy))
        if k % 100 == 0:
            derived.append(open_sky_common_share(p, proc.sky, k * 0.75))
    e, derived = np.array(e), np.array(derived).mean(axis=0)
    assert 0.55 < derived.min() and derived.max() < 0.8
    for j in range(2):
        rho = np.mean(e[:, 0, j] * e[:, 1, j]) / np.mean((e[:, 0, j] ** 2 + e[:, 1, j] ** 2) / 2)
        assert rho == pytest.approx(derived[j], abs=0.06)


def test_a_degenerate_geometry_gives_no_fix_rather_than_nan():
    """Four satellites at one elevation: up and clock cannot be told apart (H singular): no fix, nothing NaN;
    a fifth satellite higher up gives the fix."""
    from couplers.sensing.gnss_satellites import _wls_kernel

    el = math.radians(30.0)
    az = np.radians([0.0, 90.0, 180.0, 270.0, 45.0])
    els = np.array([el] * 4 + [math.radians(80.0)])
    los = np.c_[np.cos(els) * np.sin(az), np.cos(els) * np.cos(az), np.sin(els)]
    eps = np.random.default_rng(0).normal(0, 1, (2, 5))
    usable = np.array([[True] * 4 + [False], [True] * 5])
    err, cov, used, excluded, ok, usedm = _wls_kernel(los, usable, eps, np.ones(5), np.full(6, np.inf))
    assert ok.tolist() == [False, True]
    assert np.isfinite(err).all() and np.isfinite(cov).all()
    assert used.tolist() == [4, 5] and usedm.sum(axis=1).tolist() == [0, 5]


def _canyon(width=20.0, height=25.0):
    """An east-west street canyon: blocks of 45 m (5 m side streets) on both sides, ``width`` apart."""
    h = width / 2
    blocks = [shapely.box(x, s * h, x + 45, s * h + 30 * s) for x in range(-300, 300, 50) for s in (1, -1)]
    return Buildings.from_polygons([shapely.box(*g.bounds) for g in blocks], [height] * len(blocks))


def test_reflection_extra_path_is_the_image_path_and_its_rate_the_derivative():
    """In a canyon, every reflection found has the extra path of the antenna's image behind the reflecting wall
    (exact 3-D ranges to a satellite 2e7 m away, to 1 mm) and its rate coefficient is the extra path's gradient
    with respect to the antenna position (central differences, 1e-6)."""
    b = _canyon()
    edges = BuildingEdges.build(b)
    rng = np.random.default_rng(5)
    xy = np.c_[rng.uniform(-200, 150, 60), rng.uniform(-8, 8, 60)]
    az = rng.uniform(-np.pi, np.pi, 40)
    el = np.radians(rng.uniform(10, 80, 40))
    r = clearance_radius(edges.heights, 1.5, 10.0)
    blocked, _ = line_of_sight(edges, xy, az, el, 1.5, r)
    found, extra, g = reflections(edges, xy, az, el, blocked, 1.5, r)
    assert found.sum() > 50 and (found <= blocked).all() and (found < blocked).any()
    u = np.c_[np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)]
    big = 2e7
    boundary = shapely.union_all([shapely.boundary(pg) for pg in b.polygons])
    for i, k in zip(*np.nonzero(found)):
        p = np.array([xy[i, 0], xy[i, 1], 1.5])
        nrm = -g[i, k] / np.linalg.norm(g[i, k])  # g = -2 cos(el) cos(dphi) n: n points to the wall
        cphi = -(u[k, :2] / np.cos(el[k])) @ nrm
        d = extra[i, k] / (2 * np.cos(el[k]) * cphi)
        rdir = u[k, :2] / np.cos(el[k]) + 2 * cphi * nrm
        spec = xy[i] + d / cphi * rdir  # the specular point lies on a facade, below its roof
        assert shapely.distance(shapely.Point(spec), boundary) < 1e-6
        assert d / cphi * math.tan(el[k]) + 1.5 < 25.0
        img = p.copy()
        img[:2] += 2 * d * nrm
        sat = p + big * u[k]
        assert abs(np.linalg.norm(sat - img) - np.linalg.norm(sat - p) - extra[i, k]) < 1e-3
        h = 1e-3
        grad = []
        for dxy in ((h, 0.0), (0.0, h)):
            q = xy[i:i + 1] + dxy, xy[i:i + 1] - dxy
            f = [reflections(edges, qq, az[k:k + 1], el[k:k + 1], np.ones((1, 1), bool), 1.5, r) for qq in q]
            if not (f[0][0][0, 0] and f[1][0][0, 0]):
                break
            grad.append((f[0][1][0, 0] - f[1][1][0, 0]) / (2 * h))
        else:
            np.testing.assert_allclose(grad, g[i, k], atol=1e-6)


def test_reflect_mode_receives_some_blocked_signals_late_and_loses_the_rest():
    """"reflect": in the canyon some NLOS signals come in (by a facade's reflection, late), some are lost (no
    valid facade); the reflected ones bias the fix; same seed, same bytes."""
    b = _canyon()
    xy = np.c_[np.linspace(-250, 100, 40), np.zeros(40)]

    def run(seed):
        proc = SatelliteErrorProcess(GnssErrorParams(**SAT, nlos="reflect"), seed, 0.75, b)
        errs, rec, lost = [], 0, 0
        for k in range(60):
            errs.append(proc.step(k * 0.75, _ids(40), np.full(40, k == 0), None, None, None, xy + [k * 0.5, 0]))
            rec += proc.last["nlos_received"].sum()
            lost += (proc.last["nlos"] - proc.last["nlos_received"]).sum()
        return np.array(errs), rec, lost

    e, rec, lost = run(9)
    assert rec > 0 and lost > 0
    assert np.sqrt((e ** 2).sum(-1).mean()) > 3.0
    assert e.tobytes() == run(9)[0].tobytes()


def test_doppler_velocity_is_consistent_with_its_reported_covariance_in_the_open():
    """velocity = "doppler", open sky: the mean NEES of the horizontal velocity error against the reported
    covariance is inside the two-sided 0.1 % chi-square band (world and receiver budgets equal), and the 2-D
    RMS is at the datasheet's scale (0.02-0.2 m/s)."""
    proc = SatelliteErrorProcess(GnssErrorParams(**SAT, velocity="doppler"), 11, 1.0, None)
    rng = np.random.default_rng(1)
    n, steps = 20, 500
    nees, sq = [], []
    for k in range(steps):
        xy = rng.uniform(-500, 500, (n, 2))
        proc.step(k * 30.0, _ids(n), np.full(n, k == 0), None, None, None, xy)
        err, cov, ok = proc.velocity_error(rng.normal(0, 10, (n, 2)))
        assert ok.all()
        nees.append(np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov), err))
        sq.append((err ** 2).sum(-1))
    m = np.concatenate(nees)
    lo, hi = chi2.ppf([5e-4, 1 - 5e-4], 2 * m.size) / m.size
    assert lo < m.mean() < hi
    assert 0.02 < np.sqrt(np.concatenate(sq).mean()) < 0.2


def test_doppler_velocity_of_a_reflected_signal_carries_the_image_velocity():
    """A receiver driving across the canyon toward a reflecting wall sees its reflected signals' path shorten:
    the velocity error is biased; driving along the canyon (unbroken walls: their distance constant) it is not."""
    b = Buildings.from_polygons([shapely.box(-400, 10, 400, 40), shapely.box(-400, -40, 400, -10)], [25.0, 25.0])
    out = {}
    for name, v in (("across", (0.0, 10.0)), ("along", (10.0, 0.0))):
        proc = SatelliteErrorProcess(GnssErrorParams(**SAT, nlos="reflect", velocity="doppler", doppler_noise_mps=0.0,
                                                     raim_pfa=0.0), 3, 0.75, b)
        xy = np.c_[np.linspace(-250, 100, 30), np.full(30, -2.0)]
        proc.step(0.0, _ids(30), np.ones(30, bool), None, None, None, xy)
        err, _, ok = proc.velocity_error(np.tile(v, (30, 1)))
        assert ok.all() and proc.last["nlos_received"].sum() > 0
        out[name] = np.abs(err).max()
    assert out["along"] < 1e-9 < 0.05 < out["across"]


def _canyon_nees(nlos, mode, steps=200):
    """Mean position NEES and share inside the 95 % ellipse of 40 receivers driving along ``_canyon()``, and
    the run's errors and reported covariances."""
    proc = SatelliteErrorProcess(GnssErrorParams(**SAT, nlos=nlos, reported_covariance=mode), 9, 0.75, _canyon())
    xy = np.c_[np.linspace(-250, 100, 40), np.zeros(40)]
    errs, covs = [], []
    for k in range(steps):
        errs.append(proc.step(k * 0.75, _ids(40), np.full(40, k == 0), None, None, None, xy + [k * 0.5, 0]))
        covs.append(proc.reported_cov.copy())
    e, c = np.array(errs), np.array(covs)
    nees = np.einsum("kni,knij,knj->kn", e, np.linalg.inv(c), e)
    return nees.mean(), (nees <= chi2.ppf(0.95, 2)).mean(), e, c


def test_residual_covariance_covers_the_open_sky_fix_at_its_chi_square_level():
    """reported_covariance = "residual", open sky, world errors exactly the receiver's budget (as the "dop"
    test above): the fix is inside the reported 95 % ellipse at least 95 % of the time (less 3.3 binomial
    sigma of 30000 fixes); the factor, never below 1, only widens the "dop" covariance, by little in the open
    (mean NEES between 1 and 2); the errors are the "dop" receiver's, byte for byte."""
    kw = dict(model="satellites", sv_clock_orbit_m=0.0, iono_vertical_m=0.0, tropo_zenith_m=0.0, multipath_m=0.0,
              code_noise_a_m=0.8, code_noise_b_m=0.6, rx_ure_m=0.0, rx_iono_m=0.0, rx_tropo_m=0.0, rx_code_a_m=0.8,
              rx_code_b_m=0.6)
    out = {}
    for mode in ("dop", "residual"):
        proc = SatelliteErrorProcess(GnssErrorParams(**kw, reported_covariance=mode), 11, 0.75)
        out[mode] = _run(proc, 20, 1500, np.random.default_rng(5))
    (e0, c0), (e, c) = out["dop"], out["residual"]
    assert e.tobytes() == e0.tobytes()
    nees = np.einsum("kni,knij,knj->kn", e, np.linalg.inv(c), e).ravel()
    n = nees.size
    assert (nees <= chi2.ppf(0.95, 2)).mean() > 0.95 - 3.3 * math.sqrt(0.05 * 0.95 / n)
    assert 1.0 < nees.mean() < 2.0
    ratio = c[..., 0, 0] / c0[..., 0, 0]
    np.testing.assert_allclose(c, c0 * ratio[..., None, None], rtol=1e-12)  # a scale of the DOP covariance
    assert ratio.min() >= 1.0 and (ratio > 1.0).mean() > 0.2


def test_residual_covariance_brings_canyon_nees_toward_two():
    """In the street canyon the NLOS delays are not in the receiver's budget: with "dop" it is overconfident
    (mean NEES far above 2), with "residual" its residuals widen what it reports: the NEES much nearer 2
    (under a third of "dop"'s, below 6 with facade reflections, below 3 with "delay"), while "block", whose
    fix has no NLOS, stays consistent."""
    res = {(nlos, mode): _canyon_nees(nlos, mode) for nlos in ("reflect", "delay", "block")
           for mode in ("dop", "residual")}
    for nlos, bound in (("reflect", 6.0), ("delay", 3.0)):
        dop, resid = res[(nlos, "dop")][0], res[(nlos, "residual")][0]
        assert dop > 10.0 and resid < min(bound, dop / 3), (nlos, dop, resid)
        assert res[(nlos, "residual")][1] > res[(nlos, "dop")][1] + 0.4  # inside the 95 % ellipse far more often
    assert res[("block", "residual")][0] < 2.0 and res[("block", "residual")][1] > 0.95


def test_the_sky_computed_for_a_block_of_steps_equals_the_sky_of_each_step():
    """Sky.look_many against Sky.look, and the receiver's per-step sky terms (computed SKY_BLOCK steps at a time)
    against the numpy expressions of each step (its _sky_terms, receiver_variance, the trigonometry of the
    satellites above the mask), bit for bit: over three blocks of the step grid, then off the grid (another step's
    rounding), where each step computes its own row."""
    from couplers.sensing.gnss_satellites import MIN_SIN_EL, SKY_BLOCK, receiver_variance

    sky = Sky.build()
    ts = np.r_[np.arange(1, 200) * 0.75 + 43200.0, np.random.default_rng(4).uniform(0.0, 86400.0, 50)]
    many = sky.look_many(ts)
    for k, t in enumerate(ts):
        for a, b in zip(sky.look(t), many):
            assert a.dtype == b.dtype and a.tobytes() == b[k].tobytes()
    p = GnssErrorParams(model="satellites", velocity="doppler")
    proc = SatelliteErrorProcess(p, 5, 0.75)
    times = np.r_[np.arange(1, 3 * SKY_BLOCK + 5) * 0.75, 1000.1 + 0.1 * np.arange(5)]
    for t in times:
        got = proc._sky_step(float(t))
        assert proc._sky_step(float(t)) is got  # asked again in the same step: the same terms
        los, az, el, above, sin_el, _, sig_n = proc._sky_terms(float(t))
        cols = np.flatnonzero(above)
        want = {"los": los, "az": az, "el": el, "above": above, "sin_el": sin_el, "sig_n": sig_n,
                "mp": p.multipath_m / sin_el, "var_rx": receiver_variance(p, el),
                "sig_doppler": p.doppler_noise_mps * np.sqrt(1.0 + 1.0 / np.maximum(np.sin(el), MIN_SIN_EL)),
                "var_rr": p.rx_doppler_mps ** 2 * (1.0 + 1.0 / np.maximum(np.sin(el), MIN_SIN_EL))}
        for key, val in want.items():
            assert got[key].dtype == val.dtype and got[key].tobytes() == val.tobytes(), key
        for key, val in (("sin_az", np.sin(az[cols])), ("cos_az", np.cos(az[cols])), ("tan_el", np.tan(el[cols])),
                         ("cos_el", np.cos(el[cols]))):
            assert got[key][cols].tobytes() == val.tobytes(), key
    assert proc._sky_k == 1  # the off-grid times switched to one row at a time


def test_oracle_channel_gain_gives_the_fix_error_exactly():
    """``oracle_channel``: the fix error is the WLS gain times the pseudorange errors, to 1e-9. With the own errors
    set to zero (open sky) the gain times the satellites' common errors alone; in a canyon with reflections, fault
    exclusion and every error on, the gain times that step's errors (the clock column absorbs what is common to a
    receiver's ranges: each gain row sums to zero). The same for the Doppler velocity. Off: no channel, same
    fixes."""
    quiet = SatelliteErrorProcess(GnssErrorParams(**SAT, code_noise_a_m=0.0, code_noise_b_m=0.0, multipath_m=0.0,
                                                  oracle_channel=True), 2, 0.75)
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 1000, (12, 2))
    for k in range(5):
        err = quiet.step(k * 0.75, _ids(12), np.full(12, k == 0), None, None, None, xy + k)
        ch = quiet.oracle_frame()
        common = quiet._sky_terms(k * 0.75)[5]
        np.testing.assert_allclose(ch.gain @ common, err, rtol=0, atol=1e-9)
        assert ch.fix.all() and not ch.reflected.any() and ch.velocity_gain is None
        np.testing.assert_allclose(ch.gain.sum(axis=2), 0.0, atol=1e-9)
    params = dict(**SAT, nlos="reflect", velocity="doppler")
    on = SatelliteErrorProcess(GnssErrorParams(**params, oracle_channel=True), 9, 0.75, _canyon())
    off = SatelliteErrorProcess(GnssErrorParams(**params), 9, 0.75, _canyon())
    seen = {"eps": None}
    inner = on.pseudorange_errors

    def spy(*a, **kw):
        out = inner(*a, **kw)
        seen["eps"] = out[0]
        return out

    on.pseudorange_errors = spy
    xy = np.c_[np.linspace(-250, 100, 40), rng.uniform(-3, 3, 40)]
    excluded = reflected = 0
    for k in range(30):
        pos = xy + [k * 0.5, 0]
        e_on = on.step(k * 0.75, _ids(40), np.full(40, k == 0), None, None, None, pos)
        e_off = off.step(k * 0.75, _ids(40), np.full(40, k == 0), None, None, None, pos)
        assert e_on.tobytes() == e_off.tobytes() and off.oracle_frame() is None
        v = np.tile([0.4, 0.3], (40, 1))
        ve_on, vc_on, ok_on = on.velocity_error(v)
        ve_off, _, _ = off.velocity_error(v)
        assert ve_on.tobytes() == ve_off.tobytes()
        ch = on.oracle_frame()
        np.testing.assert_allclose(np.einsum("nis,ns->ni", ch.gain, seen["eps"])[ch.fix], e_on[ch.fix], rtol=0,
                                   atol=1e-9)
        assert ch.velocity_solved.tolist() == ok_on.tolist() and (ch.velocity_used <= ch.used).all()
        excluded += int(on.last["excluded"].sum())
        reflected += int(ch.reflected.sum())
        assert (ch.used.sum(axis=1) == on.last["used"]).all()
    assert excluded > 0 and reflected > 0


class _Spy:
    """A Generator's draws, recorded (shapes and values) as they are made."""

    def __init__(self, rng):
        self.rng, self.calls = rng, []

    def standard_normal(self, size=None):
        out = self.rng.standard_normal(size)
        self.calls.append(np.array(out, copy=True))
        return out


def test_visible_draws_take_n_by_m_normals_for_the_satellites_above_the_mask():
    """``draws = "visible"``: the code noise, multipath and Doppler streams give (N, M) normals a step, M the
    satellites above the mask, in those satellites' columns (zeros elsewhere); a standing vehicle keeps its
    multipath for a satellite that stays above the mask and starts from its fresh draw for one that rises; the
    common-mode and no-fix streams are those of ``draws = "all"``; same seed same bytes, another seed differs."""
    from couplers.sensing.perception import effect_rng
    from couplers.sensing.gnss_satellites import GNSS_ERROR_STREAM_TAG

    params = dict(**SAT, nlos="reflect", velocity="doppler")
    vis = SatelliteErrorProcess(GnssErrorParams(**params, draws="visible"), 5, 0.75, _canyon())
    every = SatelliteErrorProcess(GnssErrorParams(**params), 5, 0.75, _canyon())
    for name in ("code_noise", "multipath", "doppler_noise"):
        setattr(vis, name, _Spy(getattr(vis, name)))
    n = 20
    xy = np.c_[np.linspace(-250, 100, n), np.zeros(n)]
    moving = np.arange(n) % 2 == 0
    seen_rise = kept = 0
    u_prev = above_prev = None
    for k in range(8):
        t = 1500.0 * k  # 25 min a step: satellites rise and set
        pos = xy + np.where(moving[:, None], [3.0 * k, 0.0], 0.0)
        e = vis.step(t, _ids(n), np.full(n, k == 0), None, None, None, pos)
        every.step(t, _ids(n), np.full(n, k == 0), None, None, None, pos)
        vis.velocity_error(np.zeros((n, 2)))
        every.velocity_error(np.zeros((n, 2)))
        above = vis._sky_step(t)["above"]
        cols = np.flatnonzero(above)
        for name in ("code_noise", "multipath", "doppler_noise"):
            assert getattr(vis, name).calls[-1].shape == (n, cols.size)
        z = vis.multipath.calls[-1]
        assert not vis._u[:, ~above].any() and e.shape == (n, 2) and np.isfinite(e).all()
        if k:  # standing vehicles (odd rows): carried where the satellite stays above, the fresh draw where it rose
            stay, rose = above & above_prev, above & ~above_prev
            still = ~moving
            np.testing.assert_array_equal(vis._u[still][:, stay], u_prev[still][:, stay])
            np.testing.assert_array_equal(vis._u[:, rose], z[:, np.searchsorted(cols, np.flatnonzero(rose))])
            seen_rise += int(rose.sum())
            kept += int(stay.sum())
        else:
            np.testing.assert_array_equal(vis._u[:, cols], z)
        u_prev, above_prev = vis._u.copy(), above.copy()
    assert seen_rise > 0 and kept > 0
    # the draws are each stream's own sequence, in order
    for name in ("code_noise", "multipath", "doppler_noise"):
        ref = effect_rng(5, GNSS_ERROR_STREAM_TAG, name)
        for got in getattr(vis, name).calls:
            assert ref.standard_normal(got.shape).tobytes() == got.tobytes()
    # the common-mode processes and the other streams are untouched by the setting
    assert vis.sv.tobytes() == every.sv.tobytes() and vis.tropo == every.tropo
    for name in ("sv_common", "no_fix"):
        assert getattr(vis, name).bit_generator.state == getattr(every, name).bit_generator.state

    def run(seed):
        proc = SatelliteErrorProcess(GnssErrorParams(**params, draws="visible"), seed, 0.75, _canyon())
        out = b""
        for k in range(6):
            out += proc.step(0.75 * k, _ids(n), np.full(n, k == 0), None, None, None, xy + [0.5 * k, 0]).tobytes()
            out += proc.reported_cov.tobytes() + proc.velocity_error(np.tile([0.6, 0.0], (n, 1)))[0].tobytes()
        return out

    assert run(3) == run(3) and run(3) != run(4)


def test_unknown_draws_are_refused():
    for bad in ("some", "", 1, None):
        with pytest.raises(InputError) as exc:
            GnssErrorParams(**SAT, draws=bad)
        assert exc.value.field == "draws"


def test_the_receivers_draws_in_kernels_equal_numpys_draws(monkeypatch):
    """Under draws = "all" the code-noise, multipath and Doppler normals are drawn inside kernels
    (couplers.sensing.streams): fixes, reported covariances, velocities and every stream's state after equal the
    numpy draws' (streams.available() False), with receivers that enter, stay, stand still and leave."""
    from couplers.sensing import streams

    params = GnssErrorParams(**SAT, nlos="reflect", velocity="doppler", reported_covariance="residual")
    runs = []
    for kernel_draws in (True, False):
        if not kernel_draws:
            monkeypatch.setattr(streams, "available", lambda: False)
        elif not streams.available():
            pytest.skip("numba's draws are not numpy's on this installation")
        proc, rng = SatelliteErrorProcess(params, 3, 0.75, _canyon()), np.random.default_rng(4)
        ids, xy, out = _ids(0), np.empty((0, 2)), []
        for k in range(12):
            keep = rng.random(ids.size) < 0.85  # some leave, some enter
            new = rng.integers(0, 3)
            ids = np.concatenate([ids[keep], np.array([f"v{k}_{j}" for j in range(new)], dtype=object)])
            moved = np.where(rng.random((int(keep.sum()), 1)) < 0.3, 0.0, rng.normal(0, 6, (int(keep.sum()), 2)))
            xy = np.vstack([xy[keep] + moved, np.column_stack([rng.uniform(-250, 250, new), rng.uniform(-8, 8, new)])])
            entered = np.r_[np.zeros(int(keep.sum()), dtype=bool), np.ones(new, dtype=bool)]
            err = proc.step(k * 0.75, ids, entered, None, None, None, xy)
            verr, vcov, solved = proc.velocity_error(rng.normal(0, 10, (ids.size, 2)))
            out.append((err, proc.reported_cov, verr, vcov, solved, proc._u))
        states = [getattr(proc, name).bit_generator.state for name in SatelliteErrorProcess.STREAMS]
        runs.append((out, states))
    (a, sa), (b, sb) = runs
    assert sa == sb
    for x, y in zip(a, b):
        for u, v in zip(x, y):
            assert u.dtype == v.dtype and u.shape == v.shape and u.tobytes() == v.tobytes()
