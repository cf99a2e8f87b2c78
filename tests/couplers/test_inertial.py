"""Realistic inertial input (couplers.sensing.inertial): the body-frame IMU against the
net-frame input, its discretisation in turns, the bias statistics, seeding, and the coupler (other
streams untouched)."""

import math

import numpy as np
import pytest
from scipy import stats

from coloc.core.inertial import rotate, wrap_angle
from couplers.errors import InputError
from couplers.sensing.inertial import InertialParams, InertialProcess, gauss_markov_bias, true_body_motion
from couplers.net.folder import load_net_folder
from couplers.sensing.sensors import SensorParams
from couplers.sumo_coupler import SumoCoupler, SumoScenario

PERFECT = InertialParams(accel_noise_density=0.0, accel_bias_sigma=0.0, accel_turn_on_sigma=0.0,
                         gyro_noise_density=0.0, gyro_bias_sigma=0.0, gyro_turn_on_sigma=0.0)
#: Two-sided level of the statistical tests: 0.1 % (a seeded test; the level says how unlikely a
#: false failure would be for another seed).
ALPHA = 1e-3
RAD = math.pi / 180.0


def _run(params, headings, accel_net, dt=0.75, seed=1):
    """IMU frames of vehicles with ``headings`` (K, N) and net-frame accelerations (K, N, 2) (all enter at step 0)."""
    proc = InertialProcess(params, seed, dt)
    k, n = headings.shape
    ids = np.array([f"v{i}" for i in range(n)], dtype=object)
    out = []
    for j in range(k):
        out.append(proc.step(ids, np.full(n, j == 0), headings[j], accel_net[j]))
    return proc, out


def test_zero_noise_rotated_by_the_true_heading_is_the_net_frame_input():
    """Zero noise and bias: R(psi_mid) accel_body = today's net-frame input, straight or turning
    (the body frame is defined at the mid-step heading), and the yaw rate is the heading change / Ts."""
    rng = np.random.default_rng(3)
    dt, k, n = 0.75, 30, 20
    yaw = np.where(np.arange(n) < n // 2, 0.0, rng.uniform(-0.4, 0.4, n))  # half straight, half turning
    psi = rng.uniform(-np.pi, np.pi, n) + np.arange(k)[:, None] * yaw * dt
    acc = rng.normal(0.0, 1.0, (k, n, 2))
    _, frames = _run(PERFECT, psi, acc, dt)
    for j in range(1, k):
        mid = psi[j - 1] + 0.5 * wrap_angle(psi[j] - psi[j - 1])
        np.testing.assert_allclose(rotate(frames[j].accel_body, mid), acc[j], rtol=0, atol=1e-12)
        np.testing.assert_allclose(frames[j].yaw_rate, yaw, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(frames[0].accel_body, 0.0)  # entered: no previous step
    np.testing.assert_array_equal(frames[0].yaw_rate, 0.0)


@pytest.mark.parametrize("turn_s", [3.0, 5.0, 10.0])
def test_turn_discretisation_is_bounded(turn_s):
    """A steady 90 deg turn at 10 m/s: the step's body-frame acceleration is purely lateral and
    smaller than a continuous IMU's centripetal v w by 1 - sinc(w Ts / 2) <= (w Ts)^2 / 24."""
    dt, v = 0.75, 10.0
    w = (np.pi / 2) / turn_s
    psi0 = np.array([0.3])
    vel = lambda p: v * np.stack([np.cos(p), np.sin(p)], axis=-1)  # noqa: E731
    body, yaw = true_body_motion((vel(psi0 + w * dt) - vel(psi0)) / dt, psi0 + w * dt, psi0, dt)
    assert abs(body[0, 0]) < 1e-12
    rel = 1.0 - body[0, 1] / (v * w)
    assert 0.0 <= rel <= (w * dt) ** 2 / 24.0
    assert rel == pytest.approx(1.0 - math.sin(w * dt / 2) / (w * dt / 2), abs=1e-12)
    assert yaw[0] == pytest.approx(w, abs=1e-12)


def test_stationary_vehicle_yaw_rate_is_bias_plus_noise():
    """A vehicle standing still measures its gyro bias plus white noise of std N / sqrt(Ts); without
    white noise exactly its bias (turn-on + drift)."""
    n, k, dt = 5000, 3, 0.75
    psi = np.full((k, n), 1.2)
    acc = np.zeros((k, n, 2))
    params = InertialParams()
    proc, frames = _run(params, psi, acc, dt)
    resid = frames[-1].yaw_rate - proc.gyro_bias
    sd = params.gyro_noise_density * RAD / math.sqrt(dt)
    chi2 = float(np.sum(resid**2) / sd**2)
    assert stats.chi2.ppf(ALPHA / 2, n) < chi2 < stats.chi2.ppf(1 - ALPHA / 2, n)
    assert abs(resid.mean()) < stats.norm.ppf(1 - ALPHA / 2) * sd / math.sqrt(n)
    quiet = InertialParams(accel_noise_density=0.0, gyro_noise_density=0.0)
    proc, frames = _run(quiet, psi, acc, dt)
    np.testing.assert_array_equal(frames[-1].yaw_rate, proc.gyro_bias)
    np.testing.assert_array_equal(frames[-1].accel_body, proc.accel_bias)


def test_gauss_markov_drift_has_the_stationary_variance_and_correlation():
    """Drift only (no turn-on bias, no white noise), 4000 vehicles: at every sampled step the sample
    variance passes a chi-square test against sigma^2, and the correlation between steps m apart
    passes Fisher's z test against a^m, a = exp(-Ts / tau) (two-sided level ALPHA each)."""
    n, k, dt = 4000, 60, 0.75
    params = InertialParams(accel_noise_density=0.0, accel_turn_on_sigma=0.0, accel_bias_sigma=0.2,
                            accel_bias_tau_s=5.0, gyro_noise_density=0.0, gyro_turn_on_sigma=0.0,
                            gyro_bias_sigma=0.1, gyro_bias_tau_s=20.0)
    proc, frames = _run(params, np.zeros((k, n)), np.zeros((k, n, 2)), dt)
    gyro = np.array([f.yaw_rate for f in frames])  # (k, n) rad/s = the drift
    accel = np.array([f.accel_body[:, 0] for f in frames])
    z_crit = stats.norm.ppf(1 - ALPHA / 2)
    for series, sigma, tau in ((gyro, params.gyro_bias_sigma * RAD, 20.0), (accel, 0.2, 5.0)):
        for j in (0, 30, k - 1):
            chi2 = float(np.sum(series[j] ** 2) / sigma**2)  # zero mean known
            assert stats.chi2.ppf(ALPHA / 2, n) < chi2 < stats.chi2.ppf(1 - ALPHA / 2, n)
        for lag in (1, 8):
            r = np.corrcoef(series[20], series[20 + lag])[0, 1]
            expected = math.exp(-lag * dt / tau)
            assert abs(math.atanh(r) - math.atanh(expected)) * math.sqrt(n - 3) < z_crit


def test_gauss_markov_step_function():
    """b_k = a b_{k-1} + sigma sqrt(1 - a^2) w_k; fresh rows start at sigma w."""
    prev, w = np.array([1.0, 2.0]), np.array([0.5, -0.5])
    out = gauss_markov_bias(prev, w, np.array([False, True]), 0.3, 0.9)
    np.testing.assert_allclose(out, [0.9 + 0.3 * math.sqrt(1 - 0.81) * 0.5, 0.3 * -0.5])


def test_turn_on_bias_is_drawn_at_entry_and_kept():
    n, k = 50, 5
    params = InertialParams(accel_bias_sigma=0.0, gyro_bias_sigma=0.0)
    proc = InertialProcess(params, 4, 0.75)
    ids = np.array([f"v{i}" for i in range(n)], dtype=object)
    proc.step(ids, np.ones(n, bool), np.zeros(n), np.zeros((n, 2)))
    first = proc.gyro_bias.copy(), proc.accel_bias.copy()
    for _ in range(k):
        proc.step(ids, np.zeros(n, bool), np.zeros(n), np.zeros((n, 2)))
    np.testing.assert_array_equal(proc.gyro_bias, first[0])
    np.testing.assert_array_equal(proc.accel_bias, first[1])
    again = np.zeros(n, bool)
    again[3] = True  # re-entry (a teleport): a new turn-on bias
    proc.step(ids, again, np.zeros(n), np.zeros((n, 2)))
    assert proc.gyro_bias[3] != first[0][3] and np.array_equal(np.delete(proc.gyro_bias, 3), np.delete(first[0], 3))


def test_same_seed_same_bytes_other_seed_other_draws():
    rng = np.random.default_rng(0)
    psi = rng.uniform(-3, 3, (10, 8))
    acc = rng.normal(size=(10, 8, 2))
    a = _run(InertialParams(), psi, acc, seed=9)[1]
    b = _run(InertialParams(), psi, acc, seed=9)[1]
    c = _run(InertialParams(), psi, acc, seed=10)[1]
    for x, y, z in zip(a, b, c):
        assert x.accel_body.tobytes() == y.accel_body.tobytes() and x.yaw_rate.tobytes() == y.yaw_rate.tobytes()
        assert not np.array_equal(x.yaw_rate, z.yaw_rate)


@pytest.mark.parametrize("field,value", [("accel_noise_density", -1.0), ("gyro_bias_sigma", float("nan")),
                                         ("accel_bias_tau_s", 0.0), ("gyro_bias_tau_s", float("inf")),
                                         ("gyro_turn_on_sigma", True)])
def test_bad_parameters_name_the_field(field, value):
    with pytest.raises(InputError) as err:
        InertialParams(**{field: value})
    assert err.value.field == field


def test_coupler_other_streams_untouched_and_true_heading_inverts_the_imu(cross_net):
    """On the test cross (turns included): with [inertial] every other measurement of every frame is
    the same bytes as without it (GNSS, V2F, prior, links), ``accel`` is NaN, and with a perfect IMU
    R(psi_mid) accel_body is the idealised net-frame input (accel_sigma 0) at 1e-9."""
    net = load_net_folder(cross_net)

    def frames(sens):
        with SumoCoupler(SumoScenario(net=net, control="tlr", seed=5, duration_s=90.0), sens) as c:
            return list(c.frames())

    plain = frames(SensorParams(accel_sigma=0.0))
    real = frames(SensorParams(accel_sigma=0.0, inertial=InertialParams()))
    perfect = frames(SensorParams(accel_sigma=0.0, inertial=PERFECT))
    assert len(plain) == len(real) == 120
    turning = 0
    prev_heading: dict[str, float] = {}
    for a, b, c in zip(plain, real, perfect):
        assert a.imu is None and b.imu is not None
        for key in ("vehicle_ids", "entered", "prior_z", "prior_R", "gnss_z", "gnss_R", "v2f_z", "v2f_owner", "v2f_R"):
            x, y = getattr(a, key), getattr(b, key)
            assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), key
        assert (a.neighbors != b.neighbors).nnz == 0
        assert np.all(np.isnan(b.accel)) and b.accel.shape == a.accel.shape
        heading = a.truth.heading
        prev = np.array([prev_heading.get(v, np.nan) for v in a.vehicle_ids])
        cont = np.isfinite(prev) & ~a.entered
        mid = prev + 0.5 * wrap_angle(heading - prev)
        np.testing.assert_allclose(rotate(c.imu.accel_body[cont], mid[cont]), a.accel[cont], rtol=0, atol=1e-9)
        turning += int(np.count_nonzero(np.abs(c.imu.yaw_rate[cont]) > 0.05))
        prev_heading = dict(zip(a.vehicle_ids, heading))
    assert turning > 0  # the cross has turning traffic: the check covered turns


def test_inertial_table_resolves_and_round_trips():
    """[inertial] reaches the coupler inside [sensors], is written fully resolved (every key) and reads
    back the same; without it nothing is written and the sensors are the idealised ones."""
    import tomllib
    from pathlib import Path

    from experiments.config import config_from_dict
    from experiments.config_toml import config_to_toml

    project = Path(__file__).resolve().parents[2]
    data = tomllib.loads((project / "experiments" / "arterial_tlr.toml").read_text())
    data["scenario"]["net_dir"] = str(project / "sumo_nets" / "arterial")
    cfg = config_from_dict({**data, "inertial": {"gyro_turn_on_sigma": 0.2}}, Path("/x/cfg.toml"))
    assert cfg.sensors.inertial is cfg.inertial and cfg.inertial == InertialParams(gyro_turn_on_sigma=0.2)
    text = config_to_toml(cfg, {"git": "test"})
    written = tomllib.loads(text)["inertial"]
    assert set(written) == set(InertialParams.__dataclass_fields__)
    again = config_from_dict(tomllib.loads(text), Path("/x/cfg.toml"))
    assert again.sensors == cfg.sensors
    plain = config_from_dict(data, Path("/x/cfg.toml"))
    assert plain.sensors.inertial is None and "[inertial]" not in config_to_toml(plain, {})
