"""ICP-DA-LC's birth clustering (step 6 of :mod:`coloc.methods.icp_da_lc`) over candidate pairs only.

The greedy of :func:`coloc.methods.icp_da_lc.birth_clusters` compares each birth row with every
cluster seed before it. :func:`coloc.methods.icp_da_lc.birth_pairs` keeps only the (earlier row,
row) pairs that can pass the gate, exactly: for an SPD S, d' S^-1 d >= |d|^2 / lambda_max(S) >=
|d|^2 / trace(S), so a pair with |d|^2 > gate * trace(S_i + S_j) never passes it. The squared
Mahalanobis distances of the kept pairs come from one batched ``np.linalg.solve`` (LAPACK per matrix:
each value bit for bit the one of a per-row call) and :func:`birth_greedy_kernel` runs the greedy on
them, so every label is the one of the per-row loop (tests/coloc/test_birth_clusters.py keeps that loop
as reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit

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
