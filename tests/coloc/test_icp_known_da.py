"""ICP with known association: Gaussian BPA-L (19)-(22) with consensus vs a centralized joint KF.

Synthetic scenes: :func:`scenes.road_frames` (vehicles driving east on one lane by model (1),
static features on both sides, measurements by ``couplers.sensing.sensors``, seeded).
"""

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from coloc.core.models import MotionParams
from coloc.core.protocol import Estimator, KnownAssociationEstimator
from coloc.inference.bpa import bpa_localization, validate_association
from coloc.inference.consensus import connected_components
from coloc.inference.gaussian import relative_message
from coloc.inference.params import IcpParams
from coloc.inference.row_consensus import consensus_graph, row_components
from coloc.methods.centralized import CentralizedKF, one_step_joint
from coloc.methods.gnss import GnssTracker
from coloc.methods.icp_known_da import IcpKnownDA, IcpState, vehicle_prior_beliefs
from scenes import road_frames

# The true motion is driven by the measured input plus 0.05 m/s^2 inertial noise.
MOTION = MotionParams(sigma_along=0.08, sigma_cross=0.08)


def exact_params(consensus_iterations=200):
    """BPA-L run to convergence (stopping thresholds far below the Sec. V-A rule)."""
    return IcpParams(motion=MOTION, consensus_iterations=consensus_iterations, bpa_max_iterations=1000,
                     stop_pos_m=1e-10, stop_vel_mps=1e-10)


def assert_spd(cov):
    assert np.all(np.isfinite(cov))
    np.testing.assert_allclose(cov, np.swapaxes(cov, -1, -2), atol=1e-9)
    assert np.all(np.linalg.eigvalsh(cov) > 0)


def per_step_gap(frames, params):
    """Run the ICP step by step; at each step compare BPA-L to the exact joint of the same prior (11)-(12).

    BPA-L runs with the paper's own cavity in (19) (own belief = b^(0)), so that
    converged Gaussian BP must give the one-step joint means.
    Returns per-step (max vehicle position-mean gap, max vehicle covariance gap).
    """
    state = IcpState()
    gaps = []
    for f in frames:
        assert connected_components(f.neighbors)[0] == 1, "the comparison scene must stay connected"
        assoc = f.truth.v2f_feature
        used = assoc >= 0
        rows_vehicle = f.vehicle_ids[f.v2f_owner[used]]
        b0_mean, b0_cov = vehicle_prior_beliefs(state.ids, state.mean, state.cov, f, params)
        pred = state.features.predict(f.dt, params)
        fl, fe = pred.prior_information(np.unique(assoc[used]), assoc[used], rows_vehicle, params)
        res = bpa_localization(b0_mean, b0_cov, b0_mean, b0_cov, f.v2f_owner, assoc, f.v2f_z, f.v2f_R,
                               f.neighbors, fl, fe, params)
        jm, jc, _, _, _ = one_step_joint(b0_mean, b0_cov, fl, fe, f.v2f_owner, assoc, f.v2f_z, f.v2f_R)
        gaps.append((np.abs(res.mean[:, :2] - jm[:, :2]).max(), np.abs(res.cov - jc).max()))
        store = pred.record(assoc[used], rows_vehicle, res.msg_lam, res.msg_eta, f.t, params)
        state = IcpState(f.vehicle_ids, res.mean, res.cov, b0_mean, b0_cov, store)
    return np.array(gaps)


# ----------------------------------------------------------------------------- Gaussian algebra


def test_relative_message_matches_moment_form_and_uniform_gives_zero():
    rng = np.random.default_rng(0)
    l = rng.normal(size=(6, 4, 4))
    p = l @ np.swapaxes(l, 1, 2) + 0.1 * np.eye(4)
    m = rng.normal(size=(6, 4))
    r = np.diag([0.04, 0.04, 0.01, 0.01])[None].repeat(6, 0)
    off = rng.normal(size=(6, 4))
    lam = np.linalg.inv(p)
    ly, ey = relative_message(lam, np.einsum("nij,nj->ni", lam, m), off, r)
    np.testing.assert_allclose(np.linalg.inv(ly), p + r, rtol=1e-10)
    np.testing.assert_allclose(np.linalg.solve(ly, ey[..., None])[..., 0], m + off, rtol=1e-9, atol=1e-9)
    l0, e0 = relative_message(np.zeros((6, 4, 4)), np.zeros((6, 4)), off, r)
    assert np.all(l0 == 0) and np.all(e0 == 0)


def test_consensus_graph_links_only_neighbours_sensing_the_same_feature():
    adj = sp.csr_matrix(np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], dtype=bool))  # path 0-1-2
    owner = np.array([0, 0, 1, 1, 2])
    feat = np.array([7, 9, 9, 7, 7])
    g = consensus_graph(owner, feat, adj).toarray()
    expected = np.zeros((5, 5), bool)
    expected[0, 3] = expected[3, 0] = True  # feature 7: vehicles 0-1
    expected[3, 4] = expected[4, 3] = True  # feature 7: vehicles 1-2
    expected[1, 2] = expected[2, 1] = True  # feature 9: vehicles 0-1
    np.testing.assert_array_equal(g, expected)
    _, count = row_components(consensus_graph(owner, feat, adj))
    np.testing.assert_array_equal(count, [3, 2, 2, 3, 3])
    # Feature 7 seen by vehicles 0 and 2 only: 1 relays nothing, two singleton groups.
    _, count = row_components(consensus_graph(np.array([0, 2]), np.array([7, 7]), adj))
    np.testing.assert_array_equal(count, [1, 1])


def test_association_validation():
    with pytest.raises(ValueError, match="one entry per V2F row"):
        validate_association(np.array([0, 1]), np.array([1]), 2)
    with pytest.raises(ValueError, match="same feature"):
        validate_association(np.array([0, 0]), np.array([3, 3]), 2)
    with pytest.raises(ValueError, match="integer"):
        validate_association(np.array([0]), np.array([1.0]), 1)


def test_is_a_known_association_estimator_only():
    """The bound has no ``step``: it is driven through step_with_association (registry flag)."""
    est = IcpKnownDA()
    assert isinstance(est, KnownAssociationEstimator) and not isinstance(est, Estimator)
    assert not hasattr(est, "step")


# ----------------------------------------------------------------------------- vs centralized


def test_first_step_matches_joint_kf_within_1cm():
    """Step 0 (fast-start priors, new features): converged Gaussian BP = exact joint means."""
    f = road_frames(steps=1, v2v_range=25.0)[0]  # links to 1-2 neighbours each way: consensus is not one-shot
    params = exact_params(200)
    icp = IcpKnownDA(params).step_with_association(f, f.truth.v2f_feature)
    kf = CentralizedKF(params).step_with_association(f, f.truth.v2f_feature)
    gap = np.abs(icp.mean[:, :2] - kf.mean[:, :2]).max()
    cov_gap = np.abs(icp.cov - kf.cov).max()
    print(f"step 0: mean gap {gap:.2e} m, cov gap {cov_gap:.3f} (BP variances overconfident)")
    assert gap < 0.01
    # Loopy Gaussian BP: exact means, overconfident position variances.
    assert np.all(np.trace(icp.cov[:, :2, :2], axis1=1, axis2=2) <= np.trace(kf.cov[:, :2, :2], axis1=1, axis2=2) + 1e-9)


def test_every_step_matches_exact_one_step_joint_within_1cm():
    """Each step, BPA-L with 200 consensus rounds run to convergence reproduces the exact
    joint posterior means of its own prior (11)-(12) within 1 cm (measured ~1e-9 m)."""
    frames = road_frames(steps=15, v2v_range=25.0)
    gaps = per_step_gap(frames, exact_params(200))
    print("per-step mean gap (m):", np.array2string(gaps[:, 0], precision=1))
    print("per-step cov gap:", np.array2string(gaps[:, 1], precision=1))
    assert gaps[:, 0].max() < 0.01


def test_few_consensus_iterations_leave_a_measurable_gap():
    frames = road_frames(steps=15, v2v_range=25.0)
    g200 = per_step_gap(frames, exact_params(200))
    g2 = per_step_gap(frames, replace(exact_params(2), bpa_max_iterations=50))
    print(f"max mean gap: 200 rounds {g200[:, 0].max():.2e} m, 2 rounds {g2[:, 0].max():.2e} m; "
          f"max cov gap: 200 rounds {g200[:, 1].max():.2e}, 2 rounds {g2[:, 1].max():.2e}")
    assert np.all(np.isfinite(g2))
    assert g2[:, 0].max() > 10 * g200[:, 0].max()


def test_multi_step_gap_to_full_joint_kf_is_measured():
    """Over time BP carries marginal beliefs only (no vehicle-feature cross-covariance),
    so it differs from the full joint KF by decimetres; measured, not a bug."""
    frames = road_frames(steps=15, v2v_range=25.0)
    params = exact_params(200)
    icp, kf = IcpKnownDA(params), CentralizedKF(params)
    gaps = []
    for f in frames:
        a = icp.step_with_association(f, f.truth.v2f_feature)
        b = kf.step_with_association(f, f.truth.v2f_feature)
        gaps.append(np.abs(a.mean[:, :2] - b.mean[:, :2]).max())
    print("ICP vs full joint KF, per-step max position gap (m):", np.array2string(np.array(gaps), precision=3))
    assert gaps[0] < 0.01 and np.all(np.isfinite(gaps))


# ----------------------------------------------------------------------------- accuracy, robustness


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_beats_gnss_only(seed):
    """Default parameters (20 consensus rounds, Sec. V-A stopping rule) on a chain of 5 vehicles."""
    frames = road_frames(seed=seed, steps=20, v2v_range=25.0)
    icp, gnss = IcpKnownDA(IcpParams(motion=MOTION)), GnssTracker(MOTION)
    e_icp, e_gnss = [], []
    for f in frames:
        a = icp.step_with_association(f, f.truth.v2f_feature)
        g = gnss.step(f)
        e_icp.append(np.sum((a.mean[:, :2] - f.truth.x_true[:, :2]) ** 2, 1))
        e_gnss.append(np.sum((g.mean[:, :2] - f.truth.x_true[:, :2]) ** 2, 1))
        assert_spd(a.cov)
        assert_spd(a.feature_cov)
    r_icp, r_gnss = np.sqrt(np.mean(np.concatenate(e_icp))), np.sqrt(np.mean(np.concatenate(e_gnss)))
    print(f"seed {seed}: RMSE ICP {r_icp:.3f} m, GNSS {r_gnss:.3f} m")
    assert r_icp < 0.7 * r_gnss


def test_isolated_vehicles_equal_gnss_tracker():
    """No features and no neighbours: the ICP is the GNSS tracker, to the bit."""
    frames = road_frames(steps=10, n_feat=0, v2v_range=1.0)
    icp, gnss = IcpKnownDA(IcpParams(motion=MOTION)), GnssTracker(MOTION)
    for f in frames:
        a = icp.step_with_association(f, f.truth.v2f_feature)
        g = gnss.step(f)
        np.testing.assert_allclose(a.mean, g.mean, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.cov, g.cov, rtol=0, atol=1e-12)


def test_stored_message_is_the_own_sensor_belief_through_the_v2f_likelihood():
    """feature_message = "own": the message a track keeps of each row is N(own mean + z, own cov + R)
    in closed form, whatever the other features said this step; "bpa" keeps (19) with the other
    features in the cavity, which differs for a vehicle observing two features at once."""
    f = road_frames(steps=1, v2f_range=40.0)[0]
    assoc = f.truth.v2f_feature
    used = assoc >= 0
    assert np.bincount(f.v2f_owner[used]).max() >= 2, "some vehicle must observe two features"
    own_mean, own_cov = vehicle_prior_beliefs(np.empty(0, dtype=object), np.empty((0, 4)), np.empty((0, 4, 4)), f,
                                              IcpParams(motion=MOTION))
    # A vehicle belief that is not its own-sensor one, so "own" cannot coincide with b^(0) by chance.
    b0_mean, b0_cov = own_mean + 0.5, own_cov * 0.5
    fids = np.unique(assoc[used])
    zeros_l, zeros_e = np.zeros((fids.size, 4, 4)), np.zeros((fids.size, 4))
    res = {fm: bpa_localization(b0_mean, b0_cov, own_mean, own_cov, f.v2f_owner, assoc, f.v2f_z, f.v2f_R,
                                f.neighbors, zeros_l, zeros_e, IcpParams(motion=MOTION, feature_message=fm))
           for fm in ("own", "bpa")}
    owner = f.v2f_owner[used]
    cov = own_cov[owner] + f.v2f_R[used]
    mean = own_mean[owner] + f.v2f_z[used]
    np.testing.assert_allclose(np.linalg.inv(res["own"].msg_lam), cov, rtol=1e-9)
    np.testing.assert_allclose(np.linalg.solve(res["own"].msg_lam, res["own"].msg_eta[..., None])[..., 0], mean,
                               rtol=1e-9, atol=1e-9)
    # The vehicle beliefs of the step do not depend on what is stored.
    np.testing.assert_array_equal(res["own"].mean, res["bpa"].mean)
    multi = np.bincount(owner)[owner] >= 2
    assert np.abs(res["bpa"].msg_lam[multi] - res["own"].msg_lam[multi]).max() > 1e-3


def test_reported_feature_estimates_are_eq20_with_the_final_messages():
    """The step's feature estimate is b_k = b_k^(0) prod_i m_{i->k} (20) with BPA-L's final messages,
    b_k^(0) the carried track without the messages this step's observers replace (second step)."""
    frames = road_frames(steps=2, v2v_range=25.0)
    params = IcpParams(motion=MOTION)
    icp = IcpKnownDA(params)
    icp.step_with_association(frames[0], frames[0].truth.v2f_feature)
    state, f = icp.state, frames[1]
    assoc = f.truth.v2f_feature
    used = assoc >= 0
    rows_vehicle = f.vehicle_ids[f.v2f_owner[used]]
    b0_mean, b0_cov = vehicle_prior_beliefs(state.ids, state.mean, state.cov, f, params)
    own_mean, own_cov = vehicle_prior_beliefs(state.ids, state.own_mean, state.own_cov, f, params)
    pred = state.features.predict(f.dt, params)
    fids = np.unique(assoc[used])
    fl, fe = pred.prior_information(fids, assoc[used], rows_vehicle, params)
    res = bpa_localization(b0_mean, b0_cov, own_mean, own_cov, f.v2f_owner, assoc, f.v2f_z, f.v2f_R, f.neighbors,
                           fl, fe, params)
    k = np.searchsorted(fids, assoc[used])
    lam, eta = fl.copy(), fe.copy()
    np.add.at(lam, k, res.final_lam)
    np.add.at(eta, k, res.final_eta)
    est = icp.step_with_association(f, assoc)
    at = np.searchsorted(est.feature_track_ids, fids)
    assert np.array_equal(est.feature_track_ids[at], fids)
    np.testing.assert_allclose(np.linalg.inv(est.feature_cov[at]), lam, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(est.feature_mean[at], np.linalg.solve(lam, eta[..., None])[..., 0], atol=1e-6)
    # ... while the carried track holds the own-sensor messages (less information than (20)).
    carried_cov = icp.state.features.moments(params)[1][icp.state.features.lookup(fids)]
    assert np.all(np.trace(carried_cov[:, :2, :2], axis1=1, axis2=2) > np.trace(est.feature_cov[at, :2, :2], axis1=1, axis2=2))


def test_tracks_of_own_sensor_messages_are_consistent_and_final_messages_are_not():
    """Static features, 8 vehicles over 40 steps, Q_F nearly 0: the mean 2-D NEES of the feature
    tracks (2 for a consistent estimator) pooled over six seeds. Stored final BPA-L messages count
    other vehicles' evidence again in every track (measured 21.4); own-sensor messages do not
    (measured 1.81; per seed 0.73 to 3.17)."""
    nees = {"own": [], "bpa": []}
    for seed in range(1, 7):
        frames = road_frames(seed=seed, n=8, steps=40, n_feat=8, v2f_range=30.0)
        for fm in nees:
            params = IcpParams(motion=MOTION, feature_sigma_par=1e-4, feature_message=fm, feature_drop_after_s=100.0)
            icp = IcpKnownDA(params)
            for f in frames:
                icp.step_with_association(f, f.truth.v2f_feature)
                store = icp.state.features  # the carried tracks (the step's estimates are (20))
                mean, cov = store.moments(params)
                d = mean[:, :2] - f.truth.features_true[store.ids, :2]
                nees[fm].append(np.einsum("ni,nij,nj->n", d, np.linalg.inv(cov[:, :2, :2]), d))
    own, bpa = (float(np.mean(np.concatenate(nees[k]))) for k in ("own", "bpa"))
    print(f"mean feature NEES (2-D): own {own:.2f}, bpa {bpa:.2f}")
    assert 1.0 < own < 3.0
    assert bpa > 3 * own


def test_single_observers_of_new_features_gain_nothing_on_first_sight():
    """No V2V links: each vehicle alone senses each new feature; extrinsic (21) is uniform."""
    f = road_frames(steps=1, v2v_range=1.0)[0]
    assert f.v2f_z.shape[0] > 0
    a = IcpKnownDA(IcpParams(motion=MOTION)).step_with_association(f, f.truth.v2f_feature)
    g = GnssTracker(MOTION).step(f)
    np.testing.assert_allclose(a.mean, g.mean, atol=1e-9)
    np.testing.assert_allclose(a.cov, g.cov, rtol=1e-9, atol=1e-12)


def test_vehicles_entering_and_leaving_and_spd_throughout():
    frames = road_frames(steps=15, leave=(1, 5), enter=(3, 7), v2v_range=25.0)
    icp = IcpKnownDA(IcpParams(motion=MOTION))
    for f in frames:
        a = icp.step_with_association(f, f.truth.v2f_feature)
        assert a.mean.shape == (f.n_vehicles, 4)
        assert np.all(np.isfinite(a.mean))
        assert_spd(a.cov)
        if a.feature_cov is not None and len(a.feature_cov):
            assert_spd(a.feature_cov)
        if f.entered.any() and f.t > 0:  # the entering vehicle restarted near its fast-start prior
            i = np.flatnonzero(f.entered)[0]
            assert np.linalg.norm(a.mean[i, :2] - f.prior_z[i, :2]) < 10.0


def test_unobserved_feature_is_kept_then_dropped():
    frames = road_frames(steps=1, n=1, n_feat=1)
    f0 = frames[0]
    params = IcpParams(motion=MOTION, feature_drop_after_s=3.0)
    icp = IcpKnownDA(params)
    e = icp.step_with_association(f0, f0.truth.v2f_feature)
    assert e.feature_track_ids.tolist() == [0]
    p0 = e.feature_cov[0, 0, 0]
    for t in range(1, 6):  # the vehicle no longer sees the feature
        f = replace(f0, t=float(t), entered=np.zeros(1, bool), v2f_z=np.empty((0, 4)),
                    v2f_owner=np.empty(0, np.int64), v2f_R=np.empty((0, 4, 4)), truth=None)
        e = icp.step_with_association(f, np.empty(0, np.int64))
        if t <= 3:
            assert e.feature_track_ids.tolist() == [0] and e.feature_cov[0, 0, 0] > p0
        else:
            assert e.feature_track_ids.size == 0


def test_empty_frame_and_all_vehicles_gone():
    from coloc.core.frame import empty_frame

    icp = IcpKnownDA()
    e = icp.step_with_association(empty_frame(0.0, 1.0), np.empty(0, np.int64))
    assert e.mean.shape == (0, 4)
    f = road_frames(steps=1)[0]
    icp.step_with_association(f, f.truth.v2f_feature)
    e = icp.step_with_association(empty_frame(1.0, 1.0), np.empty(0, np.int64))
    assert e.mean.shape == (0, 4) and e.feature_track_ids.size > 0


def test_centralized_handles_enter_leave():
    frames = road_frames(steps=12, leave=(1, 4), enter=(3, 6))
    kf = CentralizedKF(IcpParams(motion=MOTION))
    for f in frames:
        e = kf.step_with_association(f, f.truth.v2f_feature)
        assert e.mean.shape == (f.n_vehicles, 4)
        assert_spd(e.cov)
