"""The band of the share inside the 95 % ellipse when the samples of a run share part of their error
(experiments/sweep/consistency.py, "What the share inside ... can show"): against brute-force draws of whole
runs, and the shared fraction and whitening against their definitions."""

import math

import numpy as np

from experiments.scoring import CHI2_2_95
from experiments.sweep.consistency import inside_share_band, shared_error_fraction, whitened_errors


def _brute_force_means(f, runs, samples, reps, rng, steps=1, phi=1.0):
    """The mean over ``runs`` runs of the share of samples inside, drawn sample by sample: in each run a
    shared 2-D part N(0, f I) (AR(1) over ``steps`` steps with coefficient ``phi``), ``samples`` a step with
    an independent part N(0, (1 - f) I)."""
    out = np.empty(reps)
    for i in range(reps):
        c = rng.standard_normal((runs, 2))
        inside = np.zeros(runs)
        for k in range(steps):
            if k:
                c = phi * c + math.sqrt(1.0 - phi * phi) * rng.standard_normal((runs, 2))
            e = math.sqrt(f) * c[:, None, :] + math.sqrt(1.0 - f) * rng.standard_normal((runs, samples, 2))
            inside += ((e ** 2).sum(axis=-1) <= CHI2_2_95).mean(axis=1)
        out[i] = (inside / steps).mean()
    return out


def test_band_equals_brute_force_runs_with_a_constant_shared_part():
    rng = np.random.default_rng(20261128)
    for f, runs in ((0.5, 5), (0.9, 10)):
        means = _brute_force_means(f, runs, samples=4000, reps=1500, rng=rng)
        lo, hi = inside_share_band([f] * runs)
        # 1500 draws: the 2.5 / 97.5 % quantiles carry a Monte Carlo error of about 0.004 here; the finite
        # samples of a run add a binomial spread of 0.0034 / sqrt(runs)
        assert abs(np.quantile(means, 0.025) - lo) < 0.012, (f, np.quantile(means, 0.025), lo)
        assert abs(np.quantile(means, 0.975) - hi) < 0.012, (f, np.quantile(means, 0.975), hi)


def test_band_equals_brute_force_runs_with_a_drifting_shared_part():
    rng = np.random.default_rng(7)
    tau, window, step = 200.0, 300.0, 10.0
    k = int(round(window / step)) + 1
    means = _brute_force_means(0.8, 6, samples=400, reps=1500, rng=rng, steps=k, phi=math.exp(-step / tau))
    lo, hi = inside_share_band([0.8] * 6, tau_s=tau, window_s=window, step_s=step)
    assert abs(np.quantile(means, 0.025) - lo) < 0.012
    assert abs(np.quantile(means, 0.975) - hi) < 0.012
    # a drifting shared part holds more draws a run than a constant one: a narrower band
    c_lo, c_hi = inside_share_band([0.8] * 6)
    assert c_lo < lo and hi < c_hi


def test_band_narrows_as_runs_are_added_and_widens_with_the_shared_fraction():
    widths = [np.subtract(*inside_share_band([0.8] * r)[::-1]) for r in (5, 20, 80)]
    assert widths[0] > widths[1] > widths[2] > 0
    by_f = [np.subtract(*inside_share_band([f] * 10)[::-1]) for f in (0.0, 0.3, 0.6, 0.9)]
    assert by_f[0] < 1e-12 and by_f[0] < by_f[1] < by_f[2] < by_f[3]
    assert inside_share_band([0.7] * 10, seed=3) == inside_share_band([0.7] * 10, seed=3)


def test_shared_fraction_recovers_the_simulated_split():
    rng = np.random.default_rng(11)
    for f in (0.0, 0.3, 0.9):
        steps, n = 400, 30
        c = rng.standard_normal((steps, 1, 2)) * math.sqrt(f)
        e = c + rng.standard_normal((steps, n, 2)) * math.sqrt(1.0 - f)
        t = np.repeat(np.arange(steps), n)
        got = shared_error_fraction(t, e[..., 0].ravel(), e[..., 1].ravel())
        # 400 steps: the shared part's second moment is known to about 2 / sqrt(2 * 400 * 2) = 5 % of itself
        assert abs(got - f) < 0.05 + 0.1 * f, (f, got)
    assert math.isnan(shared_error_fraction([1, 2], [0.3, 0.1], [0.2, 0.0]))  # no step with two samples


def test_whitened_errors_give_the_nees():
    rng = np.random.default_rng(5)
    a = rng.standard_normal((200, 2, 2))
    cov = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(2)
    e = rng.standard_normal((200, 2))
    wx, wy = whitened_errors(e[:, 0], e[:, 1], cov[:, 0, 0], cov[:, 1, 1], cov[:, 0, 1])
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov), e)
    np.testing.assert_allclose(wx ** 2 + wy ** 2, nees, rtol=1e-10)
