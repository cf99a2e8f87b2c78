"""Pairwise particle kernels of ICP-DA-PF (Brambilla et al. Sec. IV-C, eqs. (25)-(27)).

Every particle double sum of ICP-DA-PF is a weighted *Gauss transform* of one
particle set onto another, under the Gaussian V2F likelihood (4):

    out_j = log sum_s exp(logw_s) N(z; y_j - x_s, R)      (x_s source, y_j target particles)

* (25), eta: x = vehicle particles s_i^(v) (log-weights of (23)), y = feature
  particles s_k^(f) - z, summed once more over the feature particles;
* message i -> k (19)/(26): sources = vehicle particles shifted by z, targets =
  feature particles (``transform_batch`` with the vehicle set as source);
* message k -> i (21)/(27): sources = feature particles, targets = vehicle
  particles shifted by z.

In whitened coordinates u = L^-1 x (R = L L^T) the kernel is
exp(-|u_s - u_j|^2 / 2) / ((2 pi)^2 |L|). The V2F noise (0.1 m, 0.1 m/s) is far
narrower than the particle clouds, so most pairs contribute nothing. The
``grid`` kernel bins the source particles on a 2-D grid of cell size
r = sqrt(``cutoff_d2``) over the two whitened coordinates in which the sources
spread most, and each target visits only the 3 x 3 cells around it: a pair
left out is at whitened distance > r, so it contributes at most exp(-r^2/2) of
its source weight. The kernel bounds the mass it left out for every target
(exp(-r^2/2) sum_s w_s) and recomputes **that target exactly** (log-sum-exp over
all sources, :func:`_exact_log_sum`) whenever the bound exceeds ``rel_tol`` times the sum it found. So
every output entry is within ``rel_tol`` (default 1e-6) of the brute-force sum,
relatively, including targets far in the tails (where the grid finds nothing
and the exact sum is what remains). ``brute`` evaluates every pair, in log
domain, and is the reference.

All kernels are numba, ``cache=True``; the batched entry point runs the
independent (source set, target set, shift) problems of one BPA-L pass in
parallel (``prange``) and returns the number of pair evaluations (for
``bench/pf_kernels.py``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["KERNELS", "transform_batch", "transform_brute", "transform"]

KERNELS = ("grid", "brute")
_LOG_NORM = -2.0 * math.log(2.0 * math.pi)  # (2 pi)^(-d/2), d = 4


@nb.njit(cache=True, inline="always")
def _whiten(x, shift, linv, out):
    """out = L^-1 (x + shift) for one 4-vector (L^-1 lower triangular)."""
    for a in range(4):
        acc = 0.0
        for b in range(a + 1):
            acc += linv[a, b] * (x[b] + shift[b])
        out[a] = acc


@nb.njit(cache=True, inline="always")
def _sq_dist(u, v):
    d2 = 0.0
    for a in range(4):
        d = u[a] - v[a]
        d2 += d * d
    return d2


@nb.njit(cache=True)
def _exact_log_sum(src_w, src_logw, wmax, tgt):
    """log sum_s exp(logw_s - |u_s - u_t|^2 / 2), exact.

    One pass scaled by the largest log-weight ``wmax`` (every term <= 1); only
    when that underflows (the target is far from every source) a second,
    two-pass log-sum-exp.
    """
    acc = 0.0
    for s in range(src_w.shape[0]):
        d2 = _sq_dist(src_w[s], tgt)
        acc += math.exp(src_logw[s] - wmax - 0.5 * d2)
    if acc > 1e-250:
        return wmax + math.log(acc)
    best = -np.inf
    for s in range(src_w.shape[0]):
        d2 = _sq_dist(src_w[s], tgt)
        v = src_logw[s] - 0.5 * d2
        if v > best:
            best = v
    if best == -np.inf:
        return -np.inf
    acc = 0.0
    for s in range(src_w.shape[0]):
        d2 = _sq_dist(src_w[s], tgt)
        acc += math.exp(src_logw[s] - 0.5 * d2 - best)
    return best + math.log(acc)


@nb.njit(cache=True)
def _one_problem(src, src_logw, src_shift, tgt, tgt_shift, linv, log_norm, use_grid, cutoff_d2, rel_tol, out):
    """Fill ``out`` (Jt,) with log sum_s w_s N(...); returns the number of pair evaluations."""
    js = src.shape[0]
    jt = tgt.shape[0]
    src_w = np.empty((js, 4))
    for s in range(js):
        _whiten(src[s], src_shift, linv, src_w[s])
    tgt_w = np.empty((jt, 4))
    for t in range(jt):
        _whiten(tgt[t], tgt_shift, linv, tgt_w[t])
    pairs = 0
    wmax = -np.inf
    for s in range(js):
        if src_logw[s] > wmax:
            wmax = src_logw[s]
    if wmax == -np.inf:
        for t in range(jt):
            out[t] = -np.inf
        return 0
    if not use_grid:
        for t in range(jt):
            out[t] = _exact_log_sum(src_w, src_logw, wmax, tgt_w[t]) + log_norm
        return jt * js
    # Source weights on a linear scale relative to the largest.
    ws = np.empty(js)
    wsum = 0.0
    for s in range(js):
        ws[s] = math.exp(src_logw[s] - wmax)
        wsum += ws[s]
    # Grid axes: the two whitened coordinates with the largest source spread.
    spread = np.empty(4)
    lo = np.empty(4)
    for a in range(4):
        mn = np.inf
        mx = -np.inf
        for s in range(js):
            v = src_w[s, a]
            if v < mn:
                mn = v
            if v > mx:
                mx = v
        lo[a] = mn
        spread[a] = mx - mn
    ax = 0
    for a in range(1, 4):
        if spread[a] > spread[ax]:
            ax = a
    ay = 1 if ax == 0 else 0
    for a in range(4):
        if a != ax and spread[a] > spread[ay]:
            ay = a
    r = math.sqrt(cutoff_d2)
    cell = r
    nx = int(spread[ax] / cell) + 1
    ny = int(spread[ay] / cell) + 1
    limit = 4 * js + 64
    while nx * ny > limit:  # very spread sources: coarser cells (still >= r, so 3 x 3 covers radius r)
        cell *= 2.0
        nx = int(spread[ax] / cell) + 1
        ny = int(spread[ay] / cell) + 1
    cell_of = np.empty(js, np.int64)
    counts = np.zeros(nx * ny + 1, np.int64)
    for s in range(js):
        cx = min(int((src_w[s, ax] - lo[ax]) / cell), nx - 1)
        cy = min(int((src_w[s, ay] - lo[ay]) / cell), ny - 1)
        cell_of[s] = cx * ny + cy
        counts[cell_of[s] + 1] += 1
    for c in range(nx * ny):
        counts[c + 1] += counts[c]
    order = np.empty(js, np.int64)
    fill = counts[:-1].copy()
    for s in range(js):
        order[fill[cell_of[s]]] = s
        fill[cell_of[s]] += 1
    sorted_w = np.empty((js, 4))
    sorted_ws = np.empty(js)
    for i in range(js):
        sorted_w[i] = src_w[order[i]]
        sorted_ws[i] = ws[order[i]]
    left_out = math.exp(-0.5 * cutoff_d2) * wsum  # bound on the mass of all pairs beyond distance r
    for t in range(jt):
        fx = (tgt_w[t, ax] - lo[ax]) / cell
        fy = (tgt_w[t, ay] - lo[ay]) / cell
        acc = 0.0
        if fx > -2.0 and fy > -2.0 and fx < nx + 1.0 and fy < ny + 1.0:
            cx = int(math.floor(fx))
            cy = int(math.floor(fy))
            for gx in range(max(cx - 1, 0), min(cx + 2, nx)):
                for gy in range(max(cy - 1, 0), min(cy + 2, ny)):
                    c = gx * ny + gy
                    for i in range(counts[c], counts[c + 1]):
                        pairs += 1
                        d2 = 0.0
                        for a in range(4):
                            d = sorted_w[i, a] - tgt_w[t, a]
                            d2 += d * d
                            if d2 > cutoff_d2:  # counted in the left-out bound
                                break
                        if d2 <= cutoff_d2:
                            acc += sorted_ws[i] * math.exp(-0.5 * d2)
        if acc > 0.0 and left_out <= rel_tol * acc:
            out[t] = math.log(acc) + wmax + log_norm
        else:  # the left-out bound is not negligible: this target exactly
            out[t] = _exact_log_sum(src_w, src_logw, wmax, tgt_w[t]) + log_norm
            pairs += js
    return pairs


@nb.njit(cache=True, parallel=True)
def _batch(src_sets, src_logw, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, linv, log_norm, use_grid,
           cutoff_d2, rel_tol, out, pairs):
    for p in nb.prange(src_index.shape[0]):
        pairs[p] = _one_problem(
            src_sets[src_index[p]], src_logw[p], src_shift[p], tgt_sets[tgt_index[p]], tgt_shift[p], linv[p],
            log_norm[p], use_grid, cutoff_d2, rel_tol, out[p],
        )


def _chol_inverse(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    chol = np.linalg.cholesky(r)
    linv = np.linalg.inv(chol)
    log_norm = _LOG_NORM - np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1)
    return np.ascontiguousarray(np.tril(linv)), log_norm


def transform_batch(
    src_sets: np.ndarray,
    src_logw: np.ndarray,
    src_index: np.ndarray,
    src_shift: np.ndarray,
    tgt_sets: np.ndarray,
    tgt_index: np.ndarray,
    tgt_shift: np.ndarray,
    r: np.ndarray,
    kernel: str = "grid",
    cutoff_d2: float = 55.0,
    rel_tol: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray]:
    """P independent Gauss transforms in one parallel call.

    Problem p: sources ``src_sets[src_index[p]] + src_shift[p]`` with
    log-weights ``src_logw[p]`` (Js,), targets ``tgt_sets[tgt_index[p]] +
    tgt_shift[p]``, kernel N(y - x; 0, r[p]). Returns ``(log_out (P, Jt),
    pair_evaluations (P,))``, log_out[p, j] = log sum_s exp(logw_s) N(y_j - x_s; 0, R_p).
    """
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {KERNELS}")
    if not cutoff_d2 > 0 or not rel_tol > 0:
        raise ValueError("cutoff_d2 and rel_tol must be positive")
    src_index = np.ascontiguousarray(src_index, dtype=np.int64)
    tgt_index = np.ascontiguousarray(tgt_index, dtype=np.int64)
    p = src_index.size
    jt = tgt_sets.shape[1] if tgt_sets.ndim == 3 else 0
    out = np.empty((p, jt))
    pairs = np.zeros(p, dtype=np.int64)
    if p == 0:
        return out, pairs
    linv, log_norm = _chol_inverse(np.asarray(r, dtype=float).reshape(p, 4, 4))
    _batch(
        np.ascontiguousarray(src_sets, dtype=float), np.ascontiguousarray(src_logw, dtype=float), src_index,
        np.ascontiguousarray(src_shift, dtype=float).reshape(p, 4), np.ascontiguousarray(tgt_sets, dtype=float),
        tgt_index, np.ascontiguousarray(tgt_shift, dtype=float).reshape(p, 4), linv, log_norm,
        kernel == "grid", float(cutoff_d2), float(rel_tol), out, pairs,
    )
    return out, pairs


def transform(src, src_logw, tgt, r, kernel: str = "grid", cutoff_d2: float = 55.0, rel_tol: float = 1e-6):
    """One Gauss transform: log sum_s exp(logw_s) N(tgt_j - src_s; 0, r), (Jt,)."""
    out, _ = transform_batch(
        np.asarray(src, float)[None], np.asarray(src_logw, float)[None], np.zeros(1, np.int64), np.zeros((1, 4)),
        np.asarray(tgt, float)[None], np.zeros(1, np.int64), np.zeros((1, 4)), np.asarray(r, float)[None],
        kernel, cutoff_d2, rel_tol,
    )
    return out[0]


def transform_brute(src, src_logw, tgt, r) -> np.ndarray:
    """Plain numpy reference (scipy's logsumexp over the full pair matrix), for tests."""
    from scipy.special import logsumexp
    from scipy.stats import multivariate_normal

    d = np.asarray(tgt, float)[:, None, :] - np.asarray(src, float)[None, :, :]
    logk = multivariate_normal(mean=np.zeros(4), cov=r).logpdf(d.reshape(-1, 4)).reshape(d.shape[:2])
    return logsumexp(logk + np.asarray(src_logw, float)[None, :], axis=1)
