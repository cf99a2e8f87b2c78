"""SME filter (Zhang et al.): closed forms, invariances, reduction to the Kalman filter, seeded Monte Carlo.

* Gaussian raw moments, pseudo-measurement mean / Jacobian / covariance against closed forms,
  finite differences and sampling;
* with one vehicle and no infrastructure sensor the SME filter is the Kalman filter (1e-9);
* the update is unchanged by the conditioning shift/scale of the power sums and by the order of
  the fixes and detections;
* covariances stay symmetric positive definite over a run;
* Zhang Sec. IV Monte Carlo: SME below the KF that knows the association, for several
  infrastructure-sensor poses, with pose effects within sampling noise (the must-show test).
"""

import numpy as np
import pytest

from coloc.methods.sme import (
    SmeFilter,
    SmeParams,
    gaussian_raw_moments,
    kf_update_labelled,
    power_sums,
    pseudo_measurement_model,
    sme_predict,
    sme_update,
)
from experiments.studies.sme import paper_state_to_blocks, run_filter, simulate_run, step_errors

PAPER_X0 = paper_state_to_blocks([0, 80, 0, 0, 0, 45, 0, 45, 0, 0, 0, 80])


def test_gaussian_raw_moments_closed_form():
    mu, v = np.array([-1.5, 0.0, 2.0]), 0.7
    m = gaussian_raw_moments(mu, v, 4)
    np.testing.assert_allclose(m[0], 1)
    np.testing.assert_allclose(m[1], mu)
    np.testing.assert_allclose(m[2], mu**2 + v)
    np.testing.assert_allclose(m[3], mu**3 + 3 * mu * v)
    np.testing.assert_allclose(m[4], mu**4 + 6 * mu**2 * v + 3 * v**2)


def test_pseudo_measurement_mean_jacobian_and_covariance():
    rng = np.random.default_rng(0)
    mu, v = np.array([-0.8, 0.3, 1.1]), 0.05
    samples = mu + np.sqrt(v) * rng.standard_normal((400_000, 3))
    s = np.stack([np.sum(samples**k, axis=1) for k in (1, 2, 3)], axis=1)
    h, jac, r = pseudo_measurement_model(mu, v, "moments")
    np.testing.assert_allclose(s.mean(axis=0), h, atol=4e-3)
    np.testing.assert_allclose(np.cov(s.T), r, rtol=0.03, atol=1e-4)
    # Jacobian of the mean by central differences
    eps = 1e-6
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        num = (pseudo_measurement_model(mu + d, v, "moments")[0] - pseudo_measurement_model(mu - d, v, "moments")[0])
        np.testing.assert_allclose(jac[:, i], num / (2 * eps), rtol=1e-6, atol=1e-8)
    # the linearised covariance is the first-order term: equal as the noise vanishes
    _, _, r_lin = pseudo_measurement_model(mu, 1e-8, "linearized")
    _, _, r_mom = pseudo_measurement_model(mu, 1e-8, "moments")
    np.testing.assert_allclose(r_lin, r_mom, rtol=1e-5)
    assert np.all(np.linalg.eigvalsh(r) > 0)


def test_single_vehicle_without_sensor_is_the_kalman_filter():
    rng = np.random.default_rng(1)
    params = SmeParams(use_topology=False)
    prior = np.array([10.0, -5.0, 3.0, 1.0])
    cov = np.diag([50.0, 50.0, 25.0, 25.0])
    sme = SmeFilter(prior, cov, params, "sme")
    kf = SmeFilter(prior, cov, params, "kf")
    for t in range(30):
        z = rng.normal(0, 10, (1, 2)) + t
        a = sme.step(z, None, predict=t > 0)
        b = kf.step(z, None, predict=t > 0)
        np.testing.assert_allclose(a[0], b[0], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(a[1], b[1], rtol=1e-9, atol=1e-9)


def prediction_and_measurements(seed=2):
    rng = np.random.default_rng(seed)
    mean = np.concatenate([[*rng.normal(0, 20, 2), *rng.normal(0, 5, 2)] for _ in range(3)])
    cov = np.kron(np.eye(3), np.diag([20.0, 20.0, 4.0, 4.0]))
    pos = mean.reshape(3, 4)[:, :2]
    gps = pos + rng.normal(0, 7, (3, 2))
    sensor = (pos - [50, 80]) @ np.array([[0.6, 0.8], [-0.8, 0.6]]).T + rng.normal(0, 3, (3, 2))
    return mean, cov, gps, sensor, rng


@pytest.mark.parametrize("pseudo_noise", ["moments", "linearized"])
def test_update_invariant_to_conditioning_shift_and_order(pseudo_noise):
    mean, cov, gps, sensor, rng = prediction_and_measurements()
    params = SmeParams(pseudo_noise=pseudo_noise)
    ref = sme_update(mean, cov, gps, sensor, params)  # default centre and scale
    raw = sme_update(mean, cov, gps, sensor, params, centre=np.zeros(2), scale=1.0)  # the paper's raw powers
    other = sme_update(mean, cov, gps, sensor, params, centre=np.array([5.0, -3.0]), scale=3.0)
    shuffled = sme_update(mean, cov, rng.permutation(gps), rng.permutation(sensor), params)
    for m, c in (raw, other, shuffled):
        np.testing.assert_allclose(m, ref[0], rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(c, ref[1], rtol=1e-7, atol=1e-8)
    assert np.linalg.norm(ref[0] - mean) > 0.1


def test_topology_only_changes_the_relative_geometry_information():
    """The sensor adds information: the SME posterior with topology is tighter than without."""
    mean, cov, gps, sensor, _ = prediction_and_measurements(3)
    with_t = sme_update(mean, cov, gps, sensor, SmeParams())
    without = sme_update(mean, cov, gps, sensor, SmeParams(use_topology=False))
    assert np.trace(with_t[1]) < np.trace(without[1])


def test_covariance_stays_symmetric_positive_definite_over_a_run():
    params = SmeParams()
    sim = simulate_run(PAPER_X0, 60, 1.0, 0.5, 50.0, 10.0, [[0, 0, 0]], np.random.default_rng(4))
    prior_cov = np.kron(np.eye(3), np.diag([50.0, 50.0, 25.0, 25.0]))
    f = SmeFilter(sim["truth"][0].reshape(-1), prior_cov, params)
    for t in range(60):
        _, c = f.step(sim["gps_shuffled"][t], sim["scans"][0, t], predict=t > 0)
        np.testing.assert_array_equal(c, c.T)
        assert np.linalg.eigvalsh(c).min() > 0


def test_sme_predict_is_constant_velocity():
    mean = np.array([1.0, 2.0, 3.0, -1.0])
    m, p = sme_predict(mean, np.zeros((4, 4)), SmeParams(process_sigma=0.5, dt=1.0))
    np.testing.assert_allclose(m, [4.0, 1.0, 3.0, -1.0])
    # Zhang (8) at T = 1, per axis: delta^2 [[1/4, 1/2], [1/2, 1]]
    np.testing.assert_allclose(p[np.ix_([0, 2], [0, 2])], 0.25 * np.array([[0.25, 0.5], [0.5, 1.0]]))


def monte_carlo(poses, runs=12, n_steps=60, seed=11):
    params = SmeParams()
    prior_cov = np.kron(np.eye(3), np.diag([50.0, 50.0, 25.0, 25.0]))
    err = {("kf", 0): []}
    for r in range(runs):
        sim = simulate_run(PAPER_X0, n_steps, 1.0, 0.5, 50.0, 10.0, poses, np.random.default_rng([seed, r]))
        prior = sim["truth"][0].reshape(-1) + np.sqrt(np.diag(prior_cov)) * sim["prior_draw"]
        err[("kf", 0)].append(np.sqrt(np.mean(step_errors(run_filter("kf", sim, 0, params, prior, prior_cov),
                                                           sim["truth"])[0])))
        for k in range(len(poses)):
            est = run_filter("sme", sim, k, params, prior, prior_cov)
            err.setdefault(("sme", k), []).append(np.sqrt(np.mean(step_errors(est, sim["truth"])[0])))
    return {k: np.array(v) for k, v in err.items()}


def test_sme_beats_kalman_filter_for_any_sensor_pose():
    """Zhang Sec. IV, 12 seeded runs x 60 steps: SME total error (13) below the KF's for three sensor poses
    the filter is not told; each pose within 0.1 m of the others (same noise, rotated: sampling effect only).
    Measured: KF 10.01 m, SME 9.39 / 9.41 / 9.41 m; SME better in 10 of 12 runs for each pose."""
    poses = [[300.0, -200.0, 40.0], [-2000.0, 1500.0, 200.0], [0.0, 0.0, 0.0]]
    err = monte_carlo(poses)
    kf = err[("kf", 0)]
    means = [err[("sme", k)].mean() for k in range(len(poses))]
    for k in range(len(poses)):
        assert means[k] < kf.mean() - 0.3
        assert np.mean(err[("sme", k)] < kf) >= 0.75
    assert max(means) - min(means) < 0.1
    # a 90 degree rotation of a noise-free scan is exact: same update
    mean, cov, gps, _, _ = prediction_and_measurements(5)
    scan = mean.reshape(3, 4)[:, :2]
    a = sme_update(mean, cov, gps, scan, SmeParams())
    b = sme_update(mean, cov, gps, (scan - [100.0, 7.0]) @ np.array([[0.0, 1.0], [-1.0, 0.0]]).T, SmeParams())
    np.testing.assert_allclose(a[0], b[0], atol=1e-8)


def test_labelled_kalman_update_matches_information_form():
    mean, cov, gps, _, _ = prediction_and_measurements(6)
    m, p = kf_update_labelled(mean, cov, gps, 50.0)
    h = np.zeros((6, 12))
    for i in range(3):
        h[2 * i, 4 * i] = h[2 * i + 1, 4 * i + 1] = 1
    info = np.linalg.inv(cov) + h.T @ h / 50.0
    np.testing.assert_allclose(p, np.linalg.inv(info), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(m, np.linalg.solve(info, np.linalg.solve(cov, mean) + h.T @ gps.reshape(-1) / 50.0),
                               rtol=1e-8, atol=1e-8)
    assert power_sums(np.array([1.0, 2.0]), 2).tolist() == [3.0, 5.0]


def test_uninformative_sensor_reduces_to_sme_without_topology():
    """With a sensor variance of 1e12 m^2 the topology pseudo-measurement carries no information."""
    mean, cov, gps, sensor, _ = prediction_and_measurements(7)
    a = sme_update(mean, cov, gps, sensor, SmeParams(sensor_var=1e12))
    b = sme_update(mean, cov, gps, sensor, SmeParams(use_topology=False))
    np.testing.assert_allclose(a[0], b[0], atol=1e-6)
    np.testing.assert_allclose(a[1], b[1], atol=1e-6)


def test_paper_pseudo_measurements_have_an_exact_xy_pairing_ghost():
    """(10) is a function of (9): sum_{i<j} |p_i - p_j|^2 = sum_axes (N s_2 - s_1^2). So permuting the y
    coordinates among vehicles leaves (9) and (10) unchanged: in Zhang's scenario the ghost
    (80t, 0), (45t, 80t), (0, 45t) of the truth (80t, 0), (45t, 45t), (0, 80t) is indistinguishable,
    which is what the shipped study's one ghost-locked run in 200 follows."""
    from coloc.inference.topology import sum_sq_pairwise

    t = 7.0
    truth = np.array([[80 * t, 0.0], [45 * t, 45 * t], [0.0, 80 * t]])
    ghost = truth.copy()
    ghost[:, 1] = truth[[0, 2, 1], 1]
    for axis in range(2):
        np.testing.assert_allclose(power_sums(ghost[:, axis], 3), power_sums(truth[:, axis], 3))
    assert sum_sq_pairwise(ghost) == pytest.approx(sum_sq_pairwise(truth), rel=1e-12)
    s1, s2 = power_sums(truth[:, 0], 2)
    r1, r2 = power_sums(truth[:, 1], 2)
    assert sum_sq_pairwise(truth) == pytest.approx(3 * s2 - s1**2 + 3 * r2 - r1**2, rel=1e-12)
