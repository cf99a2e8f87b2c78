"""The radar range rate's lever arm (``[perception] lever_arm_range_rate``): the coupler's range rate of a sensor
mounted ahead of the reference point against a finite difference of the moving geometry, the estimator's
conversion with its own yaw rate against the closed form and its covariance against the Jacobian by finite
differences, zero mount identical to the conversion without the lever arm, and the switch's bad input."""

import numpy as np
import pytest

from coloc.core.detections import (
    GYRO_YAW_RATE_SIGMA,
    MountSensorDetections,
    SensorDetections,
    to_net_frame,
    with_net_detections,
)
from coloc.core.frame import empty_frame
from coloc.core.inertial import ImuFrame
from couplers.errors import InputError
from couplers.sensing.perception import PerceptionParams
from couplers.sensing.sensor_frame import SensorFrameRows, sensor_frame_rows


def _rows(seed, o=200):
    rng = np.random.default_rng(seed)
    rel = np.column_stack([rng.uniform(-60, 60, (o, 2)), rng.uniform(-15, 15, (o, 2))])
    heading = rng.uniform(-np.pi, np.pi, o)
    mount = rng.choice([2.25, -1.5, 4.0], o)
    yaw = np.deg2rad(rng.choice([0.0, 90.0, -135.0], o))
    omega = rng.uniform(-0.6, 0.6, o)  # rad/s: a tight urban turn is ~0.5
    return rel, heading, mount, yaw, omega


def _det(r, b, rdot, mount, yaw, cls=MountSensorDetections, sr=0.1, sb=np.deg2rad(0.3), srd=0.028):
    o = r.size
    return cls(range=r, bearing=b, range_rate=rdot, mount_x=mount, yaw=yaw, sigma_range=np.full(o, sr),
               sigma_bearing=np.full(o, sb), sigma_range_rate=np.full(o, srd))


def _range(rel, heading, mount, omega, t):
    """|x_F - o| at time t: the feature relative to the vehicle moves with the relative velocity, the mount point
    turns with the vehicle about its reference point at the yaw rate."""
    psi = heading + omega * t
    px = rel[:, 0] + rel[:, 2] * t - mount * np.cos(psi)
    py = rel[:, 1] + rel[:, 3] * t - mount * np.sin(psi)
    return np.hypot(px, py)


@pytest.mark.parametrize("seed", [0, 1])
def test_world_range_rate_is_the_derivative_of_the_range_from_the_turning_mount(seed):
    rel, heading, mount, yaw, omega = _rows(seed)
    _, _, rdot = sensor_frame_rows(rel, heading, mount, yaw, np.zeros((rel.shape[0], 3)), 0.0, 0.0, 0.0, omega)
    h = 1e-5
    fd = (_range(rel, heading, mount, omega, h) - _range(rel, heading, mount, omega, -h)) / (2 * h)
    np.testing.assert_allclose(rdot, fd, atol=1e-6, rtol=0)
    _, _, rdot0 = sensor_frame_rows(rel, heading, mount, yaw, np.zeros((rel.shape[0], 3)), 0.0, 0.0, 0.0)
    assert np.abs(rdot - rdot0).max() > 0.1  # the lever arm matters at these rates


@pytest.mark.parametrize("seed", [0, 1])
def test_estimator_with_the_true_yaw_rate_reproduces_the_relative_rows(seed):
    """No noise, the true heading and yaw rate: z's position is x_F - x_V and its velocity the radial component
    (from the mount point) of the vehicle-relative velocity x_F - x_V, to 1e-9."""
    rel, heading, mount, yaw, omega = _rows(seed)
    r, b, rdot = sensor_frame_rows(rel, heading, mount, yaw, np.zeros((rel.shape[0], 3)), 0.0, 0.0, 0.0, omega)
    z, R = to_net_frame(_det(r, b, rdot, mount, yaw), heading, np.zeros(r.size), yaw_rate=omega,
                        yaw_rate_var=np.full(r.size, GYRO_YAW_RATE_SIGMA ** 2))
    np.testing.assert_allclose(z[:, :2], rel[:, :2], atol=1e-9, rtol=0)
    los = rel[:, :2] - mount[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
    los /= np.linalg.norm(los, axis=1)[:, None]
    radial = (rel[:, 2:] * los).sum(axis=1)[:, None] * los
    np.testing.assert_allclose(z[:, 2:], radial, atol=1e-9, rtol=0)
    np.testing.assert_allclose(R, np.transpose(R, (0, 2, 1)), atol=1e-12)
    assert (np.linalg.eigvalsh(R) > 0).all()
    z0, _ = to_net_frame(_det(r, b, rdot, mount, yaw), heading, np.zeros(r.size))  # the lever arm not undone
    assert np.abs(z0[:, 2:] - radial).max() > 0.1


def test_covariance_is_the_jacobian_of_every_input_by_finite_differences():
    """R (tangential std 0, the second-order heading term removed) = J diag(var_r, var_b, var_rdot, var_psi,
    var_omega) J^T with J = d z / d (r, b, rdot, psi, omega) by central differences."""
    rel, heading, mount, yaw, omega = _rows(3, 60)
    r, b, rdot = sensor_frame_rows(rel, heading, mount, yaw, np.zeros((rel.shape[0], 3)), 0.0, 0.0, 0.0, omega)
    sr, sb, srd = 0.1, np.deg2rad(0.3), 0.028
    hv, ov = np.full(r.size, np.deg2rad(1.0) ** 2), np.full(r.size, 0.02 ** 2)
    z, R = to_net_frame(_det(r, b, rdot, mount, yaw, sr=sr, sb=sb, srd=srd), heading, hv, tangential_sigma=0.0,
                        yaw_rate=omega, yaw_rate_var=ov)
    k2 = 0.5 * (1.0 + np.exp(-2.0 * hv)) - 2.0 * np.exp(-0.5 * hv) + 1.0
    R2 = R - k2[:, None, None] * z[:, :, None] * z[:, None, :]

    def conv(r_, b_, rd_, psi_, om_):
        return to_net_frame(_det(r_, b_, rd_, mount, yaw), psi_, np.zeros(r.size), yaw_rate=om_)[0]

    args = [r, b, rdot, heading, omega]
    cols = []
    for k in range(5):
        h = 1e-6
        up, dn = list(args), list(args)
        up[k], dn[k] = args[k] + h, args[k] - h
        cols.append((conv(*up) - conv(*dn)) / (2 * h))
    J = np.stack(cols, axis=2)  # (O, 4, 5)
    var = np.stack([np.full(r.size, sr ** 2), np.full(r.size, sb ** 2), np.full(r.size, srd ** 2), hv, ov], axis=1)
    want = np.einsum("oik,ok,ojk->oij", J, var, J)
    np.testing.assert_allclose(R2, want, atol=1e-8, rtol=1e-6)


def test_zero_mount_gives_the_rows_and_conversion_without_the_lever_arm():
    rel, heading, _, yaw, omega = _rows(4)
    mount = np.zeros(rel.shape[0])
    w = np.random.default_rng(9).standard_normal((rel.shape[0], 3))
    with_arm = sensor_frame_rows(rel, heading, mount, yaw, w, 0.1, 0.005, 0.028, omega)
    without = sensor_frame_rows(rel, heading, mount, yaw, w, 0.1, 0.005, 0.028)
    for a, b in zip(with_arm, without):
        np.testing.assert_array_equal(a, b)
    r, b, rdot = with_arm
    hv = np.full(r.size, 1e-4)
    za, Ra = to_net_frame(_det(r, b, rdot, mount, yaw), heading, hv, yaw_rate=omega,
                          yaw_rate_var=np.full(r.size, GYRO_YAW_RATE_SIGMA ** 2))
    zb, Rb = to_net_frame(_det(r, b, rdot, mount, yaw, cls=SensorDetections), heading, hv)
    np.testing.assert_array_equal(za, zb)
    np.testing.assert_allclose(Ra, Rb, atol=1e-15, rtol=1e-13)


def _frame(det, n, imu):
    f = empty_frame(t=0.75, dt=0.75)
    from dataclasses import replace

    return replace(f, vehicle_ids=np.array([f"v{i}" for i in range(n)], dtype=object), entered=np.zeros(n, bool),
                   v2f_owner=np.arange(det.range.size) % n, v2f_sensor=det, imu=imu,
                   v2f_z=np.full((det.range.size, 4), np.nan), v2f_R=np.full((det.range.size, 4, 4), np.nan))


def test_estimators_take_the_gyroscope_and_without_an_imu_no_yaw_rate():
    """with_net_detections: mount-point rows with an IMU are converted with the gyroscope's yaw rate and its
    variance; without an IMU exactly as rows without the lever arm; plain rows ignore the IMU."""
    n, o = 5, 40
    rng = np.random.default_rng(2)
    det = _det(rng.uniform(5, 60, o), rng.uniform(-1, 1, o), rng.uniform(-10, 10, o), np.full(o, 2.25),
               np.zeros(o))
    mean = np.column_stack([rng.uniform(0, 100, (n, 2)), rng.uniform(3, 10, (n, 2))])
    cov = np.tile(np.eye(4) * 0.1, (n, 1, 1))
    imu = ImuFrame(accel_body=np.zeros((n, 2)), yaw_rate=rng.uniform(-0.5, 0.5, n))
    idx = np.arange(n)
    got, _ = with_net_detections(_frame(det, n, imu), mean, cov, idx, None, 1.0)
    plain = _det(det.range, det.bearing, det.range_rate, det.mount_x, det.yaw, cls=SensorDetections)
    ref, _ = with_net_detections(_frame(plain, n, None), mean, cov, idx, None, 1.0)
    psi = np.arctan2(mean[:, 3], mean[:, 2])
    own = np.arange(o) % n
    want = to_net_frame(det, psi[own], _heading_var(mean, cov)[own],
                        yaw_rate=imu.yaw_rate[own], yaw_rate_var=np.full(o, GYRO_YAW_RATE_SIGMA ** 2))
    np.testing.assert_array_equal(got.v2f_z, want[0])
    np.testing.assert_array_equal(got.v2f_R, want[1])
    no_imu, _ = with_net_detections(_frame(det, n, None), mean, cov, idx, None, 1.0)
    np.testing.assert_array_equal(no_imu.v2f_z, ref.v2f_z)
    np.testing.assert_array_equal(no_imu.v2f_R, ref.v2f_R)
    plain_imu, _ = with_net_detections(_frame(plain, n, imu), mean, cov, idx, None, 1.0)
    np.testing.assert_array_equal(plain_imu.v2f_z, ref.v2f_z)
    assert np.abs(got.v2f_z[:, 2:] - ref.v2f_z[:, 2:]).max() > 0.1


def _heading_var(mean, cov):
    from coloc.core.detections import heading_from_velocity

    return heading_from_velocity(mean[:, 2:4], cov[:, 2:4, 2:4])[1]


def test_coupler_yaw_rate_is_the_heading_change_over_the_step_zero_on_entry():
    rows = SensorFrameRows(PerceptionParams(detections="range_bearing", lever_arm_range_rate=True), 1)
    ids = np.array(["a", "b"], dtype=object)
    r0 = rows.true_yaw_rate(ids, np.array([True, True]), np.array([3.1, 0.0]), 0.5)
    np.testing.assert_array_equal(r0, [0.0, 0.0])
    ids1 = np.array(["b", "a", "c"], dtype=object)
    r1 = rows.true_yaw_rate(ids1, np.array([False, False, True]), np.array([0.1, -3.1, 1.0]), 0.5)
    np.testing.assert_allclose(r1, [0.2, (2 * np.pi - 6.2) / 0.5, 0.0], atol=1e-12)  # wraps across +-pi


def test_the_switch_needs_sensor_frame_detections_and_a_boolean():
    with pytest.raises(InputError, match="lever_arm_range_rate"):
        PerceptionParams(lever_arm_range_rate=True)
    with pytest.raises(InputError, match="lever_arm_range_rate"):
        PerceptionParams(detections="range_bearing", lever_arm_range_rate=1)
    assert PerceptionParams(detections="range_bearing", lever_arm_range_rate=True).lever_arm_range_rate
