"""The consensus of eq. (20) on the V2F rows: graph, Metropolis weights and participant counts."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit

from coloc.core.v2x import V2xFrame, round_deliveries
from coloc.inference.consensus import connected_components
from coloc.inference.lossy_consensus import lossy_max_consensus
from coloc.kernels.icp import rows_by_key
from coloc.kernels.lossy import running_sum_kernel

# ----------------------------------------------------------------------------- consensus groups


def consensus_graph(owner: np.ndarray, group: np.ndarray, adjacency: sp.spmatrix) -> sp.csr_matrix:
    """(O, O) graph on V2F rows: rows (i, k), (j, k) linked iff i, j are V2V neighbours.

    ``group`` (O,) is the feature each row is paired with (rows with group < 0
    take no part: no edges). One average consensus on this graph equals one
    consensus per feature restricted to the vehicles sensing it.
    """
    owner = np.asarray(owner, dtype=np.int64)
    group = np.asarray(group, dtype=np.int64)
    o = owner.size
    n = adjacency.shape[0]
    if o == 0:
        return sp.csr_matrix((0, 0), dtype=bool)
    used = group >= 0
    rows_idx = np.flatnonzero(used)
    own = sp.csr_matrix((np.ones(rows_idx.size), (rows_idx, owner[used])), shape=(o, n))
    _, g = np.unique(group[used], return_inverse=True)
    feat = sp.csr_matrix((np.ones(rows_idx.size), (rows_idx, g)), shape=(o, int(g.max()) + 1 if g.size else 0))
    adj = sp.csr_matrix(adjacency, dtype=np.float64)
    linked = (own @ adj @ own.T).multiply(feat @ feat.T)
    out = sp.csr_matrix(linked, dtype=bool)
    out.setdiag(False)
    out.eliminate_zeros()
    out.sort_indices()
    return out


def row_components(graph: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Component label and size (participant count |V_k ∩ C|) of every row."""
    n_comp, labels = connected_components(graph)
    sizes = np.bincount(labels, minlength=n_comp).astype(np.float64) if labels.size else np.zeros(0)
    return labels, sizes[labels] if labels.size else np.zeros(0)


@njit(cache=True)
def _pairwise_leaf(a, lo, n):
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True)
def _pairwise_sum(a, lo, n):
    """numpy's pairwise summation of a[lo:lo+n] (8 accumulators, halves above 128), bit for bit.

    The recursion is run on an explicit stack (numba's on-disk cache and recursion do not mix)."""
    if n <= 128:
        return _pairwise_leaf(a, lo, n)
    depth = 64
    w_lo = np.empty(depth * 3, dtype=np.int64)
    w_n = np.empty(depth * 3, dtype=np.int64)
    w_op = np.empty(depth * 3, dtype=np.int64)
    vals = np.empty(depth * 3)
    top, nv = 0, 0
    w_lo[0], w_n[0], w_op[0] = lo, n, 0
    top = 1
    while top > 0:
        top -= 1
        if w_op[top] == 1:  # combine the two last values: left + right
            vals[nv - 2] = vals[nv - 2] + vals[nv - 1]
            nv -= 1
            continue
        cl, cn = w_lo[top], w_n[top]
        if cn <= 128:
            vals[nv] = _pairwise_leaf(a, cl, cn)
            nv += 1
            continue
        n2 = cn // 2
        n2 -= n2 % 8
        w_op[top] = 1
        top += 1
        w_lo[top], w_n[top], w_op[top] = cl + n2, cn - n2, 0
        top += 1
        w_lo[top], w_n[top], w_op[top] = cl, n2, 0
        top += 1
    return vals[0]


@njit(cache=True)
def _row_consensus_kernel(owner, group, n_groups, adj_indptr, adj_indices, adj_data, n_vehicles):
    """Metropolis weights (CSR, diagonal included, columns sorted) of the row graph of
    :func:`consensus_graph` and each row's component size |V_k ∩ C| (:func:`row_components`).

    Same numbers as ``metropolis_weights(consensus_graph(...))``: off-diagonal
    w_rs = 1 / (1 + max(d_r, d_s)), w_rr = 1 - (sum of the row's off-diagonal
    weights in column order, summed as scipy's CSR row sum, i.e. numpy's add.reduceat).
    ``group`` (O,) in [0, n_groups) (every row used); rows of one group are
    linked iff their owners are V2V neighbours (a stored nonzero of the adjacency).
    """
    o = owner.size
    # Dense V2V lookup (N is a few hundred vehicles).
    adj = np.zeros((n_vehicles, n_vehicles), dtype=np.bool_)
    for i in range(n_vehicles):
        for p in range(adj_indptr[i], adj_indptr[i + 1]):
            if adj_data[p] != 0:
                adj[i, adj_indices[p]] = True
    # Rows of each group, ascending (counting sort keeps row order).
    g_count, g_rows = rows_by_key(group, n_groups)
    # Degrees, and components by union-find (links never cross groups).
    # Each row's neighbours, ascending (pairs are visited in row order), in a slot of its group's size.
    deg = np.zeros(o, dtype=np.int64)
    nb_first = np.empty(o, dtype=np.int64)
    n_slots = 0
    for g in range(n_groups):
        for a in range(g_count[g], g_count[g + 1]):
            nb_first[g_rows[a]] = n_slots
            n_slots += g_count[g + 1] - g_count[g] - 1
    nbrs = np.empty(max(n_slots, 1), dtype=np.int64)
    parent = np.arange(o)
    for g in range(n_groups):
        for a in range(g_count[g], g_count[g + 1]):
            r = g_rows[a]
            for b in range(a + 1, g_count[g + 1]):
                s = g_rows[b]
                if adj[owner[r], owner[s]] and r != s:
                    nbrs[nb_first[r] + deg[r]] = s
                    nbrs[nb_first[s] + deg[s]] = r
                    deg[r] += 1
                    deg[s] += 1
                    x, y = r, s
                    while parent[x] != x:
                        x = parent[x]
                    while parent[y] != y:
                        y = parent[y]
                    if x != y:
                        if x < y:
                            parent[y] = x
                        else:
                            parent[x] = y
    root = np.empty(o, dtype=np.int64)
    size = np.zeros(o, dtype=np.int64)
    for r in range(o):
        x = r
        while parent[x] != x:
            x = parent[x]
        root[r] = x
        size[x] += 1
    count = np.empty(o)
    for r in range(o):
        count[r] = float(size[root[r]])
    # complete component: every row linked to all the others (sum of degrees = m (m - 1))
    deg_sum = np.zeros(o, dtype=np.int64)
    for r in range(o):
        deg_sum[root[r]] += deg[r]
    complete = np.empty(o, dtype=np.bool_)
    for r in range(o):
        m = size[root[r]]
        complete[r] = deg_sum[root[r]] == m * (m - 1)
    # CSR with the diagonal: row r has deg[r] + 1 entries, columns ascending.
    indptr = np.zeros(o + 1, dtype=np.int64)
    for r in range(o):
        indptr[r + 1] = indptr[r] + deg[r] + 1
    indices = np.empty(indptr[o], dtype=np.int64)
    data = np.empty(indptr[o])
    buf = np.empty(max(1, int(deg.max()) if o else 1))
    # w_rs = 1 / (1 + max(d_r, d_s)) takes one value per degree: each computed once
    recip = np.empty(int(deg.max()) + 1 if o else 1)
    for d in range(recip.size):
        recip[d] = 1.0 / (1.0 + float(d))
    for r in range(o):
        p0 = indptr[r]
        # off-diagonal weights in column order, summed as numpy's add.reduceat does
        # (first element, then the pairwise sum of the rest): scipy's CSR row sum.
        nb = deg[r]
        for a in range(nb):
            s = nbrs[nb_first[r] + a]
            buf[a] = recip[max(deg[r], deg[s])]
        acc = buf[0] + _pairwise_sum(buf, 1, nb - 1) if nb else 0.0
        diag = 1.0 - acc
        q = p0
        placed = False
        for a in range(nb):
            s = nbrs[nb_first[r] + a]
            if not placed and s > r:
                indices[q] = r
                data[q] = diag
                q += 1
                placed = True
            indices[q] = s
            data[q] = buf[a]
            q += 1
        if not placed:
            indices[q] = r
            data[q] = diag
    return indptr, indices, data, count, complete


def _canonical_adjacency(adjacency: sp.spmatrix) -> sp.csr_matrix:
    a = adjacency if sp.isspmatrix_csr(adjacency) or isinstance(adjacency, sp.csr_array) else sp.csr_matrix(adjacency)
    if not a.has_canonical_format:
        a = sp.csr_matrix(a, copy=True)
        a.sum_duplicates()
    return a


def row_consensus_weights(
    owner: np.ndarray, group_index: np.ndarray, n_groups: int, adjacency: sp.spmatrix
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
    """Metropolis weights of :func:`consensus_graph` as CSR arrays (indptr, indices, data),
    the per-row participant count |V_k ∩ C| of :func:`row_components` and whether the row's
    component is a complete graph, in one numba pass.

    ``group_index`` (O,): every row's feature as an index in [0, n_groups) (all rows used).
    Equals ``metropolis_weights(consensus_graph(owner, group, adjacency))`` and
    ``row_components(...)[1]`` bit for bit (tests), without scipy.sparse on the small graphs.
    """
    a = _canonical_adjacency(adjacency)
    return _split4(
        _row_consensus_kernel(
            np.asarray(owner, dtype=np.int64), np.asarray(group_index, dtype=np.int64), int(n_groups),
            a.indptr.astype(np.int64), a.indices.astype(np.int64), np.asarray(a.data != 0), int(a.shape[0]),
        )
    )


def _split4(t):
    return (t[0], t[1], t[2]), t[3], t[4]



# ----------------------------------------------------------------------------- over the V2X channel


def row_links(owner: np.ndarray, group_index: np.ndarray, n_groups: int, adjacency: sp.spmatrix
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Directed links of the row graph of :func:`consensus_graph` and the V2V link each rides on.

    Returns (src (L,), dst (L,), link (L,)): row ``src`` (vehicle j, feature k) -> row ``dst``
    (vehicle i, feature k) for every stored entry ``link`` of ``adjacency`` in row i, column j (the
    directed V2V link j -> i of :func:`coloc.core.v2x.directed_links`) where both vehicles have a row
    of feature k. Rows must be unique per (vehicle, feature). Vectorised: one ``searchsorted`` over
    the rows' (vehicle, feature) keys, no loop over vehicles."""
    owner = np.asarray(owner, dtype=np.int64)
    group = np.asarray(group_index, dtype=np.int64)
    a = _canonical_adjacency(adjacency)
    indptr = a.indptr.astype(np.int64)
    indices = a.indices.astype(np.int64)
    width = max(int(n_groups), 1)
    keys = owner * width + group
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    deg = (indptr[1:] - indptr[:-1])[owner]  # incoming V2V links of each row's vehicle
    dst = np.repeat(np.arange(owner.size, dtype=np.int64), deg)
    first = np.repeat(indptr[owner] - (np.cumsum(deg) - deg), deg)
    link = first + np.arange(dst.size, dtype=np.int64)
    want = indices[link] * width + group[dst]
    pos = np.minimum(np.searchsorted(sorted_keys, want), max(owner.size - 1, 0))
    hit = sorted_keys[pos] == want if owner.size else np.zeros(0, dtype=bool)
    return order[pos[hit]], dst[hit], link[hit]


class ChannelRowConsensus:
    """The average consensus of eq. (20) on the V2F rows over the lossy V2X channel of a frame.

    Rows (vehicle i, feature k) exchange messages with the rows of the same feature at V2V
    neighbours, as on the lossless row graph (:func:`consensus_graph`), but a row of vehicle i hears
    the row of vehicle j in round r only when ``round_deliveries(v2x, r)`` delivered the V2V link
    j -> i: a vehicle's broadcast of round r carries its values for all its features at once, so
    the link mask of round r applies to every feature's consensus of that round. The average is the
    running-sum ratio consensus (Hadjicostis et al. 2016, :mod:`coloc.inference.lossy_consensus`,
    kernel :func:`coloc.kernels.lossy.running_sum_kernel`), which converges to the right average
    under asymmetric losses; each call (one BPA-L iteration) starts it afresh from the call's values
    (weights z = 1), with the out-degrees of the intended row graph.

    Rounds are counted over the whole step: ``rounds_used`` keeps increasing across calls, round
    ``rounds_used`` of the step is realised from the channel's seed, and :meth:`grant` hands out
    what is left of ``v2x.rounds_per_step`` (0 = unlimited).
    """

    def __init__(self, owner: np.ndarray, group_index: np.ndarray, n_groups: int, adjacency: sp.spmatrix,
                 v2x: V2xFrame):
        a = _canonical_adjacency(adjacency)
        if a.nnz != v2x.n_links:
            raise ValueError(f"frame.v2x has {v2x.n_links} link probabilities for {a.nnz} stored neighbors entries: "
                             "the channel must be aligned with the frame's neighbors")
        self.v2x = v2x
        self.src, self.dst, self.link = row_links(owner, group_index, n_groups, a)
        o = np.asarray(owner).size
        self.share = 1.0 / (1.0 + np.bincount(self.src, minlength=o).astype(np.float64))
        self.rounds_used = 0

    @property
    def exhausted(self) -> bool:
        """The step's round budget is used up (never with an unlimited budget)."""
        return not self.v2x.unlimited and self.rounds_used >= self.v2x.rounds_per_step

    def grant(self, wanted: int, sharing: int = 1) -> int:
        """Rounds the next exchange may use: ``wanted``, or what is left of the step's budget; with
        ``sharing`` > 1 exchanges still to come (IcpParams.budget_split = "even"), at most the rounds
        left divided among them, and at least one while any is left."""
        if self.v2x.unlimited:
            return int(wanted)
        left = int(self.v2x.rounds_per_step) - self.rounds_used
        if sharing > 1 and left > 0:
            left = max(1, left // int(sharing))
        return max(0, min(int(wanted), left))

    def average(self, x: np.ndarray, rounds: int) -> np.ndarray:
        """``rounds`` rounds of ratio consensus of the rows' values x (O, D) (the next rounds of the
        step); returns every row's estimate of its feature's average (O, D)."""
        return self._exchange(np.ascontiguousarray(x, dtype=np.float64), rounds,
                              lambda v, got: running_sum_kernel(v, self.share, self.src, self.dst, got))

    def maximum(self, x: np.ndarray, rounds: int) -> np.ndarray:
        """``rounds`` rounds of max consensus of the rows' values x (O, D) (the next rounds of the step):
        every round a row keeps the elementwise largest of its own and the values it heard
        (:func:`coloc.inference.lossy_consensus.lossy_max_consensus`); a lost message only delays it."""
        return self._exchange(np.asarray(x, dtype=np.float64), rounds,
                              lambda v, got: lossy_max_consensus(v, self.src, self.dst, got))

    def _exchange(self, x: np.ndarray, rounds: int, run) -> np.ndarray:
        """The next ``rounds`` rounds of the step (counted in ``rounds_used``) of the exchange ``run(x,
        deliveries)``; no round or no row link: x unchanged."""
        rounds = int(rounds)
        first = self.rounds_used
        self.rounds_used += rounds
        if rounds == 0 or self.src.size == 0:
            return x.copy()
        return run(x, self._deliveries(first, rounds))

    def _deliveries(self, first: int, rounds: int) -> np.ndarray:
        """(rounds, row links) bool: which row links delivered in rounds first .. first + rounds - 1."""
        got = np.empty((rounds, self.link.size), dtype=np.bool_)
        for k in range(rounds):
            got[k] = round_deliveries(self.v2x, first + k)[self.link]
        return got
