"""Fused numba passes for the per-step bookkeeping of the Gaussian ICP family.

Each kernel replaces a chain of batched numpy calls (``unique``, ``isin``, ``lexsort``, fancy
indexing, ``ufunc.at``) of :mod:`coloc.methods.icp_da_lc` and
:mod:`coloc.inference.feature_store` by one pass over preallocated arrays, with the **same
floating-point operations in the same order**: the estimates are byte for byte those of the
numpy reference (kept beside each dispatch site; ``FUSED = False`` runs it, tests compare the two).

Equation -> function (Brambilla et al.):

* (13), candidate tracks F_i,t and the Gaussian integral N(z_l; m_k - m_i, P_k + P_i + R_l) of
  every (vehicle, candidate track, row): :func:`association_terms_kernel`
  (reference ``candidate_pairs`` / ``candidate_rows`` / ``association_weights`` of icp_da_lc);
* (14)-(17), the per-vehicle BPA-DA problems laid out block by block:
  :func:`association_layout_kernel` (reference ``association_beliefs``);
* (30), the MAP pairing of the detected (vehicle, track) combos with the "gated" rule (a row
  claimed twice goes to the larger belief, ties to the lower combo): :func:`map_pairing_kernel`
  (reference ``_map_decisions`` + ``pairs_from_beliefs``);
* (12)/(20), the information of the shared feature tracks (birth x folded x stored messages,
  latest-message store): :func:`track_information_kernel` (reference
  ``FeatureStore.information``) and the (track, vehicle) membership test of the messages a
  step replaces: :func:`pair_member_kernel` (reference ``np.isin`` on pair keys).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from coloc.kernels.bpa_rows import cholesky4_soa, information_rows, predict_no_input_rows
from coloc.kernels.icp import log_gauss_kernel, rows_by_key
from coloc.kernels.kalman import gnss_step_rows
from coloc.kernels.track_index import candidate_tracks

#: Run the fused kernels (False: the batched numpy reference at every dispatch site).
FUSED = True

#: Relative margin of the gate bound of :func:`association_terms_kernel`: a pair is left unsolved only if
#: |nu_b|^2 > gate * tr S_bb * (1 + margin) for a block b. The computed d2 of such a pair is above the gate too unless its
#: relative rounding error exceeds the margin (that takes a condition number of S near 1e10; the
#: covariances here span position and velocity variances within about 1e6).
GATE_PRUNE_MARGIN = 1e-6


# ----------------------------------------------------------------------------- (13)


@njit(cache=True)
def association_terms_kernel(v_mean, v_cov, t_mean, t_cov, owner, z, r, sensing_range, gate):
    """Every (vehicle i, candidate track k, row l of i) and log N(z_l; m_k - m_i, P_k + P_i + R_l)
    with its squared Mahalanobis distance.

    Candidates: hypot(m_i - m_k) <= Rs + 3 sqrt(tr P_i,pos + tr P_k,pos); pairs ordered by
    vehicle, then track, then row (``np.nonzero`` order, rows by a stable sort on the owner). Each
    vehicle tests only the tracks an index puts within its reach (:func:`coloc.kernels.track_index.candidate_tracks`),
    not all of them: on a city the vehicles x tracks test grew with the square of the vehicles.
    ``gate``: the log-likelihood of a pair with d2 > gate is not computed (0 is returned; the
    caller gives such a pair weight 0 whatever it is); ``inf``: every pair's. A pair that the
    bound d2 >= |nu_b|^2 / tr S_bb puts beyond the gate by :data:`GATE_PRUNE_MARGIN` is not solved
    at all: log N = 0 and d2 = inf (on a city under clutter most (track, row) pairs of a vehicle are
    such pairs). b is the position or the velocity block: the squared Mahalanobis distance of a
    block (its marginal) is at most d2 (Schur complement), and tr S_bb >= the block's largest
    eigenvalue. Per block, as the velocity variances (hundreds of m^2/s^2 on a city) would
    otherwise loosen the bound on the positions.
    Returns (pair_vehicle, pair_track, pair_row, log_lik, d2)."""
    n = v_mean.shape[0]
    start, rows = rows_by_key(owner, n)  # rows of each vehicle, ascending (stable argsort of owner)
    # F_i,t from the tracks indexed by spread class and x (coloc.kernels.track_index): the pairs of the
    # full test, in its order
    c_start, c_track = candidate_tracks(v_mean, v_cov, t_mean, t_cov, sensing_range)
    total = 0
    for i in range(n):
        total += (c_start[i + 1] - c_start[i]) * (start[i + 1] - start[i])
    pv = np.empty(total, dtype=np.int64)
    pt = np.empty(total, dtype=np.int64)
    pr = np.empty(total, dtype=np.int64)
    solve = np.ones(total, dtype=np.bool_)
    prune = gate < np.inf
    bound = gate * (1.0 + GATE_PRUNE_MARGIN)
    n_solve = 0
    p = 0
    for i in range(n):
        for c in range(c_start[i], c_start[i + 1]):
            k = c_track[c]
            for a in range(start[i], start[i + 1]):
                q = rows[a]
                pv[p], pt[p], pr[p] = i, k, q
                if prune:
                    # per block (position, velocity): d2 >= the block's own d2 >= |nu_b|^2 / tr S_bb
                    cut = False
                    for blk in range(2):
                        nn, tr = 0.0, 0.0
                        for c in range(2 * blk, 2 * blk + 2):
                            x = z[q, c] - (t_mean[k, c] - v_mean[i, c])
                            nn += x * x
                            tr += (t_cov[k, c, c] + v_cov[i, c, c]) + r[q, c, c]
                        if nn > bound * tr:  # False with NaN: solved as before
                            cut = True
                    if cut:
                        solve[p] = False
                        p += 1
                        continue
                n_solve += 1
                p += 1
    # the pairs left, solved as one batch with the operations of the unpruned kernel
    nu = np.empty((4, n_solve))
    s = np.empty((16, n_solve))  # the lower triangle is read
    b = 0
    for p in range(total):
        if not solve[p]:
            continue
        i, k, q = pv[p], pt[p], pr[p]
        for c in range(4):
            nu[c, b] = z[q, c] - (t_mean[k, c] - v_mean[i, c])
            for e in range(c + 1):
                s[c * 4 + e, b] = (t_cov[k, c, e] + v_cov[i, c, e]) + r[q, c, e]
        b += 1
    log_solved, d2_solved = _log_gauss4_soa(nu, s, gate)
    log_lik = np.zeros(total)
    d2 = np.full(total, np.inf)
    b = 0
    for p in range(total):
        if solve[p]:
            log_lik[p], d2[p] = log_solved[b], d2_solved[b]
            b += 1
    return pv, pt, pr, log_lik, d2


@njit(cache=True)
def association_log_weights_kernel(v_mean, v_cov, t_mean, t_cov, owner, z, r, sensing_range, gate, new_sigma2,
                                   log_new_const, log_pd):
    """:func:`association_terms_kernel` and the log of eta(alpha = l) of (13) normalised by the density
    of a row from an untracked feature, as ``coloc.methods.icp_da_lc.association_weights`` computes it
    without clutter and field of view (its numpy is the reference): per row
    log N(z_v + m_i,v; 0, P_i,vv + R_vv + s^2 I) (:func:`coloc.kernels.icp.log_gauss_kernel`) plus
    ``log_new_const``, then per pair (``log_pd`` + log_lik) - log_new. Returns (pair_vehicle,
    pair_track, pair_row, log_w, d2)."""
    pv, pt, pr, log_lik, d2 = association_terms_kernel(v_mean, v_cov, t_mean, t_cov, owner, z, r, sensing_range,
                                                       gate)
    o = owner.size
    nu = np.empty((o, 2))
    s = np.empty((o, 2, 2))
    for q in range(o):
        i = owner[q]
        for a in range(2):
            nu[q, a] = z[q, 2 + a] + v_mean[i, 2 + a]
            for b in range(2):  # (P + R) + s^2 I, the identity's zeros added too
                s[q, a, b] = (v_cov[i, 2 + a, 2 + b] + r[q, 2 + a, 2 + b]) + new_sigma2 * (1.0 if a == b else 0.0)
    log_v, _ = log_gauss_kernel(nu, s)
    log_w = np.empty(pr.size)
    for p in range(pr.size):
        log_w[p] = (log_pd + log_lik[p]) - (log_new_const + log_v[pr[p]])
    return pv, pt, pr, log_w, d2


@njit(cache=True)
def _log_gauss4_soa(nu, s, gate=np.inf):
    """:func:`coloc.kernels.icp.log_gauss_kernel` (d = 4) for every column of ``nu`` (4, P) / ``s`` (16, P), each scalar
    step one loop over the columns (SIMD; the same operations per column); NaN where S is not PD.
    Columns whose squared distance is above ``gate`` get log N = 0 (their logarithms are skipped)."""
    p = nu.shape[1]
    l = np.empty((16, p))
    w = np.empty((4, p))
    acc = np.empty(p)
    ok = np.ones(p, dtype=np.bool_)
    cholesky4_soa(s, l, ok, acc)
    q = np.zeros(p)
    logdet = np.zeros(p)
    for i in range(4):
        nui = nu[i]
        for r in range(p):
            acc[r] = nui[r]
        for k in range(i):
            lik, wk = l[i * 4 + k], w[k]
            for r in range(p):
                acc[r] -= lik[r] * wk[r]
        lii, wi = l[i * 4 + i], w[i]
        for r in range(p):
            wi[r] = acc[r] / lii[r]
            q[r] += wi[r] * wi[r]
    log2pi = np.log(2.0 * np.pi)
    log_pdf = np.empty(p)
    for r in range(p):
        if ok[r]:
            if q[r] > gate:
                log_pdf[r] = 0.0
                continue
            for i in range(4):  # logdet = 0 + log l_00 + ... + log l_33, in this order
                logdet[r] += np.log(l[i * 4 + i, r])
            log_pdf[r] = -0.5 * (q[r] + 2.0 * logdet[r] + 4 * log2pi)
        else:
            log_pdf[r], q[r] = np.nan, np.nan
    return log_pdf, q


@njit(cache=True)
def lower_bound(a, x):
    """``np.searchsorted(a, x)`` (side "left") for an ascending int64 ``a`` and a scalar ``x``, by a
    binary search whose steps are selects rather than branches (no mispredictions on fresh data)."""
    n = a.size
    if n == 0:
        return 0
    base = 0
    while n > 1:
        half = n >> 1
        base = base + half if a[base + half] < x else base
        n -= half
    return base + 1 if a[base] < x else base


# ----------------------------------------------------------------------------- (14)-(17)


@njit(cache=True)
def _unique_inverse(keys):
    """Sorted unique values of ``keys`` and the index of every key among them. Keys within a range
    of at most 16 per key (feature and track ids, pair keys of a step) by a table over the range,
    others by a sort."""
    n = keys.size
    if n == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    lo, hi = keys[0], keys[0]
    for a in range(n):
        lo = min(lo, keys[a])
        hi = max(hi, keys[a])
    if hi - lo > 16 * n + 64:
        return _unique_inverse_sort(keys)
    slot = np.full(hi - lo + 1, -1, dtype=np.int64)
    for a in range(n):
        slot[keys[a] - lo] = 0
    u = 0
    for k in range(slot.size):
        if slot[k] == 0:
            slot[k] = u
            u += 1
    uniq = np.empty(u, dtype=np.int64)
    for k in range(slot.size):
        if slot[k] >= 0:
            uniq[slot[k]] = lo + k
    inv = np.empty(n, dtype=np.int64)
    for a in range(n):
        inv[a] = slot[keys[a] - lo]
    return uniq, inv


@njit(cache=True)
def _unique_inverse_sort(keys):
    """:func:`_unique_inverse` by a sort (any range)."""
    srt = np.sort(keys)
    uniq = np.empty(keys.size, dtype=np.int64)
    u = -1
    for a in range(srt.size):
        if u < 0 or srt[a] != uniq[u]:
            u += 1
            uniq[u] = srt[a]
    uniq = uniq[: u + 1]
    inv = np.searchsorted(uniq, keys)
    return uniq, inv


@njit(cache=True)
def repeated_pair(owner, feature):
    """Whether two rows with ``feature`` >= 0 have the same (owner, feature) (the ``np.unique`` test of
    ``coloc.inference.bpa.validate_association``): rows grouped by feature, each group's owners
    stamped in a table over the owners."""
    o = owner.size
    n_used = 0
    for q in range(o):
        if feature[q] >= 0:
            n_used += 1
    if n_used < 2:
        return False
    rows = np.empty(n_used, dtype=np.int64)
    j = 0
    for q in range(o):
        if feature[q] >= 0:
            rows[j] = q
            j += 1
    fu = np.empty(n_used, dtype=np.int64)
    lo, hi = owner[rows[0]], owner[rows[0]]
    for j in range(n_used):
        fu[j] = feature[rows[j]]
        lo = min(lo, owner[rows[j]])
        hi = max(hi, owner[rows[j]])
    uniq, inv = _unique_inverse(fu)
    start, order = rows_by_key(inv, uniq.size)
    if hi - lo > 16 * n_used + 64:  # owners spread out: compare the keys by a sort
        key = np.empty(n_used, dtype=np.int64)
        for j in range(n_used):
            key[j] = inv[j] * (hi - lo + 1) + (owner[rows[j]] - lo)
        srt = np.sort(key)
        for j in range(1, n_used):
            if srt[j] == srt[j - 1]:
                return True
        return False
    stamp = np.full(hi - lo + 1, -1, dtype=np.int64)
    for g in range(uniq.size):
        for a in range(start[g], start[g + 1]):
            v = owner[rows[order[a]]] - lo
            if stamp[v] == g:
                return True
            stamp[v] = g
    return False


def unique_inverse(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_inverse=True)`` for int64 keys (FUSED; else numpy itself)."""
    keys = np.ascontiguousarray(keys, dtype=np.int64)
    if not FUSED:
        return np.unique(keys, return_inverse=True)
    return _unique_inverse(keys)


@njit(cache=True)
def association_layout_kernel(pv, pt, pr, w, missed, n_vehicles):
    """The BPA-DA problems of all vehicles (one per vehicle with a pair of positive weight),
    laid out as :func:`coloc.inference.association.association_marginals_batch` takes them.

    ``missed`` (P,): eta(alpha = 0) of each pair's combo (equal over a combo's pairs).
    Returns (eta, k_sizes, m_sizes, combo_vehicle, combo_track, combo_start, combo_rows,
    combo_row_first, rows_sorted): combos = (vehicle, track) with a positive weight sorted by
    key vehicle * n_t + track; rows sorted by (vehicle, row)."""
    keep = np.flatnonzero(w > 0)
    nk = keep.size
    n_t = 1
    for a in range(nk):
        if pt[keep[a]] + 1 > n_t:
            n_t = pt[keep[a]] + 1
    ckey = np.empty(nk, dtype=np.int64)
    rkey = np.empty(nk, dtype=np.int64)
    for a in range(nk):
        ckey[a] = pv[keep[a]] * n_t + pt[keep[a]]
        rkey[a] = pr[keep[a]]
    combo, c_inv = _unique_inverse(ckey)
    rows_u, r_inv = _unique_inverse(rkey)
    nc, nr = combo.size, rows_u.size
    c_vehicle = combo // n_t
    c_track = combo % n_t
    r_vehicle = np.zeros(nr, dtype=np.int64)
    for a in range(nk):
        r_vehicle[r_inv[a]] = pv[keep[a]]
    # rows sorted by (vehicle, row): rows_u is ascending, so a stable sort on the vehicle
    order_r = np.argsort(r_vehicle, kind="mergesort")
    rank_r = np.empty(nr, dtype=np.int64)
    for a in range(nr):
        rank_r[order_r[a]] = a
    k_all = np.zeros(n_vehicles, dtype=np.int64)
    m_all = np.zeros(n_vehicles, dtype=np.int64)
    for c in range(nc):
        k_all[c_vehicle[c]] += 1
    for a in range(nr):
        m_all[r_vehicle[a]] += 1
    prob_of_vehicle = np.full(n_vehicles, -1, dtype=np.int64)
    n_prob = 0
    for i in range(n_vehicles):
        if k_all[i] > 0:
            prob_of_vehicle[i] = n_prob
            n_prob += 1
    k_sizes = np.empty(n_prob, dtype=np.int64)
    m_sizes = np.empty(n_prob, dtype=np.int64)
    block_off = np.empty(n_prob, dtype=np.int64)
    c_first = np.empty(n_prob, dtype=np.int64)
    r_first = np.empty(n_prob, dtype=np.int64)
    tot_b, tot_c, tot_r = 0, 0, 0
    for i in range(n_vehicles):
        g = prob_of_vehicle[i]
        if g < 0:
            continue
        k_sizes[g], m_sizes[g] = k_all[i], m_all[i]
        block_off[g], c_first[g], r_first[g] = tot_b, tot_c, tot_r
        tot_b += k_all[i] * (m_all[i] + 1)
        tot_c += k_all[i]
        tot_r += m_all[i]
    c_start = np.empty(nc, dtype=np.int64)
    c_rows = np.empty(nc, dtype=np.int64)
    c_row_first = np.empty(nc, dtype=np.int64)
    for c in range(nc):
        g = prob_of_vehicle[c_vehicle[c]]
        c_start[c] = block_off[g] + (c - c_first[g]) * (m_sizes[g] + 1)
        c_rows[c] = m_sizes[g]
        c_row_first[c] = r_first[g]
    eta = np.zeros(tot_b)
    for a in range(nk):
        eta[c_start[c_inv[a]]] = missed[keep[a]]
    for a in range(nk):
        g = prob_of_vehicle[pv[keep[a]]]
        eta[c_start[c_inv[a]] + 1 + rank_r[r_inv[a]] - r_first[g]] = w[keep[a]]
    rows_sorted = np.empty(nr, dtype=np.int64)
    for a in range(nr):
        rows_sorted[a] = rows_u[order_r[a]]
    return eta, k_sizes, m_sizes, c_vehicle, c_track, c_start, c_rows, c_row_first, rows_sorted


# ----------------------------------------------------------------------------- (30)


@njit(cache=True)
def map_pairing_kernel(pf, combo_start, combo_rows, combo_row_first, rows, combo_track, n_rows, threshold,
                       use_threshold):
    """MAP pairing (30), rule "gated": per combo the best row (largest belief, ties to the lowest
    option; detected iff that belief is > 0 and, with ``use_threshold``, b(alpha = 0) < eta_TH);
    a row claimed by several detected combos goes to the larger belief, ties to the lower combo.
    Returns the track index paired with each row (-1 = none)."""
    row_track = np.full(n_rows, -1, dtype=np.int64)
    row_val = np.zeros(n_rows)
    for c in range(combo_start.size):
        best = 0.0
        for opt in range(combo_rows[c]):
            v = pf[combo_start[c] + 1 + opt]
            if v > best or v != v:  # np.maximum: NaN wins
                best = v
        if not best > 0.0:
            continue
        if use_threshold and not pf[combo_start[c]] < threshold:
            continue
        best_opt = 0
        for opt in range(combo_rows[c]):
            if pf[combo_start[c] + 1 + opt] == best:
                best_opt = opt
                break
        q = rows[combo_row_first[c] + best_opt]
        if row_track[q] < 0 or best > row_val[q]:
            row_track[q] = combo_track[c]
            row_val[q] = best
    return row_track


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
def predict_store_kernel(folded_lam, folded_eta, q, msg_rows, msg_mean, msg_cov, dt):
    """Eq. (12) on the track store (``FeatureStore.predict``, the same numbers): every nonzero folded
    part to moments, predicted by model (2) with its track's Q_F, back to information; every stored
    message predicted with its track's Q_F (``msg_rows``), and its information (:func:`information_rows`,
    as ``to_information`` gives it). Returns (folded_lam, folded_eta, msg_mean, msg_cov, msg_lam, msg_eta)."""
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
            fq[j] = q[idx[j]]
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


# ----------------------------------------------------------------------------- merging (LC step 8)


@njit(cache=True)
def any_pair_within(xy, radius):
    """True when two rows of ``xy`` (T, 2) are within ``radius`` of each other, with a relative
    margin of 1e-9 (a pre-check: False means no pair is within ``radius`` by any rounding)."""
    t = xy.shape[0]
    r2 = (radius * (1.0 + 1e-9)) ** 2
    for a in range(t):
        for b in range(a + 1, t):
            dx = xy[a, 0] - xy[b, 0]
            dy = xy[a, 1] - xy[b, 1]
            if not dx * dx + dy * dy > r2:  # NaN: "maybe"
                return True
    return False
