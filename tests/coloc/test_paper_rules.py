"""The paper's literal rules as switches: each changes what it should and nothing else.

* ``[lc] pairing = "paper"``: (30)-(31) as written (no gate, threshold at every eta_TH, a row may
  be taken by several tracks);
* ``[lc] new_feature_density``: the density eta of (13) is divided by, as a constant;
* ``[icp] stop_on = "vehicles_and_features"``: the Sec. V-A stopping rule on features too;
* ``[single_road] / [crossroad] start = "gnss_fix"``: the first fix has the GNSS accuracy.
"""

from dataclasses import fields, replace

import numpy as np
import pytest
from scipy.stats import chi2

import coloc.inference.bpa as bpa_module
from coloc.inference.bpa import row_feature_means
from coloc.inference.params import IcpParams
from coloc.methods.icp_da_lc import (
    IcpDaLc,
    LcParams,
    association_weights,
    map_pairing,
    map_pairs,
    new_feature_log_density,
)
from coloc.methods.icp_known_da import IcpState, icp_known_da_step
from couplers.scenarios import CrossroadParams, SingleRoadParams, scenario_frames
from scenes import road_frames
from tests.coloc.test_icp_known_da import MOTION


def _weights(eta_rows):
    """Pair arrays of one vehicle from a (K, M) matrix of measurement weights."""
    k, m = np.nonzero(np.ones_like(eta_rows))
    return np.zeros(k.size, np.int64), k, m, eta_rows[k, m]


# ----------------------------------------------------------------------------- pairing (30)


def test_paper_pairing_lets_two_tracks_take_one_row():
    """Both tracks prefer the only row: "gated" gives it to the larger belief alone, "paper" to both
    (the loser as an extra pair), and the row's reported track is the larger belief in both."""
    pv, pt, pr, ww = _weights(np.array([[100.0], [30.0]]))
    gated = LcParams(eta_threshold=1.0, pairing="gated")
    paper = LcParams(eta_threshold=1.0, pairing="paper")
    rt_g, new_g, er_g, et_g = map_pairs(pv, pt, pr, ww, 1, 1, gated)
    rt_p, new_p, er_p, et_p = map_pairs(pv, pt, pr, ww, 1, 1, paper)
    assert rt_g.tolist() == rt_p.tolist() == [0]
    assert er_g.size == 0 and et_g.size == 0
    assert er_p.tolist() == [0] and et_p.tolist() == [1]
    np.testing.assert_array_equal(new_g, new_p)
    # map_pairing (one track per row) is the first half of map_pairs under either rule.
    np.testing.assert_array_equal(map_pairing(pv, pt, pr, ww, 1, 1, paper)[0], rt_p)


def test_paper_pairing_applies_the_threshold_at_eta_th_one():
    """"gated" skips the test b(alpha = 0) < eta_TH at eta_TH = 1; "paper" applies it, so a track
    whose only option is "missed" (b(0) = 1: its row weight underflowed) is not detected."""
    pv, pt, pr, ww = _weights(np.array([[1e-320, 0.0], [0.0, 50.0]]))
    # Track 0's weight is positive but so small that b(0) rounds to 1.
    rt_g, *_ = map_pairs(pv, pt, pr, ww, 1, 2, LcParams(eta_threshold=1.0, pairing="gated"))
    rt_p, *_ = map_pairs(pv, pt, pr, ww, 1, 2, LcParams(eta_threshold=1.0, pairing="paper"))
    assert rt_g.tolist() == [0, 1]
    assert rt_p.tolist() == [-1, 1]


def test_paper_pairing_has_no_gate():
    """A pair far outside the 4-dof chi-square gate: weight 0 under "gated", the Gaussian weight
    (positive) under "paper"; pairs inside the gate weigh the same under both."""
    v_mean, v_cov = np.zeros((1, 4)), np.eye(4)[None] * 0.01
    t_mean = np.array([[5.0, 0, 0, 0]])
    t_cov = np.eye(4)[None] * 0.01
    z = np.array([[5.0, 0, 0, 0], [6.2, 0, 0, 0]])  # row 1: 1.2 m off with sigma ~0.17 m
    r = np.repeat(np.eye(4)[None] * 0.01, 2, 0)
    args = (v_mean, v_cov, t_mean, t_cov, np.zeros(2, np.int64), z, r)
    _, _, pr_g, w_g = association_weights(*args, LcParams(sensing_range_m=20.0))
    _, _, pr_p, w_p = association_weights(*args, LcParams(sensing_range_m=20.0, pairing="paper"))
    d2 = 1.2**2 / 0.03
    assert d2 > chi2.ppf(0.9999, 4)
    assert w_g[pr_g == 1][0] == 0.0 and w_p[pr_p == 1][0] > 0.0
    assert w_g[pr_g == 0][0] == w_p[pr_p == 0][0]


def test_new_feature_density_replaces_the_derived_density():
    rng = np.random.default_rng(0)
    v_mean, z = rng.normal(size=(5, 4)), rng.normal(size=(5, 4))
    v_cov = np.repeat(np.eye(4)[None], 5, 0)
    r = np.repeat(np.eye(4)[None] * 0.1, 5, 0)
    derived = new_feature_log_density(v_mean, v_cov, z, r, LcParams())
    fixed = new_feature_log_density(v_mean, v_cov, z, r, LcParams(new_feature_density=1e-3))
    assert np.ptp(derived) > 0  # depends on the row's velocity
    np.testing.assert_array_equal(fixed, np.full(5, np.log(1e-3)))


@pytest.mark.parametrize("bad", [dict(pairing="literal"), dict(new_feature_density=-1.0),
                                 dict(new_feature_density=float("inf"))])
def test_lc_params_refuse_bad_values(bad):
    with pytest.raises(ValueError):
        LcParams(**bad)


def _run(est, frames, known=False):
    out = []
    for f in frames:
        if known:
            out.append(est.step_with_association(f.without_truth(), f.truth.v2f_feature))
        else:
            out.append(est.step(f.without_truth()))
    return out


def test_paper_pairing_uses_shared_rows_in_bpa_and_changes_the_estimates():
    """The crossroad with Nf = 60 features on the sidewalks (a few metres apart) and eta_TH = 1:
    under the paper's rule some rows are taken by two tracks and BPA-L uses them once per track;
    the estimates differ from the gated rule's and every covariance stays SPD."""
    cp = CrossroadParams(n_features=60, max_duration_s=15.0)
    frames = list(scenario_frames(cp, seed=2))
    params = IcpParams(motion=replace(MOTION, sigma_along=cp.sigma_along, sigma_cross=cp.sigma_cross))
    est_p = IcpDaLc(params, LcParams(eta_threshold=1.0, pairing="paper", sensing_range_m=cp.v2f_range_m))
    est_g = IcpDaLc(params, LcParams(eta_threshold=1.0, pairing="gated", sensing_range_m=cp.v2f_range_m))
    extra = 0
    for f in frames:
        rp = est_p.step(f.without_truth())
        rg = est_g.step(f.without_truth())
        extra += est_p.last.shared
        assert est_g.last.shared == 0
        for cov in rp.cov:
            np.testing.assert_allclose(cov, cov.T, atol=1e-9)
            assert np.linalg.eigvalsh(cov).min() > 0
    assert extra > 0  # some rows were taken by more than one track
    assert not np.array_equal(rp.mean, rg.mean)


def test_gated_defaults_are_the_explicit_defaults():
    """The switches' defaults are today's rules: the default LcParams/IcpParams equal the ones
    with the switches spelled out, and those give the same estimates bit for bit."""
    assert LcParams() == LcParams(pairing="gated", new_feature_density=0.0)
    assert IcpParams() == IcpParams(stop_on="vehicles")
    frames = road_frames(seed=3, steps=10)
    params = IcpParams(motion=MOTION)
    a = _run(IcpDaLc(params, LcParams(sensing_range_m=30.0)), frames)
    b = _run(IcpDaLc(replace(params, stop_on="vehicles"),
                     LcParams(sensing_range_m=30.0, pairing="gated", new_feature_density=0.0)), frames)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.mean, y.mean)
        np.testing.assert_array_equal(x.cov, y.cov)


# ----------------------------------------------------------------------------- stopping rule


def test_row_feature_means_solve_information_and_mark_singular_rows():
    lam = np.stack([np.diag([1.0, 2.0, 4.0, 8.0]), np.zeros((4, 4))])
    eta = np.array([[1.0, 2.0, 4.0, 8.0], [0.0, 0.0, 0.0, 0.0]])
    out = row_feature_means(lam, eta)
    np.testing.assert_allclose(out[0], np.ones(4))
    assert np.isnan(out[1]).all()


def test_stopping_on_features_never_stops_earlier_and_both_loops_agree(monkeypatch):
    """From the same state, BPA-L with features in the stopping rule never stops at an earlier
    iteration than with vehicles only, and over a run it stops later at some steps (a newborn
    track has no estimate before the first iteration). The numba and numpy loops stop at the
    same iteration under both rules."""
    frames = road_frames(seed=4, steps=12)
    by_vehicles = IcpParams(motion=MOTION, stop_on="vehicles")
    by_both = IcpParams(motion=MOTION, stop_on="vehicles_and_features")
    state = IcpState()
    later = 0
    for f in frames:
        blind, assoc = f.without_truth(), f.truth.v2f_feature
        its = {}
        for kernels in (True, False):
            monkeypatch.setattr(bpa_module, "BPA_KERNELS", kernels)
            its[kernels] = (icp_known_da_step(state, blind, assoc, by_vehicles)[0].iterations,
                            icp_known_da_step(state, blind, assoc, by_both)[0].iterations)
        assert its[True] == its[False]
        n_vehicles, n_both = its[True]
        assert n_both >= n_vehicles
        later += n_both > n_vehicles
        monkeypatch.setattr(bpa_module, "BPA_KERNELS", True)
        state = icp_known_da_step(state, blind, assoc, by_vehicles)[1]
    assert later > 0


# ----------------------------------------------------------------------------- start


@pytest.mark.parametrize("params", [SingleRoadParams(), CrossroadParams(n_features=10)], ids=["single", "cross"])
def test_gnss_fix_start_changes_only_the_first_fix(params):
    """start = "gnss_fix": the prior of an entering vehicle has the GNSS covariance and is drawn
    from the same stream (so z - x_true scales by gnss/prior sigma exactly); every other field of
    every frame is unchanged."""
    fast = list(scenario_frames(params, seed=5))
    fix = list(scenario_frames(replace(params, start="gnss_fix"), seed=5))
    assert len(fast) == len(fix)
    scale = np.array([params.gnss_sigma_p / params.prior_sigma_p] * 2 + [params.gnss_sigma_v / params.prior_sigma_v] * 2)
    for a, b in zip(fast, fix):
        for f in fields(a):
            if f.name in ("prior_z", "prior_R", "truth", "neighbors"):
                continue
            np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name))
        assert (a.neighbors != b.neighbors).nnz == 0
        np.testing.assert_array_equal(a.truth.x_true, b.truth.x_true)
        ent = a.entered
        np.testing.assert_allclose(b.prior_z[ent] - b.truth.x_true[ent],
                                   (a.prior_z[ent] - a.truth.x_true[ent]) * scale, rtol=1e-9, atol=1e-9)
        sig = np.array([params.gnss_sigma_p] * 2 + [params.gnss_sigma_v] * 2)
        np.testing.assert_allclose(b.prior_R[ent], np.broadcast_to(np.diag(sig**2), (int(ent.sum()), 4, 4)))


def test_unknown_start_is_refused():
    with pytest.raises(ValueError, match="start"):
        CrossroadParams(start="cold")
