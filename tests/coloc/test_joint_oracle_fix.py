"""``joint_oracle`` told the satellite world at fix level (``OracleWorld(gnss="fix")``, ``[oracle] gnss_channel
= "fix"``): z_i = p_i + l_i + sigma_c c + n with l_i in metres (stationary covariance the calibrated report less the
common part) and c one unit common state.

* Equivalence: with one constant reported std sigma for every fix the model is the field world's with
  ``common_share`` s, no field (l_i = sigma sqrt(1 - s) u_i, sigma_c = sigma sqrt(s)), which
  tests/coloc/test_joint_oracle.py checks against batch least squares; the two filters' vehicle and feature
  estimates agree to 1e-9.
* NEES: over 100 runs drawn from the fix model itself (reported stds on both sides of the calibration threshold,
  the local covariance changing with them), the average NEES of a vehicle's final position is inside the 99 %
  chi-square band of 100 runs; a filter told a common error half the size falls out of it.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from coloc.core.frame import Frame
from coloc.methods.joint_oracle import JointOracle, OracleWorld
from test_joint_oracle import DT, PARAMS, _drawn_rows, _final_nees, _frame, _scenario, _scene_start

S = 0.4
SIG = 3.0
FIELD = OracleWorld(gnss="field", tau_s=20.0, common_share=S, common_tau_s=200.0, fix_noise_share=0.05,
                    local_corr_length_m=math.inf)
# the field world's white share w of sigma^2 and local (1 - s) sigma^2: C = (1 - s + w) sigma^2, white share w / that
FIX_EQUIV = OracleWorld(gnss="fix", tau_s=20.0, common_tau_s=200.0, local_corr_length_m=math.inf,
                        fix_common_sigma_m=SIG * math.sqrt(S), fix_local_common_m2=(S - 0.05) * SIG ** 2,
                        fix_local_floor_m=0.01, fix_noise_share=0.05 / (1.0 - S + 0.05))
# the model's every term active: the calibration above 2 m, the common part taken out of the report, the floor
FIX = OracleWorld(gnss="fix", tau_s=15.0, common_tau_s=120.0, local_corr_length_m=math.inf, fix_common_sigma_m=1.2,
                  fix_local_above_m=2.0, fix_local_scale=1.8, fix_local_below_scale=1.1, fix_local_common_m2=0.5,
                  fix_local_floor_m=0.4, fix_velocity_scale=1.5, fix_noise_share=0.2)


def _constant_sigma(frames):
    out = []
    for f, assoc in frames:
        r = np.array(f.gnss_R, copy=True)
        r[:, 0, 0] = r[:, 1, 1] = SIG ** 2
        out.append((Frame(**{**f.__dict__, "gnss_R": r}), assoc))
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_equals_the_field_world_at_one_reported_std(seed):
    frames = _constant_sigma(_scenario(np.random.default_rng(seed)))
    a, b = JointOracle(params=PARAMS, world=FIELD), JointOracle(params=PARAMS, world=FIX_EQUIV)
    for f, assoc in frames:
        ra, rb = a.step_with_association(f, assoc), b.step_with_association(f, assoc)
    for key in ("mean", "cov", "feature_mean", "feature_cov"):
        x, y = getattr(ra, key), getattr(rb, key)
        np.testing.assert_allclose(y, x, rtol=0, atol=1e-9 * max(1.0, float(np.abs(x).max())))
    # the layouts match too: the local state is sigma sqrt(1 - s) times the unit one, the common sigma sqrt(s) c
    n = frames[-1][0].n_vehicles
    li = (a.world.vehicle_dim * np.arange(n)[:, None] + np.array([4, 5])).ravel()
    np.testing.assert_allclose(b.state.mean[li], SIG * math.sqrt(1 - S) * a.state.mean[li], rtol=0, atol=1e-8)


def test_equivalence_can_fail():
    """Told a different common size the fix world misses the field world's estimate."""
    frames = _constant_sigma(_scenario(np.random.default_rng(4)))
    a = JointOracle(params=PARAMS, world=FIELD)
    b = JointOracle(params=PARAMS, world=replace(FIX_EQUIV, fix_common_sigma_m=0.5))
    for f, assoc in frames:
        ra, rb = a.step_with_association(f, assoc), b.step_with_association(f, assoc)
    assert np.abs(ra.mean - rb.mean).max() > 1e-3


def test_local_covariance_is_the_calibrated_report_less_the_common_part():
    r = np.zeros((3, 4, 4))
    r[:, 0, 0] = r[:, 1, 1] = np.array([1.0, 3.0, 0.6]) ** 2
    r[:, 2, 2] = r[:, 3, 3] = 0.2 ** 2
    cov = FIX.fix_local_cov(r)
    np.testing.assert_allclose(cov[0], (1.1 ** 2 - 0.5) * np.eye(2))  # below the threshold: its factor, less 0.5
    np.testing.assert_allclose(cov[1], (1.8 ** 2 * 9.0 - 0.5) * np.eye(2))  # above: scaled, less 0.5
    np.testing.assert_allclose(cov[2], 0.4 ** 2 * np.eye(2))  # 1.21 x 0.36 - 0.5 < 0.16: the floor
    np.testing.assert_allclose(FIX.fix_velocity_cov(r)[1], 1.5 ** 2 * 0.04 * np.eye(2))
    np.testing.assert_allclose(FIX.fix_velocity_cov(r)[0], 0.04 * np.eye(2))


def _simulate_fix(rng, world: OracleWorld, n=3, k=4, steps=25):
    """One run drawn from the fix model: frames, associations and the final true vehicle states."""
    a4, b4, lv, lf, prior_r, x, prior_z, feat = _scene_start(rng, n, k)
    c = rng.standard_normal(2)
    a_l = float(world.local_coefficient(np.zeros(1), DT)[0])
    a_c = math.exp(-DT / world.common_tau_s)
    loc = None
    out = []
    for step in range(steps):
        accel = rng.normal(0, 0.5, (n, 2))
        sig = rng.uniform(0.8, 4.0, n)  # both sides of fix_local_above_m
        vel_sig = np.full(n, 0.3)
        f = _frame(step * DT, n, rng, np.full(n, step == 0), sig, np.zeros((n, 4)), vel_sig, np.zeros(0, int),
                   np.zeros((0, 4)), np.zeros((0, 4, 4)))
        cl = world.fix_local_cov(f.gnss_R)
        ll = np.linalg.cholesky(cl)
        if step == 0:
            loc = math.sqrt(1 - world.fix_noise_share) * np.einsum("nij,nj->ni", ll, rng.standard_normal((n, 2)))
        else:
            x = x @ a4.T + accel @ b4.T + rng.standard_normal((n, lv.shape[1])) @ lv.T
            feat = feat @ a4.T + rng.standard_normal((k, lf.shape[1])) @ lf.T
            loc = a_l * loc + math.sqrt((1 - a_l ** 2) * (1 - world.fix_noise_share)) * np.einsum(
                "nij,nj->ni", ll, rng.standard_normal((n, 2)))
            c = a_c * c + math.sqrt(1 - a_c ** 2) * rng.standard_normal(2)
        zg = x.copy()
        white = math.sqrt(world.fix_noise_share) * np.einsum("nij,nj->ni", ll, rng.standard_normal((n, 2)))
        zg[:, :2] += loc + world.fix_common_sigma_m * c[None, :] + white
        lvel = np.linalg.cholesky(world.fix_velocity_cov(f.gnss_R))
        zg[:, 2:] += np.einsum("nij,nj->ni", lvel, rng.standard_normal((n, 2)))
        owner, assoc, rows, rr = _drawn_rows(rng, x, feat, first=step == 0)
        f = Frame(**{**f.__dict__, "accel": accel, "gnss_z": zg, "v2f_z": rows, "v2f_owner": owner, "v2f_R": rr,
                     "prior_z": prior_z if step == 0 else f.prior_z,
                     "prior_R": prior_r if step == 0 else f.prior_R})
        out.append((f, assoc))
    return out, x


def _mean_nees(told: OracleWorld, runs: int) -> float:
    nees = []
    for seed in range(runs):
        frames, x_true = _simulate_fix(np.random.default_rng(2000 + seed), FIX)
        nees.append(_final_nees(JointOracle(params=PARAMS, world=told), frames, x_true))
    return float(np.mean(nees))


def test_nees_inside_the_99_band_where_the_fix_model_is_the_truth():
    """200 filter runs of 25 steps: 11 s on the 2-core machine."""
    runs = 100
    lo, hi = chi2.ppf([0.005, 0.995], 2 * runs) / runs
    m = _mean_nees(FIX, runs)
    assert lo <= m <= hi, (m, lo, hi)
    # the band can be left: told a common error of a fifth of its size the filter is overconfident
    wrong = _mean_nees(replace(FIX, fix_common_sigma_m=0.2 * FIX.fix_common_sigma_m), runs)
    assert wrong > hi, (wrong, hi)
