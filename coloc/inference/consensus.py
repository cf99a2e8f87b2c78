"""Distributed consensus over the V2V graph (Brambilla et al. Sec. IV-B, IV-C eqs. (28)-(29)).

ICP-DA-PF needs, for every feature k and particle f, the product over the
vehicles sensing k of their messages, eq. (28), q_k^(f) = prod_{i in V_k}
w_{i->k}^(f). Its logarithm, eq. (29), is |V_k| times the arithmetic mean of
the local log-weights, which the vehicles compute by *average consensus* [47]
(:func:`average_consensus`, Metropolis-Hastings weights); because a finite
number of rounds leaves small disagreements, a *max consensus*
(:func:`max_consensus`) follows so that every vehicle ends with identical
values (after at least diameter-many rounds).

Graph convention: ``adjacency`` is an (N, N) ``scipy.sparse`` matrix, symmetric,
with an empty diagonal; any stored nonzero is an edge (bool or numeric). The
optional ``participants`` (N,) bool mask restricts the exchange to the subgraph
induced by the participating vehicles: non-participants neither send nor
receive and keep their input values. Everything works per connected component
automatically (the iterations never cross components).

Values are (N, ...) arrays; trailing dimensions are treated as independent
scalars (e.g. (N, J) log-weights, (N, 4) means, (N, 4, 4) information
matrices). Output is float64. A -inf log-weight (a zero message) drives its
component's average to -inf, i.e. a zero product in eq. (28), which is the
correct limit; a mix of +inf and -inf gives NaN, so callers should floor
log-weights at a finite value.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.sparse.csgraph import connected_components as _cc

from coloc.kernels.icp import weighted_row_sum

__all__ = [
    "metropolis_weights",
    "average_consensus",
    "average_consensus_with_weights",
    "max_consensus",
    "connected_components",
    "restrict_adjacency",
]


def restrict_adjacency(adjacency: sp.spmatrix, participants: np.ndarray | None = None) -> sp.csr_matrix:
    """Validated boolean CSR adjacency, restricted to edges between participants.

    Raises ValueError if the matrix is not square, not symmetric, or has a
    nonzero diagonal; ``participants`` must be a bool (N,) mask.
    """
    A = sp.csr_matrix(adjacency, copy=True)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"adjacency must be square, got shape {A.shape}")
    A.eliminate_zeros()
    A = sp.csr_matrix(A.astype(bool))
    n = A.shape[0]
    if A.diagonal().any():
        raise ValueError("adjacency must have an empty diagonal")
    if (A != A.T).nnz:
        raise ValueError("adjacency must be symmetric")
    if participants is not None:
        mask = np.asarray(participants)
        if mask.dtype != np.bool_ or mask.shape != (n,):
            raise ValueError(f"participants must be a bool mask of shape ({n},)")
        D = sp.diags(mask.astype(np.float64), format="csr")
        A = sp.csr_matrix((D @ A.astype(np.float64) @ D).astype(bool))
        A.eliminate_zeros()
    A.sort_indices()
    return A


def metropolis_weights(adjacency: sp.spmatrix) -> sp.csr_matrix:
    """Metropolis-Hastings consensus weights [47].

    w_ij = 1 / (1 + max(d_i, d_j)) on edges, w_ii = 1 - sum_{j != i} w_ij,
    zero elsewhere. W is symmetric and doubly stochastic with positive
    diagonal, so x <- W x converges to the average of each connected
    component and preserves each component's sum. An isolated vertex has
    w_ii = 1.
    """
    A = restrict_adjacency(adjacency)
    n = A.shape[0]
    deg = np.diff(A.indptr).astype(np.float64)
    rows = np.repeat(np.arange(n), np.diff(A.indptr))
    cols = A.indices
    w = 1.0 / (1.0 + np.maximum(deg[rows], deg[cols]))
    off = sp.csr_matrix((w, (rows, cols)), shape=(n, n))
    diag = 1.0 - np.asarray(off.sum(axis=1)).ravel()
    W = sp.csr_matrix(off + sp.diags(diag, format="csr"))
    W.sort_indices()
    return W


@njit(cache=True)
def _average_kernel(indptr, indices, data, x, iterations):
    """``iterations`` rounds of x <- W x (W in CSR), x (N, D)."""
    n = x.shape[0]
    cur = x.copy()
    nxt = np.empty_like(x)
    for _ in range(iterations):
        for i in range(n):
            weighted_row_sum(indptr, indices, data, cur, i, nxt)
        cur, nxt = nxt, cur
    return cur


@njit(cache=True)
def _max_kernel(indptr, indices, x, iterations):
    """``iterations`` synchronous rounds of x_i <- max(x_i, max_{j in N(i)} x_j)."""
    n, d = x.shape
    cur = x.copy()
    nxt = np.empty_like(x)
    for _ in range(iterations):
        for i in range(n):
            for c in range(d):
                nxt[i, c] = cur[i, c]
            for p in range(indptr[i], indptr[i + 1]):
                j = indices[p]
                for c in range(d):
                    if cur[j, c] > nxt[i, c]:
                        nxt[i, c] = cur[j, c]
        cur, nxt = nxt, cur
    return cur


def _as_2d(values: np.ndarray, n: int) -> np.ndarray:
    x = np.asarray(values, dtype=np.float64)
    if x.ndim < 1 or x.shape[0] != n:
        raise ValueError(f"values must have leading dimension N={n}, got shape {x.shape}")
    return np.ascontiguousarray(x.reshape(n, int(np.prod(x.shape[1:], dtype=np.int64))))


def _rounds_input(values: np.ndarray, n: int, iterations: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """What every consensus starts from: ``values`` as an array, the same as (n, d) float64 rows, and
    whether the rounds have nothing to do (no vehicle, no value or no round: the values are returned)."""
    if iterations < 0:
        raise ValueError("iterations must be >= 0")
    values = np.asarray(values)
    x = _as_2d(values, n)
    return values, x, n == 0 or x.shape[1] == 0 or iterations == 0


def average_consensus(
    values: np.ndarray,
    adjacency: sp.spmatrix,
    iterations: int,
    participants: np.ndarray | None = None,
) -> np.ndarray:
    """Average consensus [47] used for the log-likelihood sum of eq. (29).

    Runs ``iterations`` synchronous rounds of x <- W x with the Metropolis
    weights of the subgraph induced by ``participants`` (all vehicles if
    None). Non-participants and isolated vehicles keep their values. Each
    connected component's sum is preserved at every round and its entries
    converge to the component mean. Multiply by the component size (see
    :func:`connected_components`) to get the sum of eq. (29).
    """
    if iterations < 0:
        raise ValueError("iterations must be >= 0")
    A = restrict_adjacency(adjacency, participants)
    values, x, idle = _rounds_input(values, A.shape[0], iterations)
    if idle:
        return x.reshape(values.shape).copy()
    return average_consensus_with_weights(values, metropolis_weights(A), iterations)


def average_consensus_with_weights(values: np.ndarray, weights: sp.csr_matrix, iterations: int) -> np.ndarray:
    """:func:`average_consensus` with the weight matrix already built (e.g. by
    :func:`metropolis_weights`), for callers that run several consensus on the
    same graph (BPA-L iterations within one time step)."""
    values, x, idle = _rounds_input(values, weights.shape[0], iterations)
    if idle:
        return x.reshape(values.shape).copy()
    out = _average_kernel(
        weights.indptr.astype(np.int64), weights.indices.astype(np.int64), weights.data, x, int(iterations)
    )
    return out.reshape(values.shape)


def max_consensus(
    values: np.ndarray,
    adjacency: sp.spmatrix,
    iterations: int,
    participants: np.ndarray | None = None,
) -> np.ndarray:
    """Max consensus run after the average consensus (Sec. IV-C, after eq. (29)).

    ``iterations`` synchronous rounds of x_i <- max(x_i, max_{j in N(i)} x_j)
    on the subgraph induced by ``participants``. After at least the
    component's diameter rounds every vehicle of a component holds the
    component maximum (elementwise over trailing dimensions).
    Non-participants keep their values.
    """
    if iterations < 0:
        raise ValueError("iterations must be >= 0")
    A = restrict_adjacency(adjacency, participants)
    values, x, idle = _rounds_input(values, A.shape[0], iterations)
    if idle:
        return x.reshape(values.shape).copy()
    out = _max_kernel(A.indptr.astype(np.int64), A.indices.astype(np.int64), x, int(iterations))
    return out.reshape(values.shape)


def connected_components(
    adjacency: sp.spmatrix, participants: np.ndarray | None = None
) -> tuple[int, np.ndarray]:
    """Connected components of the (participant-induced) V2V graph.

    Returns ``(n_components, labels)`` with labels (N,) int64 in
    [0, n_components) for participants; non-participants get label -1 and are
    not counted (each behaves as a singleton that exchanges nothing).
    """
    A = restrict_adjacency(adjacency, participants)
    n = A.shape[0]
    if n == 0:
        return 0, np.zeros(0, dtype=np.int64)
    _, labels = _cc(A, directed=False)
    labels = labels.astype(np.int64)
    if participants is None:
        return int(labels.max()) + 1, labels
    mask = np.asarray(participants, dtype=bool)
    out = np.full(n, -1, dtype=np.int64)
    _, relabel = np.unique(labels[mask], return_inverse=True)
    out[mask] = relabel
    return int(relabel.max()) + 1 if relabel.size else 0, out
