"""numba kernel for the 6-state [px, py, vx, vy, bx, by] receiver filters of ``[fusion]``
(:mod:`coloc.methods.coop_fusion`): one loop over vehicles with 6x6 arithmetic in place of the batched
numpy of :func:`coloc.methods.coop_fusion._split_gnss_step` and
:func:`coloc.methods.gnss_bias.bias_predict_update`, which stay the references (tests: equal to 1e-12).
The ``gnss`` method keeps the numpy :func:`~coloc.methods.gnss_bias.bias_predict_update` (bit-identical
benchmark); only the fusion filters use this kernel.

Model: (1) prediction with the velocity-oriented driving noise and the Gauss-Markov bias
``b' = a b + w_b``, ``Var(w_b) = (1 - a^2) s R_pos``; fix (3) ``z_pos = p + b + n``, ``Var(n) = (1 - s) R_pos``,
``z_vel = v + n_v``; the 2-dof chi-square gate on the position innovation (velocity-only update when
excluded); Joseph-form covariance update (see the two numpy references for the sources).
With ``velocity_gate`` the robust velocity of :func:`coloc.methods.gnss_bias2.velocity_deweight`
(:func:`deweight_velocity`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from coloc.kernels.kalman import _driving_q


@njit(cache=True)
def _sandwich6(a, p, out, tmp):
    """out = A P A^T for 6x6 A, P."""
    for i in range(6):
        for j in range(6):
            acc = 0.0
            for k in range(6):
                acc += a[i, k] * p[k, j]
            tmp[i, j] = acc
    for i in range(6):
        for j in range(6):
            acc = 0.0
            for k in range(6):
                acc += tmp[i, k] * a[j, k]
            out[i, j] = acc


@njit(cache=True)
def _lu_solve(s, lo, b, out, a):
    """out[:k] = S[lo:, lo:]^-1 b[lo:] (k = 4 - lo, S (4, 4), b (4, 6)) by Gaussian elimination with partial
    pivoting (as LAPACK gesv, which numpy.linalg.solve calls: S need not be positive definite); ``a`` (4, 4)
    scratch."""
    k = 4 - lo
    nc = b.shape[1]
    for i in range(k):
        for j in range(k):
            a[i, j] = s[lo + i, lo + j]
        for c in range(nc):
            out[i, c] = b[lo + i, c]
    for col in range(k):
        piv = col
        big = abs(a[col, col])
        for i in range(col + 1, k):
            if abs(a[i, col]) > big:
                big = abs(a[i, col])
                piv = i
        if piv != col:
            for j in range(k):
                t = a[col, j]
                a[col, j] = a[piv, j]
                a[piv, j] = t
            for c in range(nc):
                t = out[col, c]
                out[col, c] = out[piv, c]
                out[piv, c] = t
        for i in range(col + 1, k):
            fct = a[i, col] / a[col, col]
            for j in range(col + 1, k):
                a[i, j] -= fct * a[col, j]
            for c in range(nc):
                out[i, c] -= fct * out[col, c]
    for c in range(nc):
        for i in range(k - 1, -1, -1):
            acc = out[i, c]
            for j in range(i + 1, k):
                acc -= a[i, j] * out[j, c]
            out[i, c] = acc / a[i, i]


@njit(cache=True)
def nis2(sm, innov, k):
    """nu^T S^-1 nu of the 2-D block k..k+1 of the innovation ``innov`` (4,) and its covariance ``sm`` (4, 4):
    the chi-square statistic of the position (k = 0) or velocity (k = 2) part of a fix, 2 dof."""
    det = sm[k, k] * sm[k + 1, k + 1] - sm[k, k + 1] * sm[k + 1, k]
    w0 = (sm[k + 1, k + 1] * innov[k] - sm[k, k + 1] * innov[k + 1]) / det
    w1 = (sm[k, k] * innov[k + 1] - sm[k + 1, k] * innov[k]) / det
    return innov[k] * w0 + innov[k + 1] * w1


@njit(cache=True)
def gate_nis2(sm, rn, innov, g, sg):
    """The fault exclusion's statistic of the fix's position: :func:`nis2` of ``sm``, or where the gate's factor
    ``g`` is not 1 of S - (1 - g) R_n on the position block (the receiver's own report:
    :func:`coloc.methods.gnss_bias2.gate_nis`), built in the scratch ``sg`` (4, 4)."""
    if g == 1.0:
        return nis2(sm, innov, 0)
    for a in range(2):
        for b in range(2):
            sg[a, b] = sm[a, b] - (1.0 - g) * rn[a, b]
    return nis2(sg, innov, 0)


@njit(cache=True)
def deweight_velocity(sm, rn, innov, vel_threshold, on_innovation=False):
    """In place: where the velocity part's statistic d^2 exceeds ``vel_threshold``, R_vv and S_vv grow by
    (d^2 / threshold - 1) R_vv, or with ``on_innovation`` by (d^2 / threshold - 1) S_vv
    (:func:`coloc.methods.gnss_bias2.velocity_deweight`, Chang 2014)."""
    d2 = nis2(sm, innov, 2)
    if d2 > vel_threshold:
        f = d2 / vel_threshold - 1.0
        for a in range(2, 4):
            for b in range(2, 4):  # each entry's extra reads only that entry, before it is written
                extra = f * (sm[a, b] if on_innovation else rn[a, b])
                rn[a, b] += extra
                sm[a, b] += extra


@njit(cache=True)
def gnss6_step(mean, cov, ind, accel, z, r, predict, streak, dt, s_along, s_cross, min_speed, share, decay,
               gate_threshold, max_exclusions, common_mode, with_ind, sym_predict, vel_threshold, gate_scale,
               vel_on_innovation=False):
    """One step of the 6-state filter for every row: predict where ``predict`` (decay a = exp(-dt/tau)),
    then the fix with the gate (a row that does not predict is never gated; nor one whose ``streak``
    reached ``max_exclusions``; ``gate_threshold`` inf: no gate). ``with_ind``: the independent part
    ``ind`` carried as in :func:`coloc.methods.coop_fusion._split_gnss_step` (``common_mode``: the bias
    driving noise and the fix's noise go to the dependent part); ``sym_predict``: the predicted
    covariance symmetrized as :func:`coloc.methods.gnss_bias.bias_predict_update` does; ``gate_scale`` (N,):
    the gate's factor on the fix's position noise (:func:`coloc.methods.gnss_bias2.gate_nis`; 1: the
    noise the update takes). Returns new (mean, cov, ind, excluded); inputs are not modified."""
    n = mean.shape[0]
    m = mean.copy()
    p = cov.copy()
    pi = ind.copy()
    excluded = np.zeros(n, dtype=np.bool_)
    f = np.eye(6)
    f[0, 2] = dt
    f[1, 3] = dt
    f[4, 4] = decay
    f[5, 5] = decay
    h = 0.5 * dt * dt
    q = np.zeros((6, 6))
    tmp = np.empty((6, 6))
    out = np.empty((6, 6))
    hp = np.empty((4, 6))
    sm = np.empty((4, 4))
    sg = np.zeros((4, 4))
    x = np.empty((4, 6))
    gain = np.empty((6, 4))
    ikh = np.empty((6, 6))
    nz = np.empty((6, 6))
    innov = np.empty(4)
    l = np.empty((4, 4))
    rn = np.empty((4, 4))
    bias_q = (1.0 - decay * decay) * share
    for i in range(n):
        if predict[i]:
            q[:, :] = 0.0
            _driving_q(m[i, 2], m[i, 3], dt, s_along, s_cross, min_speed, q[:4, :4])
            m0, m1, m2, m3 = m[i, 0], m[i, 1], m[i, 2], m[i, 3]
            m[i, 0] = m0 + dt * m2 + h * accel[i, 0]
            m[i, 1] = m1 + dt * m3 + h * accel[i, 1]
            m[i, 2] = m2 + dt * accel[i, 0]
            m[i, 3] = m3 + dt * accel[i, 1]
            m[i, 4] = decay * m[i, 4]
            m[i, 5] = decay * m[i, 5]
            _sandwich6(f, p[i], out, tmp)
            for a in range(6):
                for b in range(6):
                    qb = bias_q * r[i, a - 4, b - 4] if (a >= 4 and b >= 4) else q[a, b]
                    p[i, a, b] = out[a, b] + qb
            if sym_predict:
                for a in range(6):
                    for b in range(a):
                        v = 0.5 * (p[i, a, b] + p[i, b, a])
                        p[i, a, b] = v
                        p[i, b, a] = v
            if with_ind:
                _sandwich6(f, pi[i], out, tmp)
                for a in range(6):
                    for b in range(6):
                        if a >= 4 and b >= 4:
                            qb = 0.0 if common_mode else bias_q * r[i, a - 4, b - 4]
                        else:
                            qb = q[a, b]
                        pi[i, a, b] = out[a, b] + qb
        for a in range(4):
            for b in range(4):
                rn[a, b] = r[i, a, b] * (1.0 - share) if (a < 2 and b < 2) else r[i, a, b]
        # H P (4, 6) and S = H P H^T + R_n for H = [I2 0 I2; 0 I2 0].
        for c in range(6):
            hp[0, c] = p[i, 0, c] + p[i, 4, c]
            hp[1, c] = p[i, 1, c] + p[i, 5, c]
            hp[2, c] = p[i, 2, c]
            hp[3, c] = p[i, 3, c]
        for a in range(4):
            sm[a, 0] = hp[a, 0] + hp[a, 4] + rn[a, 0]
            sm[a, 1] = hp[a, 1] + hp[a, 5] + rn[a, 1]
            sm[a, 2] = hp[a, 2] + rn[a, 2]
            sm[a, 3] = hp[a, 3] + rn[a, 3]
        innov[0] = z[i, 0] - (m[i, 0] + m[i, 4])
        innov[1] = z[i, 1] - (m[i, 1] + m[i, 5])
        innov[2] = z[i, 2] - m[i, 2]
        innov[3] = z[i, 3] - m[i, 3]
        if predict[i] and vel_threshold < np.inf:
            deweight_velocity(sm, rn, innov, vel_threshold, vel_on_innovation)
        lo = 0
        if predict[i] and streak[i] < max_exclusions and gate_threshold < np.inf:
            if gate_nis2(sm, rn, innov, gate_scale[i], sg) > gate_threshold:
                excluded[i] = True
                lo = 2
        k = 4 - lo
        # K = P H_s^T S_s^-1 = (S_s^-1 H_s P)^T.
        _lu_solve(sm, lo, hp, x, l)
        for a in range(6):
            for c in range(k):
                gain[a, c] = x[c, a]
        for a in range(6):
            acc = 0.0
            for c in range(k):
                acc += gain[a, c] * innov[lo + c]
            m[i, a] += acc
        # I - K H_s (H_s = rows lo.. of H).
        for a in range(6):
            for b in range(6):
                ikh[a, b] = 1.0 if a == b else 0.0
            for c in range(k):
                row = lo + c
                ikh[a, row] -= gain[a, c]
                if row < 2:
                    ikh[a, row + 4] -= gain[a, c]
        # K R_s K^T.
        for a in range(6):
            for b in range(6):
                acc = 0.0
                for c in range(k):
                    for d in range(k):
                        acc += gain[a, c] * rn[lo + c, lo + d] * gain[b, d]
                nz[a, b] = acc
        _sandwich6(ikh, p[i], out, tmp)
        for a in range(6):
            for b in range(a + 1):
                v = 0.5 * ((out[a, b] + nz[a, b]) + (out[b, a] + nz[b, a]))
                p[i, a, b] = v
                p[i, b, a] = v
        if with_ind:
            _sandwich6(ikh, pi[i], out, tmp)
            for a in range(6):
                for b in range(a + 1):
                    if common_mode:
                        v = 0.5 * (out[a, b] + out[b, a])
                    else:
                        v = 0.5 * ((out[a, b] + nz[a, b]) + (out[b, a] + nz[b, a]))
                    pi[i, a, b] = v
                    pi[i, b, a] = v
    return m, p, pi, excluded
