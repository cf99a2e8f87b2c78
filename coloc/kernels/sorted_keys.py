"""Sorted int64 keys in numba: the binary search and the unique-with-inverse of the fused ICP passes
(:mod:`coloc.kernels.icp_fused`, :mod:`coloc.kernels.icp_store`)."""

from __future__ import annotations

import numpy as np
from numba import njit


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
