"""ICP-DA-LC's birth clustering (step 6 of :mod:`coloc.methods.icp_da_lc`) over candidate pairs only.

The greedy of :func:`coloc.methods.icp_da_lc.birth_clusters` compares each birth row with every
cluster seed before it. :func:`birth_pairs` keeps only the (earlier row, row) pairs that can pass
the gate, exactly: for an SPD S, d' S^-1 d >= |d|^2 / lambda_max(S) >= |d|^2 / trace(S), so a pair
with |d|^2 > gate * trace(S_i + S_j) never passes it. The squared Mahalanobis distances of the
kept pairs come from one batched ``np.linalg.solve`` (LAPACK per matrix: each value bit for bit
the one of a per-row call) and :func:`birth_greedy_kernel` runs the greedy on them, so every label
is the one of the per-row loop (tests/coloc/test_birth_clusters.py keeps that loop as reference).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

#: Relative margin of the trace bound above: a pair is dropped only if |d|^2 exceeds
#: gate * trace * (1 + PRUNE_MARGIN), far beyond the rounding of the solve and of |d|^2.
PRUNE_MARGIN = 1e-6


def birth_pairs(xy: np.ndarray, cov: np.ndarray, gate_d2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pairs (i, j), j < i, that may pass the gate, with their squared Mahalanobis distance.

    Returns ``(indptr, cand_j, cand_d2)``: row i's candidates are ``cand_j[indptr[i]:indptr[i+1]]``,
    sorted by d2 (NaN last, as ``np.argsort``), then by j. Non-finite input: every pair j < i.
    """
    b = xy.shape[0]
    if np.isfinite(xy).all() and np.isfinite(cov).all():
        tr = cov[:, 0, 0] + cov[:, 1, 1]
        reach2 = gate_d2 * 2.0 * float(tr.max()) * (1.0 + PRUNE_MARGIN)
        pairs = cKDTree(xy).query_pairs(math.sqrt(max(reach2, 0.0)) * (1.0 + PRUNE_MARGIN), output_type="ndarray")
        j, i = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)  # query_pairs: first < second
        dd = xy[j] - xy[i]
        keep = (dd * dd).sum(axis=1) <= gate_d2 * (tr[i] + tr[j]) * (1.0 + PRUNE_MARGIN)
        j, i = j[keep], i[keep]
    else:
        i, j = np.tril_indices(b, -1)
        i, j = i.astype(np.int64), j.astype(np.int64)
    # The expressions of the per-row loop, batched (d = seed - row, S = S_seed + S_row).
    d = xy[j] - xy[i]
    s = cov[j] + cov[i]
    d2 = np.einsum("ni,ni->n", d, np.linalg.solve(s, d[..., None])[..., 0]) if i.size else np.empty(0)
    order = np.lexsort((j, d2, i))
    indptr = np.zeros(b + 1, dtype=np.int64)
    np.cumsum(np.bincount(i, minlength=b), out=indptr[1:])
    return indptr, np.ascontiguousarray(j[order]), np.ascontiguousarray(d2[order])


@njit(cache=True)
def birth_greedy_kernel(owner, indptr, cand_j, cand_d2, gate_d2):  # pragma: no cover - numba
    """Labels of the greedy: in row order a row joins the first seed of its sorted candidates
    (nearest, ties to the earlier seed) within the gate whose cluster holds no row of its
    vehicle, else opens a cluster (the first row of a cluster is its seed)."""
    b = owner.size
    labels = np.full(b, -1, np.int64)
    cluster_of = np.full(b, -1, np.int64)  # cluster of a seed row, -1 for other rows
    head = np.full(b, -1, np.int64)  # members of a cluster as a linked list: head[c], nxt[row]
    nxt = np.full(b, -1, np.int64)
    n_clusters = 0
    for i in range(b):
        for k in range(indptr[i], indptr[i + 1]):
            c = cluster_of[cand_j[k]]
            if c < 0:
                continue
            if cand_d2[k] > gate_d2:
                break
            r = head[c]
            while r >= 0 and owner[r] != owner[i]:
                r = nxt[r]
            if r < 0:
                labels[i] = c
                nxt[i] = head[c]
                head[c] = i
                break
        if labels[i] < 0:
            labels[i] = n_clusters
            cluster_of[i] = n_clusters
            head[n_clusters] = i
            n_clusters += 1
    return labels
