"""numba kernels of the Gaussian ICP against their numpy / scipy references (random inputs)."""

import numpy as np
import pytest
import scipy.sparse as sp

from coloc.core.models import symmetrize
from coloc.inference.bpa import _pack_sym, _unpack_sym, bpa_localization
import coloc.inference.bpa as bpa
from coloc.inference.consensus import _average_kernel, metropolis_weights
from coloc.inference.gaussian import _surely_above_floor, chi2_ppf, psd_clip, relative_message
from coloc.inference.params import IcpParams
from coloc.inference.row_consensus import (
    _pairwise_sum,
    consensus_graph,
    row_components,
    row_consensus_weights,
)
from coloc.kernels.icp import (
    complete_component_consensus,
    extrinsic_kernel,
    feature_to_vehicle_kernel,
    relative_message_kernel,
    vehicle_to_feature_kernel,
)


def random_spd(rng, n, scale=1.0, rank=4):
    a = rng.standard_normal((n, 4, rank)) * scale
    return symmetrize(a @ np.swapaxes(a, 1, 2) + (1e-3 * scale * scale * np.eye(4) if rank == 4 else 0.0))


def random_scene(rng, n=30, o=90, n_feat=25, p_edge=0.3):
    owner = rng.integers(0, n, o)
    feat = rng.integers(0, n_feat, o)
    # one row per (vehicle, feature)
    _, first = np.unique(owner * n_feat + feat, return_index=True)
    owner, feat = owner[np.sort(first)], feat[np.sort(first)]
    upper = np.triu(rng.random((n, n)) < p_edge, 1)
    adj = sp.csr_matrix(upper | upper.T)
    return owner, feat, adj


def bpa_scene(rng, n, n_feat, p_edge):
    """A BPA-L problem: :func:`random_scene` with 120 rows, vehicles and features on a 50 m scale,
    priors around the true vehicles and relative measurements with 0.1 noise. Returns (owner, feat,
    adj, the true features xf, prior_mean, prior_cov, z)."""
    owner, feat, adj = random_scene(rng, n=n, o=120, n_feat=n_feat, p_edge=p_edge)
    x = rng.standard_normal((n, 4)) * [50, 50, 5, 5]
    xf = rng.standard_normal((n_feat, 4)) * [50, 50, 0, 0]
    prior_cov = random_spd(rng, n, 1.0) + 4 * np.eye(4)
    prior_mean = x + rng.standard_normal((n, 4))
    z = xf[feat] - x[owner] + 0.1 * rng.standard_normal((owner.size, 4))
    return owner, feat, adj, xf, prior_mean, prior_cov, z


@pytest.mark.parametrize("seed", range(6))
def test_row_consensus_weights_equal_scipy_path_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    owner, feat, adj = random_scene(rng, p_edge=[0.05, 0.3, 0.9, 1.0, 0.5, 0.0][seed])
    fids, fidx = np.unique(feat, return_inverse=True)
    graph = consensus_graph(owner, feat, adj)
    w_ref = metropolis_weights(graph)
    _, count_ref = row_components(graph)
    (indptr, indices, data), count, complete = row_consensus_weights(owner, fidx, fids.size, adj)
    np.testing.assert_array_equal(indptr, w_ref.indptr)
    np.testing.assert_array_equal(indices, w_ref.indices)
    np.testing.assert_array_equal(data, w_ref.data)  # exact, incl. the pairwise-summed diagonal
    np.testing.assert_array_equal(count, count_ref)
    labels, _ = row_components(graph)
    g = graph.toarray()
    for lab in np.unique(labels):
        rows = np.flatnonzero(labels == lab)
        sub = g[np.ix_(rows, rows)] | np.eye(rows.size, dtype=bool)
        assert complete[rows].all() == sub.all() and complete[rows].any() == sub.all()


@pytest.mark.parametrize("p_edge", [0.2, 0.6, 1.0])
def test_complete_component_consensus_equals_full_rounds(p_edge):
    rng = np.random.default_rng(11)
    owner, feat, adj = random_scene(rng, n=20, o=80, n_feat=10, p_edge=p_edge)
    fids, fidx = np.unique(feat, return_inverse=True)
    (indptr, indices, data), count, complete = row_consensus_weights(owner, fidx, fids.size, adj)
    x = rng.standard_normal((owner.size, 14)) * 100
    ref = _average_kernel(indptr, indices, data, x, 20)
    out = complete_component_consensus(indptr, indices, data, x, 20, complete)
    np.testing.assert_array_equal(out[~complete], ref[~complete])  # same rounds, same order
    np.testing.assert_allclose(out[complete], ref[complete], rtol=1e-12, atol=1e-12)
    # and the component averages are reached
    for k in range(fids.size):
        rows = np.flatnonzero((fidx == k) & complete)
        if rows.size:
            np.testing.assert_allclose(out[rows], np.broadcast_to(x[rows].mean(0), out[rows].shape) if count[rows[0]] == rows.size else out[rows], rtol=1e-12, atol=1e-10)


def test_pairwise_sum_is_numpy_reduceat_bit_for_bit():
    rng = np.random.default_rng(3)
    for n in list(range(1, 300)) + [511, 1024, 3001]:
        a = rng.random(n) * rng.choice([1e-3, 1.0, 1e3], n)
        assert np.add.reduceat(a, [0])[0] == a[0] + _pairwise_sum(a, 1, n - 1)


def test_surely_above_floor_never_claims_a_clipped_matrix():
    rng = np.random.default_rng(4)
    lam = np.concatenate([random_spd(rng, 200), random_spd(rng, 100, rank=3), -random_spd(rng, 20),
                          random_spd(rng, 50) - 0.5 * np.eye(4), np.zeros((3, 4, 4))])
    sure = _surely_above_floor(lam, 0.0)
    w = np.linalg.eigh(lam)[0]
    assert not (w[sure] < 0).any()
    assert sure[:200].all() and not sure[200:320].any() and not sure[-3:].any()
    # psd_clip returns its inputs untouched when nothing is clipped, and clips as before otherwise
    eta = rng.standard_normal((lam.shape[0], 4))
    good = lam[:200]
    assert psd_clip(good, eta[:200])[0] is good
    lc, _ = psd_clip(lam, eta)
    assert (np.linalg.eigvalsh(lc) > -1e-9).all()


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_relative_message_kernel_equals_numpy(sign):
    rng = np.random.default_rng(5)
    o = 300
    lam = np.concatenate([random_spd(rng, o - 20), random_spd(rng, 10, rank=2), np.zeros((10, 4, 4))])
    eta = rng.standard_normal((o, 4)) * 10
    z = rng.standard_normal((o, 4)) * 20
    r = random_spd(rng, o, scale=0.3)
    r_inv = symmetrize(np.linalg.inv(r))
    ly, ey = relative_message(lam, eta, sign * z, r, r_inv)
    lk, ek = relative_message_kernel(lam, eta, z, sign, r_inv)
    np.testing.assert_allclose(lk, ly, rtol=1e-10, atol=1e-10 * np.abs(ly).max())
    np.testing.assert_allclose(ek, ey, rtol=1e-10, atol=1e-10 * np.abs(ey).max())


def test_iteration_kernels_equal_numpy_steps():
    rng = np.random.default_rng(6)
    n, o = 12, 40
    owner = np.sort(rng.integers(0, n, o))
    own_lam0, in_lam = random_spd(rng, n), random_spd(rng, n, 0.3)
    own_eta0, in_eta = rng.standard_normal((n, 4)), rng.standard_normal((n, 4))
    m_fv_lam, m_fv_eta = random_spd(rng, o, 0.1), rng.standard_normal((o, 4))
    z = rng.standard_normal((o, 4)) * 10
    r = random_spd(rng, o, 0.3)
    r_inv = symmetrize(np.linalg.inv(r))
    # (19)
    ml, me, packed = vehicle_to_feature_kernel(owner, own_lam0, own_eta0, in_lam, in_eta, m_fv_lam, m_fv_eta, z, r_inv)
    rl, re = relative_message(own_lam0[owner] + in_lam[owner] - m_fv_lam, own_eta0[owner] + in_eta[owner] - m_fv_eta,
                              z, r, r_inv)
    np.testing.assert_allclose(ml, rl, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(me, re, rtol=1e-10, atol=1e-10)
    al, ae = _unpack_sym(packed)
    np.testing.assert_array_equal(al, ml)
    np.testing.assert_array_equal(ae, me)
    # (21) first half
    count = rng.integers(1, 5, o).astype(float)
    f0l, f0e = random_spd(rng, o), rng.standard_normal((o, 4))
    avg = _pack_sym(random_spd(rng, o), rng.standard_normal((o, 4)))
    el, ee = extrinsic_kernel(avg, count, f0l, f0e, ml, me)
    avl, ave = _unpack_sym(avg)
    np.testing.assert_array_equal(el, f0l + count[:, None, None] * avl - ml)
    np.testing.assert_array_equal(ee, f0e + count[:, None] * ave - me)
    # (21) second half and (22)
    el = random_spd(rng, o)
    v_lam0, v_eta0 = random_spd(rng, n), rng.standard_normal((n, 4))
    prev = rng.standard_normal((n, 4))
    out = feature_to_vehicle_kernel(owner, el, ee, z, r_inv, v_lam0, v_eta0, prev)
    fl, fe = relative_message(el, ee, -z, r, r_inv)
    np.testing.assert_allclose(out[0], fl, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out[1], fe, rtol=1e-10, atol=1e-10)
    inc = np.zeros((n, o))
    inc[owner, np.arange(o)] = 1.0
    v_lam = symmetrize(v_lam0 + np.einsum("no,oij->nij", inc, fl))
    v_eta = v_eta0 + inc @ fe
    mean = np.linalg.solve(v_lam, v_eta[..., None])[..., 0]
    np.testing.assert_allclose(out[4], v_lam, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out[6], mean, rtol=1e-9, atol=1e-9)
    assert out[7] == pytest.approx(np.hypot(*(mean[:, :2] - prev[:, :2]).T).max(), rel=1e-9)
    assert out[8] == pytest.approx(np.hypot(*(mean[:, 2:] - prev[:, 2:]).T).max(), rel=1e-9)


def test_bpa_with_kernels_equals_numpy_iterations(monkeypatch):
    rng = np.random.default_rng(7)
    n, n_feat = 25, 30
    owner, feat, adj, xf, prior_mean, prior_cov, z = bpa_scene(rng, n, n_feat, p_edge=0.4)
    o = owner.size
    r = np.broadcast_to(0.01 * np.eye(4), (o, 4, 4)).copy()
    fids = np.unique(feat)
    f_lam = np.zeros((fids.size, 4, 4))
    f_lam[::2] = random_spd(rng, f_lam[::2].shape[0], 0.5)
    f_eta = np.einsum("kij,kj->ki", f_lam, xf[fids])
    params = IcpParams(consensus_iterations=5, bpa_max_iterations=6)
    args = (prior_mean, prior_cov, prior_mean, prior_cov * 1.5, owner, feat, z, r, adj, f_lam, f_eta, params)
    fast = bpa_localization(*args)
    monkeypatch.setattr(bpa, "BPA_KERNELS", False)
    ref = bpa_localization(*args)
    assert fast.iterations == ref.iterations and fast.converged == ref.converged
    np.testing.assert_allclose(fast.mean, ref.mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.cov, ref.cov, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.msg_lam, ref.msg_lam, rtol=1e-9, atol=1e-9 * np.abs(ref.msg_lam).max())
    np.testing.assert_allclose(fast.msg_eta, ref.msg_eta, rtol=1e-9, atol=1e-9 * np.abs(ref.msg_eta).max())


def test_information_kernels_equal_numpy():
    from coloc.inference.gaussian import _inv_spd, _inv_spd_numpy, from_information, to_information

    rng = np.random.default_rng(12)
    cov = random_spd(rng, 200, 3.0)
    mean = rng.standard_normal((200, 4)) * 100
    lam, eta = to_information(mean, cov)
    lam_ref = _inv_spd_numpy(cov)
    np.testing.assert_allclose(lam, lam_ref, rtol=1e-10, atol=1e-12 * np.abs(lam_ref).max())
    np.testing.assert_allclose(eta, np.einsum("nij,nj->ni", lam_ref, mean), rtol=1e-9, atol=1e-9)
    assert np.array_equal(lam, np.swapaxes(lam, 1, 2))
    m2, c2 = from_information(lam, eta)
    np.testing.assert_allclose(c2, cov, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(m2, mean, rtol=1e-9, atol=1e-7)
    np.testing.assert_allclose(_inv_spd(cov[:3].reshape(3, 1, 4, 4)), lam_ref[:3].reshape(3, 1, 4, 4), rtol=1e-10)
    # not positive definite: Gauss-Jordan fallback, like LAPACK's inverse
    indef = np.diag([2.0, -1.0, 0.5, 3.0])[None]
    np.testing.assert_allclose(_inv_spd(indef), np.linalg.inv(indef), rtol=1e-14)


def test_vehicle_prior_kernel_equals_numpy_reference():
    from coloc.core.frame import empty_frame
    from coloc.methods.gnss import gnss_predict_update
    from coloc.methods.icp_known_da import vehicle_prior_beliefs
    from coloc.core.models import MotionParams, kalman_update
    from dataclasses import replace

    rng = np.random.default_rng(13)
    n = 50
    params = IcpParams(motion=MotionParams(sigma_along=0.35, sigma_cross=0.1))
    ids = np.array([f"v{i}" for i in range(n)], dtype=object)
    prev_mean = rng.standard_normal((n, 4)) * [100, 100, 8, 8]
    prev_mean[:5, 2:] = 0.01  # slow: isotropic Q
    prev_cov = random_spd(rng, n, 1.0)
    entered = np.zeros(n, bool)
    entered[[3, 17]] = True
    prior_z = np.full((n, 4), np.nan)
    prior_R = np.full((n, 4, 4), np.nan)
    prior_z[entered] = rng.standard_normal((2, 4))
    prior_R[entered] = np.eye(4) * 4
    fr = replace(empty_frame(10.0, 0.75), vehicle_ids=ids, entered=entered, prior_z=prior_z, prior_R=prior_R,
                 accel=rng.standard_normal((n, 2)), gnss_z=prev_mean + rng.standard_normal((n, 4)),
                 gnss_R=np.broadcast_to(np.diag([4.0, 4.0, 0.04, 0.04]), (n, 4, 4)).copy())
    mean, cov = vehicle_prior_beliefs(ids, prev_mean, prev_cov, fr, params)
    old = ~entered
    m_ref, p_ref = gnss_predict_update(prev_mean[old], prev_cov[old], fr.accel[old], fr.gnss_z[old], fr.gnss_R[old],
                                       fr.dt, params.motion)
    np.testing.assert_allclose(mean[old], m_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(cov[old], p_ref, rtol=1e-10, atol=1e-12)
    m_f, p_f = kalman_update(prior_z[entered], prior_R[entered], fr.gnss_z[entered], fr.gnss_R[entered])
    np.testing.assert_allclose(mean[entered], m_f, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(cov[entered], p_f, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("d", [2, 4])
def test_log_gauss_kernel_equals_numpy(d):
    from coloc.inference.gaussian import log_gauss, log_gauss_numpy

    rng = np.random.default_rng(14)
    a = rng.standard_normal((300, d, d))
    s = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(d)
    nu = rng.standard_normal((300, d)) * 3
    lp, d2 = log_gauss(nu, s)
    lp0, d20 = log_gauss_numpy(nu, s)
    np.testing.assert_allclose(lp, lp0, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(d2, d20, rtol=1e-10, atol=1e-12)


def test_scatter_add_equals_ufunc_at_bit_for_bit():
    from coloc.kernels.icp import scatter_add

    rng = np.random.default_rng(15)
    t = rng.standard_normal((20, 4, 4))
    rows = rng.integers(0, 20, 100)
    v = rng.standard_normal((100, 4, 4)) * 1e3
    ref = t.copy()
    np.add.at(ref, rows, v)
    scatter_add(t, rows, v)
    np.testing.assert_array_equal(t, ref)


def test_scatter_max_equals_ufunc_at_bit_for_bit():
    from coloc.kernels.icp import scatter_max

    rng = np.random.default_rng(17)
    t = rng.standard_normal((20, 50))
    t[3, :5] = -np.inf
    rows = rng.integers(0, 20, 300)
    v = rng.standard_normal((300, 50)) * 3.0
    v[7, 2], v[8, :4] = np.nan, -np.inf  # NaN wins as in np.maximum
    ref = t.copy()
    np.maximum.at(ref, rows, v)
    scatter_max(t, rows, v)
    np.testing.assert_array_equal(t, ref)


def test_predict_no_input_kernel_equals_numpy():
    from coloc.kernels.icp import predict_no_input_kernel
    from coloc.core.models import predict

    rng = np.random.default_rng(16)
    mean = rng.standard_normal((100, 4)) * 50
    cov = random_spd(rng, 100)
    q = random_spd(rng, 100, 0.01)
    m, p = predict_no_input_kernel(mean, cov, q, 0.75)
    m0, p0 = predict(mean, cov, np.zeros((100, 2)), 0.75, q)
    np.testing.assert_allclose(m, m0, rtol=1e-14, atol=1e-12)
    np.testing.assert_allclose(p, p0, rtol=1e-13, atol=1e-15)
    assert np.array_equal(p, np.swapaxes(p, 1, 2))


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("cons,iters,stop", [(5, 6, 0.1), (2, 8, 0.0), (1, 3, 1e3), (0, 4, 0.1)])
def test_bpa_loop_kernel_equals_the_per_iteration_kernels(seed, cons, iters, stop, monkeypatch):
    """coloc.kernels.bpa_rows.bpa_loop_rows (all BPA-L iterations in one call) against one call per
    iteration (LOOP_KERNEL = False), byte for byte: incomplete row graphs (finite consensus), tracks
    at the velocity-only prior (rows the PSD projection leaves as they are, learnt into
    bpa._UNCLIPPED), tracks with an indefinite prior (rows it clips: the loop stops, the caller
    projects, the loop resumes), with the learnt rows and without."""
    rng = np.random.default_rng(100 + seed)
    n, n_feat = 25, 30
    owner, feat, adj, xf, prior_mean, prior_cov, z = bpa_scene(rng, n, n_feat, p_edge=0.3 + 0.1 * (seed % 3))
    o = owner.size
    r = random_spd(rng, o, 0.1) + 0.01 * np.eye(4)
    fids = np.unique(feat)
    f_lam = np.zeros((fids.size, 4, 4))
    f_lam[1::3, 2, 2] = f_lam[1::3, 3, 3] = 100.0  # velocity prior only (the birth information)
    f_lam[::3] = random_spd(rng, f_lam[::3].shape[0], 0.5)
    f_lam[2::6] = np.diag([1.0, -1e-3, 1.0, 1.0])  # indefinite: rows the projection clips
    f_eta = np.einsum("kij,kj->ki", f_lam, xf[fids])
    params = IcpParams(consensus_iterations=cons, bpa_max_iterations=iters, stop_pos_m=stop, stop_vel_mps=stop)
    args = (prior_mean, prior_cov, prior_mean, prior_cov * 1.5, owner, feat, z, r, adj, f_lam, f_eta, params)
    clipped = []
    real_clip = bpa.psd_clip

    def clip(lam, eta, floor=0.0, sure=None):
        out = real_clip(lam, eta, floor, sure)
        clipped.append(out[0] is not lam)
        return out

    monkeypatch.setattr(bpa, "psd_clip", clip)
    results = []
    for loop, learnt in [(False, None), (True, False), (True, True)]:
        monkeypatch.setattr(bpa, "LOOP_KERNEL", loop)
        if learnt is False:
            bpa._UNCLIPPED.clear()
            bpa._UNCLIPPED_ROWS[0] = np.empty((0, 16))
        clipped.clear()
        results.append(bpa_localization(*args))
        assert any(clipped)  # (the loop kernel stopped for the projection and resumed)
    ref = results[0]
    for res in results[1:]:
        assert (res.iterations, res.converged) == (ref.iterations, ref.converged)
        for field in ("mean", "cov", "msg_lam", "msg_eta", "final_lam", "final_eta"):
            assert getattr(res, field).tobytes() == getattr(ref, field).tobytes(), field


@pytest.mark.parametrize("o", [0, 1, 2, 3, 7, 64, 469])
def test_relative_message_by_numpy_blas_is_byte_identical_to_numpy(o):
    """coloc.kernels.numpy_blas (numpy's dgesv / dgemm called row by row from numba, einsum's sums)
    against the numpy reference, byte for byte: zero (uniform) beliefs, signed zeros, scales from
    1e-3 to 1e3, runs of rows with the same Lambda and R^-1; a singular S falls back to numpy (which
    raises)."""
    from coloc.inference.gaussian import relative_message_numpy
    from coloc.kernels import numpy_blas

    if not numpy_blas.available():
        pytest.skip("numpy's OpenBLAS not found: relative_message runs numpy")
    rng = np.random.default_rng(o)
    lam = random_spd(rng, o) * (10.0 ** rng.uniform(-3, 3, o))[:, None, None]
    lam[rng.random(o) < 0.15] = 0.0
    eta = rng.standard_normal((o, 4)) * 10
    eta[rng.random(o) < 0.15] = -0.0
    z = rng.standard_normal((o, 4)) * 50
    r_inv = symmetrize(np.linalg.inv(random_spd(rng, o, 0.3) + 0.01 * np.eye(4))) if o else np.empty((0, 4, 4))
    if o > 3:  # runs of rows with the same Lambda and R^-1 (a vehicle's rows; S^-1 reused), one with -0.0
        rep = np.flatnonzero(rng.random(o) < 0.5)
        rep = rep[rep > 0]
        for k in rep:
            lam[k], r_inv[k] = lam[k - 1], r_inv[k - 1]
        lam[rep[0]] = np.where(lam[rep[0]] == 0.0, -0.0, lam[rep[0]])
    for sign in (1.0, -1.0):
        ly, ey = relative_message_numpy(lam, eta, sign * z, r_inv)
        lk, ek, ok = numpy_blas.relative_message_numpy_blas(lam, eta, sign * z, r_inv)
        assert ok and lk.tobytes() == ly.tobytes() and ek.tobytes() == ey.tobytes()
        lg, eg = relative_message(lam, eta, sign * z, None, r_inv)
        assert lg.tobytes() == ly.tobytes() and eg.tobytes() == ey.tobytes()
    if o:
        bad = lam.copy()
        bad[0] = -r_inv[0]  # S = 0
        assert not numpy_blas.relative_message_numpy_blas(bad, eta, z, r_inv)[2]
        with pytest.raises(np.linalg.LinAlgError):
            relative_message(bad, eta, z, None, r_inv)


@pytest.mark.parametrize("seed", range(4))
def test_gnss_step_rows_equals_the_row_kernel(seed):
    """coloc.kernels.kalman.gnss_step_rows (vehicles as SIMD lanes) against gnss_step_kernel byte for
    byte: slow vehicles (isotropic Q), vehicles not predicted (fresh), an S that is not positive
    definite (NaN from the square root, as the row kernel gives)."""
    from coloc.kernels.kalman import gnss_step_kernel, gnss_step_rows

    rng = np.random.default_rng(seed)
    n = 70 + seed
    mean = rng.standard_normal((n, 4)) * [100, 100, 8, 8]
    mean[:6, 2:] = 0.01 * rng.standard_normal((6, 2))
    mean[6, 2:] = 0.0
    cov = random_spd(rng, n, 1.0)
    accel = rng.standard_normal((n, 2))
    z = mean + rng.standard_normal((n, 4))
    r = random_spd(rng, n, 0.5) + np.diag([4.0, 4.0, 0.04, 0.04])
    r[-1] = -10.0 * np.eye(4)  # S not PD
    predict = rng.random(n) < 0.8
    for dt in (0.75, 0.1):
        a = (mean.copy(), cov.copy())
        b = (mean.copy(), cov.copy())
        gnss_step_kernel(a[0], a[1], accel, z, r, predict, dt, 0.35, 0.1, 0.5)
        gnss_step_rows(b[0], b[1], accel, z, r, predict, dt, 0.35, 0.1, 0.5)
        assert a[0].tobytes() == b[0].tobytes() and a[1].tobytes() == b[1].tobytes()


def test_unique_inverse_kernel_equals_numpy():
    """coloc.kernels.icp_fused._unique_inverse (a table over the key range, or a sort) is np.unique."""
    from coloc.kernels.icp_fused import _unique_inverse, _unique_inverse_sort

    rng = np.random.default_rng(3)
    cases = [np.empty(0, np.int64), np.array([5]), np.array([-3, -3, 7, -1 << 40]), rng.integers(0, 60, 468),
             rng.integers(-5, 5, 100), rng.integers(0, 1 << 50, 300), np.arange(1000)[::-1], np.full(50, 9)]
    for keys in cases:
        keys = np.asarray(keys, dtype=np.int64)
        ref_u, ref_i = np.unique(keys, return_inverse=True)
        for kernel in (_unique_inverse, _unique_inverse_sort):
            u, i = kernel(keys)
            assert u.tobytes() == ref_u.astype(np.int64).tobytes() and i.tobytes() == ref_i.astype(np.int64).tobytes()


def test_lower_bound_is_searchsorted_left():
    from coloc.kernels.icp_fused import lower_bound

    rng = np.random.default_rng(5)
    for n in (0, 1, 2, 3, 7, 8, 9, 100, 1000):
        a = np.sort(rng.integers(-50, 50, n)).astype(np.int64)
        for x in (*range(-52, 53), -(1 << 62), 1 << 62):
            assert lower_bound(a, x) == np.searchsorted(a, x)


@pytest.mark.parametrize("dt", [0.75, 0.1])
def test_feature_track_q_with_still_rows_shared_equals_feature_noise_cov(dt):
    """feature_track_q's fused path (the still tracks' Q_F computed once) is feature_noise_cov byte for byte."""
    from coloc.core.models import feature_noise_cov
    from coloc.inference.feature_store import _feature_noise_cov_rows

    rng = np.random.default_rng(11)
    for frac in (0.0, 0.3, 0.9, 1.0):
        v = rng.standard_normal((40, 2)) * 2.0
        slow = rng.random(40) < frac
        v[slow] = 0.0
        v[:2] = [[1e-300, 0.0], [-3.0, 0.0]]
        slow[:2] = False
        for s_par, s_perp in ((0.01, 0.005), (0.3, 0.15)):
            ref = feature_noise_cov(v, dt, s_par, s_perp)
            assert _feature_noise_cov_rows(v, slow, dt, s_par, s_perp).tobytes() == ref.tobytes()


def test_repeated_pair_is_the_unique_test():
    from coloc.kernels.icp_fused import repeated_pair

    rng = np.random.default_rng(9)
    for trial in range(300):
        o = int(rng.integers(0, 40))
        owner = rng.integers(0, int(rng.choice([3, 30, 10**9])), o).astype(np.int64)
        feature = rng.integers(-1, int(rng.choice([2, 20, 10**6])), o).astype(np.int64)
        used = feature >= 0
        key = owner[used] * (int(feature.max(initial=0)) + 1) + feature[used]
        assert repeated_pair(owner, feature) == (np.unique(key).size != key.size)


def test_pair_member_table_is_isin_of_the_pair_keys():
    from coloc.kernels.icp_fused import pair_member_table

    rng = np.random.default_rng(10)
    for trial in range(300):
        n_m, n_r = int(rng.integers(0, 60)), int(rng.integers(0, 40))
        span_t, span_c = int(rng.choice([5, 50, 10**7])), int(rng.choice([5, 300, 10**8]))
        mt, rt = rng.integers(0, span_t, n_m), rng.integers(0, span_t, n_r)
        mc, rc = rng.integers(0, span_c, n_m), rng.integers(0, span_c, n_r)
        if n_m and n_r and trial % 2:
            k = rng.integers(0, n_r, n_m // 2)
            mt[: k.size], mc[: k.size] = rt[k], rc[k]
        if trial % 7 == 0 and n_r:
            rt[0] = -3  # not a track id: the key path
        args = [np.asarray(a, dtype=np.int64) for a in (mt, mc, rt, rc)]
        ref = np.isin(args[0] * (1 << 32) + args[1], args[2] * (1 << 32) + args[3])
        assert (pair_member_table(*args) == ref).all()


def test_chi2_ppf_is_scipy_stats_bit_for_bit():
    """The gates' quantile without scipy.stats (start-up time) is scipy.stats.chi2.ppf's number,
    bit for bit: the shipped gate probabilities and a grid of others, 1 to 6 degrees of freedom."""
    from scipy.stats import chi2

    probabilities = np.concatenate([np.linspace(1e-4, 1 - 1e-6, 997), [0.9, 0.95, 0.99, 0.999, 0.9999, 0.999999]])
    for dof in range(1, 7):
        for p in probabilities:
            assert chi2_ppf(float(p), dof) == float(chi2.ppf(p, dof)), (p, dof)
