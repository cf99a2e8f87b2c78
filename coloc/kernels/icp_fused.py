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
* (12)/(20), the shared feature-track store and the carried GNSS beliefs: :mod:`coloc.kernels.icp_store`
  (its kernels are importable from here too); sorted keys: :mod:`coloc.kernels.sorted_keys`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from coloc.kernels.bpa_rows import cholesky4_soa
from coloc.kernels.icp import log_gauss_kernel, rows_by_key
from coloc.kernels.icp_store import (  # noqa: F401  (the store's kernels, imported from here by their callers)
    carry_gnss_kernel,
    lookup_kernel,
    message_round_trip,
    pair_member_kernel,
    pair_member_table,
    predict_store_kernel,
    record_kernel,
    step_beliefs_kernel,
    track_information_kernel,
    track_moments_kernel,
)
from coloc.kernels.sorted_keys import _unique_inverse, _unique_inverse_sort, lower_bound  # noqa: F401
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


# ----------------------------------------------------------------------------- (14)-(17)


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
