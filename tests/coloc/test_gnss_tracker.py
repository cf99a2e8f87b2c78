"""The GNSS-only tracker: Kalman filter against closed-form and independent references."""

import numpy as np
import pytest
import scipy.sparse as sp

from coloc.core.frame import Frame
from coloc.core.models import (
    MotionParams,
    driving_noise_cov,
    input_matrix,
    kalman_update,
    predict,
    transition_matrix,
)
from coloc.methods.gnss import GnssTracker, gnss_predict_update


def make_frame(t, ids, z, r, accel=None, entered=None, prior_z=None, prior_R=None, dt=1.0, truth=None):
    n = len(ids)
    entered = np.zeros(n, bool) if entered is None else np.asarray(entered)
    return Frame(
        t=t, dt=dt, vehicle_ids=np.array(ids, dtype=object), entered=entered,
        prior_z=np.full((n, 4), np.nan) if prior_z is None else prior_z,
        prior_R=np.full((n, 4, 4), np.nan) if prior_R is None else prior_R,
        accel=np.zeros((n, 2)) if accel is None else accel,
        gnss_z=z, gnss_R=r, v2f_z=np.empty((0, 4)), v2f_owner=np.empty(0, np.int64),
        v2f_R=np.empty((0, 4, 4)), neighbors=sp.csr_matrix((n, n), dtype=bool), truth=truth,
    )


def test_model_matrices_closed_form():
    dt = 0.75
    a, b = transition_matrix(dt), input_matrix(dt)
    x = np.array([1.0, 2.0, 3.0, -1.0])
    acc = np.array([0.4, -0.2])
    # Constant acceleration kinematics: p + v dt + a dt^2 / 2, v + a dt.
    expected = np.array([1 + 3 * dt + 0.2 * dt**2, 2 - dt - 0.1 * dt**2, 3 + 0.4 * dt, -1 - 0.2 * dt])
    np.testing.assert_allclose(a @ x + b @ acc, expected, rtol=0, atol=1e-14)


def test_driving_noise_rotates_with_heading():
    m = MotionParams(sigma_along=0.35, sigma_cross=0.01)
    dt = 1.0
    q_east = driving_noise_cov(np.array([[10.0, 0.0]]), dt, m)[0]
    b = input_matrix(dt)
    np.testing.assert_allclose(q_east, b @ np.diag([0.35**2, 0.01**2]) @ b.T, atol=1e-15)
    q_north = driving_noise_cov(np.array([[0.0, 7.0]]), dt, m)[0]
    np.testing.assert_allclose(q_north, b @ np.diag([0.01**2, 0.35**2]) @ b.T, atol=1e-15)
    # Diagonal heading: along-track variance on the (1,1)/sqrt2 direction.
    q_diag = driving_noise_cov(np.array([[5.0, 5.0]]), dt, m)[0]
    u = np.array([1, 1, 0, 0]) / np.sqrt(2)
    assert u @ q_diag @ u == pytest.approx(0.25 * 0.35**2, rel=1e-12)
    # Standing vehicle: heading unknown, isotropic.
    q_still = driving_noise_cov(np.array([[0.1, 0.0]]), dt, m)[0]
    np.testing.assert_allclose(q_still, b @ np.diag([0.35**2, 0.35**2]) @ b.T, atol=1e-15)


def test_kalman_update_matches_textbook_loop():
    rng = np.random.default_rng(7)
    n = 20
    l = rng.normal(size=(n, 4, 4))
    p = l @ np.swapaxes(l, 1, 2) + 0.1 * np.eye(4)
    r = np.zeros((n, 4, 4))
    r[:, [0, 1, 2, 3], [0, 1, 2, 3]] = rng.uniform(0.1, 10, size=(n, 4))
    m = rng.normal(size=(n, 4))
    z = rng.normal(size=(n, 4))
    mb, pb = kalman_update(m, p, z, r)
    for i in range(n):  # textbook form, one vehicle at a time
        k = p[i] @ np.linalg.inv(p[i] + r[i])
        np.testing.assert_allclose(mb[i], m[i] + k @ (z[i] - m[i]), rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(pb[i], (np.eye(4) - k) @ p[i], rtol=1e-9, atol=1e-10)


def test_static_vehicle_converges_to_weighted_least_squares():
    """With no driving noise and no motion the KF is recursive least squares:
    the posterior mean is the information-weighted average of prior and fixes."""
    rng = np.random.default_rng(3)
    x0 = np.array([5.0, -3.0, 0.0, 0.0])
    p0 = np.diag([4.0, 4.0, 0.01, 0.01])
    m0 = x0 + rng.normal(size=4) * np.sqrt(np.diag(p0))
    r = np.diag([9.0, 9.0, 0.04, 0.04])
    m, p = m0[None], p0[None]
    zs = []
    a = transition_matrix(1.0)
    for _ in range(50):
        z = x0 + rng.normal(size=4) * np.sqrt(np.diag(r))
        zs.append(z)
        m, p = predict(m, p, np.zeros((1, 2)), 1.0, np.zeros((1, 4, 4)))
        m, p = kalman_update(m, p, z[None], r[None])
    # Velocity is exactly zero in truth but estimated: compare with the batch solution
    # of the linear model z_k = H_k x_0, H_k = A^k, x_0 ~ N(m0, p0).
    info = np.linalg.inv(p0)
    vec = info @ m0
    rinv = np.linalg.inv(r)
    for k, z in enumerate(zs, start=1):
        h = np.linalg.matrix_power(a, k)
        info = info + h.T @ rinv @ h
        vec = vec + h.T @ rinv @ z
    x0_hat = np.linalg.solve(info, vec)
    h_end = np.linalg.matrix_power(a, len(zs))
    np.testing.assert_allclose(m[0], h_end @ x0_hat, atol=1e-9)
    np.testing.assert_allclose(p[0], h_end @ np.linalg.inv(info) @ h_end.T, atol=1e-10)


def test_tracker_handles_vehicles_entering_and_leaving():
    r = np.tile(np.diag([9.0, 9.0, 0.01, 0.01]), (2, 1, 1))
    prior_R = np.tile(np.diag([4.0, 4.0, 0.01, 0.01]), (2, 1, 1))
    trk = GnssTracker(motion=MotionParams())
    z = np.array([[0, 0, 10, 0], [100, 0, 0, 10]], float)
    prior = z + 1.0
    e0 = trk.step(make_frame(0.0, ["a", "b"], z, r, entered=[True, True], prior_z=prior, prior_R=prior_R))
    # A fresh vehicle is its prior updated once by GNSS (no prediction).
    exp_m, exp_p = kalman_update(prior, prior_R, z, r)
    np.testing.assert_allclose(e0.mean, exp_m)
    np.testing.assert_allclose(e0.cov, exp_p)
    # Next step: "a" leaves, "c" enters, "b" continues (listed first).
    z1 = np.array([[100, 10, 0, 10], [50, 50, 0, 0]], float)
    prior_c = np.vstack([np.full(4, np.nan), z1[1]])
    prior_Rc = np.stack([np.full((4, 4), np.nan), prior_R[0]])
    e1 = trk.step(make_frame(1.0, ["b", "c"], z1, r, entered=[False, True], prior_z=prior_c, prior_R=prior_Rc))
    mb, pb = gnss_predict_update(e0.mean[1:2], e0.cov[1:2], np.zeros((1, 2)), z1[:1], r[:1], 1.0, MotionParams())
    np.testing.assert_allclose(e1.mean[0], mb[0])
    np.testing.assert_allclose(e1.cov[0], pb[0])
    # A vehicle marked entered again (teleport) restarts from its new prior.
    prior_again = np.vstack([z1[0] + 3.0, np.full(4, np.nan)])
    prior_R_again = np.stack([prior_R[0], np.full((4, 4), np.nan)])
    e2 = trk.step(make_frame(2.0, ["b", "c"], z1, r, entered=[True, False], prior_z=prior_again, prior_R=prior_R_again))
    exp_m2, _ = kalman_update(prior_again[:1], prior_R[:1], z1[:1], r[:1])
    np.testing.assert_allclose(e2.mean[0], exp_m2[0])
    # Empty frame is an ordinary case.
    e3 = trk.step(make_frame(3.0, [], np.empty((0, 4)), np.empty((0, 4, 4))))
    assert e3.mean.shape == (0, 4)


def test_new_vehicle_without_prior_is_an_error():
    trk = GnssTracker()
    r = np.diag([9.0, 9.0, 0.01, 0.01])[None]
    with pytest.raises(ValueError, match="fast-start prior"):
        trk.step(make_frame(0.0, ["a"], np.zeros((1, 4)), r))


def test_covariances_stay_spd_and_error_is_consistent():
    """Seeded simulation of model (1): the posterior stays SPD and the mean NEES is 4 within tolerance."""
    rng = np.random.default_rng(11)
    n, steps, dt = 200, 150, 0.75
    motion = MotionParams(sigma_along=0.35, sigma_cross=0.05)
    x = np.zeros((n, 4))
    x[:, 2] = rng.uniform(5, 14, n)
    x[:, 3] = rng.uniform(-3, 3, n)
    r = np.tile(np.diag([8.0**2, 8.0**2, 0.17**2, 0.17**2]), (n, 1, 1))
    prior_R = np.tile(np.diag([4.0, 4.0, 0.01, 0.01]), (n, 1, 1))
    trk = GnssTracker(motion=motion)
    ids = [f"v{i}" for i in range(n)]
    a_mat, b_mat = transition_matrix(dt), input_matrix(dt)
    nees = []
    for k in range(steps):
        if k:
            # Simulate with exactly the filter's Q (oriented by the true velocity; above 1 m/s here).
            q = driving_noise_cov(x[:, 2:], dt, motion)
            w = np.einsum("nij,nj->ni", np.linalg.cholesky(q + 1e-15 * np.eye(4)), rng.standard_normal((n, 4)))
            acc = rng.normal(0, 0.3, (n, 2))
            x = x @ a_mat.T + acc @ b_mat.T + w
        else:
            acc = np.zeros((n, 2))
        z = x + rng.standard_normal((n, 4)) * np.sqrt(np.diagonal(r, axis1=1, axis2=2))
        prior = x + rng.standard_normal((n, 4)) * np.sqrt(np.diagonal(prior_R, axis1=1, axis2=2)) if k == 0 else None
        fr = make_frame(k * dt, ids, z, r, accel=acc, entered=np.full(n, k == 0), prior_z=prior,
                        prior_R=prior_R if k == 0 else None, dt=dt)
        est = trk.step(fr)
        assert np.allclose(est.cov, np.swapaxes(est.cov, 1, 2))
        assert np.all(np.linalg.eigvalsh(est.cov) > 0)
        d = est.mean - x
        nees.append(np.einsum("ni,nij,nj->n", d, np.linalg.inv(est.cov), d))
    nees = np.concatenate(nees[20:])
    # Estimated velocity heading differs slightly from the truth used to orient Q: allow 10 %.
    assert nees.mean() == pytest.approx(4.0, rel=0.10)


def test_numba_kernel_matches_numpy_reference():
    from coloc.kernels.kalman import gnss_step_kernel

    rng = np.random.default_rng(5)
    n = 50
    motion = MotionParams(sigma_along=0.35, sigma_cross=0.05)
    mean = rng.normal(size=(n, 4)) * [100, 100, 8, 8]
    mean[:5, 2:] = 0.1  # slow vehicles: isotropic driving noise
    l = rng.normal(size=(n, 4, 4))
    cov = l @ np.swapaxes(l, 1, 2) + np.eye(4)
    acc = rng.normal(size=(n, 2))
    z = mean + rng.normal(size=(n, 4))
    r = np.tile(np.diag([25.0, 25.0, 0.04, 0.04]), (n, 1, 1))
    mask = rng.random(n) < 0.8
    exp_m, exp_p = mean.copy(), cov.copy()
    exp_m[mask], exp_p[mask] = gnss_predict_update(mean[mask], cov[mask], acc[mask], z[mask], r[mask], 0.75, motion)
    exp_m[~mask], exp_p[~mask] = kalman_update(mean[~mask], cov[~mask], z[~mask], r[~mask])
    got_m, got_p = mean.copy(), cov.copy()
    gnss_step_kernel(got_m, got_p, acc, z, r, mask, 0.75, 0.35, 0.05, 1.0)
    np.testing.assert_allclose(got_m, exp_m, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(got_p, exp_p, rtol=1e-9, atol=1e-9)
