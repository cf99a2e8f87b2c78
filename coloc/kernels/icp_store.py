"""Fused numba passes for the shared feature-track store of the Gaussian ICP family and the per-step carry of
the vehicles' GNSS beliefs (the bookkeeping half of :mod:`coloc.kernels.icp_fused`, whose module docstring
states the contract: the same floating-point operations in the same order as the numpy reference beside
each dispatch site).

Equation -> function (Brambilla et al.):

* (12)/(20), the information of the shared feature tracks (birth x folded x stored messages,
  latest-message store): :func:`track_information_kernel` (reference ``FeatureStore.information``),
  the store after a step :func:`record_kernel` (``FeatureStore.record``), its prediction
  :func:`predict_store_kernel`, and the (track, vehicle) membership test of the messages a step
  replaces: :func:`pair_member_kernel` / :func:`pair_member_table` (reference ``np.isin`` on pair keys);
* (11), the carried GNSS beliefs of the vehicles: :func:`carry_gnss_kernel`;
* the step's feature beliefs: :func:`step_beliefs_kernel`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from coloc.kernels.bpa_rows import information_rows, predict_no_input_rows
from coloc.kernels.kalman import gnss_step_rows
from coloc.kernels.sorted_keys import _unique_inverse, lower_bound

# ----------------------------------------------------------------------------- (12), (20)


@njit(cache=True)
def pair_member_kernel(keys, sorted_keys):
    """``np.isin(keys, sorted_keys)`` for int64 keys, ``sorted_keys`` ascending."""
    out = np.zeros(keys.size, dtype=np.bool_)
    m = sorted_keys.size
    if m == 0:
        return out
    for a in range(keys.size):
        pos = lower_bound(sorted_keys, keys[a])
        out[a] = pos < m and sorted_keys[pos] == keys[a]
    return out


@njit(cache=True)
def pair_member_table(msg_track, msg_codes, row_track, row_codes):
    """``np.isin(msg_track * 2^32 + msg_codes, row_track * 2^32 + row_codes)`` (the (track, vehicle)
    pairs of the messages among the rows'): the rows' pairs marked in a table over their tracks and
    vehicles; keys outside [0, 2^32) or spread-out ids go to :func:`pair_member_kernel`."""
    n_m, n_r = msg_track.size, row_track.size
    out = np.zeros(n_m, dtype=np.bool_)
    if n_r == 0:
        return out
    tlo, thi, clo, chi = row_track[0], row_track[0], row_codes[0], row_codes[0]
    for q in range(n_r):
        tlo, thi = min(tlo, row_track[q]), max(thi, row_track[q])
        clo, chi = min(clo, row_codes[q]), max(chi, row_codes[q])
    ok = tlo >= 0 and clo >= 0 and chi < (1 << 32) and thi - tlo <= 16 * n_r + 4096 and chi - clo <= 16 * n_r + 4096
    for q in range(n_m):
        ok = ok and msg_track[q] >= 0 and 0 <= msg_codes[q] < (1 << 32)
    if not ok:
        km = np.empty(n_m, dtype=np.int64)
        kr = np.empty(n_r, dtype=np.int64)
        for q in range(n_m):
            km[q] = msg_track[q] * (1 << 32) + msg_codes[q]
        for q in range(n_r):
            kr[q] = row_track[q] * (1 << 32) + row_codes[q]
        return pair_member_kernel(km, np.sort(kr))
    ttab = np.full(thi - tlo + 1, -1, dtype=np.int64)
    vtab = np.full(chi - clo + 1, -1, dtype=np.int64)
    nt, nv = 0, 0
    for q in range(n_r):
        if ttab[row_track[q] - tlo] < 0:
            ttab[row_track[q] - tlo] = nt
            nt += 1
        if vtab[row_codes[q] - clo] < 0:
            vtab[row_codes[q] - clo] = nv
            nv += 1
    mark = np.zeros(nt * nv, dtype=np.bool_)
    for q in range(n_r):
        mark[ttab[row_track[q] - tlo] * nv + vtab[row_codes[q] - clo]] = True
    for q in range(n_m):
        t, c = msg_track[q], msg_codes[q]
        if tlo <= t <= thi and clo <= c <= chi:
            ti, vi = ttab[t - tlo], vtab[c - clo]
            if ti >= 0 and vi >= 0:
                out[q] = mark[ti * nv + vi]
    return out


@njit(cache=True)
def lookup_kernel(ids, feature_ids):
    """Row of each id in the ascending ``ids``, -1 where absent (``FeatureStore.lookup``)."""
    out = np.full(feature_ids.size, -1, dtype=np.int64)
    m = ids.size
    if m == 0:
        return out
    for a in range(feature_ids.size):
        pos = lower_bound(ids, feature_ids[a])
        if pos > m - 1:
            pos = m - 1
        if ids[pos] == feature_ids[a]:
            out[a] = pos
    return out


@njit(cache=True)
def track_information_kernel(folded_lam, folded_eta, birth_lam, ids, msg_track, msg_lam, msg_eta, use):
    """(Lambda, eta) of every track: sym((folded + birth) + the used messages added in message
    order), eta = folded + messages. ``birth_lam`` (T, 4, 4) per track, or (1, 4, 4) for all."""
    t = ids.size
    lam = np.empty((t, 4, 4))
    eta = np.empty((t, 4))
    for k in range(t):
        kb = min(k, birth_lam.shape[0] - 1)
        for a in range(4):
            for b in range(4):
                lam[k, a, b] = folded_lam[k, a, b] + birth_lam[kb, a, b]
            eta[k, a] = folded_eta[k, a]
    rows = lookup_kernel(ids, msg_track)
    for q in range(msg_track.size):
        if not use[q]:
            continue
        k = rows[q]
        for a in range(4):
            for b in range(4):
                lam[k, a, b] = lam[k, a, b] + msg_lam[q, a, b]
            eta[k, a] = eta[k, a] + msg_eta[q, a]
    out = np.empty((t, 4, 4))
    for k in range(t):
        for a in range(4):
            for b in range(4):
                out[k, a, b] = 0.5 * (lam[k, a, b] + lam[k, b, a])
    return out, eta


@njit(cache=True)
def track_moments_kernel(folded_lam, folded_eta, birth_lam, ids, msg_track, msg_lam, msg_eta, use):
    """:func:`track_information_kernel` and the moments of its result (``from_information``:
    :func:`information_rows`) in one call. Returns (Lambda, eta, mean, cov)."""
    lam, eta = track_information_kernel(folded_lam, folded_eta, birth_lam, ids, msg_track, msg_lam, msg_eta, use)
    cov, mean = information_rows(eta, lam)
    return lam, eta, mean, cov


@njit(cache=True)
def record_kernel(ids, last_seen, folded_lam, folded_eta, msg_track, msg_mean, msg_cov, msg_time, keep,
                  row_feature, mm, mc, t, old_before, drop_after, msg_lam, msg_eta, ml, me):
    """The latest-message store after a step (``FeatureStore.record``): new tracks for new ids
    (ids stay sorted), last_seen = t for every observed track, the kept old messages then the
    step's (``mm``/``mc``, time t), messages older than ``old_before`` folded into their track in
    information form (added in message order), tracks unseen for more than ``drop_after`` dropped
    with their messages, folded parts symmetrised.

    Returns (ids, last_seen, folded_lam, folded_eta, track_src, msg_src, msg_track, msg_mean,
    msg_cov, msg_time, msg_lam, msg_eta): ``track_src`` >= 0 an old track's row, -1 - r a new track
    first seen in row r; ``msg_src`` each message's index in [old messages, the step's rows];
    ``msg_lam``, ``msg_eta``: the kept messages' information, taken from the old messages'
    (``msg_lam``, ``msg_eta`` given) and the step's (``ml``, ``me``) by ``msg_src``."""
    n_old, n_msg, o = ids.size, msg_track.size, row_feature.size
    uniq, _ = _unique_inverse(row_feature)
    first = np.full(uniq.size, o, dtype=np.int64)
    for q in range(o):
        u = lower_bound(uniq, row_feature[q])
        if q < first[u]:
            first[u] = q
    in_old = lookup_kernel(ids, uniq)
    n_new = 0
    for u in range(uniq.size):
        if in_old[u] < 0:
            n_new += 1
    # merge the sorted old ids and the sorted new ids
    nt = n_old + n_new
    ids2 = np.empty(nt, dtype=np.int64)
    src = np.empty(nt, dtype=np.int64)
    a, b, k = 0, 0, 0
    while k < nt:
        while b < uniq.size and in_old[b] >= 0:
            b += 1
        if b >= uniq.size or (a < n_old and ids[a] < uniq[b]):
            ids2[k], src[k] = ids[a], a
            a += 1
        else:
            ids2[k], src[k] = uniq[b], -1 - first[b]
            b += 1
        k += 1
    seen2 = np.empty(nt)
    f_lam = np.zeros((nt, 4, 4))
    f_eta = np.zeros((nt, 4))
    for k in range(nt):
        if src[k] >= 0:
            seen2[k] = last_seen[src[k]]
            for c in range(4):
                for e in range(4):
                    f_lam[k, c, e] = folded_lam[src[k], c, e]
                f_eta[k, c] = folded_eta[src[k], c]
        else:
            seen2[k] = t
    for u in range(uniq.size):
        seen2[lower_bound(ids2, uniq[u])] = t
    # messages: kept old ones, then the step's; fold the old ones
    m_src = np.empty(n_msg + o, dtype=np.int64)
    m_time = np.empty(n_msg + o)
    m = 0
    for q in range(n_msg):
        if keep[q]:
            m_src[m], m_time[m] = q, msg_time[q]
            m += 1
    for q in range(o):
        m_src[m], m_time[m] = n_msg + q, t
        m += 1
    n_fold = 0
    for q in range(m):
        if m_time[q] < old_before:
            n_fold += 1
    if n_fold:
        om = np.empty((n_fold, 4))
        oc = np.empty((n_fold, 4, 4))
        orow = np.empty(n_fold, dtype=np.int64)
        j = 0
        for q in range(m):
            if m_time[q] < old_before:
                s = m_src[q]
                tr = msg_track[s] if s < n_msg else row_feature[s - n_msg]
                for c in range(4):
                    om[j, c] = msg_mean[s, c] if s < n_msg else mm[s - n_msg, c]
                    for e in range(4):
                        oc[j, c, e] = msg_cov[s, c, e] if s < n_msg else mc[s - n_msg, c, e]
                orow[j] = lower_bound(ids2, tr)
                j += 1
        ol, oe = information_rows(om, oc)  # byte for byte information_kernel
        for j in range(n_fold):
            k = orow[j]
            for c in range(4):
                for e in range(4):
                    f_lam[k, c, e] = f_lam[k, c, e] + ol[j, c, e]
                f_eta[k, c] = f_eta[k, c] + oe[j, c]
    live = np.empty(nt, dtype=np.bool_)
    n_live = 0
    for k in range(nt):
        live[k] = (t - seen2[k]) <= drop_after
        if live[k]:
            n_live += 1
    out_ids = np.empty(n_live, dtype=np.int64)
    out_seen = np.empty(n_live)
    out_lam = np.empty((n_live, 4, 4))
    out_eta = np.empty((n_live, 4))
    out_src = np.empty(n_live, dtype=np.int64)
    j = 0
    for k in range(nt):
        if not live[k]:
            continue
        out_ids[j], out_seen[j], out_src[j] = ids2[k], seen2[k], src[k]
        for c in range(4):
            for e in range(4):
                out_lam[j, c, e] = 0.5 * (f_lam[k, c, e] + f_lam[k, e, c])
            out_eta[j, c] = f_eta[k, c]
        j += 1
    n_keep = 0
    for q in range(m):
        s = m_src[q]
        tr = msg_track[s] if s < n_msg else row_feature[s - n_msg]
        if not m_time[q] < old_before and live[lower_bound(ids2, tr)]:
            n_keep += 1
    k_src = np.empty(n_keep, dtype=np.int64)
    k_track = np.empty(n_keep, dtype=np.int64)
    k_mean = np.empty((n_keep, 4))
    k_cov = np.empty((n_keep, 4, 4))
    k_time = np.empty(n_keep)
    k_lam = np.empty((n_keep, 4, 4))
    k_eta = np.empty((n_keep, 4))
    j = 0
    for q in range(m):
        s = m_src[q]
        tr = msg_track[s] if s < n_msg else row_feature[s - n_msg]
        if m_time[q] < old_before or not live[lower_bound(ids2, tr)]:
            continue
        k_src[j], k_track[j], k_time[j] = s, tr, m_time[q]
        for c in range(4):
            k_mean[j, c] = msg_mean[s, c] if s < n_msg else mm[s - n_msg, c]
            k_eta[j, c] = msg_eta[s, c] if s < n_msg else me[s - n_msg, c]
            for e in range(4):
                k_cov[j, c, e] = msg_cov[s, c, e] if s < n_msg else mc[s - n_msg, c, e]
                k_lam[j, c, e] = msg_lam[s, c, e] if s < n_msg else ml[s - n_msg, c, e]
        j += 1
    return out_ids, out_seen, out_lam, out_eta, out_src, k_src, k_track, k_mean, k_cov, k_time, k_lam, k_eta


# ----------------------------------------------------------------------------- (11)


@njit(cache=True)
def carry_gnss_kernel(mean_a, cov_a, mean_b, cov_b, match, fresh, prior_z, prior_r, accel, z, r, dt, s_along,
                      s_cross, min_speed):
    """b_i^(0) of (11) for two carried tracks of every vehicle (the belief and the own-sensor one):
    the previous step's rows (``match``) or, where ``fresh``, the fast-start prior, then
    :func:`coloc.kernels.kalman.gnss_step_kernel` on each (by :func:`coloc.kernels.kalman.gnss_step_rows`;
    ``coloc.core.vehicles.carry_states`` +
    ``vehicle_prior_beliefs`` twice, the same numbers). Returns (mean_a, cov_a, mean_b, cov_b)."""
    n = match.size
    out = (np.empty((n, 4)), np.empty((n, 4, 4)), np.empty((n, 4)), np.empty((n, 4, 4)))
    for i in range(n):
        for c in range(4):
            if fresh[i]:
                out[0][i, c] = prior_z[i, c]
                out[2][i, c] = prior_z[i, c]
            else:
                out[0][i, c] = mean_a[match[i], c]
                out[2][i, c] = mean_b[match[i], c]
            for e in range(4):
                if fresh[i]:
                    out[1][i, c, e] = prior_r[i, c, e]
                    out[3][i, c, e] = prior_r[i, c, e]
                else:
                    out[1][i, c, e] = cov_a[match[i], c, e]
                    out[3][i, c, e] = cov_b[match[i], c, e]
    predict = ~fresh
    # gnss_step_kernel across the vehicles (coloc.kernels.kalman.gnss_step_rows, the same numbers)
    gnss_step_rows(out[0], out[1], accel, z, r, predict, dt, s_along, s_cross, min_speed)
    gnss_step_rows(out[2], out[3], accel, z, r, predict, dt, s_along, s_cross, min_speed)
    return out


# ----------------------------------------------------------------------------- (12)


@njit(cache=True)
def predict_store_kernel(folded_lam, folded_eta, q, q_folded, msg_rows, msg_mean, msg_cov, dt):
    """Eq. (12) on the track store (``FeatureStore.predict``, the same numbers): every nonzero folded
    part to moments, predicted by model (2) with its track's ``q_folded`` (Q_F, or Q_F with the map's
    drift), back to information; every stored message predicted with its track's Q_F ``q``
    (``msg_rows``), and its information (:func:`information_rows`, as ``to_information`` gives it).
    Returns (folded_lam, folded_eta, msg_mean, msg_cov, msg_lam, msg_eta)."""
    t = folded_lam.shape[0]
    out_lam = folded_lam.copy()
    out_eta = folded_eta.copy()
    has = np.zeros(t, dtype=np.bool_)
    for k in range(t):
        nz, nan = False, False
        for a in range(4):
            for b in range(4):
                v = folded_lam[k, a, b]
                if v != v:
                    nan = True
                elif v != 0.0:
                    nz = True
        has[k] = nz and not nan  # np.abs(lam).sum() > 0
    idx = np.flatnonzero(has)
    if idx.size:
        fl = np.empty((idx.size, 4, 4))
        fe = np.empty((idx.size, 4))
        fq = np.empty((idx.size, 4, 4))
        for j in range(idx.size):
            fl[j] = folded_lam[idx[j]]
            fe[j] = folded_eta[idx[j]]
            fq[j] = q_folded[idx[j]]
        fp, fm = information_rows(fe, fl)  # from_information: (P, m) = (Lambda^-1, Lambda^-1 eta)
        fm, fp = predict_no_input_rows(fm, fp, fq, dt)  # byte for byte predict_no_input_kernel
        nl, ne = information_rows(fm, fp)
        for j in range(idx.size):
            out_lam[idx[j]] = nl[j]
            out_eta[idx[j]] = ne[j]
    mq = np.empty((msg_rows.size, 4, 4))
    for j in range(msg_rows.size):
        mq[j] = q[msg_rows[j]]
    mm, mc = predict_no_input_rows(msg_mean, msg_cov, mq, dt)
    ml, me = information_rows(mm, mc)  # the messages' (Lambda, eta): FeatureStore._message_information
    return out_lam, out_eta, mm, mc, ml, me


@njit(cache=True)
def message_round_trip(msg_lam, msg_eta):
    """The step's messages (Lambda, eta) to moments and back, as ``FeatureStore.record`` keeps them:
    (mean, cov) = from_information, then (Lambda', eta') = to_information of those (both
    :func:`information_rows`). Returns (mean, cov, Lambda', eta')."""
    cov, mean = information_rows(msg_eta, msg_lam)
    lam, eta = information_rows(mean, cov)
    return mean, cov, lam, eta


@njit(cache=True)
def step_beliefs_kernel(lam, eta, rows, final_lam, kept_lam, final_eta, kept_eta):
    """Eq. (20) after BPA-L (``coloc.inference.bpa.step_feature_beliefs``, the same numbers): each
    row's kept message swapped for its final one in the tracks' information (added in row order),
    symmetrised, to moments. Returns (mean, cov)."""
    for q in range(rows.size):
        k = rows[q]
        for a in range(4):
            for b in range(4):
                lam[k, a, b] = lam[k, a, b] + (final_lam[q, a, b] - kept_lam[q, a, b])
        for a in range(4):
            eta[k, a] = eta[k, a] + (final_eta[q, a] - kept_eta[q, a])
    t = lam.shape[0]
    sym = np.empty((t, 4, 4))
    for k in range(t):
        for a in range(4):
            for b in range(4):
                sym[k, a, b] = 0.5 * (lam[k, a, b] + lam[k, b, a])
    cov, mean = information_rows(eta, sym)
    return mean, cov
