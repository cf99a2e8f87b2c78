"""V2F rows shuffled within their owner (a numba counting sort, :func:`coloc.kernels.icp.rows_by_key`)."""

from __future__ import annotations

import numpy as np
from numba import njit

from coloc.kernels.icp import rows_by_key


@njit(cache=True)
def _order_by_owner_then_key(owner, keys):
    """``np.lexsort((keys, owner))``: a stable counting sort by owner, then a stable insertion sort by key
    inside each owner's rows (a handful each; merge sort beyond 32)."""
    if owner.size == 0:
        return np.empty(0, dtype=np.int64)
    lo = owner.min()
    start, perm = rows_by_key(owner - lo, owner.max() - lo + 1)
    for g in range(start.size - 1):
        s, e = start[g], start[g + 1]
        if e - s > 32:
            block = perm[s:e].copy()
            perm[s:e] = block[np.argsort(keys[block], kind="mergesort")]
            continue
        for p in range(s + 1, e):
            v = perm[p]
            q = p - 1
            while q >= s and keys[perm[q]] > keys[v]:
                perm[q + 1] = perm[q]
                q -= 1
            perm[q + 1] = v
    return perm


def shuffle_within_owner(owner: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Permutation that keeps rows grouped by owner (in increasing owner order) but randomises the order
    inside each group: one uniform key per row from ``rng``, rows sorted by (owner, key)."""
    keys = rng.random(owner.size)
    return _order_by_owner_then_key(np.asarray(owner, dtype=np.int64), keys)
