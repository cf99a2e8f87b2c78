"""``gnss`` with ``[gnss_model]`` (coloc.methods.gnss_bias): the 6-D bias-state tracker against
filterpy's Kalman filter on the augmented state [p, v, b] per vehicle, against the white tracker at
bias_share = 0, its consistency where its model is the truth, and the fault exclusion."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from scipy.linalg import block_diag
from scipy.stats import chi2

from coloc.core.frame import empty_frame
from coloc.core.models import MotionParams, driving_noise_cov
from coloc.methods.gnss import GnssTracker
from coloc.methods.gnss_bias import GnssBiasTracker, GnssModelParams

MOTION = MotionParams(sigma_along=0.3, sigma_cross=0.1)


def make_frame(t, dt, ids, entered, accel, gnss_z, gnss_R, prior_z=None, prior_R=None):
    n = len(ids)
    return replace(
        empty_frame(t, dt), vehicle_ids=np.array(ids, dtype=object), entered=np.asarray(entered, dtype=bool),
        prior_z=np.full((n, 4), np.nan) if prior_z is None else prior_z,
        prior_R=np.full((n, 4, 4), np.nan) if prior_R is None else prior_R,
        accel=np.asarray(accel, float), gnss_z=np.asarray(gnss_z, float), gnss_R=np.asarray(gnss_R, float),
    )


def filterpy_kf(x, p) -> KalmanFilter:
    """filterpy's linear Kalman filter on the augmented state, started at (x, p); F, B, Q, H and R are
    given to it per step (predict(u, B, F, Q), update(z, R, H): its Joseph-form update)."""
    kf = KalmanFilter(dim_x=len(x), dim_z=4)
    kf.x, kf.P = x.copy(), p.copy()
    return kf


def scale_velocity_noise(kf, z, rn, h, threshold, on_innovation=False) -> bool:
    """The robust velocity (Chang 2014) on a reference filter's predicted state: where the velocity part of the
    innovation's d^2 exceeds ``threshold``, ``rn``'s velocity block (in place) times d^2 / threshold; with
    ``on_innovation``, plus (d^2 / threshold - 1) times the innovation covariance's velocity block (so that the
    velocity block of S is scaled by d^2 / threshold)."""
    s = h @ kf.P @ h.T + rn
    nu = (z - h @ kf.x)[2:]
    d2 = float(nu @ np.linalg.solve(s[2:, 2:], nu))
    if d2 > threshold:
        if on_innovation:
            rn[2:, 2:] += (d2 / threshold - 1.0) * s[2:, 2:]
        else:
            rn[2:, 2:] *= d2 / threshold
    return d2 > threshold


def nis_pos(kf, z, r, h) -> float:
    """The gate's statistic: the position part of the fix's normalised innovation squared, on the prior."""
    s = h @ kf.P @ h.T + r
    nu = (z - h @ kf.x)[:2]
    return float(nu @ np.linalg.solve(s[:2, :2], nu))


def match_reference(est, frames, model, matrices, shares, new_filter=filterpy_kf):
    """Step ``est`` over ``frames`` beside one reference filter per vehicle (``new_filter(x0, p0)``; the
    bias states start at zero with ``share * R_pos`` each) and assert mean, covariance and the full
    augmented state equal to 1e-9 after every step. A vehicle's first fix is an update without
    prediction; the gate excludes a fix's position (the velocity is still used) while its statistic
    exceeds chi2(gate, 2), at most ``max_exclusions`` times in a row. ``matrices(x, r, dt, model)``
    gives the step's (F, B, Q, H, R). Returns (entries, leaves, exclusions)."""
    refs: dict[str, KalmanFilter] = {}
    streak: dict[str, int] = {}
    threshold = chi2.ppf(model.innovation_gate, 2) if model.innovation_gate else math.inf
    entries = leaves = n_excluded = 0
    previous: set[str] = set()
    for fr in frames:
        out = est.step(fr)
        ids = list(fr.vehicle_ids)
        leaves += len(previous - set(ids))
        previous = set(ids)
        for i, vid in enumerate(ids):
            r = fr.gnss_R[i]
            if fr.entered[i]:
                entries += 1
                p0 = block_diag(fr.prior_R[i], *(s * r[:2, :2] for s in shares))
                refs[vid] = new_filter(np.concatenate([fr.prior_z[i], np.zeros(2 * len(shares))]), p0)
                _f, _b, _q, h, rn = matrices(refs[vid].x, r, fr.dt, model)
                refs[vid].update(fr.gnss_z[i], R=rn, H=h)
                streak[vid] = 0
            else:
                kf = refs[vid]
                f, b, q, h, rn = matrices(kf.x, r, fr.dt, model)
                kf.predict(u=fr.accel[i], B=b, F=f, Q=q)
                if nis_pos(kf, fr.gnss_z[i], rn, h) > threshold and streak[vid] < model.max_exclusions:
                    n_excluded += 1
                    streak[vid] += 1
                    assert est.last_excluded[i]
                    kf.update(fr.gnss_z[i][2:], R=rn[2:, 2:], H=h[2:])  # the velocity only
                else:
                    streak[vid] = 0
                    assert not est.last_excluded[i]
                    kf.update(fr.gnss_z[i], R=rn, H=h)
            np.testing.assert_allclose(out.mean[i], refs[vid].x[:4], rtol=0, atol=1e-9)
            np.testing.assert_allclose(out.cov[i], refs[vid].P[:4, :4], rtol=0, atol=1e-9)
            np.testing.assert_allclose(est._cov[i], refs[vid].P, rtol=0, atol=1e-9)
            np.testing.assert_allclose(est._mean[i], refs[vid].x, rtol=0, atol=1e-9)
    return entries, leaves, n_excluded


def augmented_matrices(x, r, dt, blocks):
    """F, B, Q, H and the fix's white covariance on [p, v, b_1, ...]: each (decay a, share s) of ``blocks``
    a 2-D Gauss-Markov bias with stationary covariance s R_pos (Q = (1 - a^2) s R_pos), added to the
    position fix, whose white part keeps (1 - sum s) R_pos; Q of [p, v] from the prior velocity x[2:4]."""
    n = 4 + 2 * len(blocks)
    f = np.eye(n)
    f[0, 2] = f[1, 3] = dt
    b = np.zeros((n, 2))
    b[0, 0] = b[1, 1] = 0.5 * dt * dt
    b[2, 0] = b[3, 1] = dt
    q = np.zeros((n, n))
    q[:4, :4] = driving_noise_cov(x[None, 2:4], dt, MOTION)[0]
    h = np.zeros((4, n))
    h[:, :4] = np.eye(4)
    for k, (a, share) in enumerate(blocks):
        i = 4 + 2 * k
        f[i, i] = f[i + 1, i + 1] = a
        q[i:i + 2, i:i + 2] = (1 - a * a) * share * r[:2, :2]
        h[0, i] = h[1, i + 1] = 1.0
    rn = r.copy()
    rn[:2, :2] *= 1 - sum(share for _, share in blocks)
    return f, b, q, h, rn


def reference_matrices(x, r, dt, model: GnssModelParams):
    """The tracker's model on [p, v, b]: one bias of decay exp(-dt / bias_tau_s) and share bias_share."""
    return augmented_matrices(x, r, dt, [(math.exp(-dt / model.bias_tau_s), model.bias_share)])


def random_r(rng):
    """A reported covariance: position and velocity blocks of random scale and orientation."""
    r = np.zeros((4, 4))
    for sl, scale in ((slice(0, 2), rng.uniform(1.0, 8.0)), (slice(2, 4), rng.uniform(0.05, 0.5))):
        g = rng.normal(size=(2, 2))
        r[sl, sl] = scale**2 * (0.3 * np.eye(2) + g @ g.T / 2)
    return r


def scripted_run(seed, steps, model, jumps=0.0):
    """Frames with vehicles entering and leaving at random, random inputs, random reported covariances
    (a new one every step: zone changes) and fixes around a drifting truth; ``jumps``: the probability
    of a fix 50 m off."""
    rng = np.random.default_rng(seed)
    alive: dict[str, np.ndarray] = {}
    serial = 0
    frames = []
    for t in range(steps):
        for vid in list(alive):
            if rng.random() < 0.02:
                del alive[vid]
        entered = []
        while len(alive) < 2 or (len(alive) < 7 and rng.random() < 0.1):
            alive[f"v{serial}"] = np.array([rng.uniform(-100, 100), rng.uniform(-100, 100),
                                            rng.normal(0, 8), rng.normal(0, 8)])
            entered.append(f"v{serial}")
            serial += 1
        ids = list(alive)
        n = len(ids)
        accel = rng.normal(0, 1.0, (n, 2))
        r = np.stack([random_r(rng) for _ in range(n)])
        for i, vid in enumerate(ids):
            x = alive[vid]
            alive[vid] = np.array([x[0] + x[2] + 0.5 * accel[i, 0], x[1] + x[3] + 0.5 * accel[i, 1],
                                   x[2] + accel[i, 0], x[3] + accel[i, 1]])
        truth = np.stack([alive[v] for v in ids])
        z = truth + np.einsum("nij,nj->ni", np.linalg.cholesky(r), rng.normal(size=(n, 4)))
        z[:, :2] += 3.0 * np.sin(0.05 * t)  # a slow common error
        jump = rng.random(n) < jumps
        z[jump, 0] += 50.0
        is_new = np.array([v in entered for v in ids])
        prior_z = np.where(is_new[:, None], z, np.nan)
        prior_R = np.where(is_new[:, None, None], r * 4.0, np.nan)
        frames.append(make_frame(float(t), 1.0, ids, is_new, accel, z, r, prior_z, prior_R))
    return frames


@pytest.mark.parametrize("gate", [0.0, 0.999])
def test_bias_tracker_equals_filterpy_on_the_augmented_state(gate):
    model = GnssModelParams(bias_share=0.7, bias_tau_s=40.0, innovation_gate=gate, max_exclusions=2)
    frames = scripted_run(5, 300, model, jumps=0.03 if gate else 0.0)
    est = GnssBiasTracker(motion=MOTION, model=model)
    entries, leaves, n_excluded = match_reference(est, frames, model, reference_matrices, [model.bias_share])
    assert entries > 10 and leaves > 5
    assert (n_excluded > 3) == (gate > 0)
    if gate:
        assert max_streak_hit(frames, model)


def max_streak_hit(frames, model) -> bool:
    """Some vehicle had its fix taken after max_exclusions exclusions in a row (the scripted world's
    slow common error makes long runs of exclusions)."""
    est = GnssBiasTracker(motion=MOTION, model=model)
    for fr in frames:
        est.step(fr)
        before = dict(zip(fr.vehicle_ids, est._streak))
        if any(v == model.max_exclusions for v in before.values()):
            return True
    return False


def test_zero_bias_share_is_the_white_tracker():
    model = GnssModelParams(bias_share=0.0, innovation_gate=0.0)
    white, bias = GnssTracker(motion=MOTION), GnssBiasTracker(motion=MOTION, model=model)
    for fr in scripted_run(8, 200, model):
        a, b = white.step(fr), bias.step(fr)
        np.testing.assert_allclose(b.mean, a.mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b.cov, a.cov, rtol=1e-12, atol=1e-12)


def simulate(seed, steps, model, sigma_p=4.0, sigma_v=0.2, sigma_a=0.2, dt=1.0, tracker=None):
    """One vehicle moving by model (1) (isotropic driving noise sigma_a, known input) with a GNSS fix
    whose position error is the tracker's model exactly: a Gauss-Markov bias plus white noise.
    ``tracker``: the tracker's model when not ``model`` (the draws stay the same).
    Returns (truth (steps, 4), means, covariances)."""
    rng = np.random.default_rng(seed)
    motion = MotionParams(sigma_along=sigma_a, sigma_cross=sigma_a)
    est = GnssBiasTracker(motion=motion, model=model if tracker is None else tracker)
    r = np.diag([sigma_p**2, sigma_p**2, sigma_v**2, sigma_v**2])[None]
    s, a = model.bias_share, math.exp(-dt / model.bias_tau_s)
    p0 = np.diag([25.0, 25.0, 1.0, 1.0])
    x = rng.multivariate_normal([0, 0, 10, 0], p0)
    bias = rng.normal(0, math.sqrt(s) * sigma_p, 2)
    truth, means, covs = [], [], []
    for t in range(steps):
        u = rng.normal(0, 0.5, 2)
        if t > 0:
            acc = u + rng.normal(0, sigma_a, 2)
            x = np.array([x[0] + dt * x[2] + 0.5 * dt * dt * acc[0], x[1] + dt * x[3] + 0.5 * dt * dt * acc[1],
                          x[2] + dt * acc[0], x[3] + dt * acc[1]])
            bias = a * bias + rng.normal(0, math.sqrt((1 - a * a) * s) * sigma_p, 2)
        z = x.copy()
        z[:2] += bias + rng.normal(0, math.sqrt(1 - s) * sigma_p, 2)
        z[2:] += rng.normal(0, sigma_v, 2)
        prior_z = (x + rng.multivariate_normal(np.zeros(4), p0))[None] if t == 0 else np.full((1, 4), np.nan)
        fr = make_frame(float(t), dt, ["v"], [t == 0], u[None], z[None], r, prior_z,
                        p0[None] if t == 0 else np.full((1, 4, 4), np.nan))
        out = est.step(fr)
        truth.append(x.copy())
        means.append(out.mean[0])
        covs.append(out.cov[0])
    return np.array(truth), np.array(means), np.array(covs)


def test_consistent_where_its_model_is_the_truth():
    model = GnssModelParams(bias_share=0.8, bias_tau_s=30.0, innovation_gate=0.0)
    runs = 100
    nees2, nees4 = [], []
    for seed in range(runs):
        truth, mean, cov = simulate(seed, 150, model)
        e = truth[-1] - mean[-1]
        nees2.append(e[:2] @ np.linalg.solve(cov[-1][:2, :2], e[:2]))
        nees4.append(e @ np.linalg.solve(cov[-1], e))
    for nees, dof in ((nees2, 2), (nees4, 4)):
        lo, hi = chi2.ppf([0.005, 0.995], dof * runs) / runs
        assert lo < np.mean(nees) < hi, (dof, np.mean(nees), lo, hi)


def test_the_bias_state_beats_the_white_tracker_on_a_correlated_error():
    """The same correlated fixes: the white tracker's error is larger and its NEES far above 2."""
    model = GnssModelParams(bias_share=0.8, bias_tau_s=30.0, innovation_gate=0.0)
    white_model = GnssModelParams(bias_share=0.0, innovation_gate=0.0)
    err = {"bias": [], "white": []}
    nees_white = []
    for seed in range(20):
        truth, mean, cov = simulate(seed, 150, model)
        err["bias"].append(np.sum((truth[-1, :2] - mean[-1, :2]) ** 2))
    for seed in range(20):
        t2, m2, c2 = simulate(seed, 150, model, tracker=white_model)  # the same draws
        e = t2[-1, :2] - m2[-1, :2]
        err["white"].append(e @ e)
        nees_white.append(e @ np.linalg.solve(c2[-1][:2, :2], e))
    assert np.mean(err["bias"]) < np.mean(err["white"])
    assert np.mean(nees_white) > 4.0


def test_a_50_m_jump_is_excluded_and_ordinary_fixes_are_kept():
    """Fixes from the tracker's own error model (Gauss-Markov bias + white noise, 3 m): none excluded
    but the one 50 m off, whose position is not used."""
    model = GnssModelParams(bias_share=0.8, bias_tau_s=30.0, innovation_gate=0.999)
    rng = np.random.default_rng(4)
    est = GnssBiasTracker(motion=MOTION, model=model)
    r = np.diag([9.0, 9.0, 0.04, 0.04])[None]
    a = math.exp(-1.0 / model.bias_tau_s)
    x = np.array([0.0, 0.0, 10.0, 0.0])
    bias = rng.normal(0, math.sqrt(0.8) * 3.0, 2)
    excluded = []
    for t in range(150):
        if t > 0:
            x = x + np.array([10.0, 0.0, 0.0, 0.0])
            bias = a * bias + rng.normal(0, math.sqrt((1 - a * a) * 0.8) * 3.0, 2)
        z = x + rng.normal(0, [math.sqrt(0.2) * 3.0, math.sqrt(0.2) * 3.0, 0.2, 0.2])
        z[:2] += bias
        if t == 100:
            z[0] += 50.0
        fr = make_frame(float(t), 1.0, ["v"], [t == 0], np.zeros((1, 2)), z[None], r,
                        z[None] if t == 0 else np.full((1, 4), np.nan),
                        r * 4 if t == 0 else np.full((1, 4, 4), np.nan))
        before = est._mean.copy()
        out = est.step(fr)
        excluded.append(bool(est.last_excluded[0]))
        if t == 100:
            # the position is not pulled towards the jump: within 0.5 m of the prior carried one step
            # (the velocity update moves it a little), far from the 50 m off fix
            assert np.linalg.norm(out.mean[0, :2] - (before[0, :2] + before[0, 2:4])) < 0.5
    assert excluded[100]
    assert sum(excluded) == 1


@pytest.mark.parametrize("kw", [{"bias_share": 1.0}, {"bias_share": -0.1}, {"bias_tau_s": 0.0},
                                {"bias_tau_s": math.inf}, {"innovation_gate": 1.0}, {"max_exclusions": -1}])
def test_params_refuse_values_that_break_the_model(kw):
    with pytest.raises(ValueError):
        GnssModelParams(**kw)


@pytest.mark.parametrize("inflation", ["noise", "innovation"])
def test_velocity_test_equals_filterpy(inflation):
    """``velocity_gate`` in the single model: the tracker against filterpy on [p, v, b] with the velocity noise
    scaled by d^2 / threshold where the velocity innovation's d^2 (on the prior) exceeds the threshold (or,
    ``velocity_inflation = "innovation"``, the innovation covariance's velocity block scaled by it)."""
    model = GnssModelParams(bias_share=0.7, bias_tau_s=40.0, innovation_gate=0.0, velocity_gate=0.95,
                            velocity_inflation=inflation)
    frames = scripted_run(4, 200, model)
    for fr in frames[::7]:  # reflected range rates
        fr.gnss_z[:, 3] -= 5.0
    est = GnssBiasTracker(motion=MOTION, model=model)
    thr = chi2.ppf(model.velocity_gate, 2)
    refs, scaled = {}, 0
    for fr in frames:
        out = est.step(fr)
        for i, vid in enumerate(fr.vehicle_ids):
            r = fr.gnss_R[i]
            if fr.entered[i]:
                refs[vid] = filterpy_kf(np.concatenate([fr.prior_z[i], np.zeros(2)]),
                                        block_diag(fr.prior_R[i], model.bias_share * r[:2, :2]))
                _f, _b, _q, h, rn = reference_matrices(refs[vid].x, r, fr.dt, model)
            else:
                kf = refs[vid]
                f, b, q, h, rn = reference_matrices(kf.x, r, fr.dt, model)
                kf.predict(u=fr.accel[i], B=b, F=f, Q=q)
                scaled += scale_velocity_noise(kf, fr.gnss_z[i], rn, h, thr, inflation == "innovation")
            refs[vid].update(fr.gnss_z[i], R=rn, H=h)
            np.testing.assert_allclose(out.mean[i], refs[vid].x[:4], rtol=0, atol=1e-9)
            np.testing.assert_allclose(out.cov[i], refs[vid].P[:4, :4], rtol=0, atol=1e-9)
    assert scaled > 20
