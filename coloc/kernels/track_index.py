"""Candidate tracks of each vehicle, F_i,t of (13) (Brambilla et al.): the tracks whose predicted
position is within the vehicle's sensing range plus three standard deviations,

    hypot(m_i - m_k) <= Rs + 3 sqrt(tr P_i,pos + tr P_k,pos),

found through an index instead of testing every (vehicle, track) pair, with the pairs of the full
test in its order (by vehicle, then by track). The reference is ``candidate_pairs`` of
:mod:`coloc.methods.icp_da_lc` (``np.nonzero`` of the full test); tests compare the two.

The index: the tracks are split into spread classes (tr P_k,pos within a factor of 4 of each other)
and each class is sorted by x. A vehicle scans, in each class, only the tracks within that class's
reach along x (the test's threshold with the class's largest spread), so a few wide tracks widen
the scan of their own class only; tracks with no finite x or spread, and vehicles with no finite
position or spread, are tested as the full test does.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Spread classes: class c >= 1 holds the tracks with 4^(c-1) < tr P_k,pos <= 4^c (m^2), class 0 those up
#: to 1 m^2, the last class everything wider. Any split gives the same pairs; this one keeps each class's
#: reach within a factor of 2 of its narrowest track's.
N_SPREAD_CLASSES = 16


@njit(cache=True)
def _spread_class(tr):
    c = 0
    bound = 1.0
    while c < N_SPREAD_CLASSES - 1 and tr > bound:
        bound *= 4.0
        c += 1
    return c


@njit(cache=True)
def candidate_tracks(v_mean, v_cov, t_mean, t_cov, sensing_range):
    """F_i,t of every vehicle. Returns (start (n + 1,), track): vehicle i's candidates are
    ``track[start[i]:start[i + 1]]``, ascending; the pairs are those of the full test, in its order."""
    n, nt = v_mean.shape[0], t_mean.shape[0]
    tr_t = np.empty(nt)
    for k in range(nt):
        tr_t[k] = t_cov[k, 0, 0] + t_cov[k, 1, 1]
    # the index: per class, the tracks by x (ascending, ties by index); the rest in `other`
    cls = np.full(nt, -1, dtype=np.int64)
    count = np.zeros(N_SPREAD_CLASSES + 1, dtype=np.int64)
    tr_max = np.full(N_SPREAD_CLASSES, -np.inf)
    n_other = 0
    for k in range(nt):
        if np.isfinite(t_mean[k, 0]) and np.isfinite(tr_t[k]):
            c = _spread_class(tr_t[k])
            cls[k] = c
            count[c + 1] += 1
            if tr_t[k] > tr_max[c]:
                tr_max[c] = tr_t[k]
        else:
            n_other += 1
    for c in range(N_SPREAD_CLASSES):
        count[c + 1] += count[c]
    members = np.empty(nt - n_other, dtype=np.int64)
    other = np.empty(n_other, dtype=np.int64)
    fill = count[:N_SPREAD_CLASSES].copy()
    b = 0
    for k in range(nt):
        if cls[k] >= 0:
            members[fill[cls[k]]] = k
            fill[cls[k]] += 1
        else:
            other[b] = k
            b += 1
    by_x = np.empty_like(members)
    xs = np.empty(members.size)
    for c in range(N_SPREAD_CLASSES):
        lo, hi = count[c], count[c + 1]
        if hi > lo:
            seg = members[lo:hi]
            order = np.argsort(t_mean[seg, 0], kind="mergesort")
            for j in range(hi - lo):
                by_x[lo + j] = seg[order[j]]
                xs[lo + j] = t_mean[seg[order[j]], 0]
    start = np.zeros(n + 1, dtype=np.int64)
    track = np.empty(max(8 * n, 16), dtype=np.int64)
    window = np.empty(nt, dtype=np.int64)
    for i in range(n):
        tr_v = v_cov[i, 0, 0] + v_cov[i, 1, 1]
        vx, vy = v_mean[i, 0], v_mean[i, 1]
        w = 0
        if np.isfinite(vx) and np.isfinite(vy) and np.isfinite(tr_v):
            for c in range(N_SPREAD_CLASSES):
                lo, hi = count[c], count[c + 1]
                if hi == lo:
                    continue
                # a bound on the threshold of every track of the class (each rounding step is monotone),
                # with a margin far above hypot's error: a track farther along x or y is surely out
                reach = (sensing_range + 3.0 * np.sqrt(tr_v + tr_max[c])) * (1.0 + 1e-9)
                pad = reach + 1e-6 * (abs(vx) + reach) + 1e-6  # far above the rounding of x_i - x_k
                a = lo + np.searchsorted(xs[lo:hi], vx - pad)
                e = lo + np.searchsorted(xs[lo:hi], vx + pad, side="right")
                for j in range(a, e):
                    k = by_x[j]
                    if abs(vx - t_mean[k, 0]) > reach or abs(vy - t_mean[k, 1]) > reach:
                        continue
                    window[w] = k
                    w += 1
            for j in range(other.size):
                window[w] = other[j]
                w += 1
            window[:w].sort()
        else:  # the full scan
            for k in range(nt):
                window[w] = k
                w += 1
        start[i + 1] = start[i]
        for j in range(w):
            k = window[j]
            d = np.hypot(vx - t_mean[k, 0], vy - t_mean[k, 1])
            if d <= sensing_range + 3.0 * np.sqrt(tr_v + tr_t[k]):
                if start[i + 1] == track.size:
                    grown = np.empty(2 * track.size, dtype=np.int64)
                    grown[:track.size] = track
                    track = grown
                track[start[i + 1]] = k
                start[i + 1] += 1
    return start, track[:start[n]]


@njit(cache=True)
def candidate_pairs_kernel(v_mean, v_cov, t_mean, t_cov, sensing_range):
    """:func:`candidate_tracks` as (vehicle, track) pairs, ordered by vehicle then track."""
    start, track = candidate_tracks(v_mean, v_cov, t_mean, t_cov, sensing_range)
    vi = np.empty(track.size, dtype=np.int64)
    for i in range(start.size - 1):
        for c in range(start[i], start[i + 1]):
            vi[c] = i
    return vi, track.copy()
