"""Numba kernel of the running-sum ratio consensus over lossy directed links (Hadjicostis, Vaidya and
Domínguez-García, IEEE TAC 61(6), 2016, Alg. 1); the numpy reference is
:func:`coloc.inference.lossy_consensus.running_sum_consensus` (same operations, tests)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def running_sum_kernel(x, share, src, dst, delivered):
    """Rounds of Alg. 1 on values x (O, D) with initial weights z = 1, returns y / z (O, D).

    ``share`` (O,): 1 / (1 + out-degree) of every node; ``src``, ``dst`` (L,): directed links;
    ``delivered`` (R, L) bool: which links deliver in each of the R rounds. Every node first keeps
    its share of (y, z) and adds it to its running sums (sigma, tau); a receiver adds the difference
    between the sender's running sums and the last ones it heard on that link, so mass lost in a
    round arrives with the next packet that gets through."""
    o, d = x.shape
    n_links = src.size
    y = x.copy()
    z = np.ones(o)
    sigma = np.zeros((o, d))
    tau = np.zeros(o)
    rho = np.zeros((n_links, d))
    mu = np.zeros(n_links)
    for r in range(delivered.shape[0]):
        for i in range(o):
            s = share[i]
            for c in range(d):
                y[i, c] *= s
                sigma[i, c] += y[i, c]
            z[i] *= s
            tau[i] += z[i]
        for k in range(n_links):
            if delivered[r, k]:
                a = src[k]
                b = dst[k]
                for c in range(d):
                    y[b, c] += sigma[a, c] - rho[k, c]
                    rho[k, c] = sigma[a, c]
                z[b] += tau[a] - mu[k]
                mu[k] = tau[a]
    out = np.empty_like(y)
    for i in range(o):
        for c in range(d):
            out[i, c] = y[i, c] / z[i]
    return out
