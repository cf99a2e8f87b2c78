"""Consistent cooperative fusion: split covariance intersection on the feature evidence
(config ``[fusion] rule = "split_ci"``; the method side is :mod:`coloc.methods.coop_fusion`).

Why the Gaussian BPA-L of :mod:`coloc.inference.bpa` is overconfident: a vehicle's belief (22) takes
the feature messages (21) at every step, its next prior (11) is that belief predicted, and the next
messages carry again the same vehicles' histories (their GNSS errors are the same over consecutive
steps); within a step, two features seen by one other vehicle bring its information twice. Each of
these is a fusion of estimates whose correlation the vehicles do not know.

The rule (split covariance intersection, Julier & Uhlmann, "General decentralized data fusion with
covariance intersection", Handbook of Multisensor Data Fusion, 2001; used for cooperative vehicles by
Li & Nashashibi, IEEE ITS Magazine 5(2), 2013): every estimate is split into an *independent* part,
whose error is uncorrelated with everything it is fused with, and a *dependent* part of unknown
correlation; P = P_d + P_i. Fusing (x1, P1d, P1i) with (x2, P2d, P2i) for a weight w in (0, 1):

    P1(w) = P1d / w + P1i,   P2(w) = P2d / (1 - w) + P2i,
    K = P1 H^T (H P1 H^T + P2)^-1,   x = x1 + K (x2 - H x1),   P = (I - K H) P1,
    P_i = (I - K H) P1i (I - K H)^T + K P2i K^T,   P_d = P - P_i,

which bounds the error covariance for every correlation of the dependent parts (ibid.). Here:

* what a vehicle exchanges is its *own-sensor* message only (GNSS and inertial, the message the
  tracks keep, ``IcpParams.feature_message = "own"``), so a feature's belief (20) is a sum of
  independent messages of distinct vehicles (one each, the latest), computed by the consensus of
  (20) in one pass;
* the message of feature k to vehicle i is (21) on that belief without i's own message:
  x_Vi ~ N(m_ext - z_ik, D_k + R_ik). It never holds anything of vehicle i, so its only part
  independent of vehicle i's belief is R_ik, this step's V2F noise of i; D_k (the other vehicles'
  messages) is dependent: it is correlated with the messages of i's other features and with the
  messages i took at earlier steps;
* a vehicle's messages of one step are fused with each other by split CI with the closed-form weights
  of fast covariance intersection (Niehsen, "Information fusion based on fast covariance
  intersection filtering", FUSION 2002): w_k proportional to 1 / tr(D_k,pos), the inverse trace of
  the position block (:func:`combine_messages`);
* the result is fused with the vehicle's prior by split CI with the weight that minimises the
  determinant of the posterior kinematic covariance, a 1-D golden-section search per vehicle
  (:func:`split_ci_update`); the vehicle's independent part is what its own sensors put in (GNSS,
  inertial prediction noise, fixes) and its V2F noise, the dependent part what came from features.

All kernels run over every vehicle and row of a step in one numba call (no per-object Python loop).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Golden-section iterations of the weight search (interval 0.618^n of [0, 1]: 2e-4 after 18).
SEARCH_ITERATIONS = 18
_W_MIN = 1e-4  # the search interval [_W_MIN, 1 - _W_MIN]: both parts keep a finite covariance
_PIVOT_REL = 1e-10  # a Cholesky pivot below this share of the largest diagonal: singular


@njit(cache=True)
def _chol_logdet(a, n):
    """log det of the leading n x n block of SPD ``a`` by Cholesky; -inf if not positive definite."""
    l = np.zeros((n, n))
    s = 0.0
    for j in range(n):
        d = a[j, j]
        for k in range(j):
            d -= l[j, k] * l[j, k]
        if d <= 0.0:
            return -np.inf
        l[j, j] = math.sqrt(d)
        s += math.log(d)
        for i in range(j + 1, n):
            v = a[i, j]
            for k in range(j):
                v -= l[i, k] * l[j, k]
            l[i, j] = v / l[j, j]
    return s


@njit(cache=True)
def _spd_inverse(a, n, out):
    """out[:n, :n] = inverse of SPD a[:n, :n] by Cholesky; False if a pivot is not positive (relative
    to the largest diagonal), then ``out`` is undefined."""
    scale = 0.0
    for j in range(n):
        scale = max(scale, abs(a[j, j]))
    l = np.zeros((n, n))
    for j in range(n):
        d = a[j, j]
        for k in range(j):
            d -= l[j, k] * l[j, k]
        if not d > _PIVOT_REL * scale:
            return False
        l[j, j] = math.sqrt(d)
        for i in range(j + 1, n):
            v = a[i, j]
            for k in range(j):
                v -= l[i, k] * l[j, k]
            l[i, j] = v / l[j, j]
    # inverse of L (lower), then L^-T L^-1
    li = np.zeros((n, n))
    for j in range(n):
        li[j, j] = 1.0 / l[j, j]
        for i in range(j + 1, n):
            v = 0.0
            for k in range(j, i):
                v -= l[i, k] * li[k, j]
            li[i, j] = v / l[i, i]
    for i in range(n):
        for j in range(i + 1):
            v = 0.0
            for k in range(i, n):
                v += li[k, i] * li[k, j]
            out[i, j] = v
            out[j, i] = v
    return True


@njit(cache=True)
def message_moments(ext_lam, ext_eta, z):
    """Moments of the feature -> vehicle messages (21) of every row: ``dep`` = D_k = ext_lam^-1 (the
    dependent part; the independent one is the row's R_ik), ``y`` = D_k ext_eta - z (the vehicle's
    position and velocity the message implies); ``valid`` False where the extrinsic information is
    singular (a feature no other vehicle informs: no message)."""
    o = ext_lam.shape[0]
    dep = np.zeros((o, 4, 4))
    y = np.zeros((o, 4))
    valid = np.zeros(o, dtype=np.bool_)
    inv = np.zeros((4, 4))
    for k in range(o):
        if not _spd_inverse(ext_lam[k], 4, inv):
            continue
        valid[k] = True
        for a in range(4):
            v = 0.0
            for b in range(4):
                dep[k, a, b] = inv[a, b]
                v += inv[a, b] * ext_eta[k, b]
            y[k, a] = v - z[k, a]
    return dep, y, valid


@njit(cache=True)
def combine_messages(owner, dep, r, y, valid, n):
    """Split CI of each vehicle's messages of the step with fast-CI weights w_k = (1/tr D_k,pos) /
    sum_j (1/tr D_j,pos) (Niehsen 2002). Per vehicle: the information Lambda_F = sum_k (D_k / w_k +
    R_k)^-1, the mean y_F, the covariance P_F = Lambda_F^-1 and its independent part R_F = sum_k G_k
    R_k G_k^T with G_k = P_F (D_k / w_k + R_k)^-1. Returns (y_F (n, 4), P_F (n, 4, 4), R_F (n, 4, 4),
    has (n,) bool)."""
    o = owner.size
    inv_tr = np.zeros(n)
    for k in range(o):
        if valid[k]:
            inv_tr[owner[k]] += 1.0 / (dep[k, 0, 0] + dep[k, 1, 1])
    lam_k = np.zeros((o, 4, 4))
    lam_f = np.zeros((n, 4, 4))
    eta_f = np.zeros((n, 4))
    tmp = np.zeros((4, 4))
    ok_row = valid.copy()
    for k in range(o):
        if not valid[k]:
            continue
        i = owner[k]
        w = (1.0 / (dep[k, 0, 0] + dep[k, 1, 1])) / inv_tr[i]
        for a in range(4):
            for b in range(4):
                tmp[a, b] = dep[k, a, b] / w + r[k, a, b]
        if not _spd_inverse(tmp, 4, lam_k[k]):
            ok_row[k] = False
            continue
        for a in range(4):
            v = 0.0
            for b in range(4):
                lam_f[i, a, b] += lam_k[k, a, b]
                v += lam_k[k, a, b] * y[k, b]
            eta_f[i, a] += v
    y_f = np.zeros((n, 4))
    p_f = np.zeros((n, 4, 4))
    r_f = np.zeros((n, 4, 4))
    has = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        if _spd_inverse(lam_f[i], 4, p_f[i]):
            has[i] = True
            for a in range(4):
                v = 0.0
                for b in range(4):
                    v += p_f[i, a, b] * eta_f[i, b]
                y_f[i, a] = v
    g = np.zeros((4, 4))
    gr = np.zeros((4, 4))
    for k in range(o):
        i = owner[k]
        if not (ok_row[k] and has[i]):
            continue
        for a in range(4):  # G_k = P_F Lambda_k
            for b in range(4):
                v = 0.0
                for c in range(4):
                    v += p_f[i, a, c] * lam_k[k, c, b]
                g[a, b] = v
        for a in range(4):  # G_k R_k
            for b in range(4):
                v = 0.0
                for c in range(4):
                    v += g[a, c] * r[k, c, b]
                gr[a, b] = v
        for a in range(4):  # += G_k R_k G_k^T
            for b in range(4):
                v = 0.0
                for c in range(4):
                    v += gr[a, c] * g[b, c]
                r_f[i, a, b] += v
    return y_f, p_f, r_f, has


@njit(cache=True)
def _objective(pd, pi, fd, fi, w, a, b):
    """log det of the kinematic posterior covariance of the split CI at weight w:
    log det A + log det B - log det (A + B), A = P1d,kk / w + P1i,kk, B = P2d / (1 - w) + P2i
    ((A^-1 + B^-1)^-1 = A (A + B)^-1 B)."""
    for r in range(4):
        for c in range(4):
            a[r, c] = pd[r, c] / w + pi[r, c]
            b[r, c] = fd[r, c] / (1.0 - w) + fi[r, c]
    la = _chol_logdet(a, 4)
    lb = _chol_logdet(b, 4)
    for r in range(4):
        for c in range(4):
            a[r, c] += b[r, c]
    return la + lb - _chol_logdet(a, 4)


@njit(cache=True)
def split_ci_update(mean, cov, ind, y_f, p_f, r_f, has, iterations, fixed_lo=0, fixed_hi=0):
    """Split CI of each vehicle's prior (mean (n, d), total covariance ``cov`` (n, d, d), independent
    part ``ind``; d >= 4, the first 4 states the kinematics [p, v]) with its combined feature evidence
    (y_F, P_F, R_F of :func:`combine_messages`, observing x[:4]), where ``has``. The weight w of the
    prior minimises the log det of the posterior kinematic covariance (golden section on [1e-4,
    1 - 1e-4], ``iterations`` steps; the end points are candidates too). States ``fixed_lo`` to ``fixed_hi`` - 1
    are not updated (zero gain rows; the Joseph form below holds for any gain): a consider state of the
    fusion (:mod:`coloc.methods.coop_fusion`, the common-mode bias). Returns (mean, cov, ind, weight (n,), NaN
    where nothing was fused)."""
    n, d = mean.shape
    m_out = mean.copy()
    c_out = cov.copy()
    i_out = ind.copy()
    weight = np.full(n, np.nan)
    a = np.zeros((4, 4))
    b = np.zeros((4, 4))
    pdk = np.zeros((4, 4))
    fd = np.zeros((4, 4))
    g = (math.sqrt(5.0) - 1.0) / 2.0
    p1 = np.zeros((d, d))
    s = np.zeros((4, 4))
    s_inv = np.zeros((4, 4))
    k_gain = np.zeros((d, 4))
    ikh = np.zeros((d, d))
    tmp = np.zeros((d, d))
    for i in range(n):
        if not has[i]:
            continue
        for r in range(4):
            for c in range(4):
                pdk[r, c] = cov[i, r, c] - ind[i, r, c]
                fd[r, c] = p_f[i, r, c] - r_f[i, r, c]
        pik = ind[i, :4, :4]
        lo, hi = _W_MIN, 1.0 - _W_MIN
        x1 = hi - g * (hi - lo)
        x2 = lo + g * (hi - lo)
        f1 = _objective(pdk, pik, fd, r_f[i], x1, a, b)
        f2 = _objective(pdk, pik, fd, r_f[i], x2, a, b)
        for _ in range(iterations):
            if f1 <= f2:
                hi, x2, f2 = x2, x1, f1
                x1 = hi - g * (hi - lo)
                f1 = _objective(pdk, pik, fd, r_f[i], x1, a, b)
            else:
                lo, x1, f1 = x1, x2, f2
                x2 = lo + g * (hi - lo)
                f2 = _objective(pdk, pik, fd, r_f[i], x2, a, b)
        w, best = (x1, f1) if f1 <= f2 else (x2, f2)
        for wc in (_W_MIN, 1.0 - _W_MIN):
            fc = _objective(pdk, pik, fd, r_f[i], wc, a, b)
            if fc < best:
                w, best = wc, fc
        weight[i] = w
        # P1 = P1d / w + P1i (full state), S = H P1 H^T + P_Fd / (1 - w) + R_F, K = P1 H^T S^-1.
        for r in range(d):
            for c in range(d):
                p1[r, c] = (cov[i, r, c] - ind[i, r, c]) / w + ind[i, r, c]
        for r in range(4):
            for c in range(4):
                s[r, c] = p1[r, c] + fd[r, c] / (1.0 - w) + r_f[i, r, c]
        if not _spd_inverse(s, 4, s_inv):
            weight[i] = np.nan
            continue
        for r in range(d):
            for c in range(4):
                v = 0.0
                for e in range(4):
                    v += p1[r, e] * s_inv[e, c]
                k_gain[r, c] = v
        for r in range(fixed_lo, fixed_hi):
            for c in range(4):
                k_gain[r, c] = 0.0
        for r in range(d):
            v = 0.0
            for c in range(4):
                v += k_gain[r, c] * (y_f[i, c] - mean[i, c])
            m_out[i, r] = mean[i, r] + v
        for r in range(d):  # I - K H
            for c in range(d):
                ikh[r, c] = (1.0 if r == c else 0.0) - (k_gain[r, c] if c < 4 else 0.0)
        # Joseph form: P = (I-KH) P1 (I-KH)^T + K P2 K^T; P_i = (I-KH) P1i (I-KH)^T + K R_F K^T.
        for which in range(2):
            for r in range(d):
                for c in range(d):
                    v = 0.0
                    for e in range(d):
                        v += ikh[r, e] * (p1[e, c] if which == 0 else ind[i, e, c])
                    tmp[r, c] = v
            for r in range(d):
                for c in range(r + 1):
                    v = 0.0
                    for e in range(d):
                        v += tmp[r, e] * ikh[c, e]
                    for e in range(4):
                        for f in range(4):
                            m2 = (fd[e, f] / (1.0 - w) + r_f[i, e, f]) if which == 0 else r_f[i, e, f]
                            v += k_gain[r, e] * m2 * k_gain[c, f]
                    if which == 0:
                        c_out[i, r, c] = v
                        c_out[i, c, r] = v
                    else:
                        i_out[i, r, c] = v
                        i_out[i, c, r] = v
    return m_out, c_out, i_out, weight


def feature_evidence(own_mean, own_cov, owner, feature, z, r, adjacency, feature_prior_lam, feature_prior_eta,
                     params, v2x=None, feature_ci=False):
    """The step's feature evidence of every vehicle under split CI (module docstring).

    ``own_mean``/``own_cov`` (N, 4): the vehicles' own-sensor beliefs; ``owner``/``feature``/``z``/``r``
    (O, ...): the V2F rows with stable track ids (-1: not used); ``feature_prior_lam``/``_eta``: b_k^(0)
    of (12) for the sorted unique used ids, without the messages of this step's observers
    (:meth:`coloc.inference.feature_store.FeatureStore.prior_information`). The feature belief (20) is
    the prior plus the observers' own-sensor messages (19), summed by the consensus of (20) in one pass
    (``params.consensus_iterations`` rounds; over the V2X channel when ``v2x`` is given). ``feature_ci``:
    the other vehicles' messages may be correlated with each other (receivers sharing their errors), so
    the extrinsic belief of a row is their covariance intersection with equal weights, the consensus
    average of this step's other observers' messages (count x average minus the own, over count - 1),
    and the stored messages of earlier observers are left out (leaving information out keeps the bound).

    Returns (msg_lam, msg_eta, y_f, p_f, r_f, has, comm): the messages the tracks keep (the used rows'
    own-sensor messages) and the per-vehicle evidence of :func:`combine_messages`."""
    from coloc.core.models import symmetrize
    from coloc.inference.bpa import _pack_sym, _unpack_sym
    from coloc.inference.comm import GAUSSIAN_CONSENSUS_WORDS, CommCount, broadcast_rounds
    from coloc.inference.gaussian import _inv_spd, psd_clip, relative_message, to_information
    from coloc.inference.row_consensus import ChannelRowConsensus, row_consensus_weights
    from coloc.kernels.icp import complete_component_consensus
    from coloc.kernels.icp_fused import unique_inverse

    n = own_mean.shape[0]
    feature = np.asarray(feature, dtype=np.int64)
    used = feature >= 0
    owner_u = np.ascontiguousarray(np.asarray(owner, dtype=np.int64)[used])
    z_u = np.ascontiguousarray(np.asarray(z, dtype=float)[used])
    r_u = np.ascontiguousarray(np.asarray(r, dtype=float)[used])
    o = owner_u.size
    empty = (np.zeros((n, 4)), np.zeros((n, 4, 4)), np.zeros((n, 4, 4)), np.zeros(n, dtype=bool))
    if o == 0 or n == 0:
        return (np.empty((0, 4, 4)), np.empty((0, 4)), *empty, CommCount.zeros(n))
    fids, fidx = unique_inverse(feature[used])
    lam_f0_row, eta_f0_row = feature_prior_lam[fidx], feature_prior_eta[fidx]
    (w_indptr, w_indices, w_data), count, complete = row_consensus_weights(owner_u, fidx, fids.size, adjacency)
    n_cons = int(params.consensus_iterations)
    r_inv = _inv_spd(r_u)
    own_lam, own_eta = to_information(own_mean, own_cov)
    # (19) on the own-sensor belief alone: what the vehicle sends and what the track keeps.
    m_lam, m_eta = relative_message(np.ascontiguousarray(own_lam[owner_u]), np.ascontiguousarray(own_eta[owner_u]),
                                    z_u, r_u, r_inv)
    packed = _pack_sym(m_lam, m_eta)
    if v2x is not None:
        channel = ChannelRowConsensus(owner_u, fidx, fids.size, adjacency, v2x)
        avg = channel.average(packed, channel.grant(n_cons, params.exchanges_left(params.bpa_max_iterations)))
        rounds = channel.rounds_used
    else:
        avg = complete_component_consensus(w_indptr, w_indices, w_data, packed, n_cons, complete)
        rounds = n_cons
    avg_lam, avg_eta = _unpack_sym(avg)
    # (20) at each observer, then (21): its own message out (extrinsic), projected on the PSD cone.
    if feature_ci:
        others = np.maximum(count - 1, 1).astype(float)
        ext_lam, ext_eta = psd_clip(symmetrize((count[:, None, None] * avg_lam - m_lam) / others[:, None, None]),
                                    (count[:, None] * avg_eta - m_eta) / others[:, None])
    else:
        ext_lam, ext_eta = psd_clip(symmetrize(lam_f0_row + count[:, None, None] * avg_lam - m_lam),
                                    eta_f0_row + count[:, None] * avg_eta - m_eta)
    dep, y, valid = message_moments(np.ascontiguousarray(ext_lam), np.ascontiguousarray(ext_eta), z_u)
    y_f, p_f, r_f, has = combine_messages(owner_u, dep, r_u, y, valid, n)
    comm = broadcast_rounds(owner_u, count >= 2, n, rounds, GAUSSIAN_CONSENSUS_WORDS)
    return m_lam, m_eta, y_f, p_f, r_f, has, comm
