"""numba kernels for one Gaussian BPA-L iteration, eqs. (19), (21), (22) (Brambilla et al.
Sec. IV-B/IV-D), on the V2F rows as arrays (one pass over the rows, no batched numpy
temporaries). The numpy functions in :mod:`coloc.inference` (:func:`coloc.inference.gaussian.relative_message`,
the cavity and extrinsic differences of :func:`coloc.inference.bpa.bpa_localization`) are the
reference; tests check the kernels agree with them on random inputs.

Every 4x4 inverse here is of a symmetric positive definite matrix (Lambda + R^-1, or a
vehicle belief's information) and is done by an explicit Cholesky factorisation; the
results differ from LAPACK's LU-based ``np.linalg.inv`` by rounding only.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _chol4(a, l):
    """Lower Cholesky factor of a symmetric positive definite 4x4 ``a`` into ``l``; False if not PD."""
    for j in range(4):
        d = a[j, j]
        for k in range(j):
            d -= l[j, k] * l[j, k]
        if not d > 0.0:
            return False
        d = np.sqrt(d)
        l[j, j] = d
        for i in range(j + 1, 4):
            acc = a[i, j]
            for k in range(j):
                acc -= l[i, k] * l[j, k]
            l[i, j] = acc / d
        for i in range(j):
            l[i, j] = 0.0
    return True


@njit(cache=True)
def _inv4_general(a, out, w):
    """out = a^-1 by Gauss-Jordan with partial pivoting (fallback for a matrix that is not
    numerically positive definite; LAPACK's inv would also invert it); inf/NaN if singular."""
    for i in range(4):
        for j in range(4):
            w[i, j] = a[i, j]
            out[i, j] = 1.0 if i == j else 0.0
    for c in range(4):
        p = c
        for i in range(c + 1, 4):
            if abs(w[i, c]) > abs(w[p, c]):
                p = i
        if p != c:
            for j in range(4):
                w[c, j], w[p, j] = w[p, j], w[c, j]
                out[c, j], out[p, j] = out[p, j], out[c, j]
        d = w[c, c]
        for j in range(4):
            w[c, j] /= d
            out[c, j] /= d
        for i in range(4):
            if i != c:
                f = w[i, c]
                for j in range(4):
                    w[i, j] -= f * w[c, j]
                    out[i, j] -= f * out[c, j]
    for i in range(4):
        for j in range(i + 1, 4):
            v = 0.5 * (out[i, j] + out[j, i])
            out[i, j] = v
            out[j, i] = v


@njit(cache=True)
def _inv4_spd(a, out, l, li):
    """out = a^-1 (exactly symmetric) for a symmetric positive definite 4x4 ``a``; NaN if not PD."""
    if not _chol4(a, l):
        _inv4_general(a, out, l)
        return
    # li = L^-1 (lower triangular)
    for j in range(4):
        li[j, j] = 1.0 / l[j, j]
        for i in range(j + 1, 4):
            acc = 0.0
            for k in range(j, i):
                acc -= l[i, k] * li[k, j]
            li[i, j] = acc / l[i, i]
        for i in range(j):
            li[i, j] = 0.0
    # a^-1 = L^-T L^-1
    for i in range(4):
        for j in range(i, 4):
            acc = 0.0
            for k in range(j, 4):
                acc += li[k, i] * li[k, j]
            out[i, j] = acc
            out[j, i] = acc


@njit(cache=True)
def _relative_message_row(lam, eta, offset, sign, r_inv, out_lam, out_eta, s, s_inv, t, l, li):
    """Eqs. (19)/(21) for one row: y = x + sign*offset + n, x ~ (lam, eta), n ~ N(0, R).

    S = Lambda + R^-1, Lambda_y = sym(Lambda S^-1 R^-1), eta_y = R^-1 S^-1 eta + Lambda_y sign*offset
    (:func:`coloc.inference.gaussian.relative_message`)."""
    for i in range(4):
        for j in range(4):
            s[i, j] = lam[i, j] + r_inv[i, j]
    _inv4_spd(s, s_inv, l, li)
    # t = Lambda S^-1
    for i in range(4):
        for j in range(4):
            acc = 0.0
            for k in range(4):
                acc += lam[i, k] * s_inv[k, j]
            t[i, j] = acc
    # s = t R^-1 (reuse), then symmetrise into out_lam
    for i in range(4):
        for j in range(4):
            acc = 0.0
            for k in range(4):
                acc += t[i, k] * r_inv[k, j]
            s[i, j] = acc
    for i in range(4):
        for j in range(4):
            out_lam[i, j] = 0.5 * (s[i, j] + s[j, i])
    # t = R^-1 S^-1
    for i in range(4):
        for j in range(4):
            acc = 0.0
            for k in range(4):
                acc += r_inv[i, k] * s_inv[k, j]
            t[i, j] = acc
    for i in range(4):
        a = 0.0
        for k in range(4):
            a += t[i, k] * eta[k]
        b = 0.0
        for k in range(4):
            b += out_lam[i, k] * (sign * offset[k])
        out_eta[i] = a + b


@njit(cache=True)
def relative_message_kernel(lam, eta, offset, sign, r_inv):
    """Batched :func:`_relative_message_row` (O rows), the numba twin of ``relative_message``."""
    o = lam.shape[0]
    out_lam = np.empty((o, 4, 4))
    out_eta = np.empty((o, 4))
    s, s_inv, t, l, li = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
    for r in range(o):
        _relative_message_row(lam[r], eta[r], offset[r], sign, r_inv[r], out_lam[r], out_eta[r], s, s_inv, t, l, li)
    return out_lam, out_eta


@njit(cache=True)
def vehicle_to_feature_kernel(owner, own_lam0, own_eta0, in_lam, in_eta, m_fv_lam, m_fv_eta, z, r_inv):
    """Eq. (19) for every row: cavity (own belief x messages of the vehicle's other features)
    = own0[i] + in[i] - m_{k->i}, integrated over x_V with offset +z.

    Returns the messages (O, 4, 4), (O, 4) and the consensus input (O, 14): the upper
    triangle of each (exactly symmetric) Lambda, then eta (``coloc.inference.bpa._pack_sym`` layout)."""
    o = owner.size
    out_lam = np.empty((o, 4, 4))
    out_eta = np.empty((o, 4))
    packed = np.empty((o, 14))
    cav_l = np.empty((4, 4))
    cav_e = np.empty(4)
    s, s_inv, t, l, li = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
    for r in range(o):
        i = owner[r]
        for a in range(4):
            for b in range(4):
                cav_l[a, b] = own_lam0[i, a, b] + in_lam[i, a, b] - m_fv_lam[r, a, b]
            cav_e[a] = own_eta0[i, a] + in_eta[i, a] - m_fv_eta[r, a]
        _relative_message_row(cav_l, cav_e, z[r], 1.0, r_inv[r], out_lam[r], out_eta[r], s, s_inv, t, l, li)
        c = 0
        for a in range(4):
            for b in range(a, 4):
                packed[r, c] = out_lam[r, a, b]
                c += 1
        for a in range(4):
            packed[r, 10 + a] = out_eta[r, a]
    return out_lam, out_eta, packed


@njit(cache=True)
def extrinsic_kernel(avg, count, lam_f0_row, eta_f0_row, m_vf_lam, m_vf_eta):
    """Eq. (21), first half: vehicle i's copy of b_k = b_k^(0) + |V_k ∩ C| * (consensus average)
    divided by its own message: (loc - m_{i->k}). ``avg`` in the (O, 14) packed layout."""
    o = avg.shape[0]
    ext_lam = np.empty((o, 4, 4))
    ext_eta = np.empty((o, 4))
    for r in range(o):
        c = 0
        for a in range(4):
            for b in range(a, 4):
                v = avg[r, c]
                ext_lam[r, a, b] = (lam_f0_row[r, a, b] + count[r] * v) - m_vf_lam[r, a, b]
                if b != a:
                    ext_lam[r, b, a] = (lam_f0_row[r, b, a] + count[r] * v) - m_vf_lam[r, b, a]
                c += 1
        for a in range(4):
            ext_eta[r, a] = (eta_f0_row[r, a] + count[r] * avg[r, 10 + a]) - m_vf_eta[r, a]
    return ext_lam, ext_eta


@njit(cache=True)
def feature_to_vehicle_kernel(owner, ext_lam, ext_eta, z, r_inv, v_lam0, v_eta0, prev_mean):
    """Eq. (21), second half (integrate over x_F, offset -z), and eq. (22): the vehicle beliefs
    b_i = b_i^(0) prod_k m_{k->i} (information sums in row order) and their means.

    Returns (m_fv_lam, m_fv_eta, in_lam, in_eta, v_lam, v_eta, new_mean, max |dpos|, max |dvel|)."""
    o = owner.size
    n = v_lam0.shape[0]
    m_lam = np.empty((o, 4, 4))
    m_eta = np.empty((o, 4))
    s, s_inv, t, l, li = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
    for r in range(o):
        _relative_message_row(ext_lam[r], ext_eta[r], z[r], -1.0, r_inv[r], m_lam[r], m_eta[r], s, s_inv, t, l, li)
    in_lam, in_eta, v_lam, v_eta, new_mean, dpos, dvel = vehicle_beliefs_kernel(owner, m_lam, m_eta, v_lam0, v_eta0,
                                                                                prev_mean)
    return m_lam, m_eta, in_lam, in_eta, v_lam, v_eta, new_mean, dpos, dvel


@njit(cache=True, inline="always")
def weighted_row_sum(indptr, indices, data, src, i, dst):
    """dst[i] = sum_p data[p] src[indices[p]] over row i of a CSR matrix (one consensus round of row i,
    x_i <- sum_j W_ij x_j), zero weights skipped, in the row's stored order: every consensus kernel sums
    this way, so that they agree to the last bit."""
    d = src.shape[1]
    for c in range(d):
        dst[i, c] = 0.0
    for p in range(indptr[i], indptr[i + 1]):
        w = data[p]
        if w != 0.0:
            j = indices[p]
            for c in range(d):
                dst[i, c] += w * src[j, c]


@njit(cache=True)
def complete_component_consensus(indptr, indices, data, x, iterations, complete):
    """``iterations`` rounds of x <- W x (Metropolis weights, CSR with the diagonal), where every
    row whose component is a complete graph (degree = |component| - 1) stops after one round.

    On a complete component of m rows the Metropolis matrix is W = J/m (off-diagonal
    1/(1 + (m-1)) = 1/m, diagonal 1 - (m-1)/m = 1/m): a projection, so the first round gives
    the exact average and further rounds leave it unchanged (up to rounding). With Rc >= 2 Rs
    (arterial: 250 m and 50 m) two vehicles sensing one feature are always V2V neighbours, so
    every component is complete. ``complete`` (O,) flags the rows of complete components
    (:func:`coloc.inference.row_consensus.row_consensus_weights`). Rows of other components run all rounds exactly as
    :func:`coloc.inference.consensus._average_kernel` (same operation order)."""
    o, d = x.shape
    out = np.empty_like(x)
    if iterations == 0:
        out[:] = x
        return out
    # round 1 for every row
    slow = np.empty(o, dtype=np.int64)
    n_slow = 0
    for i in range(o):
        weighted_row_sum(indptr, indices, data, x, i, out)
        if not complete[i]:
            slow[n_slow] = i
            n_slow += 1
    if n_slow == 0 or iterations == 1:
        return out
    # rows of incomplete components: rounds 2..iterations (their neighbours are in the same component)
    cur = out.copy()
    nxt = out.copy()
    for _ in range(iterations - 1):
        for a in range(n_slow):
            weighted_row_sum(indptr, indices, data, cur, slow[a], nxt)
        cur, nxt = nxt, cur
    for a in range(n_slow):
        i = slow[a]
        for c in range(d):
            out[i, c] = cur[i, c]
    return out


@njit(cache=True)
def information_kernel(mean, cov):
    """(mean (K, 4), cov (K, 4, 4)) -> (Lambda = P^-1, eta = P^-1 m), P symmetric positive definite."""
    k = mean.shape[0]
    lam = np.empty((k, 4, 4))
    eta = np.empty((k, 4))
    l, li = np.empty((4, 4)), np.empty((4, 4))
    for r in range(k):
        _inv4_spd(cov[r], lam[r], l, li)
        for a in range(4):
            acc = 0.0
            for b in range(4):
                acc += lam[r, a, b] * mean[r, b]
            eta[r, a] = acc
    return lam, eta


@njit(cache=True)
def inverse_spd_kernel(m):
    """Batched inverse (K, 4, 4) of symmetric positive definite matrices (exactly symmetric output)."""
    k = m.shape[0]
    out = np.empty((k, 4, 4))
    l, li = np.empty((4, 4)), np.empty((4, 4))
    for r in range(k):
        _inv4_spd(m[r], out[r], l, li)
    return out


@njit(cache=True)
def _scatter_add_kernel(target, rows, values):
    for k in range(rows.size):
        t = rows[k]
        for c in range(target.shape[1]):
            target[t, c] = target[t, c] + values[k, c]


def scatter_add(target: np.ndarray, rows: np.ndarray, values: np.ndarray) -> None:
    """``np.add.at(target, rows, values)`` for a C-contiguous float64 ``target`` (K, ...): rows
    added one after the other in index order, as ufunc.at does (same numbers), without its
    per-element overhead."""
    _scatter(_scatter_add_kernel, np.add, target, rows, values)


@njit(cache=True)
def _scatter_max_kernel(target, rows, values):
    for k in range(rows.size):
        t = rows[k]
        for c in range(target.shape[1]):
            v = values[k, c]
            if v > target[t, c] or v != v:  # np.maximum: NaN wins
                target[t, c] = v


def scatter_max(target: np.ndarray, rows: np.ndarray, values: np.ndarray) -> None:
    """``np.maximum.at(target, rows, values)`` for a C-contiguous float64 ``target`` (K, ...)
    (the same numbers: a maximum is exact), without ufunc.at's per-element overhead."""
    _scatter(_scatter_max_kernel, np.maximum, target, rows, values)


def _scatter(kernel, ufunc, target: np.ndarray, rows: np.ndarray, values: np.ndarray) -> None:
    """``ufunc.at(target, rows, values)`` by the numba ``kernel`` on (K, -1) views; other targets
    by ufunc.at itself."""
    k = target.shape[0]
    if not (target.flags.c_contiguous and target.dtype == np.float64):
        ufunc.at(target, rows, values)
        return
    flat = target.reshape(k, -1)
    vals = np.ascontiguousarray(np.broadcast_to(values, (len(rows),) + target.shape[1:]), dtype=np.float64)
    kernel(flat, np.asarray(rows, dtype=np.int64), vals.reshape(len(rows), -1))


@njit(cache=True)
def log_gauss_kernel(nu, s):
    """log N(nu; 0, S) and the squared Mahalanobis distance per row, S (P, d, d) symmetric positive
    definite, by an explicit Cholesky factor and forward substitution (the numpy reference is
    ``coloc.inference.gaussian.log_gauss_numpy``). A non-PD S gives NaN, as LAPACK's Cholesky would fail."""
    p, d = nu.shape
    log_pdf = np.empty(p)
    d2 = np.empty(p)
    l = np.empty((d, d))
    w = np.empty(d)
    log2pi = np.log(2.0 * np.pi)
    for r in range(p):
        ok = True
        for j in range(d):
            acc = s[r, j, j]
            for k in range(j):
                acc -= l[j, k] * l[j, k]
            if not acc > 0.0:
                ok = False
                break
            l[j, j] = np.sqrt(acc)
            for i in range(j + 1, d):
                a = s[r, i, j]
                for k in range(j):
                    a -= l[i, k] * l[j, k]
                l[i, j] = a / l[j, j]
        if not ok:
            log_pdf[r] = np.nan
            d2[r] = np.nan
            continue
        q = 0.0
        logdet = 0.0
        for i in range(d):
            a = nu[r, i]
            for k in range(i):
                a -= l[i, k] * w[k]
            w[i] = a / l[i, i]
            q += w[i] * w[i]
            logdet += np.log(l[i, i])
        d2[r] = q
        log_pdf[r] = -0.5 * (q + 2.0 * logdet + d * log2pi)
    return log_pdf, d2


@njit(cache=True)
def predict_no_input_kernel(mean, cov, q, dt):
    """Model (2) prediction (no input) per row: m = A m, P = sym(A P A^T + Q), A = [[I, dt I], [0, I]]
    (numpy reference: ``coloc.core.models.predict`` with zero input)."""
    k = mean.shape[0]
    m_out = np.empty((k, 4))
    p_out = np.empty((k, 4, 4))
    t = np.empty((4, 4))
    u = np.empty((4, 4))
    for r in range(k):
        m_out[r, 0] = mean[r, 0] + dt * mean[r, 2]
        m_out[r, 1] = mean[r, 1] + dt * mean[r, 3]
        m_out[r, 2] = mean[r, 2]
        m_out[r, 3] = mean[r, 3]
        # t = A P
        for b in range(4):
            t[0, b] = cov[r, 0, b] + dt * cov[r, 2, b]
            t[1, b] = cov[r, 1, b] + dt * cov[r, 3, b]
            t[2, b] = cov[r, 2, b]
            t[3, b] = cov[r, 3, b]
        # u = t A^T + Q
        for a in range(4):
            u[a, 0] = t[a, 0] + dt * t[a, 2] + q[r, a, 0]
            u[a, 1] = t[a, 1] + dt * t[a, 3] + q[r, a, 1]
            u[a, 2] = t[a, 2] + q[r, a, 2]
            u[a, 3] = t[a, 3] + q[r, a, 3]
        for a in range(4):
            for b in range(4):
                p_out[r, a, b] = 0.5 * (u[a, b] + u[b, a])
    return m_out, p_out


@njit(cache=True)
def surely_above_floor(lam, floor):
    """Per (4, 4) matrix: True when symmetrize(lam) - (floor + margin) I has a Cholesky
    factor with positive pivots, margin = 1e-8 * (largest |diagonal entry|). Cholesky is
    backward stable (error ~1e-15 of the entries), so such a matrix has every eigenvalue
    above ``floor`` by far more than a LAPACK eigensolver's rounding: it is never clipped.
    False means only "not proven" (singular or indefinite matrices, NaN)."""
    n = lam.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    a = np.empty((4, 4))
    l = np.empty((4, 4))
    for m in range(n):
        scale = 0.0
        for i in range(4):
            d = abs(lam[m, i, i])
            if d > scale:
                scale = d
        shift = floor + 1e-8 * scale
        for i in range(4):
            for j in range(4):
                a[i, j] = 0.5 * (lam[m, i, j] + lam[m, j, i])
            a[i, i] -= shift
        out[m] = scale > 0.0 and _chol4(a, l)  # a pivot that is not > 0 (or NaN): not proven
    return out


@njit(cache=True)
def rows_by_key(keys, n_keys):
    """Rows grouped by key, ascending within a key (a counting sort, i.e. a stable argsort of
    ``keys`` in [0, n_keys)). Returns (start (n_keys + 1,), rows): the rows of key g are
    ``rows[start[g]:start[g + 1]]``."""
    start = np.zeros(n_keys + 1, dtype=np.int64)
    for q in range(keys.size):
        start[keys[q] + 1] += 1
    for g in range(n_keys):
        start[g + 1] += start[g]
    rows = np.empty(keys.size, dtype=np.int64)
    fill = start[:n_keys].copy()
    for q in range(keys.size):
        rows[fill[keys[q]]] = q
        fill[keys[q]] += 1
    return start, rows


@njit(cache=True)
def largest_shift(new_mean, prev_mean):
    """The largest position and velocity change of any vehicle, (dpos, dvel), for the stopping rule of
    Sec. V-A; a NaN change gives inf ("not converged", as numpy's max of NaN would)."""
    dpos, dvel = 0.0, 0.0
    for i in range(new_mean.shape[0]):
        dp = np.hypot(new_mean[i, 0] - prev_mean[i, 0], new_mean[i, 1] - prev_mean[i, 1])
        dv = np.hypot(new_mean[i, 2] - prev_mean[i, 2], new_mean[i, 3] - prev_mean[i, 3])
        if dp > dpos or dp != dp:
            dpos = dp if dp == dp else np.inf
        if dv > dvel or dv != dv:
            dvel = dv if dv == dv else np.inf
    return dpos, dvel


@njit(cache=True)
def vehicle_beliefs_kernel(owner, m_lam, m_eta, v_lam0, v_eta0, prev_mean):
    """Eq. (22): b_i = b_i^(0) prod_k m_{k->i} (information sums in row order), the symmetrised
    Lambda, the means, and the largest position / velocity change from ``prev_mean`` (NaN
    propagates as "not converged", as numpy's max would). Returns (in_lam, in_eta, v_lam, v_eta,
    new_mean, dpos, dvel)."""
    o = owner.size
    n = v_lam0.shape[0]
    in_lam = np.zeros((n, 4, 4))
    in_eta = np.zeros((n, 4))
    for r in range(o):
        i = owner[r]
        for a in range(4):
            for b in range(4):
                in_lam[i, a, b] += m_lam[r, a, b]
            in_eta[i, a] += m_eta[r, a]
    v_lam = np.empty((n, 4, 4))
    v_eta = np.empty((n, 4))
    new_mean = np.empty((n, 4))
    s, cov, l, li = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
    for i in range(n):
        for a in range(4):
            for b in range(4):
                s[a, b] = v_lam0[i, a, b] + in_lam[i, a, b]
        for a in range(4):
            for b in range(4):
                v_lam[i, a, b] = 0.5 * (s[a, b] + s[b, a])
            v_eta[i, a] = v_eta0[i, a] + in_eta[i, a]
        _inv4_spd(v_lam[i], cov, l, li)
        for a in range(4):
            acc = 0.0
            for b in range(4):
                acc += cov[a, b] * v_eta[i, b]
            new_mean[i, a] = acc
    dpos, dvel = largest_shift(new_mean, prev_mean)
    return in_lam, in_eta, v_lam, v_eta, new_mean, dpos, dvel
