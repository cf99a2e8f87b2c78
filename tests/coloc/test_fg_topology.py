"""Factor-graph topology localization (Gulati et al.) against independent references.

* the topology pseudo-measurement: pose/order invariance, gradient, bias and variance (closed form vs sampling);
* without topology the gtsam graph = dense weighted least squares = RTS smoother of kf_gps_odom,
  whose last state = the filter's (the reduce-to-Kalman cross-check);
* with the old / new topology factor the gtsam LM solution = scipy least_squares on the same residuals;
* a radar with huge variance makes the topology factors vanish; shuffling / moving the radar changes nothing;
* seeded Monte Carlo: both topology graphs beat the Kalman filter.
"""

import gtsam
import numpy as np
import pytest
from scipy.optimize import least_squares

from coloc.inference.topology import (
    sum_sq_pairwise,
    sum_sq_pairwise_grad,
    topology_bias,
    topology_pseudo_measurement,
    topology_variance,
    topology_variance_eq16_literal,
)
from coloc.methods.fg_topology import FgTopologyParams, build_graph, fg_localize, kf_gps_odom, run_rmse
from experiments.studies.fg_topology import FgScenario, simulate_run

PARAMS = FgTopologyParams()


def rot(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, s], [-s, c]])


def test_topology_invariant_to_pose_and_order_and_matches_pairwise_sum():
    rng = np.random.default_rng(0)
    p = rng.normal(0, 30, (4, 2))
    direct = sum((p[i] - p[j]) @ (p[i] - p[j]) for i in range(4) for j in range(i + 1, 4))  # eq. (8) literally
    assert sum_sq_pairwise(p) == pytest.approx(direct, rel=1e-12)
    for _ in range(5):
        q = (p - rng.normal(0, 500, 2)) @ rot(rng.uniform(0, 2 * np.pi)).T
        assert sum_sq_pairwise(rng.permutation(q)) == pytest.approx(direct, rel=1e-10)


def test_topology_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    p = rng.normal(0, 10, (3, 2))
    g = sum_sq_pairwise_grad(p)
    h = 1e-5
    for i in range(3):
        for a in range(2):
            dp = np.zeros_like(p)
            dp[i, a] = h
            num = (sum_sq_pairwise(p + dp) - sum_sq_pairwise(p - dp)) / (2 * h)
            assert g[i, a] == pytest.approx(num, rel=1e-7, abs=1e-7)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_topology_bias_and_variance_match_sampling(n):
    """Closed-form mean bias and Var[z^2] ((15) + second-order term) against 200k seeded samples (2 % / 3 %)."""
    rng = np.random.default_rng(2)
    p = rng.normal(0, 5, (n, 2))
    var = 2.0
    samples = sum_sq_pairwise(p + np.sqrt(var) * rng.standard_normal((200_000, n, 2)))
    z2 = sum_sq_pairwise(p)
    assert samples.mean() - z2 == pytest.approx(topology_bias(n, var), rel=0.02)
    assert samples.var() == pytest.approx(topology_variance(z2, n, var), rel=0.03)


def test_topology_variance_first_term_is_gulati_15():
    """M Cov M' with M the gradient (16) of z^2 with respect to the 2N sensor coordinates."""
    rng = np.random.default_rng(3)
    q = rng.normal(0, 20, (3, 2))
    var = 0.1
    m = sum_sq_pairwise_grad(q).T.reshape(-1)  # [d/dx1..d/dxn, d/dy1..d/dyn] as in (16)
    eq15 = m @ (var * np.eye(6)) @ m
    assert topology_variance(sum_sq_pairwise(q), 3, var) - 4 * 2 * 9 * var**2 == pytest.approx(eq15, rel=1e-12)


def small_run(n_veh=3, n_steps=30, seed=4, **sensor):
    params = FgTopologyParams(**sensor)
    data = simulate_run(n_veh, FgScenario(n_steps=n_steps), params, np.random.default_rng(seed))
    return data, params


def dense_least_squares(gps, odom, params):
    """Independent reference: the linear GPS + odometry problem solved as one dense weighted LS per vehicle."""
    T, N, _ = gps.shape
    out = np.empty_like(gps)
    for i in range(N):
        rows, rhs, w = [], [], []
        for t in range(T):
            r = np.zeros(T)
            r[t] = 1
            rows.append(r), rhs.append(gps[t, i]), w.append(1 / params.gps_var)
            if t > 0:
                r = np.zeros(T)
                r[t], r[t - 1] = 1, -1
                rows.append(r), rhs.append(odom[t, i]), w.append(1 / params.odom_var)
        a, b, w = np.array(rows), np.array(rhs), np.sqrt(np.array(w))
        out[:, i] = np.linalg.lstsq(a * w[:, None], b * w[:, None], rcond=None)[0]
    return out


def test_graph_without_topology_is_rts_smoother_and_kalman_filter():
    data, params = small_run()
    fg, iters = fg_localize(data.gps, data.odom, data.sensor, params, "none")
    ls = dense_least_squares(data.gps, data.odom, params)
    rts, rts_cov = kf_gps_odom(data.gps, data.odom, params, smooth=True)
    kf, kf_cov = kf_gps_odom(data.gps, data.odom, params)
    np.testing.assert_allclose(fg, ls, atol=1e-6)
    np.testing.assert_allclose(rts, ls, atol=1e-9)
    np.testing.assert_allclose(kf[-1], ls[-1], atol=1e-9)  # the filter's last state is the smoother's
    assert not np.allclose(kf[:-1], ls[:-1], atol=1e-3)  # but earlier filter states are not smoothed
    for c in (kf_cov, rts_cov):
        np.testing.assert_allclose(c, np.swapaxes(c, -1, -2), atol=0)
        assert np.all(np.linalg.eigvalsh(c) > 0)


@pytest.mark.parametrize("topology", ["old", "new"])
def test_topology_graph_matches_scipy_least_squares(topology):
    """gtsam LM with the CustomFactor = scipy's trust-region LS on the same whitened residuals."""
    data, params = small_run(n_veh=3, n_steps=15, seed=5)
    fg, _ = fg_localize(data.gps, data.odom, data.sensor, params, topology)
    T, N, _ = data.gps.shape
    z2var = [topology_pseudo_measurement(data.sensor[t], params.radar_var) for t in range(T)]

    def residuals(x):
        p = x.reshape(T, N, 2)
        r = [((p - data.gps) / np.sqrt(params.gps_var)).ravel(),
             ((np.diff(p, axis=0) - data.odom[1:]) / np.sqrt(params.odom_var)).ravel()]
        if topology == "old":
            h = sum_sq_pairwise(p)
            z2, var = np.array(z2var).T
        else:  # (11): previous states moved by the odometry
            h = sum_sq_pairwise(p[:-1] + data.odom[1:])
            z2, var = np.array(z2var[1:]).T
        r.append((h - z2) / np.sqrt(var))
        return np.concatenate(r)

    ref = least_squares(residuals, data.gps.ravel(), xtol=1e-12, ftol=1e-12, gtol=1e-12).x.reshape(T, N, 2)
    np.testing.assert_allclose(fg, ref, atol=2e-3)
    plain, _ = fg_localize(data.gps, data.odom, data.sensor, params, "none")
    assert np.max(np.abs(fg - plain)) > 0.05  # the topology factor does something


def test_uninformative_radar_reduces_to_smoother():
    data, params = small_run(n_steps=40, radar_var=1e8)
    plain, _ = fg_localize(data.gps, data.odom, data.sensor, params, "none")
    for topology in ("old", "new"):
        est, _ = fg_localize(data.gps, data.odom, data.sensor, params, topology)
        np.testing.assert_allclose(est, plain, atol=1e-3)


def test_radar_order_and_pose_do_not_matter():
    """Noise-free radar scans seen from two poses and in shuffled order give the same solution."""
    rng = np.random.default_rng(6)
    data, params = small_run(n_steps=30, seed=6)
    scans = []
    for s, th in (((0.0, 0.0), 0.0), ((800.0, -300.0), 2.0)):
        local = (data.truth - np.array(s)) @ rot(th).T
        scans.append(np.array([rng.permutation(x) for x in local]))
    for topology in ("old", "new"):
        a, _ = fg_localize(data.gps, data.odom, scans[0], params, topology)
        b, _ = fg_localize(data.gps, data.odom, scans[1], params, topology)
        np.testing.assert_allclose(a, b, atol=1e-6)


def test_monte_carlo_topology_beats_kalman_filter():
    """12 seeded runs, 2 vehicles, 100 steps: both topology graphs below the KF in mean final RMSE (21),
    the old factor also below the same graph without topology. (Measured: old 2.15, new 2.35,
    no-topology 2.46, KF 3.24 m; the paper's claim new <= old does not hold here, see the study report.)"""
    res = {k: [] for k in ("old", "new", "none", "kf")}
    for run in range(12):
        data = simulate_run(2, FgScenario(n_steps=100), PARAMS, np.random.default_rng([99, run]))
        for k in ("old", "new", "none"):
            res[k].append(run_rmse(fg_localize(data.gps, data.odom, data.sensor, PARAMS, k)[0], data.truth))
        res["kf"].append(run_rmse(kf_gps_odom(data.gps, data.odom, PARAMS)[0], data.truth))
    m = {k: np.mean(v) for k, v in res.items()}
    assert m["old"] < m["kf"] - 0.5
    assert m["new"] < m["kf"] - 0.5
    assert m["old"] < m["none"]


def test_eq16_literal_variance_is_m_cov_m_with_m_the_gradient_of_z():
    """(15)-(16) as printed: M = d z / d(x_1..x_n, y_1..y_n) of z = sqrt(z^2), so M Cov M' = N var."""
    rng = np.random.default_rng(6)
    for n in (2, 3, 4):
        q = rng.normal(0, 30, (n, 2))
        z = np.sqrt(sum_sq_pairwise(q))
        m = (sum_sq_pairwise_grad(q) / (2 * z)).T.reshape(-1)
        h = 1e-6
        num = np.empty(2 * n)
        for a in range(2):
            for i in range(n):
                dq = np.zeros_like(q)
                dq[i, a] = h
                num[a * n + i] = (np.sqrt(sum_sq_pairwise(q + dq)) - np.sqrt(sum_sq_pairwise(q - dq))) / (2 * h)
        np.testing.assert_allclose(m, num, rtol=1e-6)
        assert m @ (0.1 * np.eye(2 * n)) @ m == pytest.approx(topology_variance_eq16_literal(n, 0.1), rel=1e-9)


@pytest.mark.parametrize("topology", ["old", "new"])
def test_topology_noise_option_sets_the_factor_sigma(topology):
    data, _ = small_run(n_veh=3, n_steps=6, seed=7)
    for noise in ("z2", "eq16_literal"):
        params = FgTopologyParams(topology_noise=noise)
        graph = build_graph(data.gps, data.odom, data.sensor, params, topology)
        sig = [graph.at(k).noiseModel().sigmas()[0] for k in range(graph.size())
               if isinstance(graph.at(k), gtsam.CustomFactor)]
        t0 = 0 if topology == "old" else 1
        if noise == "z2":
            want = [np.sqrt(topology_pseudo_measurement(data.sensor[t], params.radar_var)[1]) for t in range(t0, 6)]
        else:
            want = [np.sqrt(3 * params.radar_var)] * (6 - t0)
        np.testing.assert_allclose(sig, want, rtol=1e-12)
    with pytest.raises(ValueError):
        build_graph(data.gps, data.odom, data.sensor, FgTopologyParams(topology_noise="z"), topology)
