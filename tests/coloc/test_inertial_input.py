"""The estimators' side of the inertial input (coloc.core.inertial): rotation by the
estimated heading, the heading memory below the speed threshold, new vehicles, the unchanged path
without an IMU, and the trackers fed by the IMU."""

import math
from dataclasses import replace

import numpy as np
import pytest

from coloc.core.inertial import ImuFrame, estimator_input, net_frame_input, rotate, wrap_angle
from coloc.core.models import MotionParams
from coloc.core.vehicles import match_ids
from coloc.methods.gnss import GnssTracker
from couplers.sensing.inertial import InertialParams, true_body_motion
from scenes import road_frames

PERFECT = InertialParams(accel_noise_density=0.0, accel_bias_sigma=0.0, accel_turn_on_sigma=0.0,
                         gyro_noise_density=0.0, gyro_bias_sigma=0.0, gyro_turn_on_sigma=0.0)


def _circle(n=40, dt=0.75, seed=2):
    """Vehicles on circles / straight lines: true headings at t-1 and t, velocities and the step's
    net-frame change of velocity / Ts, with the body-frame IMU made from them (no noise)."""
    rng = np.random.default_rng(seed)
    psi0 = rng.uniform(-np.pi, np.pi, n)
    w = np.where(np.arange(n) % 3 == 0, 0.0, rng.uniform(-0.5, 0.5, n))
    v0, v1 = rng.uniform(2.0, 15.0, n), rng.uniform(2.0, 15.0, n)
    psi1 = psi0 + w * dt
    vel0 = v0[:, None] * np.stack([np.cos(psi0), np.sin(psi0)], axis=1)
    vel1 = v1[:, None] * np.stack([np.cos(psi1), np.sin(psi1)], axis=1)
    acc = (vel1 - vel0) / dt
    body, yaw = true_body_motion(acc, psi1, psi0, dt)
    return ImuFrame(body, yaw), vel0, acc, psi0, psi1


def test_exact_estimated_heading_gives_the_true_net_frame_input():
    """Estimated velocity = the true one (so the estimated heading is exact): the estimators' input is
    the true-heading rotation, i.e. today's net-frame input, and the kept heading is the true one at t."""
    imu, vel0, acc, _, psi1 = _circle()
    accel, heading = net_frame_input(imu, 0.75, vel0, np.full(len(vel0), np.nan), np.zeros(len(vel0), bool), 1.0)
    np.testing.assert_allclose(accel, acc, rtol=0, atol=1e-12)
    np.testing.assert_allclose(wrap_angle(heading - psi1), 0.0, atol=1e-12)


def test_slow_vehicle_dead_reckons_the_kept_heading():
    """Below the speed threshold the heading is the kept one advanced by the measured yaw rate:
    rotation at psi + r Ts / 2, kept psi + r Ts; above it, the velocity's direction (kept ignored)."""
    dt = 0.5
    imu = ImuFrame(np.array([[1.0, 0.2], [1.0, 0.2]]), np.array([0.1, 0.1]))
    vel = np.array([[0.3, 0.1], [3.0, 4.0]])  # 0.32 m/s (slow), 5 m/s
    kept = np.array([2.0, -1.0])
    accel, heading = net_frame_input(imu, dt, vel, kept, np.zeros(2, bool), 1.0)
    np.testing.assert_allclose(accel[0], rotate(imu.accel_body[:1], np.array([2.0 + 0.025]))[0], atol=1e-15)
    np.testing.assert_allclose(heading[0], 2.05, atol=1e-15)
    psi = math.atan2(4.0, 3.0)
    np.testing.assert_allclose(accel[1], rotate(imu.accel_body[1:], np.array([psi + 0.025]))[0], atol=1e-15)
    np.testing.assert_allclose(heading[1], psi + 0.05, atol=1e-15)
    # No kept heading yet (NaN): the velocity's direction even when slow.
    _, h = net_frame_input(imu, dt, vel, np.full(2, np.nan), np.zeros(2, bool), 1.0)
    np.testing.assert_allclose(h[0], math.atan2(0.1, 0.3) + 0.05, atol=1e-15)


def test_held_heading_keeps_a_slow_vehicle_s_heading_and_leaves_the_fast_one_as_dead_reckoned():
    """``[motion] imu_heading = "held"``: below the speed threshold the kept heading is neither advanced
    nor rotated by the yaw rate (a gyroscope's bias at a stop); above it, and for a vehicle without a kept
    heading, exactly the dead-reckoned input."""
    dt = 0.5
    imu = ImuFrame(np.array([[1.0, 0.2], [1.0, 0.2], [1.0, 0.2]]), np.array([0.1, 0.1, 0.1]))
    vel = np.array([[0.3, 0.1], [3.0, 4.0], [0.3, 0.1]])  # slow, fast, slow without a kept heading
    kept = np.array([2.0, -1.0, np.nan])
    fresh = np.zeros(3, bool)
    accel, heading = net_frame_input(imu, dt, vel, kept, fresh, 1.0, hold=True)
    np.testing.assert_allclose(accel[0], rotate(imu.accel_body[:1], np.array([2.0]))[0], atol=1e-15)
    assert heading[0] == 2.0
    reckoned = net_frame_input(imu, dt, vel, kept, fresh, 1.0)
    np.testing.assert_array_equal(accel[1:], reckoned[0][1:])
    np.testing.assert_array_equal(heading[1:], reckoned[1][1:])
    # A slow vehicle held over many steps keeps its heading whatever the gyroscope's bias
    h = kept.copy()
    for _ in range(80):  # a minute at 0.75 s
        _, h = net_frame_input(ImuFrame(np.zeros((3, 2)), np.full(3, math.radians(0.5))), 0.75, vel, h, fresh, 1.0,
                               hold=True)
    assert h[0] == 2.0


def test_new_vehicle_starts_from_its_prior_velocity():
    """A fresh vehicle's kept heading is its prior velocity's direction (not advanced: not predicted)."""
    frames = road_frames(steps=3, inertial=PERFECT)
    f = replace(frames[1], entered=np.array([True, False, False, False, False]),
                prior_z=np.where(np.arange(5)[:, None] == 0, np.array([[0.0, 0.0, 0.0, 2.0]]), np.nan))
    idx = np.arange(5)
    accel, heading = estimator_input(f, idx, np.tile([10.0, 0.0], (5, 1)), np.zeros(5), 1.0)
    assert heading[0] == pytest.approx(math.pi / 2)
    np.testing.assert_allclose(heading[1:], 0.0, atol=1e-15)
    assert accel.shape == (5, 2) and np.all(np.isfinite(accel))


def test_without_imu_the_input_is_frame_accel_itself():
    f = road_frames(steps=2)[1]
    accel, heading = estimator_input(f, np.arange(f.n_vehicles), np.zeros((f.n_vehicles, 2)), None, 1.0)
    assert accel is f.accel and heading is None


def test_gnss_tracker_with_a_perfect_imu_follows_the_idealised_tracker():
    """Straight road, noise-free IMU: the tracker's estimated heading is within a few hundredths of a
    radian of the truth, so its estimates stay within centimetres of the tracker fed the true net-frame
    input, and its kept headings follow the truth (east, 0 rad)."""
    motion = MotionParams(sigma_along=0.3, sigma_cross=0.05)
    ideal = road_frames(steps=15, accel_sigma=0.0)
    imu = road_frames(steps=15, inertial=PERFECT)
    a, b = GnssTracker(motion=motion), GnssTracker(motion=motion)
    for fa, fb in zip(ideal, imu):
        ea, eb = a.step(fa), b.step(fb)
        assert np.all(np.isfinite(eb.mean)) and np.all(np.linalg.eigvalsh(eb.cov) > 0)
    assert np.max(np.abs(b._heading)) < 0.05
    # Both trackers see the same GNSS fixes; the inputs differ only by the estimated-heading error.
    assert np.max(np.abs(ea.mean[:, :2] - eb.mean[:, :2])) < 0.02  # 5.6 mm measured


def test_rows_follow_vehicles_between_steps():
    """The kept headings travel with their vehicles when rows are reordered (match_ids)."""
    prev_ids = np.array(["a", "b", "c"], dtype=object)
    kept = np.array([0.1, 0.2, 0.3])
    cur = np.array(["c", "d", "a"], dtype=object)
    idx = match_ids(prev_ids, cur)
    from coloc.core.inertial import carried_heading

    np.testing.assert_array_equal(carried_heading(kept, idx), [0.3, np.nan, 0.1])
