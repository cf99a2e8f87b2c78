"""The numba kernel of the [fusion] 6-state receiver filters (coloc.kernels.gnss6) against its numpy
references: the cooperative belief (coop_fusion._split_gnss_step, its independent part included) and the
own-sensor track (gnss_bias.bias_predict_update), on random inputs: equal to 1e-12, same exclusions."""

import numpy as np
import pytest

from coloc.core.models import MotionParams
from coloc.methods.coop_fusion import _gnss6, _split_gnss_step
from coloc.methods.gnss_bias import H, GnssModelParams, bias_predict_update

MOTION = MotionParams(sigma_along=0.7, sigma_cross=0.3, heading_min_speed=1.0)
MODELS = (GnssModelParams(), GnssModelParams(bias_share=0.0, innovation_gate=0.0),
          GnssModelParams(bias_share=0.5, bias_tau_s=20.0, innovation_gate=0.99, max_exclusions=3),
          GnssModelParams(velocity_gate=0.99), GnssModelParams(bias_share=0.3, velocity_gate=0.5, innovation_gate=0.0),
          GnssModelParams(velocity_gate=0.99, velocity_inflation="innovation"),
          # the gate on the receiver's own report (rows with a calibrated std above 2 x 1.5 m taken back by 1/4)
          GnssModelParams(gate_on="report", degraded_above_m=1.5, degraded_position_scale=2.0))


def spd(rng, n, k, scale):
    a = rng.normal(size=(n, k, k))
    return scale * (a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(k))


def inputs(seed, n=300):
    rng = np.random.default_rng(seed)
    mean = rng.normal(scale=20.0, size=(n, 6))
    mean[: n // 4, 2:4] = rng.normal(scale=0.3, size=(n // 4, 2))  # below heading_min_speed: isotropic Q
    ind = spd(rng, n, 6, 0.5)
    cov = ind + spd(rng, n, 6, 1.0)
    r = spd(rng, n, 4, 2.0)
    z = mean @ H.T + rng.normal(scale=2.0, size=(n, 4))
    z[rng.random(n) < 0.3, :2] += rng.normal(scale=40.0, size=(1, 2))  # faults for the gate
    z[rng.random(n) < 0.3, 2:] += rng.normal(scale=6.0, size=(1, 2))  # faulty range rates for the velocity test
    accel = rng.normal(size=(n, 2))
    predict = rng.random(n) < 0.8
    streak = rng.integers(0, 12, size=n)
    return mean, cov, ind, accel, z, r, predict, streak


def close(a, b):
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(b).max()))


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("common_mode", [False, True])
def test_cooperative_belief_kernel_equals_numpy(seed, model, common_mode):
    mean, cov, ind, accel, z, r, predict, streak = inputs(seed)
    before = [a.copy() for a in (mean, cov, ind)]
    ref = _split_gnss_step(mean, cov, ind, accel, z, r, predict, 0.1, MOTION, model, streak, common_mode)
    got = _gnss6(mean, cov, ind, accel, z, r, predict, 0.1, MOTION, model, streak, common_mode)
    np.testing.assert_array_equal(got[3], ref[3])
    if model.innovation_gate > 0:
        assert 0 < ref[3].sum() < predict.sum()  # both update kinds are exercised
    for g, e in zip(got[:3], ref[:3]):
        close(g, e)
    for a, b in zip((mean, cov, ind), before):
        np.testing.assert_array_equal(a, b)  # inputs untouched


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("model", MODELS)
def test_own_track_kernel_equals_bias_predict_update(seed, model):
    mean, cov, _, accel, z, r, predict, streak = inputs(seed)
    m, p, ex = bias_predict_update(mean, cov, accel, z, r, predict, 0.1, MOTION, model, streak)
    gm, gp, _, gex = _gnss6(mean, cov, None, accel, z, r, predict, 0.1, MOTION, model, streak, with_ind=False)
    np.testing.assert_array_equal(gex, ex)
    close(gm, m)
    close(gp, p)


def test_empty_batch():
    e6, e66 = np.empty((0, 6)), np.empty((0, 6, 6))
    m, p, pi, ex = _gnss6(e6, e66, e66, np.empty((0, 2)), np.empty((0, 4)), np.empty((0, 4, 4)),
                          np.empty(0, bool), 0.1, MOTION, GnssModelParams(), np.empty(0, np.int64))
    assert m.shape == (0, 6) and p.shape == (0, 6, 6) and ex.shape == (0,)


def test_gate_on_the_report_in_the_kernel_where_it_decides():
    """Fixes near the gate, so that the receiver's own report and the calibrated one exclude different rows: the
    kernel equals its numpy references row for row in both filters."""
    from dataclasses import replace

    mean, cov, ind, accel, z, r, predict, streak = inputs(4)
    cov, ind = 0.01 * cov, 0.005 * ind  # a tight prediction: the fix's noise decides the gate
    z = z.copy()
    z[:, :2] = (mean @ H.T)[:, :2] + np.random.default_rng(5).normal(scale=2.0, size=(len(z), 2))
    model = MODELS[-1]
    got = _gnss6(mean, cov, ind, accel, z, r, predict, 0.1, MOTION, model, streak)
    ref = _split_gnss_step(mean, cov, ind, accel, z, r, predict, 0.1, MOTION, model, streak, False)
    base = _gnss6(mean, cov, ind, accel, z, r, predict, 0.1, MOTION, replace(model, gate_on="calibrated"), streak)
    assert (got[3] & ~base[3]).sum() > 3 and not (base[3] & ~got[3]).any()
    np.testing.assert_array_equal(got[3], ref[3])
    for g, e in zip(got[:3], ref[:3]):  # the tight prediction costs digits: 1e-9 of the largest entry
        np.testing.assert_allclose(g, e, rtol=0, atol=1e-9 * max(1.0, np.abs(e).max()))
