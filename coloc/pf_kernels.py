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
``tree`` kernel puts the (whitened) sources in a k-d tree with the weight sum
and bounding box of every node; each target walks it nearest child first and
leaves out a node whose every pair is so far away that
exp(-dmin^2 / 2) x (all source weight) <= ``rel_tol`` x (the sum found so far).
The nodes left out are disjoint, so the mass they hold is at most ``rel_tol``
times the sum found: **every output entry is within rel_tol (default 1e-6) of
the brute-force sum, relatively**, tails included: a target's terms are scaled
by its distance to the sources' bounding box, so targets far from every source
do not underflow (where they still would, :func:`_exact_log_sum` sums in log
domain). Leaf sums (leaves of ``_LEAF_SIZE`` sources) use a polynomial exp
(:func:`_exp_neg`, relative error below 2e-10) so that they vectorize. How much
it saves depends on the clouds: the pairs it must visit lie within about 6
whitened units of the target, a small share of 8 m GNSS clouds (11 % of the
pairs at J = 5000, counted per whole leaf) and two fifths of clouds only 1.5 m
or 0.7 m wide (``bench/pf_kernels.py``). ``brute`` evaluates every pair, in log
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

KERNELS = ("tree", "brute")
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
def _one_problem(src, src_logw, src_shift, tgt, tgt_shift, linv, log_norm, use_tree, rel_tol, out):
    """Fill ``out`` (Jt,) with log sum_s w_s N(...); returns the number of pair evaluations."""
    js = src.shape[0]
    jt = tgt.shape[0]
    src_w = np.empty((js, 4))
    for s in range(js):
        _whiten(src[s], src_shift, linv, src_w[s])
    tgt_w = np.empty((jt, 4))
    for t in range(jt):
        _whiten(tgt[t], tgt_shift, linv, tgt_w[t])
    wmax = -np.inf
    for s in range(js):
        if src_logw[s] > wmax:
            wmax = src_logw[s]
    if wmax == -np.inf:
        for t in range(jt):
            out[t] = -np.inf
        return 0
    if not use_tree:
        for t in range(jt):
            out[t] = _exact_log_sum(src_w, src_logw, wmax, tgt_w[t]) + log_norm
        return jt * js
    ws = np.empty(js)  # source weights on a linear scale relative to the largest
    for s in range(js):
        ws[s] = math.exp(src_logw[s] - wmax)
    acc = np.empty(jt)
    low = np.empty(jt)
    pairs = _tree_sums(src_w, ws, tgt_w, rel_tol, acc, low)
    for t in range(jt):
        if acc[t] > 1e-250:
            out[t] = math.log(acc[t]) - 0.5 * low[t] + wmax + log_norm
        else:  # the box bound was too loose (terms underflow on a linear scale): the log-domain sum
            out[t] = _exact_log_sum(src_w, src_logw, wmax, tgt_w[t]) + log_norm
            pairs += js
    return pairs


# Sources per leaf. Larger leaves prune less but sum at the vectorized rate: at J = 5000 a
# transform where every pair counts took 0.20 / 0.10 / 0.07 s with leaves of 64 / 256 / 1024,
# one where the tree skips 97 % of the pairs 0.008 / 0.012 / 0.016 s (bench cases, one core).
_LEAF_SIZE = 512


@nb.njit(cache=True)
def _build_tree(pts, ws, leaf_size):
    """k-d tree over the (whitened) source points: median splits on the widest box side.

    Returns the permutation (sources of node n are perm[start[n]:end[n]]), child
    indices (-1 for leaves), bounding boxes and the weight sum of every node.
    """
    n = pts.shape[0]
    max_nodes = 4 * (n // leaf_size) + 4
    perm = np.arange(n)
    start = np.empty(max_nodes, np.int64)
    end = np.empty(max_nodes, np.int64)
    left = np.full(max_nodes, -1, np.int64)
    right = np.full(max_nodes, -1, np.int64)
    lo = np.empty((max_nodes, 4))
    hi = np.empty((max_nodes, 4))
    wsum = np.empty(max_nodes)
    stack = np.empty(128, np.int64)
    start[0], end[0] = 0, n
    n_nodes, sp = 1, 1
    stack[0] = 0
    while sp > 0:
        sp -= 1
        node = stack[sp]
        a, b = start[node], end[node]
        w = 0.0
        for d in range(4):
            lo[node, d] = np.inf
            hi[node, d] = -np.inf
        for i in range(a, b):
            s = perm[i]
            w += ws[s]
            for d in range(4):
                v = pts[s, d]
                if v < lo[node, d]:
                    lo[node, d] = v
                if v > hi[node, d]:
                    hi[node, d] = v
        wsum[node] = w
        if b - a <= leaf_size:
            continue
        dim = 0
        for d in range(1, 4):
            if hi[node, d] - lo[node, d] > hi[node, dim] - lo[node, dim]:
                dim = d
        if not hi[node, dim] > lo[node, dim]:  # identical points: one leaf
            continue
        idx = perm[a:b].copy()
        vals = np.empty(b - a)
        for i in range(b - a):
            vals[i] = pts[idx[i], dim]
        order = np.argsort(vals, kind="mergesort")
        for i in range(b - a):
            perm[a + i] = idx[order[i]]
        mid = (a + b) // 2
        left[node], right[node] = n_nodes, n_nodes + 1
        start[n_nodes], end[n_nodes] = a, mid
        start[n_nodes + 1], end[n_nodes + 1] = mid, b
        stack[sp] = n_nodes
        stack[sp + 1] = n_nodes + 1
        sp += 2
        n_nodes += 2
    return perm, start, end, left, right, lo, hi, wsum


@nb.njit(cache=True, inline="always")
def _box_sq_dist(lo, hi, u):
    d2 = 0.0
    for a in range(4):
        if u[a] < lo[a]:
            d = lo[a] - u[a]
            d2 += d * d
        elif u[a] > hi[a]:
            d = u[a] - hi[a]
            d2 += d * d
    return d2


_EXP_NEG_MAX = 690.0  # exp(-690) = 2.6e-300: every squaring below stays a normal number


@nb.njit(cache=True, inline="always")
def _exp_neg(y):
    """exp(-y) for y >= 0 in plain arithmetic (so that leaf loops vectorize; numba's math.exp does not).

    exp(-y) = exp(-y / 1024)^1024: a degree-14 Taylor polynomial on [0, 0.67], then ten
    squarings; exactly 0 from y = _EXP_NEG_MAX on, so that no squaring passes through
    subnormal numbers (10x slower on x86). Relative error below 2e-10 below that (tests),
    far inside the kernels' 1e-6; the terms dropped are 1e-300 below the leaf's scale.
    """
    x = -min(y, _EXP_NEG_MAX) * (1.0 / 1024.0)
    p = 1.0 / 87178291200.0
    p = p * x + 1.0 / 6227020800.0
    p = p * x + 1.0 / 479001600.0
    p = p * x + 1.0 / 39916800.0
    p = p * x + 1.0 / 3628800.0
    p = p * x + 1.0 / 362880.0
    p = p * x + 1.0 / 40320.0
    p = p * x + 1.0 / 5040.0
    p = p * x + 1.0 / 720.0
    p = p * x + 1.0 / 120.0
    p = p * x + 1.0 / 24.0
    p = p * x + 1.0 / 6.0
    p = p * x + 0.5
    p = p * x + 1.0
    p = p * x + 1.0
    for _ in range(10):
        p = p * p
    return p if y < _EXP_NEG_MAX else 0.0


@nb.njit(cache=True, fastmath={"reassoc", "contract"})
def _leaf_sum(px, py, pvx, pvy, pw, u0, u1, u2, u3, low):
    """sum_i w_i exp(-(|p_i - u|^2 - low) / 2) over whole arrays, low <= every |p_i - u|^2 (vectorized).

    The caller passes a leaf's slices: with start / end indices instead, LLVM inlines this loop into
    the tree walk and no longer vectorizes it (7e7 against 5e8 pairs/s, one core of this machine).
    """
    acc = 0.0
    for i in range(px.shape[0]):
        d0, d1, d2, d3 = px[i] - u0, py[i] - u1, pvx[i] - u2, pvy[i] - u3
        acc += pw[i] * _exp_neg(0.5 * (d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3 - low))
    return acc


@nb.njit(cache=True)
def _tree_sums(src_w, ws, tgt_w, rel_tol, acc_out, low_out):
    """acc_out[t] = exp(low_out[t] / 2) sum_s ws_s exp(-|u_s - u_t|^2 / 2) within rel_tol (relative), k-d tree pruned.

    low_out[t] is the squared distance from target t to the sources' bounding box, a lower
    bound of every pair's: the scaling keeps targets far from every source from underflowing.

    A node whose every pair lies at whitened distance >= dmin contributes at
    most W_node exp(-dmin^2 / 2). Nearest child first; a node is skipped when
    exp(-dmin^2 / 2) <= rel_tol acc / W (acc: the sum found so far, W: all
    source weight). Skipped nodes are disjoint, so the mass left out is at
    most sum_n W_n rel_tol acc / W <= rel_tol acc <= rel_tol x (exact sum).
    Returns the number of pair evaluations.
    """
    js = src_w.shape[0]
    perm, start, end, left, right, lo, hi, wsum = _build_tree(src_w, ws, _LEAF_SIZE)
    px, py, pvx, pvy, pw = np.empty(js), np.empty(js), np.empty(js), np.empty(js), np.empty(js)
    for i in range(js):  # leaf-contiguous, one array per coordinate: the leaf loop vectorizes
        s = perm[i]
        px[i], py[i], pvx[i], pvy[i], pw[i] = src_w[s, 0], src_w[s, 1], src_w[s, 2], src_w[s, 3], ws[s]
    total = wsum[0]
    stack = np.empty(256, np.int64)
    stack_d2 = np.empty(256)
    pairs = 0
    for t in range(tgt_w.shape[0]):
        u = tgt_w[t]
        acc = 0.0
        stack[0] = 0
        stack_d2[0] = _box_sq_dist(lo[0], hi[0], u)
        low = stack_d2[0]  # a lower bound of every |u_s - u|^2: terms scaled by exp(low / 2) stay <= 1
        low_out[t] = low
        sp = 1
        while sp > 0:
            sp -= 1
            node = stack[sp]
            if acc > 0.0 and math.exp(-0.5 * (stack_d2[sp] - low)) * total <= rel_tol * acc:
                continue
            if left[node] < 0:
                a, b = start[node], end[node]
                acc += _leaf_sum(px[a:b], py[a:b], pvx[a:b], pvy[a:b], pw[a:b], u[0], u[1], u[2], u[3], low)
                pairs += end[node] - start[node]
                continue
            c1, c2 = left[node], right[node]
            d1 = _box_sq_dist(lo[c1], hi[c1], u)
            d2 = _box_sq_dist(lo[c2], hi[c2], u)
            if d1 <= d2:  # push the farther child first: the nearer one is visited next
                c1, c2, d1, d2 = c2, c1, d2, d1
            stack[sp], stack_d2[sp] = c1, d1
            stack[sp + 1], stack_d2[sp + 1] = c2, d2
            sp += 2
        acc_out[t] = acc
    return pairs


@nb.njit(cache=True, parallel=True)
def _batch(src_sets, src_logw, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, linv, log_norm, use_tree,
           rel_tol, out, pairs):
    for p in nb.prange(src_index.shape[0]):
        pairs[p] = _one_problem(
            src_sets[src_index[p]], src_logw[p], src_shift[p], tgt_sets[tgt_index[p]], tgt_shift[p], linv[p],
            log_norm[p], use_tree, rel_tol, out[p],
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
    kernel: str = "tree",
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
    if not rel_tol > 0:
        raise ValueError("rel_tol must be positive")
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
        kernel == "tree", float(rel_tol), out, pairs,
    )
    return out, pairs


def transform(src, src_logw, tgt, r, kernel: str = "tree", rel_tol: float = 1e-6):
    """One Gauss transform: log sum_s exp(logw_s) N(tgt_j - src_s; 0, r), (Jt,)."""
    out, _ = transform_batch(
        np.asarray(src, float)[None], np.asarray(src_logw, float)[None], np.zeros(1, np.int64), np.zeros((1, 4)),
        np.asarray(tgt, float)[None], np.zeros(1, np.int64), np.zeros((1, 4)), np.asarray(r, float)[None],
        kernel, rel_tol,
    )
    return out[0]


def transform_brute(src, src_logw, tgt, r) -> np.ndarray:
    """Plain numpy reference (scipy's logsumexp over the full pair matrix), for tests."""
    from scipy.special import logsumexp
    from scipy.stats import multivariate_normal

    d = np.asarray(tgt, float)[:, None, :] - np.asarray(src, float)[None, :, :]
    logk = multivariate_normal(mean=np.zeros(4), cov=r).logpdf(d.reshape(-1, 4)).reshape(d.shape[:2])
    return logsumexp(logk + np.asarray(src_logw, float)[None, :], axis=1)
