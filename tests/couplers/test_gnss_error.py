"""Realistic GNSS error (couplers.sensing.gnss_error): Gauss-Markov statistics per zone,
white noise at tau = 0, NLOS episodes, building density, bad parameters, and the coupler."""

import math

import numpy as np
import pytest
from shapely.geometry import box

from couplers.errors import InputError
from couplers.sensing.gnss_error import (
    GnssErrorParams,
    GnssErrorProcess,
    building_density_grid,
    episode_start_probability,
    gauss_markov_coefficient,
)
from couplers.net.buildings import Buildings
from couplers.net.folder import load_net_folder
from couplers.sensing.sensors import SensorParams
from couplers.sumo_coupler import SumoCoupler, SumoScenario

NO_NLOS = dict(nlos_zones=(), nlos_rate_per_min=())


def _run(params, n=400, steps=3000, dt=0.75, seed=1, zone_of=None, sp_of=None, xy=None):
    """Errors (steps, n, 2) of ``n`` vehicles present throughout; zone_of(k) -> (n,) zone names."""
    proc = GnssErrorProcess(params, seed, dt)
    rng = np.random.default_rng(seed + 100)
    ids = np.array([f"v{i}" for i in range(n)], dtype=object)
    entered = np.ones(n, bool)
    out = np.empty((steps, n, 2))
    xy = np.zeros((n, 2)) if xy is None else xy
    for k in range(steps):
        zone = zone_of(k)
        out[k] = proc.step(k * dt, ids, entered, rng.standard_normal((n, 2)), sp_of(zone), zone, xy)
        entered = np.zeros(n, bool)
    return out


SP = {"A": 3.0, "C": 15.0}


def _sp(zone):
    return np.array([SP[z] for z in zone])


@pytest.mark.parametrize("switching", [False, True])
def test_gauss_markov_autocorrelation_at_tau_and_stationary_std_per_zone(switching):
    """Half the vehicles in zone A (3 m), half in C (15 m); with ``switching`` every vehicle changes
    zone every 20 steps (the normalised state carries on, the error is rescaled)."""
    tau, dt, n, steps = 30.0, 0.75, 400, 3000
    base = np.array(["A", "C"] * (n // 2), dtype=object)
    flip = {"A": "C", "C": "A"}

    def zone_of(k):
        if switching and (k // 20) % 2:
            return np.array([flip[z] for z in base], dtype=object)
        return base

    e = _run(GnssErrorParams(tau_s=tau, **NO_NLOS), n=n, steps=steps, dt=dt, zone_of=zone_of, sp_of=_sp)
    zones = np.stack([zone_of(k) for k in range(steps)])
    u = e / _sp(zones.ravel()).reshape(steps, n)[:, :, None]
    lag = int(round(tau / dt))
    rho = float((u[lag:] * u[:-lag]).mean() / (u * u).mean())
    # Effective samples ~ n * 2 axes * steps / (2 tau / dt) = 24000: standard error ~0.007.
    assert rho == pytest.approx(math.exp(-1.0), abs=0.03)
    assert gauss_markov_coefficient(dt, tau) ** lag == pytest.approx(math.exp(-1.0), rel=1e-12)
    for z, sp in SP.items():
        sel = zones == z
        std = float(np.sqrt((e[sel] ** 2).mean()))
        assert std == pytest.approx(sp, rel=0.04)


def test_tau_zero_is_white_noise_exactly():
    n, steps = 20, 50
    rng = np.random.default_rng(3)
    proc = GnssErrorProcess(GnssErrorParams(tau_s=0.0, **NO_NLOS), 1, 0.75)
    ids = np.array([f"v{i}" for i in range(n)], dtype=object)
    sp = rng.uniform(3, 15, n)
    for k in range(steps):
        w = rng.standard_normal((n, 2))
        np.testing.assert_array_equal(proc.step(k * 0.75, ids, np.zeros(n, bool), w, sp, np.full(n, "C"), np.zeros((n, 2))),
                                      sp[:, None] * w)


def test_nlos_episodes_time_share_and_bias_magnitude():
    """Zone C at 1 start / min, mean duration 10 s: alternating renewal, biased share
    10 / (60 + 10) (up to the step discretisation); mean bias magnitude = nlos_bias_mean_m."""
    params = GnssErrorParams(tau_s=0.0, nlos_zones=("C",), nlos_rate_per_min=(1.0,), nlos_mean_duration_s=10.0,
                             nlos_bias_mean_m=10.0)
    n, steps, dt = 300, 4000, 0.75
    proc = GnssErrorProcess(params, 4, dt)
    ids = np.array([f"v{i}" for i in range(n)], dtype=object)
    zone = np.array(["C"] * (n // 2) + ["A"] * (n // 2), dtype=object)
    w = np.zeros((n, 2))
    biased = np.zeros(n)
    mags = []
    prev = np.zeros(n, bool)
    for k in range(steps):
        e = proc.step(k * dt, ids, np.zeros(n, bool) if k else np.ones(n, bool), w, np.ones(n), zone, np.zeros((n, 2)))
        on = proc.in_episode
        biased += on
        mags.append(np.hypot(e[on & ~prev, 0], e[on & ~prev, 1]))
        prev = on
    share_c = biased[: n // 2].sum() / (steps * n / 2)
    # Off: a start may come at the step an episode ends, so geometric on {0, 1, ...} steps of
    # p = 1 - exp(-dt / 60 s); on: ceil(X / dt) steps, X ~ Exp(10 s).
    p = float(episode_start_probability(1.0, dt))
    mean_off = dt * (1 - p) / p
    mean_on = dt / (1 - math.exp(-dt / 10.0))  # E[ceil(X / dt)] dt for X ~ Exp(10)
    assert share_c == pytest.approx(mean_on / (mean_on + mean_off), rel=0.06)
    assert biased[n // 2:].sum() == 0  # zone A has no episodes
    m = np.concatenate(mags)
    assert m.size > 1000 and m.mean() == pytest.approx(10.0, rel=0.08)


def test_building_density_drives_episode_rates():
    blds = Buildings.from_polygons([box(0, 0, 200, 200)])
    grid = building_density_grid(blds, radius_m=50.0)
    d = grid.at(np.array([[100.0, 100.0], [-100.0, 100.0], [0.0, 100.0]]))
    assert d[0] == pytest.approx(1.0, abs=0.02) and d[1] == 0.0 and d[2] == pytest.approx(0.5, abs=0.05)
    proc = GnssErrorProcess(GnssErrorParams(nlos_rate_per_density_per_min=3.0), 1, 0.75, buildings=blds)
    rates = proc.start_rates(np.array(["A", "A", "A"]), np.array([[100.0, 100.0], [-100.0, 100.0], [0.0, 100.0]]))
    np.testing.assert_allclose(rates, 3.0 * d)


@pytest.mark.parametrize("kwargs, field", [
    (dict(tau_s=-1.0), "tau_s"), (dict(tau_s=float("inf")), "tau_s"),
    (dict(nlos_zones=("C",), nlos_rate_per_min=(-0.5,)), "nlos_rate_per_min[0]"),
    (dict(nlos_zones=("C",), nlos_rate_per_min=(1.0, 2.0)), "nlos_rate_per_min"),
    (dict(nlos_mean_duration_s=0.0), "nlos_mean_duration_s"), (dict(nlos_bias_mean_m=-1.0), "nlos_bias_mean_m"),
    (dict(nlos_rate_per_density_per_min=-1.0), "nlos_rate_per_density_per_min"),
])
def test_bad_parameters_name_the_field(kwargs, field):
    with pytest.raises(InputError) as err:
        GnssErrorParams(**kwargs)
    assert err.value.field == field


def test_bad_gnss_error_table_names_file_and_field():
    import tomllib
    from pathlib import Path

    from experiments.config import config_from_dict

    root = Path(__file__).resolve().parents[2]
    data = tomllib.loads((root / "experiments" / "arterial_tlr.toml").read_text())
    data["scenario"]["net_dir"] = str(root / "sumo_nets" / "arterial")
    data["gnss_error"] = {"tau_s": -2.0}
    with pytest.raises(InputError) as err:
        config_from_dict(data, Path("/x/cfg.toml"))
    assert (err.value.path, err.value.field) == ("/x/cfg.toml", "gnss_error.tau_s")


def test_coupler_tau_zero_equals_idealised_frames_and_keeps_nominal_R(cross_net):
    """tau_s = 0 without episodes: GNSS measurements equal to the idealised coupler's, byte for byte;
    with tau_s = 30 s the measurement differs but gnss_R is still the zone's nominal covariance."""
    net = load_net_folder(cross_net)

    def frames(sens):
        with SumoCoupler(SumoScenario(net=net, control="tlr", seed=5, duration_s=60.0), sens) as c:
            return [(fr.gnss_z.copy(), fr.gnss_R.copy(), fr.v2f_z.copy(), fr.accel.copy()) for fr in c.frames()]

    ideal = frames(SensorParams())
    white = frames(SensorParams(gnss_error=GnssErrorParams(tau_s=0.0, **NO_NLOS)))
    gm = frames(SensorParams(gnss_error=GnssErrorParams(tau_s=30.0)))
    assert len(ideal) == len(white) == len(gm) == 80
    for a, b, c in zip(ideal, white, gm):
        for x, y in zip(a, b):
            assert x.tobytes() == y.tobytes()
        np.testing.assert_array_equal(a[1], c[1])  # nominal R
        np.testing.assert_array_equal(a[0][:, 2:], c[0][:, 2:])  # velocity error: the same white draws
        np.testing.assert_array_equal(a[2], c[2])  # V2F and inertial streams untouched
        np.testing.assert_array_equal(a[3], c[3])
    assert any(not np.array_equal(a[0], c[0]) for a, c in zip(ideal, gm) if a[0].size)


@pytest.mark.parametrize("with_buildings", [False, True])
@pytest.mark.parametrize("bias_mean_m", [10.0, 0.0])
def test_step_kernels_equal_the_numpy_reference(with_buildings, bias_mean_m):
    """GnssErrorProcess.step (episode draws in numba, couplers.sensing.streams) against step_reference (numpy
    draws), byte for byte, with vehicles entering and leaving, episodes starting and ending, with the start
    probability per zone and per building-density cell; every stream left in the same state."""
    blds = Buildings.from_polygons([box(0, 0, 200, 200), box(300, 0, 340, 80)]) if with_buildings else None
    params = GnssErrorParams(tau_s=20.0, nlos_zones=("C",), nlos_rate_per_min=(6.0,), nlos_mean_duration_s=5.0,
                             nlos_bias_mean_m=bias_mean_m, nlos_rate_per_density_per_min=12.0)
    fused, ref = (GnssErrorProcess(params, 7, 0.75, buildings=blds) for _ in range(2))
    rng = np.random.default_rng(21)
    pool = np.array([f"v{i}" for i in range(60)], dtype=object)
    present = rng.random(60) < 0.7
    running = 0
    for k in range(300):
        leave, come = rng.random(60) < 0.03, rng.random(60) < 0.05
        entered = come & ~present
        present = (present & ~leave) | come
        ids = pool[present]
        n = ids.size
        zone = np.where(rng.random(n) < 0.5, "C", "A").astype(object)
        xy = rng.uniform(-50, 400, (n, 2))
        w = rng.standard_normal((n, 2))
        got = fused.step(k * 0.75, ids, entered[present], w, _sp(zone), zone, xy)
        want = ref.step_reference(k * 0.75, ids, entered[present], w, _sp(zone), zone, xy)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(fused.in_episode, ref.in_episode)
        np.testing.assert_array_equal(fused._end, ref._end)
        running += int(np.isfinite(ref._end).sum())
    assert running > 100  # vehicle-steps inside an episode
    for name in GnssErrorProcess.STREAMS:
        assert getattr(fused, name).random() == getattr(ref, name).random()
