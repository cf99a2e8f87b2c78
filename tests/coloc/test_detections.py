"""Sensor-frame detections (coloc.core.detections, couplers.sensing.sensor_frame): the estimator's
conversion against the coupler's geometry, the heading Jacobian against finite differences, and the
converted covariance against a Monte Carlo of heading errors."""

import numpy as np
import pytest
from scipy import stats

from coloc.core.detections import (
    HEADING_VAR_UNKNOWN,
    HeadingMemory,
    SensorDetections,
    heading_from_velocity,
    to_net_frame,
    vehicle_headings,
)
from coloc.core.frame import empty_frame
from couplers.sensing.perception import PerceptionNoise, PerceptionParams, SensorSpec, perceive
from couplers.sensing.sensor_frame import relative_states, sensor_frame_rows

ALPHA = 1e-3  # two-sided 0.1 % level of the statistical tests here


def _rows(seed, o=200):
    rng = np.random.default_rng(seed)
    rel = np.column_stack([rng.uniform(-60, 60, (o, 2)), rng.uniform(-15, 15, (o, 2))])
    heading = rng.uniform(-np.pi, np.pi, o)
    mount = rng.choice([0.0, -1.5, 2.0], o)
    yaw = np.deg2rad(rng.choice([0.0, 90.0, -135.0], o))
    return rel, heading, mount, yaw


def _det(r, b, rdot, mount, yaw, sr=0.1, sb=np.deg2rad(0.3), srd=0.028):
    o = r.size
    return SensorDetections(range=r, bearing=b, range_rate=rdot, mount_x=mount, yaw=yaw,
                            sigma_range=np.full(o, sr), sigma_bearing=np.full(o, sb), sigma_range_rate=np.full(o, srd))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_true_heading_reproduces_the_relative_rows(seed):
    """No noise, the true heading with zero variance: z's position is x_F - x_V and its velocity the radial
    component of x_F - x_V's, to 1e-9 (mounts and yaws of every kind)."""
    rel, heading, mount, yaw = _rows(seed)
    r, b, rdot = sensor_frame_rows(rel, heading, mount, yaw, np.zeros((rel.shape[0], 3)), 0.0, 0.0, 0.0)
    z, R = to_net_frame(_det(r, b, rdot, mount, yaw), heading, np.zeros(rel.shape[0]))
    np.testing.assert_allclose(z[:, :2], rel[:, :2], atol=1e-9, rtol=0)
    los = (rel[:, :2] - mount[:, None] * np.column_stack([np.cos(heading), np.sin(heading)]))
    los /= np.linalg.norm(los, axis=1)[:, None]
    radial = (rel[:, 2:] * los).sum(axis=1)[:, None] * los
    np.testing.assert_allclose(z[:, 2:], radial, atol=1e-9, rtol=0)
    np.testing.assert_allclose(R, np.transpose(R, (0, 2, 1)), atol=1e-12)
    assert (np.linalg.eigvalsh(R) > 0).all()


def test_perceive_rows_in_sensor_frame_convert_back_to_the_same_world_draw():
    """One perceive() draw (detections and clutter) re-expressed per sensor without noise, converted with the
    true heading: the true rows give x_F - x_V, the clutter rows their net-frame points, to 1e-9."""
    rng = np.random.default_rng(5)
    n, k = 6, 80
    x_true = np.column_stack([rng.uniform(0, 100, (n, 2)), rng.uniform(-10, 10, (n, 2))])
    heading = rng.uniform(-np.pi, np.pi, n)
    feats = np.column_stack([rng.uniform(-50, 150, (k, 2)), np.zeros((k, 2))])
    sensors = (SensorSpec(name="front", fov_deg=120.0, range_m=80.0, mount_x_m=1.0, clutter_per_scan=2.0),
               SensorSpec(name="side", fov_deg=90.0, range_m=30.0, yaw_deg=90.0, mount_x_m=-2.0, clutter_per_scan=2.0))
    params = PerceptionParams(sensors=sensors, occlusion_vehicles=False, occlusion_buildings=False)
    owner = np.repeat(np.arange(n), k)
    feat = np.tile(np.arange(k), n)
    det = perceive(x_true=x_true, heading=heading, features_true=feats, pair_owner=owner, pair_feature=feat,
                   params=params, noise=PerceptionNoise(3))
    assert (det.feature >= 0).sum() > 20 and (det.feature < 0).sum() > 5
    mount = np.array([s.mount_x_m for s in sensors])[det.sensor]
    yaw = np.deg2rad([s.yaw_deg for s in sensors])[det.sensor]
    psi = heading[det.owner]
    rel = relative_states(det, x_true, feats)
    r, b, rdot = sensor_frame_rows(rel, psi, mount, yaw, np.zeros((det.owner.size, 3)), 0.0, 0.0, 0.0)
    # Inside each sensor's field of view: |bearing| <= fov / 2.
    half = np.deg2rad([s.fov_deg for s in sensors])[det.sensor] / 2
    assert (np.abs(b) <= half + 1e-9).all()
    z, _ = to_net_frame(_det(r, b, rdot, mount, yaw), psi, np.zeros(det.owner.size))
    real = det.feature >= 0
    np.testing.assert_allclose(z[real, :2], feats[det.feature[real], :2] - x_true[det.owner[real], :2], atol=1e-9, rtol=0)
    np.testing.assert_allclose(z[~real, :2], det.z[~real, :2], atol=1e-9, rtol=0)


def test_heading_jacobian_matches_finite_differences():
    """d z / d psi of to_net_frame (the heading column of R's Jacobian) against central differences."""
    rel, heading, mount, yaw = _rows(4, o=50)
    r, b, rdot = sensor_frame_rows(rel, heading, mount, yaw, np.zeros((50, 3)), 0.0, 0.0, 0.0)
    det = _det(r, b, rdot, mount, yaw, sr=0.0, sb=0.0, srd=0.0)
    _, R0 = to_net_frame(det, heading, np.zeros(50), tangential_sigma=0.0)
    eps = 1e-8  # R's heading term is J J^T heading_var to first order (the second-order term is O(heading_var^2))
    _, R1 = to_net_frame(det, heading, np.full(50, eps), tangential_sigma=0.0)
    h = 1e-6
    zp, _ = to_net_frame(det, heading + h, np.zeros(50))
    zm, _ = to_net_frame(det, heading - h, np.zeros(50))
    jac = (zp - zm) / (2 * h)
    np.testing.assert_allclose((R1 - R0) / eps, jac[:, :, None] * jac[:, None, :], atol=1e-4, rtol=1e-6)
    # 1 deg at 50 m across the line of sight: 0.87 m.
    d1 = _det(np.array([50.0]), np.array([0.0]), np.array([0.0]), np.array([0.0]), np.array([0.0]))
    za, _ = to_net_frame(d1, np.array([0.0]), np.zeros(1))
    zb, _ = to_net_frame(d1, np.array([np.deg2rad(1.0)]), np.zeros(1))
    assert np.linalg.norm(zb[0, :2] - za[0, :2]) == pytest.approx(0.8726, abs=1e-3)


def test_heading_variance_from_velocity_matches_monte_carlo():
    rng = np.random.default_rng(8)
    v = np.array([[8.0, 3.0]])
    p = np.array([[[0.04, 0.01], [0.01, 0.09]]])
    psi, var = heading_from_velocity(v, p)
    draws = rng.multivariate_normal(v[0], p[0], 200_000)
    mc = np.arctan2(draws[:, 1], draws[:, 0])
    assert psi[0] == pytest.approx(np.arctan2(3.0, 8.0))
    assert var[0] == pytest.approx(mc.var(), rel=0.02)
    _, var0 = heading_from_velocity(np.zeros((1, 2)), p)  # a stopped vehicle: a heading uniform on the circle
    assert var0[0] == HEADING_VAR_UNKNOWN


@pytest.mark.parametrize("sigma_deg", [0.5, 2.0, 5.0])
def test_converted_position_is_consistent_under_heading_error(sigma_deg):
    """Seeded Monte Carlo: range, bearing and range-rate noise and the estimator's heading error drawn from
    their distributions; the 2-D position NEES of the converted rows with R has mean 2 (chi-square, 2 dof, x
    rows) inside its two-sided 0.1 % band. At 2 and 5 deg this needs R's second-order heading term."""
    rng = np.random.default_rng(11)
    rel, heading, mount, yaw = _rows(9, o=4000)
    sb = np.deg2rad(0.3)
    w = rng.standard_normal((rel.shape[0], 3))
    r, b, rdot = sensor_frame_rows(rel, heading, mount, yaw, w, 0.1, sb, 0.028)
    var = np.full(rel.shape[0], np.deg2rad(sigma_deg) ** 2)
    est = heading + np.sqrt(var) * rng.standard_normal(rel.shape[0])
    z, R = to_net_frame(_det(r, b, rdot, mount, yaw, sb=sb), est, var)
    e = z[:, :2] - rel[:, :2]
    nees = np.einsum("oi,oij,oj->o", e, np.linalg.inv(R[:, :2, :2]), e)
    total, dof = float(nees.sum()), 2 * rel.shape[0]
    assert stats.chi2.sf(total, dof) > ALPHA / 2 and stats.chi2.cdf(total, dof) > ALPHA / 2
    # Without the heading term the same rows are overconfident: the test can fail.
    _, R_no = to_net_frame(_det(r, b, rdot, mount, yaw, sb=sb), est, np.zeros(rel.shape[0]))
    nees_no = np.einsum("oi,oij,oj->o", e, np.linalg.inv(R_no[:, :2, :2]), e)
    assert stats.chi2.sf(float(nees_no.sum()), dof) < ALPHA / 2


def test_slow_vehicle_keeps_its_last_heading():
    """Above heading_min_speed the heading is the velocity's; below, the kept one (and its variance); a vehicle
    never fast enough gets the velocity's direction with a capped variance; fresh vehicles forget."""
    frame = empty_frame(0.0, 0.5)
    from dataclasses import replace

    frame = replace(frame, vehicle_ids=np.array(["a", "b", "c"], dtype=object), entered=np.array([False, False, True]))
    mean = np.array([[0, 0, 0.1, 0.2], [0, 0, 0.05, 0.0], [0, 0, 0.0, 0.3]], dtype=float)
    cov = np.tile(np.eye(4) * 0.01, (3, 1, 1))
    memory = HeadingMemory(np.array([1.0, np.nan, 2.0]), np.array([1e-4, np.nan, 1e-4]))
    psi, var, kept = vehicle_headings(frame, mean, cov, np.array([0, 1, 2]), memory, min_speed=1.0)
    assert psi[0] == 1.0 and kept.heading[0] == 1.0  # slow, kept (held), its variance grown by one step
    assert var[0] == pytest.approx(1e-4 + (0.01 * 0.5) ** 2) and kept.var[0] == var[0]
    assert psi[1] == 0.0 and var[1] == HEADING_VAR_UNKNOWN and np.isnan(kept.heading[1])  # slow, none kept
    assert psi[2] == pytest.approx(np.pi / 2) and np.isnan(kept.heading[2])  # fresh: forgets
    fast = mean.copy()
    fast[:, 2:] = [[5.0, 5.0], [5.0, 5.0], [5.0, 5.0]]
    psi, var, kept = vehicle_headings(frame, fast, cov, np.array([0, 1, 2]), memory, min_speed=1.0)
    np.testing.assert_allclose(psi, np.pi / 4)
    np.testing.assert_allclose(kept.heading, np.pi / 4)
    np.testing.assert_allclose(var, 0.01 / 50)
