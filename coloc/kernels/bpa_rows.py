"""The BPA-L message kernels of :mod:`coloc.kernels.icp` computed across rows (structure of arrays).

:mod:`coloc.kernels.icp` runs eqs. (19), (21), (22) row by row, each row a chain of 4x4 operations
that the compiler cannot vectorise. Here every 4x4 entry is a contiguous array over the rows, and
each scalar operation of the row-by-row code becomes one loop over all rows: the same IEEE
operations in the same order for every row (no reassociation, no fused multiply-add), so the
results are **byte for byte** those of the row kernels, and the loops run on SIMD lanes
(~4x on 400 rows, docs/performance.md). Tests compare the two.

Equation -> function (Brambilla et al.):

* the integral of a Gaussian belief against the V2F likelihood (4), y = x + sign z + n, in
  information form (the inner step of (19) and (21)): :func:`_relative_message_soa`
  (row twin :func:`coloc.kernels.icp._relative_message_row`);
* (19) cavity and vehicle -> feature messages with the consensus input: :func:`vehicle_to_feature_rows`
  (twin :func:`coloc.kernels.icp.vehicle_to_feature_kernel`);
* (19), (20) and the first half of (21) in one call: :func:`bpa_forward_rows` (the twins above,
  :func:`coloc.kernels.icp.complete_component_consensus`, :func:`coloc.kernels.icp.extrinsic_kernel`
  and the PSD pre-check :func:`coloc.kernels.icp.surely_above_floor`, one after the other);
* (21) second half and (22): :func:`feature_to_vehicle_rows` (twin
  :func:`coloc.kernels.icp.feature_to_vehicle_kernel`);
* (mean, cov) <-> (Lambda, eta): :func:`information_rows` (twin :func:`coloc.kernels.icp.information_kernel`),
  and the SPD inverse :func:`inverse_rows` (twin :func:`coloc.kernels.icp.inverse_spd_kernel`);
* (12), model (2) without input: :func:`predict_no_input_rows` (twin :func:`coloc.kernels.icp.predict_no_input_kernel`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from coloc.kernels.icp import (
    _inv4_general,
    complete_component_consensus,
    extrinsic_kernel,
    largest_shift,
    surely_above_floor,
    vehicle_beliefs_kernel,
)


@njit(cache=True)
def cholesky4_soa(s, l, ok, acc):
    """Lower Cholesky factor of every column of ``s`` (16, o) (entries a*4+b, the lower triangle
    read) into ``l``, the operations of :func:`coloc.kernels.icp._chol4` in its order; ``ok``
    cleared where a pivot is not > 0 (or NaN): such a column's factor is meaningless."""
    o = s.shape[1]
    for j in range(4):
        sjj = s[j * 4 + j]
        for r in range(o):
            acc[r] = sjj[r]
        for k in range(j):
            ljk = l[j * 4 + k]
            for r in range(o):
                acc[r] -= ljk[r] * ljk[r]
        ljj = l[j * 4 + j]
        for r in range(o):
            if not acc[r] > 0.0:
                ok[r] = False
                acc[r] = 1.0  # any value
            ljj[r] = np.sqrt(acc[r])
        for i in range(j + 1, 4):
            sij = s[i * 4 + j]
            for r in range(o):
                acc[r] = sij[r]
            for k in range(j):
                lik, ljk = l[i * 4 + k], l[j * 4 + k]
                for r in range(o):
                    acc[r] -= lik[r] * ljk[r]
            lij = l[i * 4 + j]
            for r in range(o):
                lij[r] = acc[r] / ljj[r]


@njit(cache=True)
def _inv4_spd_soa(s, si, acc):
    """si = s^-1 for every row (columns of the (16, o) arrays, entry a*4+b), the operations of
    :func:`coloc.kernels.icp._inv4_spd` in its order: Cholesky, L^-1, L^-T L^-1; rows that are
    not numerically positive definite by :func:`coloc.kernels.icp._inv4_general`."""
    o = s.shape[1]
    _inv4_spd_soa_ws(s, si, acc, np.empty((16, o)), np.empty((16, o)), np.empty(o, dtype=np.bool_))


@njit(cache=True)
def _inv4_spd_soa_ws(s, si, acc, c, li, ok):
    """:func:`_inv4_spd_soa` with the workspace given: ``c``, ``li`` (16, o) (only their lower
    triangles are written and read), ``ok`` (o,) bool (reset here)."""
    o = s.shape[1]
    ok[:] = True
    cholesky4_soa(s, c, ok, acc)
    for j in range(4):
        cjj, lijj = c[j * 4 + j], li[j * 4 + j]
        for r in range(o):
            lijj[r] = 1.0 / cjj[r]
        for i in range(j + 1, 4):
            for r in range(o):
                acc[r] = 0.0
            for k in range(j, i):
                cik, likj = c[i * 4 + k], li[k * 4 + j]
                for r in range(o):
                    acc[r] -= cik[r] * likj[r]
            cii, liij = c[i * 4 + i], li[i * 4 + j]
            for r in range(o):
                liij[r] = acc[r] / cii[r]
    for i in range(4):
        for j in range(i, 4):
            for r in range(o):
                acc[r] = 0.0
            for k in range(j, 4):
                a, b = li[k * 4 + i], li[k * 4 + j]
                for r in range(o):
                    acc[r] += a[r] * b[r]
            x, y = si[i * 4 + j], si[j * 4 + i]
            for r in range(o):
                x[r] = acc[r]
                y[r] = acc[r]
    if not ok.all():
        m, out, w = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
        for r in range(o):
            if ok[r]:
                continue
            for a in range(4):
                for b in range(4):
                    m[a, b] = s[a * 4 + b, r]
            _inv4_general(m, out, w)
            for a in range(4):
                for b in range(4):
                    si[a * 4 + b, r] = out[a, b]


@njit(cache=True)
def _matmul_soa(x, y, out, acc):
    """out = x @ y for every row (acc = 0, then += x[i,k] y[k,j] for k = 0..3)."""
    o = x.shape[1]
    for i in range(4):
        for j in range(4):
            for r in range(o):
                acc[r] = 0.0
            for k in range(4):
                a, b = x[i * 4 + k], y[k * 4 + j]
                for r in range(o):
                    acc[r] += a[r] * b[r]
            dst = out[i * 4 + j]
            for r in range(o):
                dst[r] = acc[r]


@njit(cache=True)
def _relative_message_soa(lam, eta, offset, sign, r_inv, out_lam, out_eta):
    """:func:`coloc.kernels.icp._relative_message_row` for every row: S = Lambda + R^-1,
    Lambda_y = sym(Lambda S^-1 R^-1), eta_y = R^-1 S^-1 eta + Lambda_y sign*offset.
    ``lam``/``r_inv``/``out_lam`` (16, o), ``eta``/``offset``/``out_eta`` (4, o)."""
    o = lam.shape[1]
    ws = np.empty((5, 16, o))
    _relative_message_soa_ws(lam, eta, offset, sign, r_inv, out_lam, out_eta, ws, np.empty((2, o)),
                             np.empty(o, dtype=np.bool_))


@njit(cache=True)
def _relative_message_soa_ws(lam, eta, offset, sign, r_inv, out_lam, out_eta, ws, ws1, ok):
    """:func:`_relative_message_soa` with the workspace given: ``ws`` (5, 16, o), ``ws1`` (2, o),
    ``ok`` (o,) bool."""
    o = lam.shape[1]
    acc, d = ws1[0], ws1[1]
    s, s_inv, t = ws[0], ws[1], ws[2]
    for c in range(16):
        sc, lc, rc = s[c], lam[c], r_inv[c]
        for r in range(o):
            sc[r] = lc[r] + rc[r]
    _inv4_spd_soa_ws(s, s_inv, acc, ws[3], ws[4], ok)
    _matmul_soa(lam, s_inv, t, acc)
    _matmul_soa(t, r_inv, s, acc)  # s = Lambda S^-1 R^-1 (s reused)
    for i in range(4):
        for j in range(4):
            a, b, dst = s[i * 4 + j], s[j * 4 + i], out_lam[i * 4 + j]
            for r in range(o):
                dst[r] = 0.5 * (a[r] + b[r])
    _matmul_soa(r_inv, s_inv, t, acc)  # t = R^-1 S^-1
    for i in range(4):
        for r in range(o):
            acc[r] = 0.0
        for k in range(4):
            a, b = t[i * 4 + k], eta[k]
            for r in range(o):
                acc[r] += a[r] * b[r]
        for r in range(o):
            d[r] = 0.0
        for k in range(4):
            a, b = out_lam[i * 4 + k], offset[k]
            for r in range(o):
                d[r] += a[r] * (sign * b[r])
        dst = out_eta[i]
        for r in range(o):
            dst[r] = acc[r] + d[r]


@njit(cache=True)
def _soa4(x):
    """(o, m) -> (m, o): one contiguous array per entry."""
    o, m = x.shape
    out = np.empty((m, o))
    for r in range(o):
        for a in range(m):
            out[a, r] = x[r, a]
    return out


@njit(cache=True)
def _aos16(x):
    """(16, o) -> (o, 4, 4), the inverse of :func:`_soa16`."""
    return np.ascontiguousarray(x.T).reshape((x.shape[1], 4, 4))


@njit(cache=True)
def _soa16(x):
    """(o, 4, 4) -> (16, o), entry a*4+b."""
    return _soa4(np.ascontiguousarray(x).reshape((x.shape[0], 16)))


@njit(cache=True)
def vehicle_to_feature_rows(owner, own_lam0, own_eta0, in_lam, in_eta, m_fv_lam, m_fv_eta, z, r_inv):
    """:func:`coloc.kernels.icp.vehicle_to_feature_kernel` (eq. (19)), same outputs byte for byte."""
    o = owner.size
    cav_l = np.empty((16, o))
    cav_e = np.empty((4, o))
    for r in range(o):
        i = owner[r]
        for a in range(4):
            for b in range(4):
                cav_l[a * 4 + b, r] = own_lam0[i, a, b] + in_lam[i, a, b] - m_fv_lam[r, a, b]
            cav_e[a, r] = own_eta0[i, a] + in_eta[i, a] - m_fv_eta[r, a]
    ol = np.empty((16, o))
    oe = np.empty((4, o))
    _relative_message_soa(cav_l, cav_e, _soa4(z), 1.0, _soa16(r_inv), ol, oe)
    out_lam = np.empty((o, 4, 4))
    out_eta = np.empty((o, 4))
    packed = np.empty((o, 14))
    for r in range(o):
        c = 0
        for a in range(4):
            for b in range(4):
                out_lam[r, a, b] = ol[a * 4 + b, r]
                if b >= a:
                    packed[r, c] = ol[a * 4 + b, r]
                    c += 1
            out_eta[r, a] = oe[a, r]
            packed[r, 10 + a] = oe[a, r]
    return out_lam, out_eta, packed


@njit(cache=True)
def feature_to_vehicle_rows(owner, ext_lam, ext_eta, z, r_inv, v_lam0, v_eta0, prev_mean):
    """:func:`coloc.kernels.icp.feature_to_vehicle_kernel` (eqs. (21), (22)), same outputs byte for byte."""
    o = owner.size
    n = v_lam0.shape[0]
    ol = np.empty((16, o))
    oe = np.empty((4, o))
    _relative_message_soa(_soa16(ext_lam), _soa4(ext_eta), _soa4(z), -1.0, _soa16(r_inv), ol, oe)
    m_lam, m_eta = _aos16(ol), np.ascontiguousarray(oe.T)
    # (22), as the row kernel (the same function)
    in_lam, in_eta, v_lam, v_eta, new_mean, dpos, dvel = vehicle_beliefs_kernel(owner, m_lam, m_eta, v_lam0, v_eta0,
                                                                                prev_mean)
    return m_lam, m_eta, in_lam, in_eta, v_lam, v_eta, new_mean, dpos, dvel


@njit(cache=True)
def information_rows(mean, cov):
    """:func:`coloc.kernels.icp.information_kernel` ((mean, cov) -> (P^-1, P^-1 m)), byte for byte."""
    k = mean.shape[0]
    si = np.empty((16, k))
    acc = np.empty(k)
    _inv4_spd_soa(_soa16(cov), si, acc)
    lam = _aos16(si)
    eta = np.empty((k, 4))
    for a in range(4):
        for r in range(k):
            acc[r] = 0.0
        for b in range(4):
            x = si[a * 4 + b]
            for r in range(k):
                acc[r] += x[r] * mean[r, b]
        for r in range(k):
            eta[r, a] = acc[r]
    return lam, eta


@njit(cache=True)
def inverse_rows(m):
    """:func:`coloc.kernels.icp.inverse_spd_kernel` (batched SPD 4x4 inverse), byte for byte."""
    k = m.shape[0]
    si = np.empty((16, k))
    _inv4_spd_soa(_soa16(m), si, np.empty(k))
    return _aos16(si)


@njit(cache=True)
def bpa_forward_rows(owner, own_lam0, own_eta0, in_lam, in_eta, m_fv_lam, m_fv_eta, z, r_inv, w_indptr, w_indices,
                     w_data, n_iter_cons, complete, count, lam_f0_row, eta_f0_row):
    """One BPA-L iteration up to the PSD projection, in one call: (19) (:func:`vehicle_to_feature_rows`),
    (20) by consensus on complete components, the extrinsic information of (21) and which rows are
    surely positive definite (:func:`coloc.kernels.icp.surely_above_floor`, floor 0). Returns
    (m_vf_lam, m_vf_eta, avg, ext_lam, ext_eta, sure)."""
    m_vf_lam, m_vf_eta, packed = vehicle_to_feature_rows(owner, own_lam0, own_eta0, in_lam, in_eta, m_fv_lam,
                                                         m_fv_eta, z, r_inv)
    avg = complete_component_consensus(w_indptr, w_indices, w_data, packed, n_iter_cons, complete)
    ext_lam, ext_eta = extrinsic_kernel(avg, count, lam_f0_row, eta_f0_row, m_vf_lam, m_vf_eta)
    return m_vf_lam, m_vf_eta, avg, ext_lam, ext_eta, surely_above_floor(ext_lam, 0.0)


@njit(cache=True)
def predict_no_input_rows(mean, cov, q, dt):
    """:func:`coloc.kernels.icp.predict_no_input_kernel` (model (2): m = A m, P = sym(A P A^T + Q)),
    byte for byte, each scalar step one loop over the rows."""
    k = mean.shape[0]
    m_out = np.empty((k, 4))
    p_out = np.empty((k, 4, 4))
    for r in range(k):
        m_out[r, 0] = mean[r, 0] + dt * mean[r, 2]
        m_out[r, 1] = mean[r, 1] + dt * mean[r, 3]
        m_out[r, 2] = mean[r, 2]
        m_out[r, 3] = mean[r, 3]
    p = _soa16(cov)
    qq = _soa16(q)
    t = np.empty((16, k))
    for b in range(4):  # t = A P
        t0, t1, t2, t3 = t[b], t[4 + b], t[8 + b], t[12 + b]
        p0, p1, p2, p3 = p[b], p[4 + b], p[8 + b], p[12 + b]
        for r in range(k):
            t0[r] = p0[r] + dt * p2[r]
            t1[r] = p1[r] + dt * p3[r]
            t2[r] = p2[r]
            t3[r] = p3[r]
    u = np.empty((16, k))
    for a in range(4):  # u = t A^T + Q
        ta0, ta1, ta2, ta3 = t[a * 4], t[a * 4 + 1], t[a * 4 + 2], t[a * 4 + 3]
        u0, u1, u2, u3 = u[a * 4], u[a * 4 + 1], u[a * 4 + 2], u[a * 4 + 3]
        q0, q1, q2, q3 = qq[a * 4], qq[a * 4 + 1], qq[a * 4 + 2], qq[a * 4 + 3]
        for r in range(k):
            u0[r] = ta0[r] + dt * ta2[r] + q0[r]
            u1[r] = ta1[r] + dt * ta3[r] + q1[r]
            u2[r] = ta2[r] + q2[r]
            u3[r] = ta3[r] + q3[r]
    for r in range(k):
        for a in range(4):
            for b in range(4):
                p_out[r, a, b] = 0.5 * (u[a * 4 + b, r] + u[b * 4 + a, r])
    return m_out, p_out


#: :func:`bpa_loop_rows` status: the stopping rule held / ``it_last`` iterations ran / a row of
#: the extrinsic information may need the PSD projection (the caller projects and resumes).
LOOP_CONVERGED, LOOP_MAX_ITERATIONS, LOOP_NEEDS_CLIP = 0, 1, 2


@njit(cache=True)
def _sure_soa(lam, sure, a, l, ok, acc):
    """:func:`coloc.kernels.icp.surely_above_floor` with floor 0 for every column of ``lam`` (16, o):
    the same operations per column (scale, shift, symmetrised matrix minus the shift, Cholesky
    pivots), workspace ``a``, ``l`` (16, o), ``ok`` (o,) bool, ``acc`` (o,). Returns whether all are sure."""
    o = lam.shape[1]
    for r in range(o):
        scale = 0.0
        for i in range(4):
            d = abs(lam[i * 4 + i, r])
            if d > scale:
                scale = d
        acc[r] = 0.0 + 1e-8 * scale  # floor + 1e-8 * scale
        sure[r] = scale > 0.0
    for i in range(4):
        for j in range(i + 1):  # the lower triangle is read
            x, y, dst = lam[i * 4 + j], lam[j * 4 + i], a[i * 4 + j]
            for r in range(o):
                dst[r] = 0.5 * (x[r] + y[r])
        dst = a[i * 4 + i]
        for r in range(o):
            dst[r] -= acc[r]
    ok[:] = True
    cholesky4_soa(a, l, ok, acc)
    every = True
    for r in range(o):
        sure[r] = sure[r] and ok[r]
        if not sure[r]:
            every = False
    return every


@njit(cache=True)
def _known_unclipped(lam, r, safe):
    """True when the symmetrised matrix of column ``r`` of ``lam`` (16, o) is bit for bit one of the
    rows of ``safe`` (W, 16): matrices that numpy's eigh was seen to leave unclipped."""
    for w in range(safe.shape[0]):
        same = True
        for a in range(4):
            for b in range(4):
                v = 0.5 * (lam[a * 4 + b, r] + lam[b * 4 + a, r])
                if np.float64(v).view(np.int64) != np.float64(safe[w, a * 4 + b]).view(np.int64):
                    same = False
                    break
            if not same:
                break
        if same:
            return True
    return False


@njit(cache=True)
def _vehicle_beliefs_soa(owner, m_l, m_e, v_lam0, v_eta0, prev_mean, in_l, in_e, vl, ve, new_mean, ws, acc, okn):
    """:func:`coloc.kernels.icp.vehicle_beliefs_kernel` (eq. (22)) with the messages, the sums and the
    beliefs as (16, .) / (4, .) arrays (``m_l``, ``m_e`` over the rows; ``in_l`` .. ``ve`` over the
    vehicles, written here): the same operations in the same order per vehicle, the inverse by
    :func:`_inv4_spd_soa` (that of :func:`coloc.kernels.icp._inv4_spd`). ``ws`` (3, 16, n).
    Returns (dpos, dvel)."""
    o = owner.size
    n = v_lam0.shape[0]
    in_l[:] = 0.0
    in_e[:] = 0.0
    for r in range(o):
        i = owner[r]
        for c in range(16):
            in_l[c, i] += m_l[c, r]
        for a in range(4):
            in_e[a, i] += m_e[a, r]
    for i in range(n):
        for a in range(4):
            for b in range(4):
                s_ab = v_lam0[i, a, b] + in_l[a * 4 + b, i]
                s_ba = v_lam0[i, b, a] + in_l[b * 4 + a, i]
                vl[a * 4 + b, i] = 0.5 * (s_ab + s_ba)
            ve[a, i] = v_eta0[i, a] + in_e[a, i]
    cov = ws[0]
    _inv4_spd_soa_ws(vl, cov, acc, ws[1], ws[2], okn)
    for a in range(4):
        for i in range(n):
            acc[i] = 0.0
        for b in range(4):
            x, y = cov[a * 4 + b], ve[b]
            for i in range(n):
                acc[i] += x[i] * y[i]
        for i in range(n):
            new_mean[i, a] = acc[i]
    return largest_shift(new_mean, prev_mean)


@njit(cache=True)
def bpa_loop_rows(owner, own_lam0, own_eta0, v_lam0, v_eta0, z, r_inv, w_indptr, w_indices, w_data, n_iter_cons,
                  complete, count, lam_f0_row, eta_f0_row, in_lam, in_eta, m_fv_lam, m_fv_eta, mean, it_first, it_last,
                  stop_pos, stop_vel, safe):
    """BPA-L iterations ``it_first``..``it_last`` (19)-(22) in one call, each one exactly
    :func:`bpa_forward_rows`, the PSD projection of :func:`coloc.inference.gaussian.psd_clip`, then
    :func:`feature_to_vehicle_rows` and the stopping rule (the operations of those kernels in their
    order, on rows kept as structure of arrays between them). ``in_lam`` .. ``mean``: the state
    after iteration ``it_first`` - 1. The projection is known to leave a row unchanged when
    :func:`coloc.kernels.icp.surely_above_floor` proves it positive definite, or when its
    symmetrised matrix is bit for bit a row of ``safe`` (W, 16) (numpy's eigh, a deterministic
    function of the bits, found no eigenvalue below 0 there); otherwise the loop stops before the
    projection with status :data:`LOOP_NEEDS_CLIP` and the caller projects and finishes the iteration.

    Returns (status, it, m_vf_lam, m_vf_eta, v_lam, v_eta, in_lam, in_eta, m_fv_lam, m_fv_eta, mean, cov,
    ext_lam, ext_eta, sure): the messages (19) of the last iteration, the beliefs (22) (after
    iteration ``it``, ``mean`` and ``cov`` = ``v_lam``^-1 as ``from_information`` computes them; with
    :data:`LOOP_NEEDS_CLIP` those of ``it`` - 1 (``cov`` then meaningless) and ``ext_lam``, ``ext_eta``,
    ``sure`` of iteration ``it`` before the projection)."""
    o = owner.size
    n = v_lam0.shape[0]
    zs = _soa4(z)
    rs = _soa16(r_inv)
    ws = np.empty((5, 16, o))
    ws1 = np.empty((2, o))
    okw = np.empty(o, dtype=np.bool_)
    cav_l, cav_e = np.empty((16, o)), np.empty((4, o))
    vf_l, vf_e = np.empty((16, o)), np.empty((4, o))
    ext_l, ext_e = np.empty((16, o)), np.empty((4, o))
    fv_l = _soa16(m_fv_lam)
    fv_e = _soa4(m_fv_eta)
    packed = np.empty((o, 14))
    sure = np.empty(o, dtype=np.bool_)
    in_l, in_e = _soa16(in_lam), _soa4(in_eta)  # (22)'s sums and beliefs over the vehicles
    vl, ve = _soa16(v_lam0), _soa4(v_eta0)
    mean = np.ascontiguousarray(mean).copy()
    new_mean = np.empty((n, 4))
    wsn = np.empty((3, 16, n))
    accn = np.empty(n)
    okn = np.empty(n, dtype=np.bool_)
    status = LOOP_MAX_ITERATIONS
    it = it_first
    for it in range(it_first, it_last + 1):
        # (19): vehicle_to_feature_rows
        for r in range(o):
            i = owner[r]
            for a in range(4):
                for b in range(4):
                    cav_l[a * 4 + b, r] = own_lam0[i, a, b] + in_l[a * 4 + b, i] - fv_l[a * 4 + b, r]
                cav_e[a, r] = own_eta0[i, a] + in_e[a, i] - fv_e[a, r]
        _relative_message_soa_ws(cav_l, cav_e, zs, 1.0, rs, vf_l, vf_e, ws, ws1, okw)
        for r in range(o):
            c = 0
            for a in range(4):
                for b in range(a, 4):
                    packed[r, c] = vf_l[a * 4 + b, r]
                    c += 1
                packed[r, 10 + a] = vf_e[a, r]
        # (20), (21) first half: bpa_forward_rows
        avg = complete_component_consensus(w_indptr, w_indices, w_data, packed, n_iter_cons, complete)
        for r in range(o):
            c = 0
            for a in range(4):
                for b in range(a, 4):
                    v = avg[r, c]
                    ext_l[a * 4 + b, r] = (lam_f0_row[r, a, b] + count[r] * v) - vf_l[a * 4 + b, r]
                    if b != a:
                        ext_l[b * 4 + a, r] = (lam_f0_row[r, b, a] + count[r] * v) - vf_l[b * 4 + a, r]
                    c += 1
            for a in range(4):
                ext_e[a, r] = (eta_f0_row[r, a] + count[r] * avg[r, 10 + a]) - vf_e[a, r]
        if not _sure_soa(ext_l, sure, ws[0], ws[1], okw, ws1[0]):
            for r in range(o):
                if not sure[r] and not _known_unclipped(ext_l, r, safe):
                    status = LOOP_NEEDS_CLIP
                    break
            if status == LOOP_NEEDS_CLIP:
                break
        # (21) second half, (22): feature_to_vehicle_rows
        _relative_message_soa_ws(ext_l, ext_e, zs, -1.0, rs, fv_l, fv_e, ws, ws1, okw)
        dpos, dvel = _vehicle_beliefs_soa(owner, fv_l, fv_e, v_lam0, v_eta0, mean, in_l, in_e, vl, ve, new_mean, wsn,
                                          accn, okn)
        mean, new_mean = new_mean, mean
        if dpos < stop_pos and dvel < stop_vel:
            status = LOOP_CONVERGED
            break
    if status == LOOP_NEEDS_CLIP:
        ext_lam, ext_eta = _aos16(ext_l), np.ascontiguousarray(ext_e.T)
    else:
        ext_lam, ext_eta = np.empty((0, 4, 4)), np.empty((0, 4))
    return (status, it, _aos16(vf_l), np.ascontiguousarray(vf_e.T), _aos16(vl), np.ascontiguousarray(ve.T),
            _aos16(in_l), np.ascontiguousarray(in_e.T), _aos16(fv_l), np.ascontiguousarray(fv_e.T), mean,
            _aos16(wsn[0]), ext_lam, ext_eta, sure)
