"""Realistic V2X, coupler side (couplers.sensing.v2x, coloc.core.v2x): penetration against the
configured rate and nested across rates, delivery ratio per distance against the configured curve,
the NLOS curve exactly for links through buildings, directed losses, determinism, the [v2x] table,
and the coupler with and without it."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binomtest, norm
from shapely.affinity import rotate
from shapely.geometry import LineString, box

from coloc.core.v2x import V2xFrame, deliveries, directed_links, round_deliveries
from couplers.errors import InputError
from couplers.net.buildings import Buildings
from couplers.net.folder import load_net_folder
from couplers.sensing.perception import PerceptionParams, SensorSpec
from couplers.sensing.sensors import SensorParams, neighbor_graph
from couplers.sensing.v2x import (
    DEFAULT_PDR_DISTANCE_M,
    DEFAULT_PDR_LOS,
    DEFAULT_PDR_NLOS,
    V2xChannel,
    V2xParams,
    delivery_probability,
    derived_pdr,
    equipped,
    link_nlos,
)
from netfixture import arterial_config

ROOT = Path(__file__).resolve().parents[2]
ALPHA = 1e-3  # two-sided 0.1 % level of every statistical test here

# A table whose LOS and NLOS curves differ everywhere inside 300 m (so a link's curve is identifiable).
TABLE = V2xParams(pdr_distance_m=(0.0, 100.0, 200.0, 300.0), pdr_los=(0.95, 0.8, 0.5, 0.3),
                  pdr_nlos=(0.7, 0.4, 0.1, 0.0))


def _ids(n: int, prefix: str = "flow") -> np.ndarray:
    return np.array([f"{prefix}{k // 7}.{k}" for k in range(n)], dtype=object)


# --- penetration ----------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [1, 7])
@pytest.mark.parametrize("rate", [0.05, 0.1, 0.25, 0.5, 0.75])
def test_equipped_share_matches_the_rate(seed, rate):
    ids = _ids(20000)
    k = int(equipped(ids, seed, rate).sum())
    assert binomtest(k, ids.size, rate).pvalue > ALPHA, (k, ids.size, rate)


def test_equipped_sets_are_nested_across_rates_and_differ_across_seeds():
    ids = _ids(5000)
    rates = (0.05, 0.1, 0.25, 0.5, 0.75, 1.0)
    sets = [equipped(ids, 3, r) for r in rates]
    for low, high in zip(sets, sets[1:]):
        assert np.all(high[low]) and high.sum() > low.sum()
    assert sets[-1].all()
    other = equipped(ids, 4, 0.5)
    assert 0.4 < np.mean(other == sets[3]) < 0.6  # another seed: an independent draw


def test_channel_caches_equipment_per_vehicle_across_steps():
    ids = _ids(400)
    ch = V2xChannel(V2xParams(penetration_rate=0.3), seed=5)
    want = dict(zip(ids, equipped(ids, 5, 0.3)))
    rng = np.random.default_rng(0)
    for _ in range(30):  # vehicles come and go, in any order
        present = ids[np.sort(rng.choice(ids.size, 120, replace=False))]
        rng.shuffle(present)
        np.testing.assert_array_equal(ch.equipped(present), [want[v] for v in present])


# --- link model -----------------------------------------------------------------------------------


def test_default_table_is_the_stated_derivation():
    d = np.array(DEFAULT_PDR_DISTANCE_M)
    np.testing.assert_array_equal(np.round(derived_pdr(d, True), 3), DEFAULT_PDR_LOS)
    np.testing.assert_array_equal(np.round(derived_pdr(d, False), 3), DEFAULT_PDR_NLOS)
    V2xParams()  # the defaults pass their own validation (non-increasing, in [0, 1])


def test_delivery_probability_interpolates_and_is_zero_beyond_the_table():
    d = np.array([0.0, 50.0, 100.0, 250.0, 300.0, 300.0001, 1e4])
    np.testing.assert_allclose(delivery_probability(d, np.zeros(d.size, bool), TABLE),
                               [0.95, 0.875, 0.8, 0.4, 0.3, 0.0, 0.0])
    np.testing.assert_allclose(delivery_probability(d, np.ones(d.size, bool), TABLE),
                               [0.7, 0.55, 0.4, 0.05, 0.0, 0.0, 0.0])


def _pairs_at(distances: np.ndarray) -> np.ndarray:
    """Two vehicles per distance, each pair 10 km from the others (one V2V link per pair)."""
    xy = np.zeros((2 * distances.size, 2))
    xy[0::2, 1] = xy[1::2, 1] = 1e4 * np.arange(distances.size)
    xy[1::2, 0] = distances
    return xy


def test_empirical_delivery_per_distance_matches_the_curve():
    """Links at fixed distances (table points and points in between), 2000 rounds, both directions:
    4000 packets per distance, binomial test against the interpolated curve at 0.1 %."""
    dist = np.array([10.0, 60.0, 100.0, 150.0, 199.0, 240.0, 290.0])
    xy = _pairs_at(dist)
    nb = neighbor_graph(xy, 400.0)
    ch = V2xChannel(TABLE, seed=11)
    v2x = ch.frame(xy, nb)
    src, dst = directed_links(nb)
    pair = np.minimum(src, dst) // 2
    want = delivery_probability(dist, np.zeros(dist.size, bool), TABLE)
    np.testing.assert_allclose(v2x.delivery_prob, want[pair])
    got = deliveries(v2x, 0, 2000)
    for k, p in enumerate(want):
        hits = got[:, pair == k]
        assert binomtest(int(hits.sum()), hits.size, p).pvalue > ALPHA, (dist[k], hits.mean(), p)


def test_empirical_delivery_per_distance_bin_on_a_random_scene():
    """A random geometric graph under the default curve: per 25 m bin, the delivered count over 300
    rounds against its Poisson-binomial mean and variance (normal approximation, two-sided 0.1 %)."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 600, (150, 2))
    nb = neighbor_graph(xy, 250.0)
    v2x = V2xChannel(V2xParams(), seed=2).frame(xy, nb)
    src, dst = directed_links(nb)
    d = np.hypot(*(xy[src] - xy[dst]).T)
    got = deliveries(v2x, 0, 300)
    p = v2x.delivery_prob
    for lo in range(0, 250, 25):
        m = (d >= lo) & (d < lo + 25)
        assert m.sum() > 20
        mean = 300 * p[m].sum()
        var = 300 * (p[m] * (1 - p[m])).sum()
        z = (got[:, m].sum() - mean) / np.sqrt(max(var, 1e-12))
        assert 2 * norm.sf(abs(z)) > ALPHA or var < 1e-6 and got[:, m].sum() == round(mean), (lo, z)


def _random_buildings(rng, size: float, count: int) -> Buildings:
    blds = []
    for _ in range(count):
        cx, cy = rng.uniform(0, size, 2)
        w, h = rng.uniform(5, 40, 2)
        blds.append(rotate(box(cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2), rng.uniform(0, 90)))
    return Buildings.from_polygons(blds)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nlos_curve_exactly_for_links_through_buildings(seed):
    """Random scenes: the link flags against a brute-force shapely check per link, and each link's
    probability from the NLOS curve exactly where flagged."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 300, (80, 2))
    blds = _random_buildings(rng, 300, 12)
    nb = neighbor_graph(xy, 200.0)
    src, dst = directed_links(nb)
    brute = np.array([any(LineString([xy[j], xy[i]]).intersects(g) for g in blds.polygons)
                      for j, i in zip(src, dst)])
    flags = link_nlos(xy, nb, blds)
    np.testing.assert_array_equal(flags, brute)
    assert 0.1 < flags.mean() < 0.9  # both kinds occur
    v2x = V2xChannel(TABLE, seed=seed, buildings=blds).frame(xy, nb)
    d = np.hypot(*(xy[src] - xy[dst]).T)
    los = np.interp(d, TABLE.pdr_distance_m, TABLE.pdr_los, right=0.0)
    nlos = np.interp(d, TABLE.pdr_distance_m, TABLE.pdr_nlos, right=0.0)
    np.testing.assert_array_equal(v2x.delivery_prob, np.where(brute, nlos, los))
    # No buildings (or an empty file): every link is LOS.
    assert not link_nlos(xy, nb, None).any()
    assert not link_nlos(xy, nb, Buildings.from_polygons([])).any()


def test_losses_are_directed_and_independent():
    """i hears j while j misses i in the same round: as often as 2 p (1 - p) predicts."""
    dist = np.full(200, 150.0)  # p = 0.65 under TABLE
    xy = _pairs_at(dist)
    nb = neighbor_graph(xy, 400.0)
    v2x = V2xChannel(TABLE, seed=4).frame(xy, nb)
    src, dst = directed_links(nb)
    got = deliveries(v2x, 0, 50)
    fwd = got[:, src < dst]  # CSR order: the pair's two entries in the same pair order
    back = got[:, src > dst]
    assert np.all(np.minimum(src, dst)[src < dst] == np.minimum(src, dst)[src > dst])
    one_way = fwd != back
    p = 0.65
    assert binomtest(int(one_way.sum()), one_way.size, 2 * p * (1 - p)).pvalue > ALPHA


def test_same_seed_same_bytes_and_rounds_are_fixed_by_index():
    rng = np.random.default_rng(8)
    scenes = [rng.uniform(0, 400, (60, 2)) for _ in range(5)]
    blds = _random_buildings(rng, 400, 8)

    def run(seed):
        ch = V2xChannel(V2xParams(rounds_per_step=7), seed=seed, buildings=blds)
        out = []
        for xy in scenes:
            nb = neighbor_graph(xy, 250.0)
            v = ch.frame(xy, nb)
            out.append((v.delivery_prob.tobytes(), v.seed, deliveries(v, 0, 7).tobytes()))
        return out

    a, b, c = run(1), run(1), run(2)
    assert a == b
    assert [x[1] for x in a] != [x[1] for x in c]
    assert len({x[1] for x in a}) == len(scenes)  # one seed per step
    v = V2xFrame(delivery_prob=np.full(500, 0.5), rounds_per_step=3, seed=123)
    r2 = round_deliveries(v, 2)
    np.testing.assert_array_equal(r2, round_deliveries(v, 2))  # any caller, any order: same round
    np.testing.assert_array_equal(deliveries(v, 1, 3)[1], r2)
    assert (r2 != round_deliveries(v, 3)).any()
    assert v.rounds_available(20) == 3 and V2xFrame(np.empty(0), 0, 1).rounds_available(20) == 20


def test_v2x_frame_refuses_bad_values():
    for kwargs in (dict(delivery_prob=np.array([1.2]), rounds_per_step=0, seed=1),
                   dict(delivery_prob=np.array([0.5]), rounds_per_step=-1, seed=1),
                   dict(delivery_prob=np.array([0.5]), rounds_per_step=0, seed=-3)):
        with pytest.raises(ValueError):
            V2xFrame(**kwargs)
    with pytest.raises(ValueError):
        round_deliveries(V2xFrame(np.array([0.5]), 0, 1), -1)


# --- the [v2x] table ------------------------------------------------------------------------------


@pytest.mark.parametrize("kwargs, field", [
    (dict(penetration_rate=0.0), "penetration_rate"),
    (dict(penetration_rate=1.01), "penetration_rate"),
    (dict(pdr_distance_m=(0.0, 50.0, 50.0), pdr_los=(1, 1, 1), pdr_nlos=(1, 1, 1)), "pdr_distance_m[2]"),
    (dict(pdr_distance_m=(-1.0, 50.0), pdr_los=(1, 1), pdr_nlos=(1, 1)), "pdr_distance_m[0]"),
    (dict(pdr_distance_m=(0.0, 50.0), pdr_los=(0.5, 0.9), pdr_nlos=(1, 1)), "pdr_los[1]"),
    (dict(pdr_distance_m=(0.0, 50.0), pdr_los=(1.0, 0.9), pdr_nlos=(1.5, 0.2)), "pdr_nlos[0]"),
    (dict(pdr_distance_m=(0.0, 50.0), pdr_los=(1.0,), pdr_nlos=(1, 1)), "pdr_los"),
    (dict(pdr_distance_m=(), pdr_los=(), pdr_nlos=()), "pdr_distance_m"),
    (dict(rounds_per_step=-1), "rounds_per_step"),
    (dict(rounds_per_step=2.5), "rounds_per_step"),
    (dict(rounds_per_step=0), "rounds_per_step"),
    (dict(rounds_per_step="infinite"), "rounds_per_step"),
    (dict(channel="perfect"), "channel"),
])
def test_bad_v2x_parameters_name_the_field(kwargs, field):
    with pytest.raises(InputError) as err:
        V2xParams(**kwargs)
    assert err.value.field == field


@pytest.mark.parametrize("extra, field", [
    ("[v2x]\npenetration_rate = 0.0", "v2x.penetration_rate"),
    ("[v2x]\npdr_distance_m = [0.0, 100.0]\npdr_los = [0.5, 0.6]\npdr_nlos = [0.5, 0.1]", "v2x.pdr_los[1]"),
    ("[v2x]\npdr_distance_m = [0.0, 100.0]\npdr_los = [1.0, 0.6]\npdr_nlos = [0.5]", "v2x.pdr_nlos"),
    ("[v2x]\nrounds_per_step = 2.5", "v2x.rounds_per_step"),
    ("[v2x]\nrounds_per_step = -2", "v2x.rounds_per_step"),
    ("[v2x]\nrounds_per_step = 0", "v2x.rounds_per_step"),
    ("[v2x]\nrounds_per_step = true", "v2x.rounds_per_step"),
    ("[v2x]\nrange = 3", "v2x.range"),
    ("[sensors]\nv2x = {}", "sensors.v2x"),
    ("[v2x]\n[infra]\nrsu_junctions = ['J1']", "v2x"),
])
def test_bad_v2x_table_names_file_and_field(extra, field):
    from experiments.config import config_from_dict

    with pytest.raises(InputError) as err:
        config_from_dict(arterial_config(extra), Path("/x/cfg.toml"))
    assert err.value.path == "/x/cfg.toml" and err.value.field == field


def test_v2x_refused_for_the_controlled_scenarios():
    from experiments.config import config_from_dict

    data = tomllib.loads((ROOT / "experiments" / "crossroad.toml").read_text())
    data["v2x"] = {"penetration_rate": 0.5}
    with pytest.raises(InputError) as err:
        config_from_dict(data, Path("/x/crossroad.toml"))
    assert err.value.field == "v2x" and "sumo" in err.value.message


def test_v2x_table_resolves_and_round_trips():
    from experiments.config import config_from_dict
    from experiments.config_toml import config_to_toml

    cfg = config_from_dict(arterial_config("[v2x]\npenetration_rate = 0.25\nrounds_per_step = 10\n"), Path("/x/cfg.toml"))
    assert cfg.sensors.v2x is cfg.v2x and cfg.v2x.penetration_rate == 0.25 and cfg.v2x.rounds_per_step == 10
    text = config_to_toml(cfg, {"git": "test"})
    again = config_from_dict(tomllib.loads(text), Path("/x/cfg.toml"))
    assert again.sensors == cfg.sensors
    plain = config_from_dict(arterial_config(""), Path("/x/cfg.toml"))
    assert plain.sensors.v2x is None and "[v2x]" not in config_to_toml(plain, {})


# --- the coupler ----------------------------------------------------------------------------------


def _frames(net, sensors, seed=2, duration=90.0):
    from couplers.sumo_coupler import SumoCoupler, SumoScenario

    with SumoCoupler(SumoScenario(net=net, control="tlr", seed=seed, duration_s=duration), sensors) as c:
        frames = list(c.frames())
    return frames, c


def _same_frame(a, b):
    for name in ("t", "dt", "vehicle_ids", "entered", "prior_z", "prior_R", "accel", "gnss_z", "gnss_R", "v2f_z",
                 "v2f_owner", "v2f_R"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert (a.neighbors != b.neighbors).nnz == 0
    np.testing.assert_array_equal(a.truth.x_true, b.truth.x_true)
    np.testing.assert_array_equal(a.truth.v2f_feature, b.truth.v2f_feature)


def test_full_penetration_changes_nothing_but_adds_the_channel(cross_net):
    """[v2x] at penetration 1: every other field of every frame identical to a run without the table
    (new streams only), with [perception] and [gnss_error] too."""
    from couplers.sensing.gnss_error import GnssErrorParams

    net = load_net_folder(cross_net)
    base = SensorParams(perception=PerceptionParams(), gnss_error=GnssErrorParams())
    plain, _ = _frames(net, base)
    with_v2x, _ = _frames(net, SensorParams(perception=PerceptionParams(), gnss_error=GnssErrorParams(),
                                            v2x=V2xParams(rounds_per_step=5)))
    assert len(plain) == len(with_v2x) == 120
    links = 0
    for a, b in zip(plain, with_v2x):
        _same_frame(a, b)
        assert a.v2x is None and b.v2x.rounds_per_step == 5
        assert b.v2x.delivery_prob.shape == (b.neighbors.nnz,)
        links += b.neighbors.nnz
    assert links > 100


def test_unequipped_vehicles_leave_the_frame_but_occlude_and_count_in_traffic(cross_net, monkeypatch):
    import couplers.sumo_coupler as sc
    import libsumo

    seen = {}
    real = sc.perceive

    def spy(**kw):
        seen.setdefault("calls", []).append((len(libsumo.vehicle.getIDList()), kw["occluder_corners"].shape[0],
                                             kw["x_true"].shape[0], kw["observer_occluder"].copy()))
        return real(**kw)

    monkeypatch.setattr(sc, "perceive", spy)
    net = load_net_folder(cross_net)
    spec = SensorSpec(name="s", fov_deg=360.0, range_m=40.0)
    frames, c = _frames(net, SensorParams(perception=PerceptionParams(sensors=(spec,)),
                                          v2x=V2xParams(penetration_rate=0.4)), duration=150.0)
    all_frames, c_all = _frames(net, SensorParams(), duration=150.0)
    ids_all = set().union(*(set(f.vehicle_ids) for f in all_frames))
    ids_eq = set().union(*(set(f.vehicle_ids) for f in frames))
    assert ids_eq < ids_all
    want = equipped(np.array(sorted(ids_all), dtype=object), 2, 0.4)
    assert ids_eq == {v for v, e in zip(sorted(ids_all), want) if e}
    assert c.traffic.stats.rows == c_all.traffic.stats.rows  # SUMO's statistics: every vehicle
    for fr, fa in zip(frames, all_frames):
        assert set(fr.vehicle_ids) <= set(fa.vehicle_ids)
        assert fr.neighbors.shape == (fr.n_vehicles, fr.n_vehicles) and fr.v2x.n_links == fr.neighbors.nnz
    # Every SUMO vehicle is an occluder; the observers are the equipped ones, mapped to their footprints.
    assert any(n_road > n_obs for n_road, _, n_obs, _ in seen["calls"])
    for n_road, n_corners, n_obs, obs in seen["calls"]:
        assert n_corners == n_road and obs.size == n_obs and np.all(obs >= 0) and np.unique(obs).size == n_obs


def test_arterial_quarter_penetration_end_to_end():
    """The runner's frame source on experiments/arterial_tlr.toml, 60 s, [v2x] penetration 0.25: about
    a quarter of the vehicles in the frames (binomial over the distinct vehicles)."""
    from experiments.config import config_from_dict
    from experiments.runner import frame_source

    def ids(extra):
        cfg = config_from_dict(arterial_config(extra), ROOT / "experiments" / "arterial_tlr.toml",
                               {"run.duration_s": 60.0, "run.methods": ["gnss"]})
        out = set()
        with frame_source(cfg) as src:
            for fr in src.frames():
                out |= set(fr.vehicle_ids)
                assert (fr.v2x is None) == (extra == "")
        return out

    every, quarter = ids(""), ids("[v2x]\npenetration_rate = 0.25\n")
    assert quarter < every and len(every) > 40
    assert binomtest(len(quarter), len(every), 0.25).pvalue > ALPHA


def test_ideal_channel_delivers_every_link_every_round(cross_net):
    """channel = "ideal": delivery probability 1 on every link, every round delivers;
    every other field as with the curves."""
    net = load_net_folder(cross_net)
    curves, _ = _frames(net, SensorParams(v2x=V2xParams(penetration_rate=0.5)))
    ideal, _ = _frames(net, SensorParams(v2x=V2xParams(penetration_rate=0.5, channel="ideal")))
    links = 0
    for a, b in zip(curves, ideal):
        _same_frame(a, b)
        assert (b.v2x.delivery_prob == 1.0).all() and b.v2x.seed == a.v2x.seed
        assert round_deliveries(b.v2x, 3).all()
        links += b.neighbors.nnz
    assert links > 100


def test_unlimited_rounds_is_the_default_and_the_frame_carries_zero():
    assert V2xParams().rounds_per_step == "unlimited" and V2xParams().round_budget == 0
    assert V2xParams(rounds_per_step=4).round_budget == 4
