"""The numba kernel of the [fusion] 8-state receiver filters (coloc.kernels.gnss8, the two-state model) against
its numpy references: the cooperative belief (coop_fusion._split_gnss_step, its independent part included) and
the own-sensor track (gnss_bias2.two_state_predict_update), on random inputs: equal to 1e-12, same exclusions."""

import numpy as np
import pytest

from coloc.core.models import MotionParams
from coloc.methods.coop_fusion import _gnss8, _split_gnss_step
from coloc.methods.gnss_bias import GnssModelParams
from coloc.methods.gnss_bias2 import H8, two_state_predict_update

MOTION = MotionParams(sigma_along=0.7, sigma_cross=0.3, heading_min_speed=1.0)
MODELS = (GnssModelParams(bias_model="two_state"),
          GnssModelParams(bias_model="two_state", common_update="augmented"),
          GnssModelParams(bias_model="two_state", innovation_gate=0.0, common_share=0.3, local_share=0.2),
          GnssModelParams(bias_model="two_state", innovation_gate=0.99, max_exclusions=3, local_length_m=5.0,
                          local_tau_s=10.0, common_tau_s=40.0),
          GnssModelParams(bias_model="two_state", bias_follows_report=True),
          GnssModelParams(bias_model="two_state", bias_follows_report=True, common_update="augmented"),
          GnssModelParams(bias_model="two_state", common_share=0.0, common_sigma_m=1.3, velocity_gate=0.99),
          GnssModelParams(bias_model="two_state", common_sigma_m=0.7, velocity_gate=0.5, common_update="augmented"),
          GnssModelParams(bias_model="two_state", common_share=0.0, common_sigma_m=1.3, velocity_gate=0.99,
                          velocity_inflation="innovation"),
          # the gate on the receiver's own report (rows with a calibrated std above 2 x 1.5 m taken back by 1/4)
          GnssModelParams(bias_model="two_state", gate_on="report", degraded_above_m=1.5,
                          degraded_position_scale=2.0, velocity_gate=0.99))


def spd(rng, n, k, scale):
    a = rng.normal(size=(n, k, k))
    return scale * (a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(k))


def inputs(seed, n=300):
    rng = np.random.default_rng(seed)
    mean = rng.normal(scale=20.0, size=(n, 8))
    mean[: n // 4, 2:4] = rng.normal(scale=0.3, size=(n // 4, 2))  # below heading_min_speed: isotropic Q
    ind = spd(rng, n, 8, 0.5)
    cov = ind + spd(rng, n, 8, 1.0)
    r = spd(rng, n, 4, 2.0)
    z = mean @ H8.T + rng.normal(scale=2.0, size=(n, 4))
    z[rng.random(n) < 0.3, :2] += rng.normal(scale=40.0, size=(1, 2))  # faults for the gate
    z[rng.random(n) < 0.3, 2:] += rng.normal(scale=6.0, size=(1, 2))  # faulty range rates for the velocity test
    accel = rng.normal(size=(n, 2))
    predict = rng.random(n) < 0.8
    streak = rng.integers(0, 12, size=n)
    r_prev = spd(rng, n, 2, 2.0)
    same = rng.random(n) < 0.5
    r_prev[same] = r[same, :2, :2]  # an unchanged report: no map
    return mean, cov, ind, accel, z, r, predict, streak, r_prev


def close(a, b):
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(b).max()))


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("common_mode", [False, True])
def test_cooperative_belief_kernel_equals_numpy(seed, model, common_mode):
    mean, cov, ind, accel, z, r, predict, streak, r_prev = inputs(seed)
    before = [a.copy() for a in (mean, cov, ind)]
    ref = _split_gnss_step(mean, cov, ind, accel, z, r, predict, 0.1, MOTION, model, streak, common_mode, r_prev)
    got = _gnss8(mean, cov, ind, accel, z, r, predict, 0.1, MOTION, model, streak, common_mode, r_prev=r_prev)
    np.testing.assert_array_equal(got[3], ref[3])
    if model.innovation_gate > 0:
        assert 0 < ref[3].sum() < predict.sum()  # both update kinds are exercised
    for g, e in zip(got[:3], ref[:3]):
        close(g, e)
    for a, b in zip((mean, cov, ind), before):
        np.testing.assert_array_equal(a, b)  # inputs untouched


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("model", MODELS)
def test_own_track_kernel_equals_two_state_predict_update(seed, model):
    mean, cov, _, accel, z, r, predict, streak, r_prev = inputs(seed)
    m, p, ex = two_state_predict_update(mean, cov, accel, z, r, predict, 0.1, MOTION, model, streak, r_prev)
    gm, gp, _, gex = _gnss8(mean, cov, None, accel, z, r, predict, 0.1, MOTION, model, streak, with_ind=False,
                            r_prev=r_prev)
    np.testing.assert_array_equal(gex, ex)
    close(gm, m)
    close(gp, p)


def test_consider_leaves_the_common_mode_estimate():
    mean, cov, ind, accel, z, r, predict, streak, r_prev = inputs(3)
    model = GnssModelParams(bias_model="two_state")
    m, _, _, _ = _gnss8(mean, cov, ind, accel, z, r, predict, 0.1, MOTION, model, streak)
    decay = np.where(predict, np.exp(-0.1 / model.common_tau_s), 1.0)
    close(m[:, 4:6], decay[:, None] * mean[:, 4:6])


def test_empty_batch():
    e8, e88 = np.empty((0, 8)), np.empty((0, 8, 8))
    m, p, pi, ex = _gnss8(e8, e88, e88, np.empty((0, 2)), np.empty((0, 4)), np.empty((0, 4, 4)),
                          np.empty(0, bool), 0.1, MOTION, GnssModelParams(bias_model="two_state"),
                          np.empty(0, np.int64))
    assert m.shape == (0, 8) and p.shape == (0, 8, 8) and ex.shape == (0,)


def test_gate_on_the_report_in_the_kernel_where_it_decides():
    """Fixes near the gate, so that the receiver's own report and the calibrated one exclude different rows: the
    kernel equals its numpy references row for row in both filters."""
    from dataclasses import replace

    mean, cov, ind, accel, z, r, predict, streak, r_prev = inputs(4)
    cov, ind = 0.01 * cov, 0.005 * ind  # a tight prediction: the fix's noise decides the gate
    z = z.copy()
    z[:, :2] = (mean @ H8.T)[:, :2] + np.random.default_rng(5).normal(scale=2.0, size=(len(z), 2))
    model = MODELS[-1]
    got = _gnss8(mean, cov, ind, accel, z, r, predict, 0.1, MOTION, model, streak, r_prev=r_prev)
    ref = _split_gnss_step(mean, cov, ind, accel, z, r, predict, 0.1, MOTION, model, streak, False, r_prev)
    base = _gnss8(mean, cov, ind, accel, z, r, predict, 0.1, MOTION, replace(model, gate_on="calibrated"), streak, r_prev=r_prev)
    assert (got[3] & ~base[3]).sum() > 3 and not (base[3] & ~got[3]).any()
    np.testing.assert_array_equal(got[3], ref[3])
    for g, e in zip(got[:3], ref[:3]):  # the tight prediction costs digits: 1e-9 of the largest entry
        np.testing.assert_allclose(g, e, rtol=0, atol=1e-9 * max(1.0, np.abs(e).max()))
