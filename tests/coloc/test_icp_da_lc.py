"""ICP-DA-LC (Brambilla et al. Sec. IV-D): eta (13), MAP pairing (30), track birth/merge, end to end."""

import numpy as np
import pytest
from scipy.stats import chi2, multivariate_normal

from coloc.inference.association import association_marginals_both, association_marginals_batch
from coloc.inference.feature_store import FeatureStore
from coloc.inference.gaussian import to_information
from coloc.inference.params import IcpParams
from coloc.methods.icp_da_lc import IcpDaLc, LcParams, association_weights, birth_clusters, map_pairing
from coloc.methods.icp_known_da import IcpKnownDA
from scenes import road_frames
from tests.coloc.test_icp_known_da import MOTION


def test_batch_association_equals_one_by_one():
    rng = np.random.default_rng(3)
    shapes = [(2, 3), (0, 2), (3, 0), (4, 4), (1, 1)]
    probs = [rng.random((k, m + 1)) * rng.choice([1e-8, 1.0, 1e8], size=(k, m + 1)) for k, m in shapes]
    pf, pn = association_marginals_batch(np.concatenate([p.ravel() for p in probs]),
                                         [s[0] for s in shapes], [s[1] for s in shapes])
    off = noff = 0
    for p in probs:
        a, b = association_marginals_both(p)
        np.testing.assert_array_equal(pf[off:off + p.size].reshape(p.shape), a)
        np.testing.assert_array_equal(pn[noff:noff + p.shape[1] - 1], b)
        off, noff = off + p.size, noff + p.shape[1] - 1


def test_eta_is_the_gaussian_integral_of_eq13_over_the_new_feature_density():
    lc = LcParams(sensing_range_m=40.0, detection_probability=0.9, new_feature_velocity_sigma=0.7,
                  new_feature_rate=2.0, gate_probability=0.999999)
    v_mean = np.array([[0.0, 0.0, 10.0, 0.0]])
    v_cov = np.diag([1.0, 2.0, 0.04, 0.05])[None]
    t_mean = np.array([[12.0, 5.0, 0.0, 0.0], [-30.0, 1.0, 0.0, 0.0]])
    t_cov = np.stack([np.diag([0.5, 0.5, 0.01, 0.01]), np.diag([0.2, 0.3, 0.01, 0.02])])
    z = np.array([[12.5, 4.0, -10.1, 0.2], [-29.0, 1.5, -9.8, 0.1]])
    r = np.repeat(np.diag([0.01, 0.01, 0.01, 0.01])[None], 2, 0)
    pv, pt, pr, w = association_weights(v_mean, v_cov, t_mean, t_cov, np.array([0, 0]), z, r, lc)
    assert sorted(zip(pt.tolist(), pr.tolist())) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    for k, l, wk in zip(pt, pr, w):
        lik = multivariate_normal(t_mean[k] - v_mean[0], t_cov[k] + v_cov[0] + r[l]).pdf(z[l])
        new_v = multivariate_normal(-v_mean[0, 2:], v_cov[0, 2:, 2:] + r[l, 2:, 2:] + 0.49 * np.eye(2)).pdf(z[l, 2:])
        new = 2.0 / (np.pi * 40.0**2) * new_v
        s = t_cov[k] + v_cov[0] + r[l]
        nu = z[l] - (t_mean[k] - v_mean[0])
        if nu @ np.linalg.solve(s, nu) > chi2.ppf(0.999999, 4):
            assert wk == 0.0  # gated
        else:
            np.testing.assert_allclose(wk, 0.9 * lik / new, rtol=1e-9)
    assert np.count_nonzero(w) == 2  # each row fits one track


def test_gate_zeroes_far_pairs_and_out_of_range_tracks_are_not_candidates():
    lc = LcParams(sensing_range_m=20.0)
    v_mean = np.zeros((1, 4))
    v_cov = np.eye(4)[None] * 0.01
    t_mean = np.array([[5.0, 0, 0, 0], [200.0, 0, 0, 0]])
    t_cov = np.repeat(np.eye(4)[None] * 0.01, 2, 0)
    z = np.array([[5.0, 0, 0, 0], [-5.0, 0, 0, 0]])
    r = np.repeat(np.eye(4)[None] * 0.01, 2, 0)
    pv, pt, pr, w = association_weights(v_mean, v_cov, t_mean, t_cov, np.zeros(2, np.int64), z, r, lc)
    assert set(pt.tolist()) == {0}  # the track 200 m away is not a candidate
    assert w[pr == 0][0] > 0 and w[pr == 1][0] == 0.0


def _weights(eta_rows):
    """pair arrays for one vehicle from a (K, M) matrix of measurement weights."""
    k, m = np.nonzero(np.ones_like(eta_rows))
    return np.zeros(k.size, np.int64), k, m, eta_rows[k, m]


def test_map_pairing_threshold_discards_ambiguous_rows():
    # Two tracks, two rows; track 0 fits both rows equally (ambiguous), track 1 fits row 1 only.
    w = np.array([[5.0, 5.0], [0.0, 50.0]])
    pv, pt, pr, ww = _weights(w)
    lc_keep_all = LcParams(eta_threshold=1.0, detection_probability=0.9)
    rt, new = map_pairing(pv, pt, pr, ww, 1, 2, lc_keep_all)
    assert rt.tolist() == [0, 1]
    # A track whose detection belief is weak is not detected under eta_TH = 0.5.
    w = np.array([[0.02, 0.0], [0.0, 50.0]])
    pv, pt, pr, ww = _weights(w)
    rt_half, _ = map_pairing(pv, pt, pr, ww, 1, 2, LcParams(eta_threshold=0.5, detection_probability=0.9))
    rt_all, _ = map_pairing(pv, pt, pr, ww, 1, 2, LcParams(eta_threshold=1.0, detection_probability=0.9))
    assert rt_half.tolist() == [-1, 1] and rt_all.tolist() == [0, 1]


def test_map_pairing_conflict_goes_to_the_larger_belief():
    w = np.array([[100.0], [1.0]])  # both tracks want the only row
    pv, pt, pr, ww = _weights(w)
    rt, new = map_pairing(pv, pt, pr, ww, 1, 1, LcParams(eta_threshold=1.0))
    assert rt.tolist() == [0]
    assert 0.0 <= new[0] < 0.5


def test_birth_clusters_join_vehicles_not_rows_of_one_vehicle():
    xy = np.array([[0.0, 0.0], [0.5, 0.0], [0.3, 0.2], [10.0, 0.0], [0.2, 0.1]])
    owner = np.array([0, 1, 1, 2, 3])
    cov = np.repeat(np.eye(2)[None] * 0.5, 5, 0)
    labels = birth_clusters(owner, xy, cov, gate_d2=9.21)
    # rows 0 (vehicle 0) and 1 (vehicle 1) join; row 2 is vehicle 1 again: its own track; row 3 is far;
    # row 4 joins the nearest admissible cluster (row 2's, 0.14 m, before row 0's, 0.22 m).
    assert labels.tolist() == [0, 0, 1, 2, 1]


def _msg(mean, var):
    lam, eta = to_information(np.asarray(mean, float)[None], (np.eye(4) * var)[None])
    return lam, eta


def test_track_store_replaces_a_vehicles_message_and_accumulates_different_vehicles():
    params = IcpParams(motion=MOTION, feature_sigma_par=0.0)
    store = FeatureStore()
    for t in range(10):  # one vehicle re-sends the same-quality message: no growth of information
        lam, eta = _msg([1.0, 2.0, 0, 0], 1.0)
        store = store.record(np.array([7]), np.array(["a"], dtype=object), lam, eta, float(t), params)
    _, cov = store.moments(params)
    np.testing.assert_allclose(cov[0, 0, 0], 1.0, rtol=1e-9)
    lam, eta = _msg([3.0, 2.0, 0, 0], 1.0)
    store = store.record(np.array([7]), np.array(["b"], dtype=object), lam, eta, 10.0, params)
    mean, cov = store.moments(params)
    np.testing.assert_allclose(cov[0, 0, 0], 0.5, rtol=1e-9)
    np.testing.assert_allclose(mean[0, :2], [2.0, 2.0], rtol=1e-9)
    # Merging a second track holding a newer message of vehicle "a": the newer replaces the older.
    lam, eta = _msg([5.0, 2.0, 0, 0], 1.0)
    store = store.record(np.array([9]), np.array(["a"], dtype=object), lam, eta, 11.0, params)
    merged = store.merge(np.array([9]), np.array([7]))
    assert merged.ids.tolist() == [7]
    mean, cov = merged.moments(params)
    np.testing.assert_allclose(mean[0, 0], 4.0, rtol=1e-9)  # (a at 5 + b at 3) / 2
    np.testing.assert_allclose(cov[0, 0, 0], 0.5, rtol=1e-9)


def _run(est, frames, known=False):
    out = []
    for f in frames:
        blind = f.without_truth()
        out.append(est.step_with_association(blind, f.truth.v2f_feature) if known else est.step(blind))
    return out


def _rmse(frames, ests):
    e = np.concatenate([np.sum((r.mean[:, :2] - f.truth.x_true[:, :2]) ** 2, 1) for f, r in zip(frames, ests)])
    return float(np.sqrt(e.mean()))


@pytest.mark.parametrize("seed", [1, 2])
def test_separated_features_are_associated_correctly_and_reach_the_known_da_bound(seed):
    """Features 30 m apart. The first steps (fast-start priors, sigma 2 m) may open duplicate tracks
    for one feature (births more than merge_gate_m apart); they are merged within two steps. From
    step 3 on every row is paired, one track per true feature; RMSE within 1 % of known DA
    (measured: equal to 1e-12 on seeds 1-3 with the statistical birth gate)."""
    frames = road_frames(seed=seed, steps=20, v2v_range=25.0)
    params = IcpParams(motion=MOTION)
    lc_est = _run(IcpDaLc(params, LcParams(sensing_range_m=30.0)), frames)
    kd_est = _run(IcpKnownDA(params), frames, known=True)
    pairs = set()
    for f, r in list(zip(frames, lc_est))[3:]:
        assert np.all(r.v2f_assignment >= 0)
        pairs.update(zip(r.v2f_assignment.tolist(), f.truth.v2f_feature.tolist()))
    tracks_of = {}
    for trk, true in pairs:
        tracks_of.setdefault(true, set()).add(trk)
    assert all(len(v) == 1 for v in tracks_of.values()), tracks_of  # one track per feature
    assert len({trk for trk, _ in pairs}) == len(tracks_of)  # one feature per track
    r_lc, r_kd = _rmse(frames, lc_est), _rmse(frames, kd_est)
    print(f"seed {seed}: RMSE LC {r_lc:.3f} m, known DA {r_kd:.3f} m")
    assert r_lc <= 1.01 * r_kd


def test_empty_frames_and_no_features():
    from coloc.core.frame import empty_frame

    est = IcpDaLc()
    e = est.step(empty_frame(0.0, 1.0))
    assert e.mean.shape == (0, 4) and e.v2f_assignment.shape == (0,)
    for f in road_frames(steps=3, n_feat=0):
        e = est.step(f)
        assert e.mean.shape == (f.n_vehicles, 4)


def _map_pairing_reference(pv, pt, pr, w, n_rows, lc):
    """Per-vehicle loop: BP on each vehicle's (track x row) matrix, then (30) with conflicts."""
    row_track = np.full(n_rows, -1)
    row_new = np.ones(n_rows)
    keep = w > 0
    pv, pt, pr, w = pv[keep], pt[keep], pr[keep], w[keep]
    for v in np.unique(pv):
        sel = pv == v
        tk, ti = np.unique(pt[sel], return_inverse=True)
        rk, ri = np.unique(pr[sel], return_inverse=True)
        eta = np.zeros((tk.size, rk.size + 1))
        eta[:, 0] = 1.0 - lc.detection_probability
        eta[ti, ri + 1] = w[sel]
        b, new = association_marginals_both(eta, lc.bp_iterations, lc.bp_tol)
        row_new[rk] = new
        best = np.argmax(b[:, 1:], axis=1)
        score = b[np.arange(tk.size), best + 1]
        det = (score > 0) & ((b[:, 0] < lc.eta_threshold) | (lc.eta_threshold >= 1.0))
        for j in np.argsort(-score, kind="stable"):
            if det[j] and row_track[rk[best[j]]] < 0:
                row_track[rk[best[j]]] = tk[j]
    return row_track, row_new


@pytest.mark.parametrize("eta_th", [0.5, 1.0])
def test_vectorised_map_pairing_equals_the_per_vehicle_loop(eta_th):
    rng = np.random.default_rng(11)
    lc = LcParams(eta_threshold=eta_th)
    for _ in range(50):
        n_veh, n_trk = rng.integers(1, 6), rng.integers(1, 7)
        owner = np.sort(rng.integers(0, n_veh, rng.integers(1, 15)))
        pv, pt, pr = [], [], []
        for v in range(n_veh):
            rows = np.flatnonzero(owner == v)
            for k in rng.choice(n_trk, rng.integers(0, n_trk + 1), replace=False):
                for r in rows:
                    pv.append(v), pt.append(k), pr.append(r)
        pv, pt, pr = (np.array(a, dtype=np.int64) for a in (pv, pt, pr))
        w = rng.exponential(5.0, pv.size) * (rng.random(pv.size) < 0.7)
        got = map_pairing(pv, pt, pr, w, n_veh, owner.size, lc)
        ref = _map_pairing_reference(pv, pt, pr, w, owner.size, lc)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_allclose(got[1], ref[1], rtol=1e-12)


def test_candidate_pairs_indexed_as_dense(monkeypatch):
    """On a city (vehicles x tracks above DENSE_PAIRS_MAX) the numpy reference finds the tracks with a k-d
    tree, and the fused path with the spread-class index (coloc.kernels.track_index): the same pairs, in the
    same order, as the dense test of every (vehicle, track)."""
    from coloc.kernels import icp_fused
    from coloc.methods import icp_da_lc as lcmod

    rng = np.random.default_rng(3)
    lc = LcParams()
    for nv, nt in ((300, 2000), (40, 7), (1, 500)):
        vm, tm = rng.uniform(0, 2000, (nv, 4)), rng.uniform(0, 2000, (nt, 4))
        vm[0, :2] = tm[0, :2] + [lc.sensing_range_m, 0.0]  # on the edge of the reach
        vc = np.eye(4) * rng.uniform(0.01, 40.0, (nv, 1, 1))
        tc = np.eye(4) * rng.uniform(0.0, 3.0, (nt, 1, 1))
        monkeypatch.setattr(icp_fused, "FUSED", False)
        monkeypatch.setattr(lcmod, "DENSE_PAIRS_MAX", 10**12)
        dense = lcmod.candidate_pairs(vm, vc, tm, tc, lc)
        monkeypatch.setattr(lcmod, "DENSE_PAIRS_MAX", 0)
        tree = lcmod.candidate_pairs(vm, vc, tm, tc, lc)
        monkeypatch.setattr(icp_fused, "FUSED", True)
        indexed = lcmod.candidate_pairs(vm, vc, tm, tc, lc)
        assert dense[0].size > 0
        for a, b, c in zip(dense, tree, indexed):
            assert a.dtype == b.dtype == c.dtype == np.int64 and np.array_equal(a, b) and np.array_equal(a, c)
