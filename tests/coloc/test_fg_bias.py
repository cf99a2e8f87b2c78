"""``fg_topology_new`` with ``[gnss_model]`` (coloc.methods.fg_bias, FgTopologyInfra._rsu_step_bias): the receiver
bias as a Gauss-Markov chain of factors, on scenes whose fixes carry exactly that bias (the model is the truth)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from coloc.core.models import MotionParams
from coloc.methods.fg_topology import FgTopologyInfra
from coloc.methods.gnss_bias import GnssModelParams
from coloc.methods.infra import InfraMethodParams, home_rsu
from scenes import infra_frames

MOTION = MotionParams(sigma_along=0.35, sigma_cross=0.1)
# No fault exclusion: the simulated fixes have no faults, so every fix is a factor (and the reference KF's).
MODEL = GnssModelParams(bias_share=0.8, bias_tau_s=30.0, innovation_gate=0.0)


def bias_frames(seed: int, n_veh: int, n_steps: int, model: GnssModelParams = MODEL, sigma: float = 3.0,
                sigma_v: float = 0.1) -> list:
    """:func:`scenes.infra_frames` with the fixes of the estimator's model: z = p + b + n with the Gauss-Markov
    bias b (stationary start, decay exp(-dt / tau), share s of sigma^2) and white n ((1 - s) sigma^2); the
    velocity fix white (sigma_v). Every vehicle enters at step 0 from its fix (``prior_has_fix``)."""
    frames = infra_frames(n_steps=n_steps, n_veh=n_veh, seed=seed, features=False)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xF6B]))
    s, dt = model.bias_share, frames[0].dt
    a = math.exp(-dt / model.bias_tau_s)
    r = np.diag([sigma**2, sigma**2, sigma_v**2, sigma_v**2])
    b = math.sqrt(s) * sigma * rng.standard_normal((n_veh, 2))
    out = []
    for k, f in enumerate(frames):
        if k:
            b = a * b + math.sqrt((1 - a * a) * s) * sigma * rng.standard_normal((n_veh, 2))
        z = f.truth.x_true.copy()
        z[:, :2] += b + math.sqrt(1 - s) * sigma * rng.standard_normal((n_veh, 2))
        z[:, 2:] += sigma_v * rng.standard_normal((n_veh, 2))
        gr = np.broadcast_to(r, (n_veh, 4, 4)).copy()
        kw = {"gnss_z": z, "gnss_R": gr}
        if k == 0:
            kw.update(prior_z=z.copy(), prior_R=gr.copy(), prior_has_fix=np.ones(n_veh, dtype=bool))
        out.append(replace(f, **kw))
    return out


def _fg(window: int = 6) -> FgTopologyInfra:
    return FgTopologyInfra(InfraMethodParams(motion=MOTION, fg_window_steps=window), gnss_model=MODEL)


def test_one_vehicle_is_the_augmented_kalman_filter():
    """One vehicle (no topology factor): linear-Gaussian, the window's marginalisation exact, so the smoother's
    latest position and its marginal covariance are the augmented Kalman filter's on [p, b] (odometry as
    the input, p' = p + d with odom_var I; b' = a b with (1 - a^2) s R; z = p + b with (1 - s) R), started
    from the same joint (p, b) belief (the bias tracker's, predicted)."""
    frames = bias_frames(seed=4, n_veh=1, n_steps=30)
    fg = _fg(window=4)
    s, a = MODEL.bias_share, math.exp(-frames[0].dt / MODEL.bias_tau_s)
    h = np.hstack([np.eye(2), np.eye(2)])
    x = p = None
    checked = 0
    for f in frames:
        prev = (fg.gnss._ids.copy(), fg.gnss._mean.copy(), fg.gnss._cov.copy())
        out = fg.step(f.without_truth())
        if not out.covered[0]:
            x = None
            continue
        rz = f.gnss_R[0, :2, :2]
        if x is None:
            m6, c6, held = fg._start_beliefs6(f, np.array([0]), prev)
            assert not held[0]
            sel = [0, 1, 4, 5]
            x, p = m6[0, sel], c6[0][np.ix_(sel, sel)]
        else:
            f4 = np.diag([1.0, 1.0, a, a])
            q = np.zeros((4, 4))
            q[:2, :2] = f.infra.odom_var * np.eye(2)
            q[2:, 2:] = (1 - a * a) * s * rz
            x = f4 @ x + np.r_[f.infra.odom[0], 0.0, 0.0]
            p = f4 @ p @ f4.T + q
        sm = h @ p @ h.T + (1 - s) * rz
        k = p @ h.T @ np.linalg.inv(sm)
        x = x + k @ (f.gnss_z[0, :2] - h @ x)
        p = (np.eye(4) - k @ h) @ p
        np.testing.assert_allclose(out.mean[0, :2], x[:2], atol=1e-5, rtol=0)
        np.testing.assert_allclose(out.cov[0, :2, :2], p[:2, :2], atol=1e-8, rtol=1e-8)
        checked += 1
    assert checked > 15


def test_bias_model_widens_the_white_covariance_and_keeps_the_paper_path():
    """The white factor graph reports the tracker's covariance; the bias chain reports its own marginal, which
    with correlated fixes is wider than the white 4-D tracker's (the fixes do not average out)."""
    frames = bias_frames(seed=5, n_veh=4, n_steps=16)
    white = FgTopologyInfra(InfraMethodParams(motion=MOTION))
    biased = _fg()
    for f in frames:
        w = white.step(f.without_truth())
        b = biased.step(f.without_truth())
    cov = w.covered & b.covered
    assert cov.sum() >= 2
    assert np.all(np.trace(b.cov[cov, :2, :2], axis1=1, axis2=2) > np.trace(w.cov[cov, :2, :2], axis1=1, axis2=2))
    assert biased.stats["topology_updates"] > 5


@pytest.mark.slow
def test_nees_where_the_model_is_the_truth():
    """100 runs of 4 vehicles through one RSU (GNSS 3 m with the bias of MODEL, radar 0.3 m, odometry 0.1 m):
    the 2-D position NEES of every vehicle at step 18 (all four in range since step 6, the set unchanged),
    400 samples; their mean inside the 99 % chi-square band of 800 degrees of freedom (the vehicles of a run
    share the topology factors, so the band is approximate)."""
    k_star = 18
    nees = []
    for run in range(100):
        frames = bias_frames(seed=1000 + run, n_veh=4, n_steps=k_star + 1)
        fg = _fg()
        for f in frames:
            out = fg.step(f.without_truth())
        assert np.all(out.covered) and np.all(home_rsu(f.infra.v2i) >= 0)
        e = out.mean[:, :2] - f.truth.x_true[:, :2]
        nees.extend(np.einsum("ni,ni->n", e, np.linalg.solve(out.cov[:, :2, :2], e[..., None])[..., 0]))
    n = len(nees)
    lo, hi = chi2.ppf([0.005, 0.995], 2 * n) / n
    assert lo <= np.mean(nees) <= hi, (np.mean(nees), lo, hi)
