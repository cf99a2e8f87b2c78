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
(:func:`_exp_neg`, relative error below 1e-12) so that they vectorize. How much
it saves depends on the clouds: the pairs it must visit lie within about 6
whitened units of the target, a small share of 8 m GNSS clouds (11 % of the
pairs at J = 5000, counted per whole leaf) and two fifths of clouds only 1.5 m
or 0.7 m wide (``bench/pf_kernels.py``). ``brute`` evaluates every pair, in log
domain, and is the reference.

All kernels are numba, ``cache=True``; the batched entry point runs the
independent (source set, target set, shift) problems of one BPA-L pass in
parallel (``prange``) and returns the number of pair evaluations (for
``bench/pf_kernels.py``).

BPA-L sums the same pairs under the same kernel in every iteration of a step;
only the source weights (the cavities) change. :func:`fixed_transforms` builds
those problems' kernel matrices once (float32, every pair, scaled per target by
its nearest source) and :func:`transform_fixed` then sums them for any weights
as a matrix-vector product with the same per-entry ``rel_tol`` guarantee: about
6.6e9 pairs per second on two cores of this machine, where the tree's exp
manages about 1.7e9 (memory bound: 4 bytes a pair).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["KERNELS", "FixedTransforms", "KernelWorkspace", "RepeatedTransforms", "fixed_transforms",
           "fixed_transforms_summed", "kept_problem_count", "transform_batch", "transform_brute", "transform",
           "transform_fixed"]

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
def _scaled_weights(src_logw, ws):
    """ws = exp(logw - max) (every source weight relative to the largest); returns (max, sum of ws)."""
    wmax = -np.inf
    for s in range(src_logw.shape[0]):
        wmax = max(wmax, src_logw[s])
    total = 0.0
    for s in range(src_logw.shape[0]):
        ws[s] = math.exp(src_logw[s] - wmax) if wmax > -np.inf else 0.0
        total += ws[s]
    return wmax, total


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
    ws = np.empty(js)  # source weights on a linear scale relative to the largest
    wmax, _ = _scaled_weights(src_logw, ws)
    if wmax == -np.inf:
        for t in range(jt):
            out[t] = -np.inf
        return 0
    if not use_tree:
        for t in range(jt):
            out[t] = _exact_log_sum(src_w, src_logw, wmax, tgt_w[t]) + log_norm
        return jt * js
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


_EXP_NEG_MAX = 690.0  # exp(-690) = 2.6e-300: terms 1e-300 below the leaf's scale are dropped
_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01  # ln 2 split in two (Cody and Waite): k * _LN2_HI is exact for k < 2^20
_LN2_LO = 1.90821492927058770002e-10


@intrinsic
def _f64_from_bits(typingctx, bits):
    """The float64 whose IEEE-754 bit pattern is the int64 ``bits`` (an LLVM bitcast, vectorizes)."""
    sig = types.float64(types.int64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return sig, codegen


@nb.njit(cache=True, inline="always")
def _exp_neg(y):
    """exp(-y) for y >= 0 in plain arithmetic (so that leaf loops vectorize; numba's math.exp does not).

    Range reduction exp(-y) = 2^-k exp(r), k = round(y / ln 2), r = k ln 2 - y in [-ln2 / 2, ln2 / 2]
    (ln 2 in two parts, so r is exact to the last bits), a degree-10 Taylor polynomial for exp(r)
    and 2^-k written straight into the exponent bits. Relative error below 1e-12 (tests; 3e-13
    measured), far inside the kernels' 1e-6; exactly 0 from y = _EXP_NEG_MAX on (terms 1e-300
    below the leaf's scale). Against the former exp(-y / 1024)^1024 (a polynomial and ten
    squarings) the tree transform is 1.3-1.4x faster (``bench/pf_kernels.py``, J = 5000, this
    machine, AVX-512: 0.027-0.030 s against 0.037-0.041 s on the smoothed cases).
    """
    yc = min(y, _EXP_NEG_MAX)
    k = math.floor(yc * _LOG2E + 0.5)
    r = (k * _LN2_HI - yc) + k * _LN2_LO
    p = 1.0 / 3628800.0
    p = p * r + 1.0 / 362880.0
    p = p * r + 1.0 / 40320.0
    p = p * r + 1.0 / 5040.0
    p = p * r + 1.0 / 720.0
    p = p * r + 1.0 / 120.0
    p = p * r + 1.0 / 24.0
    p = p * r + 1.0 / 6.0
    p = p * r + 0.5
    p = p * r + 1.0
    p = p * r + 1.0
    scale = _f64_from_bits((1023 - np.int64(k)) << 52)  # 2^-k, k <= 996 here: a normal number
    return p * scale if y < _EXP_NEG_MAX else 0.0


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


# ----------------------------------------------------------------------------- kept kernel matrices

# A kept kernel value is exp(-(q - q_min) / 2) in float32 (q: the pair's squared whitened distance,
# q_min: the target's nearest source), 0 from (q - q_min) / 2 = 87 on (exp(-87) = 1.6e-38, the
# smallest normal float32 is 1.2e-38: no subnormal arithmetic in the sums). Per entry the sum then
# errs by at most 2^-24 (float32 rounding, every term positive) plus the dropped mass, at most
# W exp(-87) for source weight W; an entry whose sum is below W exp(-87) / (rel_tol - 2^-24) is
# summed again exactly, so every entry keeps the ``rel_tol`` guarantee of the tree kernel.
_DENSE_CUT = 87.0
_F32_EPS = 2.0 ** -24
DENSE_BYTES_PER_PAIR = 4


@nb.njit(cache=True, fastmath={"reassoc", "contract"})
def _dense_row(px, py, pvx, pvy, u0, u1, u2, u3, q, row):
    """row[s] = exp(-(q_s - q_min) / 2) as float32 (0 beyond _DENSE_CUT); returns q_min. Whole arrays
    (as :func:`_leaf_sum`: with indices into larger ones LLVM stops vectorizing)."""
    qmin = np.inf
    for s in range(px.shape[0]):
        d0, d1, d2, d3 = px[s] - u0, py[s] - u1, pvx[s] - u2, pvy[s] - u3
        q[s] = d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3
        qmin = min(qmin, q[s])
    for s in range(px.shape[0]):
        y = 0.5 * (q[s] - qmin)
        row[s] = np.float32(_exp_neg(y) if y < _DENSE_CUT else 0.0)
    return qmin


@nb.njit(cache=True, fastmath={"reassoc", "contract"})
def _dense_row_sum(row, ws):
    acc = 0.0
    for s in range(row.shape[0]):
        acc += row[s] * ws[s]
    return acc


@nb.njit(cache=True)
def _finish_dense(acc, total, wmax, low, log_norm, src_w, src_logw, tgt_w, rel_tol, out):
    """out[t] = log of the weighted sum of row t from its product ``acc[t]`` with the scaled weights; the
    exact log-sum where the float32 values cannot vouch for it (the sum below the dropped mass bound)."""
    if wmax == -np.inf:
        out[:] = -np.inf
        return
    floor = total * math.exp(-_DENSE_CUT) / (rel_tol - _F32_EPS)
    for t in range(acc.shape[0]):
        if acc[t] > floor:
            out[t] = math.log(acc[t]) - 0.5 * low[t] + wmax + log_norm
        else:  # every term in log domain
            out[t] = _exact_log_sum(src_w, src_logw, wmax, tgt_w[t]) + log_norm


@nb.njit(cache=True)
def _dense_problem(src, src_shift, tgt, tgt_shift, linv, values, low, src_w, tgt_w, first_logw, log_norm, rel_tol,
                   first_out):
    """Whiten one problem's particles and fill its kernel values (Jt, Js) and q_min (Jt,); with
    ``first_logw`` (Js,) (empty: none) also its sum for those weights into ``first_out``, each row
    while it is still in cache (the first BPA-L iteration's)."""
    js, jt = src.shape[0], tgt.shape[0]
    for s in range(js):
        _whiten(src[s], src_shift, linv, src_w[s])
    for t in range(jt):
        _whiten(tgt[t], tgt_shift, linv, tgt_w[t])
    px, py, pvx, pvy = src_w[:, 0].copy(), src_w[:, 1].copy(), src_w[:, 2].copy(), src_w[:, 3].copy()
    q = np.empty(js)
    summed = first_logw.shape[0] > 0
    ws = np.empty(js if summed else 0)
    wmax, total = _scaled_weights(first_logw, ws) if summed else (0.0, 0.0)
    acc = np.empty(jt)
    for t in range(jt):
        low[t] = _dense_row(px, py, pvx, pvy, tgt_w[t, 0], tgt_w[t, 1], tgt_w[t, 2], tgt_w[t, 3], q, values[t])
        if summed:
            acc[t] = _dense_row_sum(values[t], ws)
    if summed:
        _finish_dense(acc, total, wmax, low, log_norm, src_w, first_logw, tgt_w, rel_tol, first_out)


@nb.njit(cache=True, parallel=True)
def _build_dense(src_sets, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, linv, values, low, src_w, tgt_w,
                 first_logw, log_norm, rel_tol, first_out):
    for p in nb.prange(src_index.shape[0]):
        _dense_problem(src_sets[src_index[p]], src_shift[p], tgt_sets[tgt_index[p]], tgt_shift[p], linv[p],
                       values[p], low[p], src_w[p], tgt_w[p], first_logw[p], log_norm[p], rel_tol, first_out[p])


@nb.njit(cache=True, parallel=True)
def _apply_dense(values, low, log_norm, src_w, tgt_w, src_logw, problems, rel_tol, out):
    """out[q, t] = log sum_s exp(logw_s) N(...) of the kept problem ``problems[q]`` for the weights
    ``src_logw[q]``, from the kept values; exact log-sum where they cannot vouch."""
    for q in nb.prange(problems.shape[0]):
        p = problems[q]
        ws = np.empty(values.shape[2])
        wmax, total = _scaled_weights(src_logw[q], ws)
        acc = np.empty(values.shape[1])
        if wmax > -np.inf:
            for t in range(values.shape[1]):
                acc[t] = _dense_row_sum(values[p, t], ws)
        _finish_dense(acc, total, wmax, low[p], log_norm[p], src_w[p], src_logw[q], tgt_w[p], rel_tol, out[q])


class KernelWorkspace:
    """Reusable float32 storage for kept kernel matrices, owned by one estimator.

    Memory new to a process is slow to write in the parallel build here (single road, J = 5000:
    the first step that writes the 1.6 GB built in 1.7 s in a process's first run, 0.4 s in its
    second, whose estimator had new storage too), so the storage is kept and grown from step to
    step; every value is written by :func:`fixed_transforms` before it is read.
    """

    def __init__(self) -> None:
        self._buffer = np.empty(0, np.float32)

    def arrays(self, *counts: int) -> list[np.ndarray]:
        """Disjoint flat float32 arrays of the given lengths (valid until the next call)."""
        need = int(sum(counts))
        if self._buffer.size < need:
            self._buffer = np.empty(need, np.float32)
        bounds = np.cumsum((0,) + tuple(int(c) for c in counts))
        return [self._buffer[a:b] for a, b in zip(bounds[:-1], bounds[1:])]


@dataclass(frozen=True)
class FixedTransforms:
    """P Gauss transforms whose particles and kernels stay fixed while the source weights change
    (the BPA-L iterations of one step): the problems in ``kept`` hold their kernel matrices
    (float32, :func:`_build_dense`), the others are summed anew by :func:`transform_batch`."""

    args: tuple  # (src_sets, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r) as given
    kernel: str
    rel_tol: float
    kept: np.ndarray  # (P,) bool
    values: np.ndarray  # (K, Jt, Js) float32, the kept problems in order
    low: np.ndarray  # (K, Jt)
    log_norm: np.ndarray  # (K,)
    src_w: np.ndarray  # (K, Js, 4) whitened sources (for the exact fallback)
    tgt_w: np.ndarray  # (K, Jt, 4)
    build_pairs: np.ndarray  # (P,) kernel evaluations of the build


def kept_problem_count(n_problems: int, js: int, jt: int, kernel: str, rel_tol: float, max_bytes: float) -> int:
    """How many of the problems (the first ones) keep their kernel matrices within ``max_bytes``."""
    if kernel != "tree" or not rel_tol > 4.0 * _F32_EPS or js == 0 or jt == 0:
        return 0
    return min(n_problems, int(max_bytes // (DENSE_BYTES_PER_PAIR * js * jt)))


def fixed_transforms(src_sets, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r, kernel: str = "tree",
                     rel_tol: float = 1e-6, max_bytes: float = 0.0, storage: np.ndarray | None = None
                     ) -> FixedTransforms:
    """Prepare :func:`transform_batch`'s problems for repeated sums (:func:`transform_fixed`).

    With ``kernel = "tree"`` the first problems whose kernel matrices fit in ``max_bytes``
    (4 bytes per pair) keep them: each later sum is then a matrix-vector product, about four times
    the pair rate of the tree's exp (``bench/pf_kernels.py``), exact to ``rel_tol`` per entry as
    the tree (needs ``rel_tol`` above float32's 2^-24; below it nothing is kept). ``storage``: a flat
    float32 array of at least :func:`kept_problem_count` x Jt x Js values to build them in
    (:class:`KernelWorkspace`); None allocates.
    """
    return _build_fixed(src_sets, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r, kernel, rel_tol,
                        max_bytes, storage, None)[0]


def fixed_transforms_summed(src_sets, src_logw, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r,
                            kernel: str = "tree", rel_tol: float = 1e-6, max_bytes: float = 0.0,
                            storage: np.ndarray | None = None) -> tuple[FixedTransforms, np.ndarray, np.ndarray]:
    """:func:`fixed_transforms` and, in the same pass, ``transform_fixed(fixed, src_logw)``: each kept
    row is summed while it is still in cache, so the first sum costs no second read of the matrices
    (BPA-L's first iteration). Returns ``(fixed, log_out (P, Jt), kernel evaluations (P,))``, the
    evaluations those of the problems not kept (the build's are in ``fixed.build_pairs``)."""
    src_logw = np.ascontiguousarray(src_logw, dtype=float)
    fixed, kept_out = _build_fixed(src_sets, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r, kernel,
                                   rel_tol, max_bytes, storage, src_logw)
    out, pairs = _sum_fixed(fixed, src_logw, kept_out)
    return fixed, out, pairs


class RepeatedTransforms:
    """:func:`transform_batch`'s problems summed again and again for new source weights (BPA-L's
    iterations): the first :meth:`sum` builds the kept kernel matrices while it sums
    (:func:`fixed_transforms_summed`), every later one is their product (:func:`transform_fixed`)."""

    def __init__(self, src_sets, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r, kernel: str = "tree",
                 rel_tol: float = 1e-6, max_bytes: float = 0.0, storage: np.ndarray | None = None):
        self._problems = (src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r)
        self._src_sets = src_sets
        self._options = (kernel, rel_tol, max_bytes, storage)
        self.fixed: FixedTransforms | None = None

    def sum(self, src_logw: np.ndarray, problems: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(log_out (P, Jt), kernel evaluations (P,))`` for source log-weights (P, Js); the first
        call's evaluations include the build's. ``problems``: after the first call, sum only these
        (as :func:`transform_fixed`)."""
        if self.fixed is None:
            if problems is not None:
                raise ValueError("the first sum builds the kept matrices of every problem")
            self.fixed, out, pairs = fixed_transforms_summed(self._src_sets, src_logw, *self._problems,
                                                             *self._options)
            return out, pairs + self.fixed.build_pairs
        return transform_fixed(self.fixed, src_logw, problems)


def _build_fixed(src_sets, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r, kernel, rel_tol, max_bytes,
                 storage, first_logw) -> tuple[FixedTransforms, np.ndarray]:
    src_index = np.ascontiguousarray(src_index, dtype=np.int64)
    tgt_index = np.ascontiguousarray(tgt_index, dtype=np.int64)
    p = src_index.size
    args = (src_sets, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r)
    js = src_sets.shape[1] if np.ndim(src_sets) == 3 else 0
    jt = tgt_sets.shape[1] if np.ndim(tgt_sets) == 3 else 0
    k = kept_problem_count(p, js, jt, kernel, rel_tol, max_bytes)
    kept = np.arange(p) < k
    if storage is None:
        values = np.empty((k, jt, js), np.float32)
    else:
        values = storage[: k * jt * js].reshape(k, jt, js)
    low, src_w, tgt_w = np.empty((k, jt)), np.empty((k, js, 4)), np.empty((k, jt, 4))
    log_norm = np.empty(k)
    build_pairs = np.zeros(p, np.int64)
    first_kept = np.empty((k, 0)) if first_logw is None else np.ascontiguousarray(first_logw[kept])
    kept_out = np.empty((k, jt if first_logw is not None else 0))
    if k:
        linv, log_norm = _chol_inverse(np.asarray(r, dtype=float).reshape(p, 4, 4)[kept])
        _build_dense(np.ascontiguousarray(src_sets, dtype=float), src_index[kept],
                     np.ascontiguousarray(np.asarray(src_shift, dtype=float).reshape(p, 4)[kept]),
                     np.ascontiguousarray(tgt_sets, dtype=float), tgt_index[kept],
                     np.ascontiguousarray(np.asarray(tgt_shift, dtype=float).reshape(p, 4)[kept]),
                     linv, values, low, src_w, tgt_w, first_kept, log_norm, float(rel_tol), kept_out)
        build_pairs[kept] = js * jt
    fixed = FixedTransforms(args, kernel, float(rel_tol), kept, values, low, log_norm, src_w, tgt_w, build_pairs)
    return fixed, kept_out


def transform_fixed(fixed: FixedTransforms, src_logw: np.ndarray,
                    problems: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`transform_batch` of the prepared problems with source log-weights ``src_logw`` (P, Js).

    Returns ``(log_out (P, Jt), kernel evaluations (P,))``; a kept problem evaluates none (its matrix
    was built by :func:`fixed_transforms`, whose ``build_pairs`` count them). ``problems``: sum only
    these (sorted indices; ``src_logw`` and the output have one row each, in their order); every
    problem's sum is the same, bit for bit, with or without the others."""
    src_logw = np.ascontiguousarray(src_logw, dtype=float)
    problems = np.arange(fixed.kept.size) if problems is None else np.asarray(problems, dtype=np.int64)
    kept = fixed.kept[problems]
    kept_out = np.empty((int(kept.sum()), fixed.low.shape[1]))
    if kept.any():  # the kept problems are the first ones, stored in order
        _apply_dense(fixed.values, fixed.low, fixed.log_norm, fixed.src_w, fixed.tgt_w,
                     np.ascontiguousarray(src_logw[kept]), problems[kept], fixed.rel_tol, kept_out)
    return _sum_fixed(fixed, src_logw, kept_out, problems)


def _sum_fixed(fixed: FixedTransforms, src_logw: np.ndarray, kept_out: np.ndarray,
               problems: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The sums of ``problems`` (all P if None): the kept problems' ``kept_out``, the others by
    :func:`transform_batch`."""
    p = fixed.kept.size
    problems = np.arange(p) if problems is None else problems
    kept = fixed.kept[problems]
    jt = fixed.args[3].shape[1] if np.ndim(fixed.args[3]) == 3 else 0
    out = np.empty((problems.size, jt))
    pairs = np.zeros(problems.size, np.int64)
    out[kept] = kept_out
    rest = ~kept
    if rest.any():
        src_sets, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r = fixed.args
        sel = problems[rest]
        out[rest], pairs[rest] = transform_batch(
            src_sets, src_logw[rest], src_index[sel], np.asarray(src_shift, float).reshape(p, 4)[sel], tgt_sets,
            tgt_index[sel], np.asarray(tgt_shift, float).reshape(p, 4)[sel],
            np.asarray(r, float).reshape(p, 4, 4)[sel], fixed.kernel, fixed.rel_tol)
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
