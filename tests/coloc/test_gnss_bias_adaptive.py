"""Adaptive fading of ``gnss`` with ``[gnss_model]`` (``adaptive_window_s``, coloc.methods.gnss_bias): the
plain filter where the fading factor is 1, consistent (not overconfident, not far from it) where the model
is the truth, and the covariance grows where the fixes carry an error the model does not."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from coloc.methods.gnss_bias import GnssBiasTracker, GnssModelParams
from tests.coloc.test_gnss_bias import MOTION, make_frame, scripted_run, simulate


def test_off_by_default_and_the_plain_update_where_innovations_are_small():
    """adaptive_window_s = 0 is the default; with it on, every step whose average normalized innovation
    stays <= 1 is the plain filter to 1e-12 (here: fixes on the prediction, innovation 0)."""
    assert GnssModelParams().adaptive_window_s == 0.0
    plain = GnssModelParams(bias_share=0.8, bias_tau_s=30.0)
    adapt = GnssModelParams(bias_share=0.8, bias_tau_s=30.0, adaptive_window_s=20.0)
    a, b = GnssBiasTracker(motion=MOTION, model=plain), GnssBiasTracker(motion=MOTION, model=adapt)
    r = np.diag([9.0, 9.0, 0.04, 0.04])[None]
    x = np.array([0.0, 0.0, 10.0, 0.0])
    for t in range(60):
        z = x + np.array([10.0 * t, 0.0, 0.0, 0.0])
        fr = make_frame(float(t), 1.0, ["v"], [t == 0], np.zeros((1, 2)), z[None], r,
                        z[None] if t == 0 else np.full((1, 4), np.nan),
                        r * 4 if t == 0 else np.full((1, 4, 4), np.nan))
        ea, eb = a.step(fr), b.step(fr)
        np.testing.assert_allclose(eb.mean, ea.mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(eb.cov, ea.cov, rtol=1e-12, atol=1e-12)
    assert np.all(b._nis <= 1.0)


def test_consistent_where_its_model_is_the_truth():
    """100 seeded runs of the linear-Gaussian scenario of test_gnss_bias (the tracker's model is the
    truth): the average 2-D NEES at the last step inside the 99 % chi-square band of 100 runs. The fading
    factor is >= 1, so the filter can only be more conservative than the plain one; this bounds by how much."""
    model = GnssModelParams(bias_share=0.8, bias_tau_s=30.0, innovation_gate=0.0, adaptive_window_s=30.0)
    runs = 100
    nees = []
    for seed in range(runs):
        truth, mean, cov = simulate(seed, 150, model)
        e = truth[-1, :2] - mean[-1, :2]
        nees.append(e @ np.linalg.solve(cov[-1][:2, :2], e))
    lo, hi = chi2.ppf([0.005, 0.995], 2 * runs) / runs
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)


def test_a_lasting_unmodelled_offset_inflates_the_covariance():
    """A 12 m offset on every fix for 20 steps (an NLOS-like episode below the 0.999 gate of a 3 m
    receiver): the adaptive tracker's covariance grows and its NEES during the episode is lower than
    the plain tracker's, which stays overconfident."""
    rng = np.random.default_rng(3)
    r = np.diag([9.0, 9.0, 0.04, 0.04])[None]
    trackers = {k: GnssBiasTracker(motion=MOTION, model=GnssModelParams(bias_share=0.8, bias_tau_s=30.0,
                                                                        adaptive_window_s=w))
                for k, w in (("plain", 0.0), ("adaptive", 10.0))}
    x = np.array([0.0, 0.0, 10.0, 0.0])
    nees = {k: [] for k in trackers}
    var = {k: [] for k in trackers}
    for t in range(120):
        truth = x + np.array([10.0 * t, 0.0, 0.0, 0.0])
        z = truth + rng.normal(0, [3.0, 3.0, 0.2, 0.2])
        if 80 <= t < 100:
            z[:2] += np.array([12.0 / math.sqrt(2), 12.0 / math.sqrt(2)])
        fr = make_frame(float(t), 1.0, ["v"], [t == 0], np.zeros((1, 2)), z[None], r,
                        z[None] if t == 0 else np.full((1, 4), np.nan),
                        r * 4 if t == 0 else np.full((1, 4, 4), np.nan))
        for k, tr in trackers.items():
            out = tr.step(fr)
            e = truth[:2] - out.mean[0, :2]
            if 85 <= t < 100:
                nees[k].append(e @ np.linalg.solve(out.cov[0, :2, :2], e))
                var[k].append(np.trace(out.cov[0, :2, :2]))
    assert np.mean(var["adaptive"]) > 1.5 * np.mean(var["plain"])
    assert np.mean(nees["adaptive"]) < 0.8 * np.mean(nees["plain"])


def test_batch_with_entries_and_exits_runs_and_stays_finite():
    model = GnssModelParams(adaptive_window_s=15.0)
    est = GnssBiasTracker(motion=MOTION, model=model)
    for fr in scripted_run(5, 150, model, jumps=0.02):
        out = est.step(fr)
        assert np.isfinite(out.mean).all() and np.isfinite(out.cov).all()
        assert len(est._nis) == len(fr.vehicle_ids) and (est._nis > 0).all()


@pytest.mark.parametrize("w", [-1.0, math.inf, math.nan])
def test_refuses_a_bad_window(w):
    with pytest.raises(ValueError):
        GnssModelParams(adaptive_window_s=w)
