"""numba kernel for the 8-state [px, py, vx, vy, cx, cy, lx, ly] receiver filters of ``[fusion]`` under
``[gnss_model] bias_model = "two_state"`` (:mod:`coloc.methods.coop_fusion`): one loop over vehicles with 8x8
arithmetic in place of the batched numpy of :func:`coloc.methods.coop_fusion._split_gnss_step` and
:func:`coloc.methods.gnss_bias2.two_state_predict_update`, which stay the references (tests: equal to 1e-12).
The ``gnss`` method keeps the numpy :func:`~coloc.methods.gnss_bias2.two_state_predict_update`; only the
fusion filters use this kernel, as :mod:`coloc.kernels.gnss6` for the 6-state model.

Model (:mod:`coloc.methods.gnss_bias2`, where the sources are): (1) prediction with the velocity-oriented
driving noise; the common-mode bias ``c' = a_c c + w_c``, ``Var(w_c) = (1 - a_c^2) s_c R_pos``; the local bias
``l' = a_l l + w_l``, ``a_l = exp(-Ts / local_tau_s - |v| Ts / local_length_m)`` with |v| the row's own prior
speed estimate, ``Var(w_l) = (1 - a_l^2) s_l R_pos``; fix ``z_pos = p + c + l + n``, ``Var(n) = (1 - s_c - s_l)
R_pos``, ``z_vel = v + n_v``; the 2-dof chi-square gate on the position innovation (velocity-only update when
excluded); ``consider``: the common-mode gain rows are zero (Schmidt); Joseph-form covariance update. With
``bias_follows_report`` both biases are mapped by the row's report map T (``c' = a_c T c``, ``l' = a_l T l``;
:func:`coloc.methods.gnss_bias.report_map`, computed by the caller).

The independent part (``with_ind``; the split of :mod:`coloc.inference.split_ci`): the common-mode bias's
driving noise is always in it (the rule of :mod:`coloc.methods.coop_fusion`: the feature evidence is taken in
the common-mode frame, so nothing of it is correlated with c); with ``common_mode`` the local bias's driving
noise and the fix's noise go to the dependent part.
With ``velocity_gate`` the robust velocity of :func:`coloc.methods.gnss_bias2.velocity_deweight`
(:func:`coloc.kernels.gnss6.deweight_velocity`); ``common_sigma_m`` adds its variance to the common-mode bias.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from coloc.kernels.gnss6 import _lu_solve, deweight_velocity, gate_nis2, nis2
from coloc.kernels.kalman import _driving_q

D = 8


@njit(cache=True)
def _sandwich8(a, p, out, tmp):
    """out = A P A^T for 8x8 A, P."""
    for i in range(D):
        for j in range(D):
            acc = 0.0
            for k in range(D):
                acc += a[i, k] * p[k, j]
            tmp[i, j] = acc
    for i in range(D):
        for j in range(D):
            acc = 0.0
            for k in range(D):
                acc += tmp[i, k] * a[j, k]
            out[i, j] = acc


@njit(cache=True)
def gnss8_step(mean, cov, ind, accel, z, r, predict, streak, dt, s_along, s_cross, min_speed, common_share,
               local_share, decay_c, local_tau_s, local_length_m, consider, gate_threshold, max_exclusions,
               common_mode, with_ind, sym_predict, tmap, mapped, common_var, vel_threshold, gate_scale,
               vel_on_innovation=False):
    """One step of the 8-state filter for every row: predict where ``predict`` (``decay_c`` = exp(-dt /
    common_tau_s); the local decay per row from its prior speed), then the fix with the gate (a row that does
    not predict is never gated; nor one whose ``streak`` reached ``max_exclusions``; ``gate_threshold`` inf:
    no gate). ``with_ind``: the independent part ``ind`` carried (module docstring); ``sym_predict``: the
    predicted covariance symmetrized as :func:`coloc.methods.gnss_bias2.two_state_predict_update` does;
    ``mapped``: the biases mapped by ``tmap`` (N, 2, 2) (``bias_follows_report``); ``common_var``: the
    common-mode bias's own variance per axis (``common_sigma_m``^2, added to its share of the report);
    ``vel_threshold``: the velocity gate's chi-square threshold (inf: none; a predicted row whose velocity
    innovation's d^2 exceeds it has its velocity noise scaled by d^2 / threshold,
    :func:`coloc.methods.gnss_bias2.velocity_deweight`); ``gate_scale`` (N,): the gate's factor on the fix's
    position noise (:func:`coloc.methods.gnss_bias2.gate_nis`; 1: the noise the update takes). Returns new
    (mean, cov, ind, excluded); inputs are not modified."""
    n = mean.shape[0]
    m = mean.copy()
    p = cov.copy()
    pi = ind.copy()
    excluded = np.zeros(n, dtype=np.bool_)
    f = np.eye(D)
    f[0, 2] = dt
    f[1, 3] = dt
    h = 0.5 * dt * dt
    q = np.zeros((D, D))
    qk = np.zeros((4, 4))
    tmp = np.empty((D, D))
    out = np.empty((D, D))
    hp = np.empty((4, D))
    sm = np.empty((4, 4))
    sg = np.zeros((4, 4))
    x = np.empty((4, D))
    gain = np.empty((D, 4))
    ikh = np.empty((D, D))
    nz = np.empty((D, D))
    innov = np.empty(4)
    lsc = np.empty((4, 4))
    rn = np.empty((4, 4))
    qc = (1.0 - decay_c * decay_c) * common_share
    white = 1.0 - common_share - local_share
    for i in range(n):
        if predict[i]:
            speed = math.hypot(m[i, 2], m[i, 3])
            a_l = math.exp(-dt / local_tau_s - speed * dt / local_length_m)
            ql = (1.0 - a_l * a_l) * local_share
            for a in range(2):
                for b in range(2):
                    t_ab = tmap[i, a, b] if mapped else (1.0 if a == b else 0.0)
                    f[4 + a, 4 + b] = decay_c * t_ab
                    f[6 + a, 6 + b] = a_l * t_ab
            _driving_q(m[i, 2], m[i, 3], dt, s_along, s_cross, min_speed, qk)
            q[:, :] = 0.0
            for a in range(4):
                for b in range(4):
                    q[a, b] = qk[a, b]
            for a in range(2):
                for b in range(2):
                    q[4 + a, 4 + b] = qc * r[i, a, b]
                    if common_var > 0.0 and a == b:
                        q[4 + a, 4 + b] += (1.0 - decay_c * decay_c) * common_var
                    q[6 + a, 6 + b] = ql * r[i, a, b]
            m0, m1, m2, m3 = m[i, 0], m[i, 1], m[i, 2], m[i, 3]
            m[i, 0] = m0 + dt * m2 + h * accel[i, 0]
            m[i, 1] = m1 + dt * m3 + h * accel[i, 1]
            m[i, 2] = m2 + dt * accel[i, 0]
            m[i, 3] = m3 + dt * accel[i, 1]
            if mapped:
                c0, c1, l0, l1 = m[i, 4], m[i, 5], m[i, 6], m[i, 7]
                m[i, 4] = f[4, 4] * c0 + f[4, 5] * c1
                m[i, 5] = f[5, 4] * c0 + f[5, 5] * c1
                m[i, 6] = f[6, 6] * l0 + f[6, 7] * l1
                m[i, 7] = f[7, 6] * l0 + f[7, 7] * l1
            else:
                m[i, 4] = decay_c * m[i, 4]
                m[i, 5] = decay_c * m[i, 5]
                m[i, 6] = a_l * m[i, 6]
                m[i, 7] = a_l * m[i, 7]
            _sandwich8(f, p[i], out, tmp)
            for a in range(D):
                for b in range(D):
                    p[i, a, b] = out[a, b] + q[a, b]
            if sym_predict:
                for a in range(D):
                    for b in range(a):
                        v = 0.5 * (p[i, a, b] + p[i, b, a])
                        p[i, a, b] = v
                        p[i, b, a] = v
            if with_ind:
                _sandwich8(f, pi[i], out, tmp)
                for a in range(D):
                    for b in range(D):
                        qi = 0.0 if (common_mode and a >= 6 and b >= 6) else q[a, b]
                        pi[i, a, b] = out[a, b] + qi
        for a in range(4):
            for b in range(4):
                rn[a, b] = r[i, a, b] * white if (a < 2 and b < 2) else r[i, a, b]
        # H P (4, 8) and S = H P H^T + R_n for H = [I2 0 I2 I2; 0 I2 0 0].
        for c in range(D):
            hp[0, c] = p[i, 0, c] + p[i, 4, c] + p[i, 6, c]
            hp[1, c] = p[i, 1, c] + p[i, 5, c] + p[i, 7, c]
            hp[2, c] = p[i, 2, c]
            hp[3, c] = p[i, 3, c]
        for a in range(4):
            sm[a, 0] = hp[a, 0] + hp[a, 4] + hp[a, 6] + rn[a, 0]
            sm[a, 1] = hp[a, 1] + hp[a, 5] + hp[a, 7] + rn[a, 1]
            sm[a, 2] = hp[a, 2] + rn[a, 2]
            sm[a, 3] = hp[a, 3] + rn[a, 3]
        innov[0] = z[i, 0] - (m[i, 0] + m[i, 4] + m[i, 6])
        innov[1] = z[i, 1] - (m[i, 1] + m[i, 5] + m[i, 7])
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
        # K = P H_s^T S_s^-1 = (S_s^-1 H_s P)^T; the common-mode rows zero under consider.
        _lu_solve(sm, lo, hp, x, lsc)
        for a in range(D):
            for c in range(k):
                gain[a, c] = 0.0 if (consider and (a == 4 or a == 5)) else x[c, a]
        for a in range(D):
            acc = 0.0
            for c in range(k):
                acc += gain[a, c] * innov[lo + c]
            m[i, a] += acc
        # I - K H_s (H_s = rows lo.. of H).
        for a in range(D):
            for b in range(D):
                ikh[a, b] = 1.0 if a == b else 0.0
            for c in range(k):
                row = lo + c
                ikh[a, row] -= gain[a, c]
                if row < 2:
                    ikh[a, row + 4] -= gain[a, c]
                    ikh[a, row + 6] -= gain[a, c]
        # K R_s K^T.
        for a in range(D):
            for b in range(D):
                acc = 0.0
                for c in range(k):
                    for e in range(k):
                        acc += gain[a, c] * rn[lo + c, lo + e] * gain[b, e]
                nz[a, b] = acc
        _sandwich8(ikh, p[i], out, tmp)
        for a in range(D):
            for b in range(a + 1):
                v = 0.5 * ((out[a, b] + nz[a, b]) + (out[b, a] + nz[b, a]))
                p[i, a, b] = v
                p[i, b, a] = v
        if with_ind:
            _sandwich8(ikh, pi[i], out, tmp)
            for a in range(D):
                for b in range(a + 1):
                    if common_mode:
                        v = 0.5 * (out[a, b] + out[b, a])
                    else:
                        v = 0.5 * ((out[a, b] + nz[a, b]) + (out[b, a] + nz[b, a]))
                    pi[i, a, b] = v
                    pi[i, b, a] = v
    return m, p, pi, excluded
