"""Other road users, persistent false alarms and the classifier's error (couplers.sensing.road_users):
detection at the configured probabilities (binomial tests, two-sided 0.1 % level, seeded), occlusion
by every footprint but the target's own, persistent sites fixed for a run."""

import numpy as np
import pytest
from scipy import stats

from couplers.sensing.occlusion import vehicle_footprints
from couplers.sensing.perception import PerceptionParams, SensorSpec
from couplers.sensing.road_users import (
    CLASS_VEHICLE,
    RoadUserNoise,
    confuse_classes,
    perceive_targets,
    persistent_clutter_sites,
)

ALPHA = 1e-3  # two-sided 0.1 % level of every statistical test here


def _params(pd=0.8, **kw):
    sensors = (SensorSpec(name="surround", fov_deg=360.0, range_m=40.0, pd_near=pd, pd_far=pd, clutter_per_scan=0.0),
               SensorSpec(name="front", fov_deg=90.0, range_m=40.0, pd_near=pd, pd_far=pd, clutter_per_scan=0.0))
    return PerceptionParams(sensors=sensors, occlusion_buildings=False, **kw)


def _scan(params, noise, targets, target_pd, occluder=None, corners=None, observer_occluder=None):
    x = np.array([[0.0, 0.0, 10.0, 0.0]])
    n_t = targets.shape[0]
    return perceive_targets(
        x_true=x, direction=np.array([[1.0, 0.0]]), heading=np.zeros(1), targets=targets, target_pd=target_pd,
        target_occluder=np.full(n_t, -1, dtype=np.int64) if occluder is None else occluder,
        pair_owner=np.zeros(n_t, dtype=np.int64), pair_target=np.arange(n_t), params=params, noise=noise,
        occluder_corners=corners, observer_occluder=np.full(1, -1) if observer_occluder is None else observer_occluder)


def test_road_users_detected_at_the_sensor_pd():
    """Targets in view of one sensor (behind the vehicle) and of two (ahead): each sensor detects with its
    P_D = 0.8, so a target seen by two is reported with 1 - 0.2^2; one row per detected target, its relative
    velocity the true one + noise."""
    params, noise = _params(0.8), RoadUserNoise(11)
    targets = np.array([[-20.0, 5.0, 3.0, 0.0], [-10.0, -15.0, 0.0, 1.0], [20.0, 3.0, 5.0, 0.0],
                        [30.0, -4.0, 8.0, 0.0]])
    scans = 3000
    hits = np.zeros(4, dtype=np.int64)
    vel_err = []
    for _ in range(scans):
        owner, tgt, _, z, _, sv = _scan(params, noise, targets, np.full(4, -1.0))
        assert np.unique(tgt).size == tgt.size  # one row per target
        np.add.at(hits, tgt, 1)
        vel_err.append((z[:, 2:] - (targets[tgt, 2:] - [10.0, 0.0])) / sv[:, None])
    for k, p in enumerate((0.8, 0.8, 1 - 0.2**2, 1 - 0.2**2)):
        assert stats.binomtest(int(hits[k]), scans, p).pvalue > ALPHA, (k, hits[k] / scans, p)
    e = np.concatenate(vel_err)
    assert abs(e.mean()) < 4 / np.sqrt(e.size) and 0.95 < e.std() < 1.05


def test_vehicle_target_not_occluded_by_itself_but_by_another():
    """A vehicle target's own footprint never hides it; another footprint on the sight line does."""
    params, noise = _params(1.0), RoadUserNoise(2)
    # footprints: target vehicle (front bumper at x = 22.5, 5 m long), a blocker at x = 12.5 on the line to y = 8
    corners = vehicle_footprints(np.array([[22.5, 0.0], [12.5, 4.0]]), np.zeros(2), np.array([5.0, 5.0]),
                                 np.array([2.0, 2.0]))
    targets = np.array([[20.0, 0.0, 0.0, 0.0], [20.0, 8.0, 0.0, 0.0]])
    _, tgt, *_ = _scan(params, noise, targets, np.full(2, -1.0), occluder=np.array([0, -1]), corners=corners)
    assert tgt.tolist() == [0]  # its own footprint does not hide target 0; the blocker hides target 1
    _, tgt, *_ = _scan(params, noise, targets, np.full(2, -1.0), occluder=np.array([-1, -1]), corners=corners)
    assert tgt.tolist() == []  # (without the exemption it would hide itself)


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("growth", [0.0, 3.0])
@pytest.mark.parametrize("with_buildings", [False, True])
def test_target_rows_kernel_equals_reference(seed, growth, with_buildings):
    """perceive_targets (field of view, draws and occlusion in one kernel, detection and rows in another) equals
    its numpy reference exactly on seeded scenes, and leaves its streams where the reference leaves them:
    vehicles (footprints occluding, each exempt for its own), persistent sites (fixed P_D), three sensors of which
    two have the same sigma (growth 0: ties broken by the sensor listed first), with and without buildings."""
    rng = np.random.default_rng(seed)
    sensors = (SensorSpec(name="surround", fov_deg=360.0, range_m=50.0, pd_near=0.9, pd_far=0.6, sigma_p_m=0.3,
                          sigma_growth=growth, clutter_per_scan=0.0),
               SensorSpec(name="front", fov_deg=120.0, range_m=80.0, pd_near=0.95, pd_far=0.5, sigma_p_m=0.3,
                          sigma_growth=growth, clutter_per_scan=0.0),
               SensorSpec(name="rear", fov_deg=90.0, range_m=40.0, yaw_deg=180.0, mount_x_m=-4.0, pd_near=0.8,
                          pd_far=0.8, sigma_p_m=0.2, sigma_growth=growth, clutter_per_scan=0.0))
    params = PerceptionParams(sensors=sensors, occlusion_buildings=with_buildings)
    buildings = None
    if with_buildings:
        import shapely

        from couplers.net.buildings import Buildings

        corner_size = rng.uniform([0, 0, 3, 3], [140, 140, 15, 15], (12, 4))
        boxes = [shapely.box(x, y, x + w, y + h) for x, y, w, h in corner_size]
        buildings = Buildings.from_polygons(boxes, list(rng.uniform(5.0, 30.0, len(boxes))))
    n, s = 40, 30
    xy = rng.uniform(0.0, 150.0, (n, 2))
    heading = rng.uniform(-np.pi, np.pi, n)
    direction = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    x_true = np.hstack([xy, rng.normal(0.0, 8.0, (n, 2))])
    corners = vehicle_footprints(xy, heading, np.full(n, 4.5), np.full(n, 1.8))
    targets = np.vstack([np.hstack([xy - 2.25 * direction, x_true[:, 2:]]),
                         np.hstack([rng.uniform(0.0, 150.0, (s, 2)), np.zeros((s, 2))])])
    target_pd = np.concatenate([np.full(n, -1.0), np.full(s, 0.7)])
    occluder = np.concatenate([np.arange(n), np.full(s, -1)])
    owner, tgt = np.nonzero(np.hypot(*(xy[:, None, :] - targets[None, :, :2]).transpose(2, 0, 1)) <= 80.0)
    keep = occluder[tgt] != owner
    out, states = [], []
    for reference in (False, True):
        noise = RoadUserNoise(seed)
        out.append(perceive_targets(
            x_true=x_true, direction=direction, heading=heading, targets=targets, target_pd=target_pd,
            target_occluder=occluder, pair_owner=owner[keep], pair_target=tgt[keep], params=params,
            noise=noise, occluder_corners=corners, observer_occluder=np.arange(n), reference=reference,
            buildings=buildings))
        states.append([getattr(noise, name).bit_generator.state for name in RoadUserNoise.STREAMS])
    assert out[0][0].size > 50  # enough detections to mean something
    for new, ref in zip(*out):
        assert new.dtype == ref.dtype and new.shape == ref.shape
        assert new.tobytes() == ref.tobytes()
    assert states[0] == states[1]


def test_persistent_sites_fixed_and_beside_the_lane():
    lanes = [(np.array([[0.0, 0.0], [1000.0, 0.0]]), 3.2), (np.array([[0.0, 50.0], [0.0, 550.0], [300.0, 550.0]]), 3.2)]
    a = persistent_clutter_sites(lanes, 20.0, np.random.default_rng(4))
    b = persistent_clutter_sites(lanes, 20.0, np.random.default_rng(4))
    assert np.array_equal(a, b) and a.shape[0] > 0
    # Poisson count over 1.8 km at 20 per km: 36 expected (0.1 % two-sided bounds of Poisson(36): 18..58)
    counts = [persistent_clutter_sites(lanes, 20.0, np.random.default_rng(s)).shape[0] for s in range(200)]
    assert abs(np.mean(counts) - 36.0) < 3.29 * 6.0 / np.sqrt(200)
    first = a[(a[:, 1] < 10) & (a[:, 0] > 0) & (a[:, 0] < 1000)]
    on_first = a[np.abs(a[:, 1]) < 10]
    assert first.shape == on_first.shape
    # right of the direction of travel (+x): y < 0, between w / 2 + 0.5 and w / 2 + 3 m from the lane
    assert np.all((on_first[:, 1] <= -2.1) & (on_first[:, 1] >= -4.6))


def test_persistent_clutter_recurs_at_its_rate_at_fixed_places():
    """Sites seen by one or by two sensors are reported with persistent_clutter_pd (one draw per vehicle, site
    and scan), at their place within the row's noise, scan after scan."""
    pd = 0.6
    params, noise = _params(0.3, persistent_clutter_pd=pd), RoadUserNoise(5)
    sites = np.array([[-15.0, 3.0, 0.0, 0.0], [25.0, 2.0, 0.0, 0.0], [10.0, -30.0, 0.0, 0.0]])
    scans = 3000
    hits = np.zeros(3, dtype=np.int64)
    for _ in range(scans):
        _, tgt, _, z, sp, _ = _scan(params, noise, sites, np.full(3, pd))
        np.add.at(hits, tgt, 1)
        err = (z[:, :2] - sites[tgt, :2]) / sp[:, None]
        assert np.all(np.abs(err) < 6)
        assert np.allclose(z[:, 2:], -np.array([10.0, 0.0]), atol=6 * 0.1)  # static: relative velocity -v
    for k in range(3):
        assert stats.binomtest(int(hits[k]), scans, pd).pvalue > ALPHA, (k, hits[k] / scans)


def test_class_error_rate():
    rng = np.random.default_rng(3)
    klass = np.full(20000, CLASS_VEHICLE, dtype=np.int8)
    assert confuse_classes(klass, 0.0, rng) is klass
    out = confuse_classes(klass, 0.1, rng)
    wrong = int(np.count_nonzero(out != CLASS_VEHICLE))
    assert stats.binomtest(wrong, klass.size, 0.1).pvalue > ALPHA
    assert set(np.unique(out[out != CLASS_VEHICLE]).tolist()) == {0, 1}


@pytest.mark.parametrize("key,value", [("persistent_clutter_per_km", -1.0), ("persistent_clutter_pd", 1.5),
                                       ("class_error", -0.1)])
def test_bad_values_refused(key, value):
    from couplers.errors import InputError

    with pytest.raises(InputError) as exc:
        PerceptionParams(**{key: value})
    assert exc.value.field == key


def test_coupler_reports_road_users_and_fixed_persistent_clutter(cross_net):
    """SUMO run on the cross net: vehicle rows are other vehicles' footprint centres (never the observer's own),
    class vehicle, not a feature; persistent rows lie at the run's fixed sites, class static; landmark and
    clutter rows are the perception's."""
    from couplers.net.folder import load_net_folder
    from couplers.sensing.road_users import KIND_LANDMARK, KIND_PERSISTENT_CLUTTER, KIND_VEHICLE
    from couplers.sensing.sensors import SensorParams
    from couplers.sumo_coupler import SumoCoupler, SumoScenario

    spec = SensorSpec(name="s", fov_deg=360.0, range_m=40.0, pd_near=1.0, pd_far=1.0, clutter_per_scan=0.5,
                      sigma_p_m=0.01, sigma_growth=0.0, sigma_v_mps=0.01)
    perception = PerceptionParams(sensors=(spec,), occlusion_vehicles=False, road_users=True,
                                  persistent_clutter_per_km=20.0, persistent_clutter_pd=1.0)
    kinds, sites = np.zeros(5, dtype=np.int64), None
    with SumoCoupler(SumoScenario(net=load_net_folder(cross_net), control="tlr", seed=2, duration_s=60.0),
                     SensorParams(perception=perception)) as c:
        for fr in c.frames():
            if sites is None and c.persistent_sites is not None:
                sites = c.persistent_sites.copy()
            kind = fr.truth.v2f_kind
            assert kind.shape == fr.truth.v2f_feature.shape == fr.v2f_class.shape
            kinds += np.bincount(kind, minlength=5)
            assert np.all((fr.truth.v2f_feature >= 0) == (kind == KIND_LANDMARK))
            assert np.all((fr.v2f_class == CLASS_VEHICLE) == (kind == KIND_VEHICLE))
            pos = fr.truth.x_true[fr.v2f_owner, :2] + fr.v2f_z[:, :2]
            veh = kind == KIND_VEHICLE
            if veh.any():
                own = np.hypot(*(pos[veh] - fr.truth.x_true[fr.v2f_owner[veh], :2]).T)
                assert own.min() > 1.0  # another vehicle's centre, never the observer's own
                d = np.hypot(*(pos[veh][:, None] - fr.truth.x_true[None, :, :2]).transpose(2, 0, 1))
                assert np.all(d.min(axis=1) < 10.0)
            per = kind == KIND_PERSISTENT_CLUTTER
            if per.any():
                assert np.array_equal(c.persistent_sites, sites)
                d = np.hypot(*(pos[per][:, None] - sites[None]).transpose(2, 0, 1))
                assert np.all(d.min(axis=1) < 0.1) and np.all(fr.v2f_class[per] == 0)
    assert kinds[KIND_VEHICLE] > 0 and kinds[KIND_PERSISTENT_CLUTTER] > 0 and kinds[KIND_LANDMARK] > 0
