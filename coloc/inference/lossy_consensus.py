"""Consensus over lossy, asymmetric V2V links: the average by exchange of running sums, and the maximum.

The building block for realistic V2X (a channel that drops packets per message and round, and a
budget of rounds per step). The Gaussian BPA-L runs the same algorithm on its row graph with the
numba kernel :func:`coloc.kernels.lossy.running_sum_kernel` (checked against
:func:`running_sum_consensus`; :class:`coloc.inference.row_consensus.ChannelRowConsensus`); the
particle ICP does not use this module yet.

Plain average consensus (Metropolis weights, :mod:`coloc.inference.consensus`) keeps the network sum only
when every message arrives: a packet that i receives from j but j's partner never receives from
i moves mass out of the sum, and the nodes agree on a wrong value. Ratio (push-sum) consensus
with *running sums* (Hadjicostis, Vaidya and Domínguez-García, "Robust distributed average
consensus via exchange of running sums", IEEE Trans. Automatic Control 61(6), 2016, Alg. 1)
keeps it: each node broadcasts the running sum of everything it has ever sent; a receiver takes
the difference to the last running sum it heard from that sender, so a lost packet's mass
arrives with the next one that gets through. The ratio y/z converges to the exact average as
long as every link gets a packet through now and then.

Functions (all vectorised over directed links; one round is a few ``bincount`` calls):

- :func:`running_sum_consensus`: rounds of the algorithm over given per-round deliveries.
- :func:`lossy_max_consensus`: max consensus; a lost packet only delays it.
- :func:`lossy_metropolis_consensus`: the plain Metropolis iteration on the same deliveries, the
  reference that loses the average (kept for the tests and the benchmark).

Links are directed pairs ``(src, dst)`` that the V2V graph intends (both directions of every
undirected link); ``delivered[k, e]`` says whether round ``k``'s packet on link ``e`` arrived.
A node's out-degree is the number of its intended links (a broadcast: it does not know who
heard it).
"""

from __future__ import annotations

import numpy as np


def _out_degree(src: np.ndarray, n: int) -> np.ndarray:
    return np.bincount(src, minlength=n).astype(float)


def running_sum_consensus(values: np.ndarray, src: np.ndarray, dst: np.ndarray, delivered: np.ndarray,
                          weights: np.ndarray | None = None) -> np.ndarray:
    """Hadjicostis et al. (2016) Alg. 1: the weighted average of ``values`` at every node.

    values: (N, ...) the nodes' initial values (trailing dimensions are independent scalars); weights: (N,) initial z (default ones, so the
    result is the plain average; ``weights`` w_i give sum(w_i x_i) / sum(w_i) with values = w x);
    src, dst: (E,) directed links; delivered: (R, E) bool, one row per round.
    Returns (N, ...): y / z after the R rounds (exact once every link has delivered often enough).
    """
    values = np.asarray(values, dtype=float)
    shape = values.shape
    values = values.reshape(shape[0], -1)
    n, d = values.shape
    src = np.asarray(src, dtype=np.int64)
    dst = np.asarray(dst, dtype=np.int64)
    share = 1.0 / (1.0 + _out_degree(src, n))  # 1 / (1 + D_j^+)
    y = values.copy()
    z = np.ones(n) if weights is None else np.asarray(weights, dtype=float).copy()
    sigma = np.zeros((n, d))  # running sums a node has broadcast
    tau = np.zeros(n)
    rho = np.zeros((src.size, d))  # per link: the sender's last running sum the receiver heard
    mu = np.zeros(src.size)
    for got in np.asarray(delivered, dtype=bool):
        sigma += y * share[:, None]
        tau += z * share
        new_rho = np.where(got[:, None], sigma[src], rho)
        new_mu = np.where(got, tau[src], mu)
        y = y * share[:, None] + _scatter_rows(dst, new_rho - rho, n)
        z = z * share + np.bincount(dst, weights=new_mu - mu, minlength=n)
        rho, mu = new_rho, new_mu
    return (y / z[:, None]).reshape(shape)


def _scatter_rows(index: np.ndarray, rows: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros((n, rows.shape[1]))
    for c in range(rows.shape[1]):
        out[:, c] = np.bincount(index, weights=rows[:, c], minlength=n)
    return out


def lossy_max_consensus(values: np.ndarray, src: np.ndarray, dst: np.ndarray, delivered: np.ndarray) -> np.ndarray:
    """Max consensus: every round a node keeps the largest of its own value and those it received."""
    x = np.asarray(values, dtype=float).copy()
    for got in np.asarray(delivered, dtype=bool):
        heard = np.full_like(x, -np.inf)
        np.maximum.at(heard, dst[got], x[src[got]])
        x = np.maximum(x, heard)
    return x


def lossy_metropolis_consensus(values: np.ndarray, src: np.ndarray, dst: np.ndarray,
                               delivered: np.ndarray) -> np.ndarray:
    # values (N, D)
    """Plain average consensus with Metropolis weights 1 / (1 + max(d_i, d_j)) on the intended graph;
    a node updates with what it received: x_i += sum_j w_ij (x_j - x_i) over delivered links j -> i.
    Exact with no losses; with asymmetric losses it converges, but not to the average."""
    x = np.asarray(values, dtype=float).copy()
    n = x.shape[0]
    deg = _out_degree(np.asarray(src), n)
    w = 1.0 / (1.0 + np.maximum(deg[src], deg[dst]))
    for got in np.asarray(delivered, dtype=bool):
        delta = (x[src] - x[dst]) * (w * got)[:, None]
        x = x + _scatter_rows(dst, delta, n)
    return x
