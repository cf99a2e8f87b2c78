"""Realistic perception (couplers.sensing.perception) against brute-force references and its
configured statistics; buildings.geojson in a net folder; the [perception] table end to end."""

import json
import math
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
import shapely
from scipy import stats
from scipy.spatial import cKDTree
from shapely.affinity import rotate, translate
from shapely.geometry import LineString, box

from couplers.errors import InputError
from couplers.net.buildings import Buildings
from couplers.net.folder import load_net_folder
from couplers.sensing.occlusion import occluded_by_buildings, occluded_by_vehicles, vehicle_footprints
from couplers.sensing.perception import (
    PerceptionNoise,
    PerceptionParams,
    SensorSpec,
    clutter_points,
    detection_probability,
    fov_candidates,
    perceive,
    range_sigma,
    sensor_origins,
)
from couplers.sensing.sensors import SensorParams, features_in_range
from netfixture import arterial_config

ROOT = Path(__file__).resolve().parents[2]
ALPHA = 1e-3  # two-sided 0.1 % level of every statistical test here

SENSORS = (
    SensorSpec(name="front", fov_deg=120.0, range_m=80.0, yaw_deg=0.0, mount_x_m=0.0),
    SensorSpec(name="rear_left", fov_deg=90.0, range_m=40.0, yaw_deg=135.0, mount_x_m=-3.0),
    SensorSpec(name="surround", fov_deg=360.0, range_m=25.0, mount_x_m=-2.0),
)


def _scene(seed: int, n_veh: int = 60, n_feat: int = 50, size: float = 160.0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, size, (n_veh, 2))
    heading = rng.uniform(-np.pi, np.pi, n_veh)
    speed = rng.uniform(0, 14, n_veh)
    x_true = np.hstack([xy, speed[:, None] * np.stack([np.cos(heading), np.sin(heading)], 1)])
    length = rng.uniform(4.0, 12.0, n_veh)
    width = rng.uniform(1.6, 2.5, n_veh)
    feats = np.hstack([rng.uniform(0, size, (n_feat, 2)), np.zeros((n_feat, 2))])
    blds = []
    for _ in range(4):
        cx, cy = rng.uniform(0, size, 2)
        w, h = rng.uniform(5, 25, 2)
        blds.append(rotate(box(cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2), rng.uniform(0, 90)))
    return x_true, heading, length, width, feats, Buildings.from_polygons(blds)


def _footprint_brute(p, h, length, width):
    """The SUMO convention built another way: a box centred half a length behind the front bumper."""
    c = p - 0.5 * length * np.array([math.cos(h), math.sin(h)])
    return translate(rotate(box(-length / 2, -width / 2, length / 2, width / 2), math.degrees(h), origin=(0, 0)), *c)


def _visible_brute(x_true, heading, length, width, feats, buildings, sensors, occlusion=True):
    """(sensor, vehicle, feature) triples in the field of view and not occluded, by plain loops."""
    polys = [_footprint_brute(x_true[i, :2], heading[i], length[i], width[i]) for i in range(len(heading))]
    fov, vis = set(), set()
    for s, spec in enumerate(sensors):
        for i in range(len(heading)):
            h = heading[i]
            o = x_true[i, :2] + spec.mount_x_m * np.array([math.cos(h), math.sin(h)])
            b = h + math.radians(spec.yaw_deg)
            for k in range(len(feats)):
                d = feats[k, :2] - o
                # rotate into the boresight frame instead of wrapping angles
                lx = math.cos(b) * d[0] + math.sin(b) * d[1]
                ly = -math.sin(b) * d[0] + math.cos(b) * d[1]
                if math.hypot(*d) > spec.range_m:
                    continue
                if spec.fov_deg < 360 and abs(math.degrees(math.atan2(ly, lx))) > spec.fov_deg / 2:
                    continue
                fov.add((s, i, k))
                if occlusion:
                    line = LineString([o, feats[k, :2]])
                    if any(line.intersects(polys[j]) for j in range(len(polys)) if j != i):
                        continue
                    if any(line.intersects(g) for g in buildings.polygons):
                        continue
                vis.add((s, i, k))
    return fov, vis


def _sigma_at(x_true, heading, feats, i, k, spec):
    o = sensor_origins(x_true[i:i + 1, :2], heading[i:i + 1], spec)[0]
    return float(range_sigma(np.array([np.hypot(*(feats[k, :2] - o))]), spec)[0])


def _pairs(x_true, feats, reach):
    return features_in_range(x_true[:, :2], cKDTree(feats[:, :2]), reach)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_field_of_view_and_occlusion_match_shapely_brute_force(seed):
    x_true, heading, length, width, feats, blds = _scene(seed)
    params = PerceptionParams(sensors=SENSORS)
    owner, feat = _pairs(x_true, feats, params.max_reach_m)
    corners = vehicle_footprints(x_true[:, :2], heading, length, width)
    fov, vis = set(), set()
    for s, spec in enumerate(SENSORS):
        origin = sensor_origins(x_true[:, :2], heading, spec)
        idx, _ = fov_candidates(origin, heading, owner, feats[feat, :2], spec)
        start, end = origin[owner[idx]], feats[feat[idx], :2]
        occ = occluded_by_vehicles(start, end, corners, owner[idx]) | occluded_by_buildings(start, end, blds)
        fov |= {(s, int(owner[j]), int(feat[j])) for j in idx}
        vis |= {(s, int(owner[j]), int(feat[j])) for j, o in zip(idx, occ) if not o}
    fov_b, vis_b = _visible_brute(x_true, heading, length, width, feats, blds, SENSORS)
    assert fov == fov_b
    assert vis == vis_b
    assert len(fov) > 100 and 0 < len(fov - vis) < len(fov)  # the scenes do occlude, but not everything


def test_perceive_with_certain_detection_reports_every_visible_feature_once():
    """P_D = 1, no clutter: the detected (vehicle, feature) pairs are the union over sensors of the
    brute-force visible set, one row each, with the noise of the best sensor that sees it."""
    x_true, heading, length, width, feats, blds = _scene(7)
    sensors = tuple(SensorSpec(name=s.name, fov_deg=s.fov_deg, range_m=s.range_m, yaw_deg=s.yaw_deg, mount_x_m=s.mount_x_m,
                               pd_near=1.0, pd_far=1.0, clutter_per_scan=0.0) for s in SENSORS)
    params = PerceptionParams(sensors=sensors)
    owner, feat = _pairs(x_true, feats, params.max_reach_m)
    det = perceive(x_true=x_true, heading=heading, features_true=feats, pair_owner=owner, pair_feature=feat,
                   params=params, noise=PerceptionNoise(1), occluder_corners=vehicle_footprints(x_true[:, :2], heading, length, width),
                   observer_occluder=np.arange(len(heading)), buildings=blds)
    _, vis_b = _visible_brute(x_true, heading, length, width, feats, blds, sensors)
    got = list(zip(det.owner.tolist(), det.feature.tolist()))
    assert len(got) == len(set(got))
    assert set(got) == {(i, k) for _, i, k in vis_b}
    assert (det.feature >= 0).all() and det.stats["detected"] == len(got) and det.stats["clutter"] == 0
    # v2f_R is the covariance of the chosen sensor at its distance, and it is the smallest on offer.
    for r in range(det.owner.size):
        i, k, s = det.owner[r], det.feature[r], det.sensor[r]
        sig = _sigma_at(x_true, heading, feats, i, k, sensors[s])
        assert det.R[r, 0, 0] == pytest.approx(sig ** 2) and det.R[r, 2, 2] == pytest.approx(0.01)
        offered = [_sigma_at(x_true, heading, feats, i, k, sensors[q]) for q in range(len(sensors)) if (q, i, k) in vis_b]
        assert sig == pytest.approx(min(offered))
    # Noise drawn with the reported covariance: normalised residuals have unit variance.
    res = (det.z - (feats[det.feature] - x_true[det.owner])) / np.sqrt(np.diagonal(det.R, axis1=1, axis2=2))
    chi2 = float((res ** 2).sum())
    dof = res.size
    assert stats.chi2.sf(chi2, dof) > ALPHA / 2 and stats.chi2.cdf(chi2, dof) > ALPHA / 2


def test_detection_counts_follow_the_configured_probability():
    """One vehicle, features at known distances in a front radar's beam: binomial counts at 0.1 %."""
    spec = SensorSpec(name="radar", fov_deg=120.0, range_m=80.0, pd_near=0.95, pd_far=0.4, clutter_per_scan=0.0)
    params = PerceptionParams(sensors=(spec,), occlusion_vehicles=False, occlusion_buildings=False)
    dists = np.array([2.0, 20.0, 45.0, 70.0, 79.0])
    feats = np.hstack([np.stack([dists, np.zeros_like(dists)], 1), np.zeros((dists.size, 2))])
    x_true = np.array([[0.0, 0.0, 10.0, 0.0]])
    heading = np.array([0.0])
    owner, feat = np.zeros(dists.size, dtype=np.int64), np.arange(dists.size)
    noise = PerceptionNoise(11)
    steps = 4000
    counts = np.zeros(dists.size, dtype=int)
    for _ in range(steps):
        det = perceive(x_true=x_true, heading=heading, features_true=feats, pair_owner=owner, pair_feature=feat,
                       params=params, noise=noise)
        counts[det.feature] += 1
    p = detection_probability(dists, spec)
    np.testing.assert_allclose(p, 0.95 + (0.4 - 0.95) * dists / 80.0)
    for c, pk in zip(counts, p):
        assert stats.binomtest(int(c), steps, float(pk)).pvalue > ALPHA


def test_clutter_is_poisson_and_uniform_over_the_field_of_view():
    spec = SensorSpec(name="radar", fov_deg=120.0, range_m=80.0, yaw_deg=30.0, clutter_per_scan=2.5)
    rng = np.random.default_rng(5)
    n_veh, scans = 50, 200
    origin = rng.uniform(-500, 500, (n_veh, 2))
    heading = rng.uniform(-np.pi, np.pi, n_veh)
    per_scan, local = [], []
    for _ in range(scans):
        owner, sensor, pts, r = clutter_points(origin[None], heading, PerceptionParams(sensors=(spec,)), rng)
        assert (sensor == 0).all()
        per_scan.append(np.bincount(owner, minlength=n_veh))
        d = pts - origin[owner]
        b = heading[owner] + math.radians(spec.yaw_deg)
        ang = np.arctan2(-np.sin(b) * d[:, 0] + np.cos(b) * d[:, 1], np.cos(b) * d[:, 0] + np.sin(b) * d[:, 1])
        local.append(np.stack([np.hypot(d[:, 0], d[:, 1]), ang], 1))
        np.testing.assert_allclose(r, np.hypot(d[:, 0], d[:, 1]))
    counts = np.concatenate(per_scan)
    # Poisson: mean (normal approximation of a sum of Poissons) and dispersion index (chi-square, n - 1 dof).
    n = counts.size
    z = (counts.sum() - n * spec.clutter_per_scan) / math.sqrt(n * spec.clutter_per_scan)
    assert 2 * stats.norm.sf(abs(z)) > ALPHA
    disp = float(((counts - counts.mean()) ** 2).sum() / counts.mean())
    assert stats.chi2.sf(disp, n - 1) > ALPHA / 2 and stats.chi2.cdf(disp, n - 1) > ALPHA / 2
    # Uniform over the sector's area: 5 radial rings of equal area x 6 equal angular slices.
    loc = np.concatenate(local)
    half = math.radians(spec.fov_deg) / 2
    assert (loc[:, 0] <= spec.range_m + 1e-9).all() and (np.abs(loc[:, 1]) <= half + 1e-9).all()
    ring = np.minimum((loc[:, 0] / spec.range_m) ** 2 * 5, 4.999).astype(int)
    sl = np.minimum((loc[:, 1] + half) / (2 * half) * 6, 5.999).astype(int)
    cells = np.bincount(ring * 6 + sl, minlength=30)
    assert stats.chisquare(cells).pvalue > ALPHA


def test_clutter_rows_in_perceive_are_static_objects_with_truth_minus_one():
    spec = SensorSpec(name="s", fov_deg=360.0, range_m=30.0, clutter_per_scan=3.0, sigma_p_m=1e-9, sigma_v_mps=1e-9)
    params = PerceptionParams(sensors=(spec,))
    x_true = np.array([[0.0, 0.0, 5.0, 1.0], [100.0, 0.0, -3.0, 0.0]])
    det = perceive(x_true=x_true, heading=np.array([0.2, np.pi]), features_true=np.empty((0, 4)),
                   pair_owner=np.empty(0, dtype=np.int64), pair_feature=np.empty(0, dtype=np.int64),
                   params=params, noise=PerceptionNoise(3))
    assert det.z.shape[0] > 0 and (det.feature == -1).all()
    np.testing.assert_allclose(det.z[:, 2:], -x_true[det.owner, 2:], atol=1e-6)
    assert (np.hypot(det.z[:, 0], det.z[:, 1]) <= 30.0 + 1e-6).all()


@pytest.mark.parametrize("kwargs, field", [
    (dict(fov_deg=0.0), "fov_deg"), (dict(fov_deg=360.5), "fov_deg"), (dict(fov_deg=-10.0), "fov_deg"),
    (dict(pd_near=-0.1), "pd_near"), (dict(pd_far=1.01), "pd_far"), (dict(clutter_per_scan=-1.0), "clutter_per_scan"),
    (dict(range_m=0.0), "range_m"), (dict(range_m=float("inf")), "range_m"), (dict(sigma_p_m=0.0), "sigma_p_m"),
    (dict(sigma_growth=-1.0), "sigma_growth"),
])
def test_bad_sensor_parameters_name_the_field(kwargs, field):
    with pytest.raises(InputError) as err:
        SensorSpec(**kwargs)
    assert err.value.field == field


@pytest.mark.parametrize("extra, field", [
    ("[perception]\n[[perception.sensors]]\nfov_deg = 361.0", "perception.sensors[0].fov_deg"),
    ("[perception]\n[[perception.sensors]]\nname = 'a'\n[[perception.sensors]]\npd_near = 2.0", "perception.sensors[1].pd_near"),
    ("[perception]\n[[perception.sensors]]\nclutter_per_scan = -0.5", "perception.sensors[0].clutter_per_scan"),
    ("[perception]\nsensors = []", "perception.sensors"),
    ("[perception]\nrange = 3", "perception.range"),
    ("[sensors]\nperception = {}", "sensors.perception"),
])
def test_bad_perception_table_names_file_and_field(extra, field):
    from experiments.config import config_from_dict

    with pytest.raises(InputError) as err:
        config_from_dict(arterial_config(extra), Path("/x/cfg.toml"))
    assert err.value.path == "/x/cfg.toml" and err.value.field == field


def test_perception_table_resolves_and_round_trips():
    from experiments.config import config_from_dict
    from experiments.config_toml import config_to_toml

    extra = ("[perception]\nocclusion_buildings = false\n[[perception.sensors]]\nname = 'front'\nfov_deg = 120.0\n"
             "[[perception.sensors]]\nname = 'around'\nfov_deg = 360.0\nrange_m = 30.0\nclutter_per_scan = 0.5\n"
             "[gnss_error]\ntau_s = 20.0\n")
    cfg = config_from_dict(arterial_config(extra), Path("/x/cfg.toml"))
    assert cfg.sensors.perception is cfg.perception and cfg.sensors.gnss_error is cfg.gnss_error
    assert [s.name for s in cfg.perception.sensors] == ["front", "around"]
    text = config_to_toml(cfg, {"git": "test"})
    again = config_from_dict(tomllib.loads(text), Path("/x/cfg.toml"))
    assert again.sensors == cfg.sensors
    plain = config_from_dict(arterial_config(""), Path("/x/cfg.toml"))
    assert plain.sensors == SensorParams() and "[perception]" not in config_to_toml(plain, {})


# --- buildings.geojson --------------------------------------------------------------------------


def _with_buildings(cross_net: Path, tmp_path: Path, doc) -> Path:
    folder = tmp_path / "net"
    shutil.copytree(cross_net, folder)
    (folder / "buildings.geojson").write_text(json.dumps(doc) if not isinstance(doc, str) else doc)
    return folder


def _feature(coords, **props):
    return {"type": "Feature", "properties": props, "geometry": {"type": "Polygon", "coordinates": [coords]}}


def test_buildings_file_is_read(cross_net, tmp_path):
    doc = {"type": "FeatureCollection", "features": [
        _feature([[20, 20], [60, 20], [60, 60], [20, 60], [20, 20]], height=25.0),
        _feature([[-60, 20], [-20, 20], [-20, 60], [-60, 60], [-60, 20]])]}
    net = load_net_folder(_with_buildings(cross_net, tmp_path, doc))
    assert len(net.buildings) == 2 and net.buildings.heights[0] == 25.0 and np.isnan(net.buildings.heights[1])
    assert load_net_folder(cross_net).buildings is None


@pytest.mark.parametrize("doc, field", [
    ("{not json", None),
    ({"type": "FeatureCollection", "features": [_feature([[0, 0], [10, 10], [10, 0], [0, 10], [0, 0]])]},
     "features[0].geometry"),  # self-intersecting bow tie
    ({"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
                                                 "geometry": {"type": "Point", "coordinates": [0, 0]}}]},
     "features[0].geometry"),
    ({"type": "FeatureCollection", "features": [_feature([[0, 0], [1, 0], [1, 1], [0, 0]], height=-3)]},
     "features[0].properties.height"),
    ({"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": "EPSG:4326"}}, "features": []}, "crs"),
])
def test_bad_buildings_file_names_file_and_field(cross_net, tmp_path, doc, field):
    folder = _with_buildings(cross_net, tmp_path, doc)
    with pytest.raises(InputError) as err:
        load_net_folder(folder)
    assert err.value.path.endswith("buildings.geojson") and err.value.field == field


def test_buildings_referenced_but_missing(cross_net, tmp_path):
    folder = tmp_path / "net"
    shutil.copytree(cross_net, folder)
    scen = (folder / "scenario.toml").read_text().replace("[files]\n", "[files]\nbuildings = \"blocks.geojson\"\n")
    (folder / "scenario.toml").write_text(scen)
    with pytest.raises(InputError) as err:
        load_net_folder(folder)
    assert err.value.path.endswith("scenario.toml") and err.value.field == "files.buildings"


def test_buildings_occlude_in_the_coupler(cross_net, tmp_path):
    """A wall along the east arm's north side hides the features behind it from every vehicle."""
    from couplers.sumo_coupler import SumoCoupler, SumoScenario

    net = load_net_folder(cross_net)
    feats = net.features.xy
    doc = {"type": "FeatureCollection", "features": [_feature([[10, 8], [390, 8], [390, 9], [10, 9], [10, 8]])]}
    walled = load_net_folder(_with_buildings(cross_net, tmp_path, doc))
    hidden = (feats[:, 1] > 9) & (feats[:, 0] > 60) & (feats[:, 0] < 340)
    spec = SensorSpec(name="s", fov_deg=360.0, range_m=40.0, pd_near=1.0, pd_far=1.0, clutter_per_scan=0.0)
    sens = SensorParams(perception=PerceptionParams(sensors=(spec,), occlusion_vehicles=False))

    def seen_from_arm(folder_net):
        seen = set()
        with SumoCoupler(SumoScenario(net=folder_net, control="tlr", seed=2, duration_s=90.0), sens) as c:
            for fr in c.frames():
                on_arm = (fr.truth.x_true[:, 1] < 8) & (fr.truth.x_true[:, 0] > 10)
                seen |= set(fr.truth.v2f_feature[on_arm[fr.v2f_owner]].tolist())
        return seen

    hidden_ids = set(np.flatnonzero(hidden).tolist())
    assert len(hidden_ids) >= 4
    assert hidden_ids <= seen_from_arm(net)  # without the wall they are seen
    assert not (hidden_ids & seen_from_arm(walled))


# --- end to end -----------------------------------------------------------------------------------


def test_arterial_with_perception_has_clutter_and_fewer_true_detections():
    """The runner's own frame source on experiments/arterial_tlr.toml, 90 s, with and without [perception]."""
    from experiments.config import config_from_dict
    from experiments.runner import frame_source

    def tally(extra):
        cfg = config_from_dict(arterial_config(extra), ROOT / "experiments" / "arterial_tlr.toml",
                               {"run.duration_s": 90.0, "run.methods": ["gnss"]})
        true_rows = clutter = steps = 0
        with frame_source(cfg) as src:
            for fr in src.frames():
                steps += 1
                f = fr.truth.v2f_feature
                true_rows += int((f >= 0).sum())
                clutter += int((f == -1).sum())
                assert fr.v2f_R.shape == (f.size, 4, 4) and fr.v2f_owner.size == f.size
                assert np.all(np.linalg.eigvalsh(fr.v2f_R) > 0)
        return steps, true_rows, clutter

    steps, ideal_true, ideal_clutter = tally("")
    steps_p, real_true, real_clutter = tally("[perception]\n")
    assert steps == steps_p == 120
    assert ideal_clutter == 0 and real_clutter > steps  # default: 1 per scan and sensor
    assert 0 < real_true < ideal_true


def test_range_bearing_frames_are_the_net_xy_world_in_the_sensor_frame(cross_net):
    """The SUMO coupler with detections = "range_bearing": the same rows (owners, truth, order) and every other
    measurement byte for byte as with "net_xy"; v2f_z / v2f_R NaN; the rows converted back with the true heading
    lie within a few sigma of the net_xy rows (both noisy: each its own draw of the same world)."""
    from dataclasses import replace as dc_replace

    from coloc.core.detections import to_net_frame
    from couplers.sumo_coupler import SumoCoupler, SumoScenario

    net = load_net_folder(cross_net)
    spec = SensorSpec(name="s", fov_deg=120.0, range_m=40.0, mount_x_m=-1.0, clutter_per_scan=0.5)
    per = PerceptionParams(sensors=(spec,), occlusion_vehicles=True)

    def frames(kind):
        sens = SensorParams(perception=dc_replace(per, detections=kind))
        with SumoCoupler(SumoScenario(net=net, control="tlr", seed=4, duration_s=60.0), sens) as c:
            return list(c.frames())

    xy, rb = frames("net_xy"), frames("range_bearing")
    assert len(xy) == len(rb)
    rows = 0
    for a, b in zip(xy, rb):
        assert a.v2f_sensor is None and b.v2f_sensor is not None
        for f in ("gnss_z", "prior_z", "accel", "v2f_owner"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
        np.testing.assert_array_equal(a.truth.v2f_feature, b.truth.v2f_feature)
        assert np.isnan(b.v2f_z).all() and np.isnan(b.v2f_R).all()
        if not b.v2f_owner.size:
            continue
        psi = b.truth.heading[b.v2f_owner]
        z, R = to_net_frame(b.v2f_sensor, psi, np.zeros(psi.size))
        d = z[:, :2] - a.v2f_z[:, :2]
        m2 = np.einsum("oi,oij,oj->o", d, np.linalg.inv(R[:, :2, :2] + a.v2f_R[:, :2, :2]), d)
        assert (m2 < 40.0).all()  # chi-square 2 dof: P(> 40) ~ 2e-9
        rows += b.v2f_owner.size
    assert rows > 50


def test_lever_arm_frames_change_only_the_range_rates_of_turning_vehicles(cross_net):
    """The SUMO coupler with lever_arm_range_rate: the same frames as without (range, bearing, every other array
    byte for byte) but for the range rates, which differ exactly by the mount point's motion omega mount_x
    u_perp(psi) projected on the line of sight, omega the heading's change over the step from the frames'
    truth (0 on entry), up to the bearing noise; the rows come as MountSensorDetections."""
    from dataclasses import replace as dc_replace

    from coloc.core.detections import MountSensorDetections
    from couplers.sumo_coupler import SumoCoupler, SumoScenario

    net = load_net_folder(cross_net)
    spec = SensorSpec(name="s", fov_deg=120.0, range_m=40.0, mount_x_m=2.25, clutter_per_scan=0.5)
    per = PerceptionParams(sensors=(spec,), occlusion_vehicles=True, detections="range_bearing")

    def frames(on):
        sens = SensorParams(perception=dc_replace(per, lever_arm_range_rate=on))
        with SumoCoupler(SumoScenario(net=net, control="tlr", seed=4, duration_s=90.0), sens) as c:
            return list(c.frames())

    off, on = frames(False), frames(True)
    prev = {}
    turning = 0
    for a, b in zip(off, on):
        assert type(b.v2f_sensor) is MountSensorDetections and type(a.v2f_sensor) is not MountSensorDetections
        np.testing.assert_array_equal(a.v2f_sensor.range, b.v2f_sensor.range)
        np.testing.assert_array_equal(a.v2f_sensor.bearing, b.v2f_sensor.bearing)
        np.testing.assert_array_equal(a.gnss_z, b.gnss_z)
        psi = b.truth.heading
        ids = list(b.vehicle_ids)
        om = np.array([0.0 if (b.entered[i] or v not in prev) else
                       ((psi[i] - prev[v] + np.pi) % (2 * np.pi) - np.pi) / b.dt for i, v in enumerate(ids)])
        prev = dict(zip(ids, psi))
        o = b.v2f_owner
        phi = psi[o] + b.v2f_sensor.yaw + b.v2f_sensor.bearing
        # the mount point's velocity omega m u_perp(psi) along the line of sight u(phi): omega m sin(phi - psi)
        want = -om[o] * 2.25 * np.sin(phi - psi[o])
        # the line of sight from the reported (noisy) bearing: off by sigma_b ~ 0.005 rad, so 2 % of omega m
        err = np.abs(b.v2f_sensor.range_rate - a.v2f_sensor.range_rate - want)
        assert (err <= 0.02 * np.abs(om[o] * 2.25) + 1e-12).all()
        turning += int((np.abs(want) > 0.01).sum())
    assert turning > 10
