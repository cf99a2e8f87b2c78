"""ICP-DA-LC under clutter (estimator side of realistic sensing): the clutter intensity in the normaliser of
eta (13) and the tracks' existence probability (module docstring of coloc.methods.icp_da_lc,
step 9)."""

from dataclasses import replace

import numpy as np
import pytest

from coloc.inference.params import IcpParams
from coloc.methods.gnss import GnssTracker
from coloc.inference.association import association_marginals_exact
from coloc.inference.existence import TrackExistence, birth_existence, existence_update
from coloc.methods.icp_da_lc import (
    IcpDaLc,
    LcParams,
    association_beliefs,
    clutter_log_density,
    new_feature_log_density,
    new_feature_share,
)
from scenes import road_frames
from tests.coloc.test_icp_known_da import MOTION

CLUTTER_RANGE_M = 30.0
GNSS_SP = 3.0  # m: an urban receiver (the arterial's zones: 1-5 m)


def with_clutter(frames, per_scan: float, seed: int, keep_features: bool = True):
    """Add Poisson(per_scan) false detections per vehicle and frame, uniform over a disc of
    CLUTTER_RANGE_M around the vehicle, looking like static objects (z_v = -v_true + noise), truth
    index -1; with ``keep_features`` False the frame's real rows are removed first."""
    rng = np.random.default_rng(seed)
    out = []
    for f in frames:
        n = f.n_vehicles
        k = rng.poisson(per_scan, n)
        owner = np.repeat(np.arange(n), k)
        r = CLUTTER_RANGE_M * np.sqrt(rng.random(owner.size))
        phi = rng.uniform(0, 2 * np.pi, owner.size)
        z = np.zeros((owner.size, 4))
        z[:, 0], z[:, 1] = r * np.cos(phi), r * np.sin(phi)
        z[:, 2:] = -f.truth.x_true[owner, 2:] + rng.normal(0, 0.1, (owner.size, 2))
        z[:, :2] += rng.normal(0, 0.2, (owner.size, 2))
        cov = np.diag([0.04, 0.04, 0.01, 0.01])
        old = slice(None) if keep_features else slice(0, 0)
        all_owner = np.concatenate([f.v2f_owner[old], owner])
        order = np.argsort(all_owner, kind="stable")
        out.append(replace(
            f,
            v2f_z=np.concatenate([f.v2f_z[old], z])[order],
            v2f_owner=all_owner[order],
            v2f_R=np.concatenate([f.v2f_R[old], np.repeat(cov[None], owner.size, 0)])[order],
            truth=replace(f.truth, v2f_feature=np.concatenate([f.truth.v2f_feature[old],
                                                               np.full(owner.size, -1)])[order]),
        ))
    return out


def _lc(per_scan, existence=True):
    return LcParams(sensing_range_m=CLUTTER_RANGE_M, eta_threshold=0.5,
                    clutter_intensity=per_scan / (np.pi * CLUTTER_RANGE_M**2), track_existence=existence)


def test_clutter_density_joins_the_new_feature_density():
    """lambda_c f_c is the static-object velocity Gaussian times lambda_c, added to mu_new f_new."""
    rng = np.random.default_rng(1)
    v_mean, z = rng.normal(size=(4, 4)), rng.normal(size=(4, 4))
    v_cov = np.repeat(np.eye(4)[None] * 0.5, 4, 0)
    r = np.repeat(np.eye(4)[None] * 0.1, 4, 0)
    lc = LcParams(clutter_intensity=2e-3)
    d = z[:, 2:] + v_mean[:, 2:]
    ref = np.log(2e-3) - np.log(2 * np.pi * 0.6) - 0.5 * np.einsum("ni,ni->n", d, d) / 0.6
    np.testing.assert_allclose(clutter_log_density(v_mean, v_cov, z, r, lc), ref, rtol=1e-12)
    base = new_feature_log_density(v_mean, v_cov, z, r, LcParams())
    np.testing.assert_allclose(new_feature_log_density(v_mean, v_cov, z, r, lc), np.logaddexp(base, ref), rtol=1e-12)


@pytest.mark.parametrize("bad", [dict(clutter_intensity=-1.0), dict(survival_probability=0.0),
                                 dict(drop_existence=0.5, confirm_existence=0.4), dict(confirm_existence=1.0)])
def test_bad_existence_parameters(bad):
    with pytest.raises(ValueError):
        LcParams(**bad)


def test_existence_update_against_enumeration():
    """One vehicle, two tracks with existence r1, r2 and two rows: P(k exists | z) = 1 - b(0)(1 - q)
    with the exact association marginals equals the posterior enumerated over existence x
    one-to-one association (to 1e-12); with the loopy BP's marginals (this 2 x 2 problem has a
    loop) it is within 2 %."""
    lc = LcParams(detection_probability=0.8)
    r = np.array([0.3, 0.9])
    w = np.array([[5.0, 0.2], [0.1, 3.0]])  # normalised likelihoods eta(l) / r
    pv, pt, pr = np.zeros(4, np.int64), np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1])
    ww = w[pt, pr]
    # association_weights' w already holds P_D (eta(l) = P_D N / (mu_new f_new)); step 9 scales it by r.
    ab = association_beliefs(pv, pt, pr, ww * lc.detection_probability * r[pt], 1, 2,
                             replace(lc, bp_iterations=500, bp_tol=1e-14),
                             (1.0 - r * lc.detection_probability)[pt])
    got = existence_update(r, ab, np.full(2, lc.detection_probability), np.empty(0, np.int64), np.empty(0))
    # Enumeration: states (e1, e2) x assignments a (0 = none), weight prod_k f(e_k, a_k).
    post = np.zeros(2)
    total = 0.0
    for e in [(0, 0), (0, 1), (1, 0), (1, 1)]:
        for a in [(0, 0), (1, 0), (2, 0), (0, 1), (0, 2), (1, 2), (2, 1)]:
            wt = 1.0
            for k in range(2):
                prior = r[k] if e[k] else 1 - r[k]
                if a[k] == 0:
                    wt *= prior * ((1 - lc.detection_probability) if e[k] else 1.0)
                else:
                    wt *= prior * lc.detection_probability * w[k, a[k] - 1] if e[k] else 0.0
            total += wt
            post += wt * np.array(e)
    exact = post / total
    eta = np.column_stack([1 - r * lc.detection_probability, (w * r[:, None]) * lc.detection_probability])
    p_exact = association_marginals_exact(eta)
    q = r * (1 - lc.detection_probability) / (1 - r * lc.detection_probability)
    np.testing.assert_allclose(1 - p_exact[:, 0] * (1 - q), exact, rtol=1e-12)
    np.testing.assert_allclose(got, exact, rtol=2e-2)


def test_missed_candidates_lose_odds_by_one_minus_pd_and_births_add_log_odds():
    lc = LcParams(detection_probability=0.9)
    r = np.array([0.5, 0.5])
    got = existence_update(r, None, np.empty(0), np.array([0, 0, 0]), np.full(3, lc.detection_probability))
    np.testing.assert_allclose(got[0] / (1 - got[0]), 0.1**3, rtol=1e-12)
    assert got[1] == 0.5
    share = np.array([0.2, 0.5, 0.9])
    np.testing.assert_allclose(birth_existence(share, np.array([0, 0, 1]), 2), [0.2, 0.9])
    te = TrackExistence(np.array([3, 7]), np.array([0.95, 0.2]))
    assert te.confirmed(np.array([-1, 3, 7, 9]), LcParams().confirm_existence).tolist() == [False, True, False, False]
    m = te.merged(np.array([7]), np.array([3]))
    assert m.ids.tolist() == [3] and m.r.tolist() == [0.95]


def test_new_feature_share_is_one_without_clutter():
    rng = np.random.default_rng(2)
    v_mean, z = rng.normal(size=(3, 4)), rng.normal(size=(3, 4))
    v_cov = np.repeat(np.eye(4)[None], 3, 0)
    r = np.repeat(np.eye(4)[None] * 0.1, 3, 0)
    np.testing.assert_array_equal(new_feature_share(v_mean, v_cov, z, r, LcParams()), np.ones(3))
    share = new_feature_share(v_mean, v_cov, z, r, LcParams(clutter_intensity=1e-4))
    assert np.all((share > 0) & (share < 1))


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_clutter_alone_confirms_no_track_and_vehicles_equal_gnss(seed):
    """No real feature, one false detection per vehicle and scan (five vehicles 10 m apart, each
    with clutter over a 30 m disc), track existence on: no track is ever confirmed, every row is
    reported discarded, and the vehicles are exactly the GNSS tracker's. Without existence the
    same clutter starts tracks that pull the vehicles off GNSS."""
    frames = with_clutter(road_frames(seed=seed, steps=15, n_feat=0, gnss_sp=GNSS_SP), 1.0, seed)
    params = IcpParams(motion=MOTION)
    confirmed = IcpDaLc(params, _lc(1.0))
    unconfirmed = IcpDaLc(params, _lc(1.0, existence=False))
    gnss = GnssTracker(MOTION)
    moved = 0.0
    for f in frames:
        blind = f.without_truth()
        e_c, e_u, e_g = confirmed.step(blind), unconfirmed.step(blind), gnss.step(blind)
        assert not confirmed.last.existence.confirmed(confirmed.last.existence.ids, confirmed.lc.confirm_existence).any()
        assert np.all(e_c.v2f_assignment == -1) and e_c.feature_track_ids.size == 0
        np.testing.assert_array_equal(e_c.mean, e_g.mean)
        np.testing.assert_array_equal(e_c.cov, e_g.cov)
        moved = max(moved, float(np.abs(e_u.mean - e_g.mean).max()))
    assert moved > 0.1


def _rmse(frames, ests):
    e = np.concatenate([np.sum((r.mean[:, :2] - f.truth.x_true[:, :2]) ** 2, 1) for f, r in zip(frames, ests)])
    return float(np.sqrt(e.mean()))


def run_under_clutter(est, frames):
    """``est`` and the GNSS tracker on ``frames``: their estimates, and the rows ``est`` used for the
    vehicles that were real and that were clutter. Every covariance is checked SPD on the way."""
    gnss = GnssTracker(MOTION)
    out, out_g = [], []
    used_clutter = used_real = 0
    for f in frames:
        blind = f.without_truth()
        out.append(est.step(blind))
        out_g.append(gnss.step(blind))
        a = out[-1].v2f_assignment
        used_clutter += int(((a >= 0) & (f.truth.v2f_feature < 0)).sum())
        used_real += int(((a >= 0) & (f.truth.v2f_feature >= 0)).sum())
        assert np.all(np.linalg.eigvalsh(out[-1].cov).min(axis=1) > 0)
    return out, out_g, used_real, used_clutter


def test_real_features_are_confirmed_under_clutter_and_help_the_vehicles():
    """Landmarks 30 m apart plus one false detection per vehicle and scan: the landmarks' tracks
    are confirmed within the window, clutter's are not, and the vehicles beat GNSS."""
    seed = 4
    frames = with_clutter(road_frames(seed=seed, steps=20, n_feat=4, v2v_range=25.0, gnss_sp=GNSS_SP), 1.0, seed)
    out_lc, out_g, used_real, used_clutter = run_under_clutter(IcpDaLc(IcpParams(motion=MOTION), _lc(1.0)), frames)
    assert used_real > 10 * max(used_clutter, 1)
    assert _rmse(frames, out_lc) < _rmse(frames, out_g)


def test_own_consistency_reset_returns_far_vehicles_to_their_own_track():
    """A vehicle whose cooperative position is outside the 2-dof gate of its own-sensor track takes
    the own-sensor belief; one inside keeps its belief. Gate 0.9999: d^2 > 18.42."""
    from coloc.methods.icp_da_lc import own_consistency_reset

    own_mean = np.zeros((3, 4))
    own_cov = np.repeat(np.diag([4.0, 4.0, 0.1, 0.1])[None], 3, 0)  # 2 m per axis
    mean = np.array([[8.0, 0.0, 0, 0], [8.7, 0.0, 0, 0], [3.0, 3.0, 0, 0]])  # d^2 = 16, 18.9, 4.5
    cov = np.repeat(np.eye(4)[None] * 0.01, 3, 0)
    m, c, reset = own_consistency_reset(mean, cov, own_mean, own_cov, 0.9999)
    assert reset.tolist() == [False, True, False]
    np.testing.assert_array_equal(m[1], own_mean[1])
    np.testing.assert_array_equal(c[1], own_cov[1])
    np.testing.assert_array_equal(m[[0, 2]], mean[[0, 2]])
    with pytest.raises(ValueError):
        LcParams(own_consistency_gate=1.0)
