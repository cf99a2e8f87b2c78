"""numba kernels for the per-vehicle 4x4 Kalman steps (the numpy versions in
``coloc.core.models`` are the reference; tests check they agree)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _driving_acc(vx, vy, s_along, s_cross, min_speed):
    """The driving acceleration's covariance of model (1) oriented by the velocity (isotropic below
    min_speed): its entries (a00, a11, a01)."""
    speed = np.hypot(vx, vy)
    if speed < min_speed:
        c, s, p2, q2 = 1.0, 0.0, s_along * s_along, s_along * s_along
    else:
        c, s = vx / speed, vy / speed
        p2, q2 = s_along * s_along, s_cross * s_cross
    return c * c * p2 + s * s * q2, s * s * p2 + c * c * q2, c * s * (p2 - q2)


@njit(cache=True)
def _driving_q(vx, vy, dt, s_along, s_cross, min_speed, q):
    """Q of model (1) oriented by the velocity (isotropic below min_speed), written into q (4,4)."""
    a00, a11, a01 = _driving_acc(vx, vy, s_along, s_cross, min_speed)
    h = 0.5 * dt * dt
    # B = [h I; dt I]; Q = B Acc B^T.
    q[0, 0] = h * h * a00
    q[0, 1] = h * h * a01
    q[1, 1] = h * h * a11
    q[0, 2] = h * dt * a00
    q[0, 3] = h * dt * a01
    q[1, 2] = h * dt * a01
    q[1, 3] = h * dt * a11
    q[2, 2] = dt * dt * a00
    q[2, 3] = dt * dt * a01
    q[3, 3] = dt * dt * a11
    for i in range(4):
        for j in range(i):
            q[i, j] = q[j, i]


@njit(cache=True)
def _cholesky4_solve_into(s, b, out, l, y):
    """out = S^-1 b for a symmetric positive definite 4x4 S (explicit Cholesky, no LAPACK call);
    ``l`` (4, 4) and ``y`` (4,) scratch (every entry read is written first)."""
    for i in range(4):
        for j in range(i + 1):
            acc = s[i, j]
            for k in range(j):
                acc -= l[i, k] * l[j, k]
            if i == j:
                l[i, i] = np.sqrt(acc)
            else:
                l[i, j] = acc / l[j, j]
    for c in range(b.shape[1]):
        for i in range(4):
            acc = b[i, c]
            for k in range(i):
                acc -= l[i, k] * y[k]
            y[i] = acc / l[i, i]
        for i in range(3, -1, -1):
            acc = y[i]
            for k in range(i + 1, 4):
                acc -= l[k, i] * out[k, c]
            out[i, c] = acc / l[i, i]


@njit(cache=True)
def _mm4(a, b, out):
    for i in range(4):
        for j in range(4):
            acc = 0.0
            for k in range(4):
                acc += a[i, k] * b[k, j]
            out[i, j] = acc


@njit(cache=True)
def _mm4_bt(a, b, out):
    """out = a @ b.T"""
    for i in range(4):
        for j in range(4):
            acc = 0.0
            for k in range(4):
                acc += a[i, k] * b[j, k]
            out[i, j] = acc


@njit(cache=True)
def gnss_step_kernel(mean, cov, accel, z, r, predict_mask, dt, s_along, s_cross, min_speed):
    """In place, per vehicle: predict by model (1) where ``predict_mask``, then the
    Kalman update with H = I (model (3)) in Joseph form:
    K = P (P + R)^-1, m += K (z - m), P = (I - K) P (I - K)^T + K R K^T."""
    n = mean.shape[0]
    h = 0.5 * dt * dt
    q = np.zeros((4, 4))
    p = np.empty((4, 4))
    s = np.empty((4, 4))
    kt = np.empty((4, 4))
    k = np.empty((4, 4))
    ik = np.empty((4, 4))
    t1 = np.empty((4, 4))
    t2 = np.empty((4, 4))
    innov = np.empty(4)
    chol = np.zeros((4, 4))
    y = np.zeros(4)
    for i in range(n):
        m0, m1, m2, m3 = mean[i, 0], mean[i, 1], mean[i, 2], mean[i, 3]
        for a in range(4):
            for b in range(4):
                p[a, b] = cov[i, a, b]
        if predict_mask[i]:
            _driving_q(m2, m3, dt, s_along, s_cross, min_speed, q)
            ax, ay = accel[i, 0], accel[i, 1]
            m0, m1, m2, m3 = m0 + dt * m2 + h * ax, m1 + dt * m3 + h * ay, m2 + dt * ax, m3 + dt * ay
            # P <- A P A^T + Q with A = [[I, dt I], [0, I]], written out.
            for a in range(4):
                t1[a, 0] = p[a, 0] + dt * p[a, 2]
                t1[a, 1] = p[a, 1] + dt * p[a, 3]
                t1[a, 2] = p[a, 2]
                t1[a, 3] = p[a, 3]
            for b in range(4):
                p[0, b] = t1[0, b] + dt * t1[2, b] + q[0, b]
                p[1, b] = t1[1, b] + dt * t1[3, b] + q[1, b]
                p[2, b] = t1[2, b] + q[2, b]
                p[3, b] = t1[3, b] + q[3, b]
        for a in range(4):
            for b in range(4):
                s[a, b] = p[a, b] + r[i, a, b]
        _cholesky4_solve_into(s, p, kt, chol, y)  # K^T = S^-1 P
        for a in range(4):
            for b in range(4):
                k[a, b] = kt[b, a]
                ik[a, b] = (1.0 if a == b else 0.0) - kt[b, a]
        innov[0] = z[i, 0] - m0
        innov[1] = z[i, 1] - m1
        innov[2] = z[i, 2] - m2
        innov[3] = z[i, 3] - m3
        mm = (m0, m1, m2, m3)
        for a in range(4):
            acc = mm[a]
            for b in range(4):
                acc += k[a, b] * innov[b]
            mean[i, a] = acc
        _mm4(ik, p, t1)
        _mm4_bt(t1, ik, t2)  # (I-K) P (I-K)^T
        _mm4(k, r[i], t1)
        _mm4_bt(t1, k, s)  # K R K^T
        for a in range(4):
            for b in range(4):
                cov[i, a, b] = 0.5 * (t2[a, b] + s[a, b] + t2[b, a] + s[b, a])


@njit(cache=True)
def _mm_soa(x, y, out, bt):
    """out = x @ y (``bt``: x @ y.T) for every column of the (16, n) arrays, entry a*4+b: acc = 0,
    then += x[i,k] y[k,j] for k = 0..3 (:func:`_mm4`, :func:`_mm4_bt`)."""
    n = x.shape[1]
    for i in range(4):
        for j in range(4):
            dst = out[i * 4 + j]
            for v in range(n):
                dst[v] = 0.0
            for k in range(4):
                a = x[i * 4 + k]
                b = y[j * 4 + k] if bt else y[k * 4 + j]
                for v in range(n):
                    dst[v] += a[v] * b[v]


@njit(cache=True)
def gnss_step_rows(mean, cov, accel, z, r, predict_mask, dt, s_along, s_cross, min_speed):
    """:func:`gnss_step_kernel` (in place), byte for byte, each scalar step of it one loop over the
    vehicles (the 4x4 entries as (16, n) arrays): the same operations in the same order per
    vehicle. The prediction is computed for every vehicle and kept where ``predict_mask``."""
    n = mean.shape[0]
    h = 0.5 * dt * dt
    m = np.empty((4, n))
    p = np.empty((16, n))
    rr = np.empty((16, n))
    for v in range(n):
        for a in range(4):
            m[a, v] = mean[v, a]
            for b in range(4):
                p[a * 4 + b, v] = cov[v, a, b]
                rr[a * 4 + b, v] = r[v, a, b]
    # model (1): Q by _driving_q, then m <- A m + B a, P <- A P A^T + Q
    q = np.empty((16, n))
    for v in range(n):
        if not predict_mask[v]:
            continue
        a00, a11, a01 = _driving_acc(m[2, v], m[3, v], s_along, s_cross, min_speed)
        q[0, v] = h * h * a00
        q[1, v] = h * h * a01
        q[5, v] = h * h * a11
        q[2, v] = h * dt * a00
        q[3, v] = h * dt * a01
        q[6, v] = h * dt * a01
        q[7, v] = h * dt * a11
        q[10, v] = dt * dt * a00
        q[11, v] = dt * dt * a01
        q[15, v] = dt * dt * a11
        for i in range(4):
            for j in range(i):
                q[i * 4 + j, v] = q[j * 4 + i, v]
        ax, ay = accel[v, 0], accel[v, 1]
        m0, m1, m2, m3 = m[0, v], m[1, v], m[2, v], m[3, v]
        m[0, v], m[1, v], m[2, v], m[3, v] = m0 + dt * m2 + h * ax, m1 + dt * m3 + h * ay, m2 + dt * ax, m3 + dt * ay
    t1 = np.empty((16, n))
    for a in range(4):
        for v in range(n):
            t1[a * 4 + 0, v] = p[a * 4 + 0, v] + dt * p[a * 4 + 2, v]
            t1[a * 4 + 1, v] = p[a * 4 + 1, v] + dt * p[a * 4 + 3, v]
            t1[a * 4 + 2, v] = p[a * 4 + 2, v]
            t1[a * 4 + 3, v] = p[a * 4 + 3, v]
    for b in range(4):
        for v in range(n):
            if predict_mask[v]:
                p[0 * 4 + b, v] = t1[0 * 4 + b, v] + dt * t1[2 * 4 + b, v] + q[0 * 4 + b, v]
                p[1 * 4 + b, v] = t1[1 * 4 + b, v] + dt * t1[3 * 4 + b, v] + q[1 * 4 + b, v]
                p[2 * 4 + b, v] = t1[2 * 4 + b, v] + q[2 * 4 + b, v]
                p[3 * 4 + b, v] = t1[3 * 4 + b, v] + q[3 * 4 + b, v]
    # Kalman update (3): S = P + R, K^T = S^-1 P (_cholesky4_solve_into)
    s = np.empty((16, n))
    for e in range(16):
        for v in range(n):
            s[e, v] = p[e, v] + rr[e, v]
    ll = np.empty((16, n))
    acc = np.empty(n)
    for i in range(4):
        for j in range(i + 1):
            for v in range(n):
                acc[v] = s[i * 4 + j, v]
            for k in range(j):
                for v in range(n):
                    acc[v] -= ll[i * 4 + k, v] * ll[j * 4 + k, v]
            if i == j:
                for v in range(n):
                    ll[i * 4 + i, v] = np.sqrt(acc[v])
            else:
                for v in range(n):
                    ll[i * 4 + j, v] = acc[v] / ll[j * 4 + j, v]
    kt = np.empty((16, n))
    y = np.empty((4, n))
    for c in range(4):
        for i in range(4):
            for v in range(n):
                acc[v] = p[i * 4 + c, v]
            for k in range(i):
                for v in range(n):
                    acc[v] -= ll[i * 4 + k, v] * y[k, v]
            for v in range(n):
                y[i, v] = acc[v] / ll[i * 4 + i, v]
        for i in range(3, -1, -1):
            for v in range(n):
                acc[v] = y[i, v]
            for k in range(i + 1, 4):
                for v in range(n):
                    acc[v] -= ll[k * 4 + i, v] * kt[k * 4 + c, v]
            for v in range(n):
                kt[i * 4 + c, v] = acc[v] / ll[i * 4 + i, v]
    k_ = np.empty((16, n))
    ik = np.empty((16, n))
    for a in range(4):
        for b in range(4):
            for v in range(n):
                k_[a * 4 + b, v] = kt[b * 4 + a, v]
                ik[a * 4 + b, v] = (1.0 if a == b else 0.0) - kt[b * 4 + a, v]
    innov = np.empty((4, n))
    for a in range(4):
        for v in range(n):
            innov[a, v] = z[v, a] - m[a, v]
    for a in range(4):
        for v in range(n):
            acc[v] = m[a, v]
        for b in range(4):
            for v in range(n):
                acc[v] += k_[a * 4 + b, v] * innov[b, v]
        for v in range(n):
            mean[v, a] = acc[v]
    t2 = np.empty((16, n))
    _mm_soa(ik, p, t1, False)
    _mm_soa(t1, ik, t2, True)  # (I-K) P (I-K)^T
    _mm_soa(k_, rr, t1, False)
    _mm_soa(t1, k_, s, True)  # K R K^T
    for a in range(4):
        for b in range(4):
            for v in range(n):
                cov[v, a, b] = 0.5 * (t2[a * 4 + b, v] + s[a * 4 + b, v] + t2[b * 4 + a, v] + s[b * 4 + a, v])
