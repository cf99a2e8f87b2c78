"""``[gnss_model] bias_model = "two_state"`` (coloc.methods.gnss_bias2): the 8-D tracker against filterpy's
Kalman filter on the augmented state [p, v, c, l] (and, for ``common_update = "consider"``, which filterpy has
no form of, a Schmidt filter whose update is written out here) per vehicle, against the single model at
``local_share = 0``, and its consistency where its model is the truth."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from scipy.stats import chi2

from coloc.core.models import MotionParams
from coloc.methods.gnss_bias import GnssBiasTracker, GnssModelParams
from tests.coloc.test_gnss_bias import (MOTION, augmented_matrices, filterpy_kf, make_frame, match_reference,
                                        scale_velocity_noise, scripted_run)

TWO = GnssModelParams(bias_model="two_state", common_share=0.45, common_tau_s=300.0, local_share=0.35,
                      local_length_m=15.0, local_tau_s=90.0, innovation_gate=0.0)


class SchmidtKF(KalmanFilter):
    """The Schmidt-Kalman (consider) filter on [p, v, c, l] (Simon 2006, Sec. 7.5): filterpy's prediction,
    and an update written out here because filterpy has none: the gain of the estimated states, zero rows
    for the considered common bias c, P = (I - K H) P (I - K H)^T + K R K^T."""

    def update(self, z, R=None, H=None):
        s = H @ self.P @ H.T + R
        k = self.P @ H.T @ np.linalg.inv(s)
        k[4:6] = 0.0
        self.x = self.x + k @ (z - H @ self.x)
        ikh = np.eye(len(self.x)) - k @ H
        self.P = ikh @ self.P @ ikh.T + k @ R @ k.T


def schmidt_kf(x, p) -> SchmidtKF:
    kf = SchmidtKF(dim_x=len(x), dim_z=4)
    kf.x, kf.P = x.copy(), p.copy()
    return kf


def reference_matrices(x, r, dt, model: GnssModelParams):
    """The tracker's model on [p, v, c, l]: the common bias decays with common_tau_s, the local one with
    local_tau_s and the distance driven at the prior speed over local_length_m."""
    a_c = math.exp(-dt / model.common_tau_s)
    a_l = math.exp(-dt / model.local_tau_s - math.hypot(x[2], x[3]) * dt / model.local_length_m)
    return augmented_matrices(x, r, dt, [(a_c, model.common_share), (a_l, model.local_share)])


@pytest.mark.parametrize("gate,update", [(0.0, "augmented"), (0.999, "augmented"), (0.999, "consider")])
def test_two_state_tracker_equals_filterpy_on_the_augmented_state(gate, update):
    model = replace(TWO, innovation_gate=gate, max_exclusions=2, common_update=update)
    frames = scripted_run(5, 300, model, jumps=0.03 if gate else 0.0)
    est = GnssBiasTracker(motion=MOTION, model=model)
    entries, _, n_excluded = match_reference(est, frames, model, reference_matrices,
                                             [model.common_share, model.local_share],
                                             schmidt_kf if update == "consider" else filterpy_kf)
    assert entries > 10
    assert (n_excluded > 3) == (gate > 0)


@pytest.mark.parametrize("kw", [{}, {"innovation_gate": 0.999, "max_exclusions": 2}, {"bias_follows_report": True}])
def test_no_local_share_is_the_single_model(kw):
    single = GnssModelParams(bias_share=0.7, bias_tau_s=40.0, **{"innovation_gate": 0.0, **kw})
    two = replace(single, bias_model="two_state", common_share=0.7, common_tau_s=40.0, local_share=0.0,
                  common_update="augmented")
    a, b = GnssBiasTracker(motion=MOTION, model=single), GnssBiasTracker(motion=MOTION, model=two)
    for fr in scripted_run(8, 200, single, jumps=0.03):
        x, y = a.step(fr), b.step(fr)
        np.testing.assert_allclose(y.mean, x.mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(y.cov, x.cov, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(a.last_excluded, b.last_excluded)


def simulate_two(seed, steps, model, sigma_p=4.0, sigma_v=0.2, sigma_a=0.2, dt=1.0):
    """One vehicle by model (1) with a fix whose position error is the two-state model exactly: the local
    bias's decay uses the tracker's own prior speed estimate, as the model defines it. Returns the last
    step's (truth, mean, covariance)."""
    rng = np.random.default_rng(seed)
    motion = MotionParams(sigma_along=sigma_a, sigma_cross=sigma_a)
    est = GnssBiasTracker(motion=motion, model=model)
    r = np.diag([sigma_p**2, sigma_p**2, sigma_v**2, sigma_v**2])[None]
    sc, sl = model.common_share, model.local_share
    a_c = math.exp(-dt / model.common_tau_s)
    p0 = np.diag([25.0, 25.0, 1.0, 1.0])
    x = rng.multivariate_normal([0, 0, 10, 0], p0)
    c = rng.normal(0, math.sqrt(sc) * sigma_p, 2)
    loc = rng.normal(0, math.sqrt(sl) * sigma_p, 2)
    out = None
    for t in range(steps):
        u = rng.normal(0, 0.5, 2)
        if t > 0:
            speed = math.hypot(*est._mean[0, 2:4])
            a_l = math.exp(-dt / model.local_tau_s - speed * dt / model.local_length_m)
            acc = u + rng.normal(0, sigma_a, 2)
            x = np.array([x[0] + dt * x[2] + 0.5 * dt * dt * acc[0], x[1] + dt * x[3] + 0.5 * dt * dt * acc[1],
                          x[2] + dt * acc[0], x[3] + dt * acc[1]])
            c = a_c * c + rng.normal(0, math.sqrt((1 - a_c * a_c) * sc) * sigma_p, 2)
            loc = a_l * loc + rng.normal(0, math.sqrt((1 - a_l * a_l) * sl) * sigma_p, 2)
        z = x.copy()
        z[:2] += c + loc + rng.normal(0, math.sqrt(1 - sc - sl) * sigma_p, 2)
        z[2:] += rng.normal(0, sigma_v, 2)
        prior_z = (x + rng.multivariate_normal(np.zeros(4), p0))[None] if t == 0 else np.full((1, 4), np.nan)
        fr = make_frame(float(t), dt, ["v"], [t == 0], u[None], z[None], r, prior_z,
                        p0[None] if t == 0 else np.full((1, 4, 4), np.nan))
        out = est.step(fr)
    return x, out.mean[0], out.cov[0]


@pytest.mark.slow
@pytest.mark.parametrize("update", ["augmented", "consider"])
def test_consistent_where_its_model_is_the_truth(update):
    model = replace(TWO, common_update=update)
    runs = 100
    nees2, nees4 = [], []
    for seed in range(runs):
        truth, mean, cov = simulate_two(seed, 150, model)
        e = truth - mean
        nees2.append(e[:2] @ np.linalg.solve(cov[:2, :2], e[:2]))
        nees4.append(e @ np.linalg.solve(cov, e))
    for nees, dof in ((nees2, 2), (nees4, 4)):
        lo, hi = chi2.ppf([0.005, 0.995], dof * runs) / runs
        assert lo < np.mean(nees) < hi, (update, dof, np.mean(nees), lo, hi)


@pytest.mark.parametrize("kw", [{"bias_model": "double"}, {"common_update": "schmidt"}, {"common_tau_s": 0.0},
                                {"local_length_m": -1.0}, {"local_tau_s": math.inf}, {"common_share": 1.0},
                                {"local_share": -0.1},
                                {"bias_model": "two_state", "common_share": 0.6, "local_share": 0.4},
                                {"bias_model": "two_state", "adaptive_window_s": 10.0},
                                {"common_sigma_m": -0.1}, {"common_sigma_m": math.nan},
                                {"bias_model": "two_state", "velocity_gate": 1.0}])
def test_two_state_params_refuse_values_that_break_the_model(kw):
    with pytest.raises(ValueError):
        GnssModelParams(**kw)


def test_the_other_methods_keep_the_single_model():
    two = replace(TWO, bias_share=0.6, bias_tau_s=50.0)
    single = two.single_model()
    assert single.bias_model == "single" and single.state_dim == 6
    assert (single.bias_share, single.bias_tau_s) == (0.6, 50.0)
    assert TWO.state_dim == 8 and GnssModelParams().single_model() == GnssModelParams()


@pytest.mark.parametrize("update", ["augmented", "consider"])
def test_common_sigma_and_velocity_test_equal_filterpy(update):
    """``common_sigma_m`` and ``velocity_gate``: the tracker against a filter written on filterpy with the
    common-mode bias's covariance s_c R + sigma_c^2 I and, where the velocity innovation's d^2 (on the
    prior) exceeds the threshold, the velocity noise scaled by d^2 / threshold (Chang 2014)."""
    model = replace(TWO, common_update=update, common_sigma_m=1.3, velocity_gate=0.95)
    frames = scripted_run(7, 200, model)
    for fr in frames[::9]:  # reflected range rates: velocities metres per second off
        fr.gnss_z[:, 2] += 4.0
    est = GnssBiasTracker(motion=MOTION, model=model)
    refs = {}
    thr = chi2.ppf(model.velocity_gate, 2)
    sig2 = model.common_sigma_m ** 2 * np.eye(2)
    scaled = 0
    for fr in frames:
        out = est.step(fr)
        for i, vid in enumerate(fr.vehicle_ids):
            r = fr.gnss_R[i]
            f, b, q, h, rn = reference_matrices(refs[vid].x if vid in refs else np.zeros(8), r, fr.dt, model)
            a_c = math.exp(-fr.dt / model.common_tau_s)
            q[4:6, 4:6] += (1.0 - a_c * a_c) * sig2
            if fr.entered[i]:
                p0 = np.zeros((8, 8))
                p0[:4, :4] = fr.prior_R[i]
                p0[4:6, 4:6] = model.common_share * r[:2, :2] + sig2
                p0[6:8, 6:8] = model.local_share * r[:2, :2]
                x0 = np.concatenate([fr.prior_z[i], np.zeros(4)])
                refs[vid] = schmidt_kf(x0, p0) if update == "consider" else filterpy_kf(x0, p0)
                refs[vid].update(fr.gnss_z[i], R=rn, H=h)
            else:
                kf = refs[vid]
                kf.predict(u=fr.accel[i], B=b, F=f, Q=q)
                scaled += scale_velocity_noise(kf, fr.gnss_z[i], rn, h, thr)
                kf.update(fr.gnss_z[i], R=rn, H=h)
            np.testing.assert_allclose(out.mean[i], refs[vid].x[:4], rtol=0, atol=1e-9)
            np.testing.assert_allclose(out.cov[i], refs[vid].P[:4, :4], rtol=0, atol=1e-9)
    assert scaled > 20


def test_consider_keeps_the_common_sigma_in_the_position():
    """Vehicles that start from their own receiver's fix (``start = "gnss_fix"``: the entry prior is the
    fix, with the report's covariance plus sigma_c^2 I) and a consider common-mode bias of size sigma_c: no
    number of fixes brings a position variance below sigma_c^2 per axis (a single receiver cannot tell that
    error from its position); without it (sigma_c = 0) the variance falls below."""
    low = {}
    for sigma in (2.0, 0.0):
        model = replace(TWO, common_update="consider", common_sigma_m=sigma)
        est = GnssBiasTracker(motion=MOTION, model=model)
        smallest = math.inf
        for fr in scripted_run(3, 300, model):
            fr = replace(fr, prior_R=np.where(fr.entered[:, None, None], fr.gnss_R, np.nan),
                         prior_has_fix=np.asarray(fr.entered, dtype=bool))
            out = est.step(fr)
            smallest = min(smallest, np.linalg.eigvalsh(out.cov[:, :2, :2]).min())
        low[sigma] = smallest
    assert low[2.0] >= 4.0 * (1 - 1e-9)
    assert low[0.0] < 4.0
