"""Approximate Gauss transforms of ICP-DA-PF (``[pf] kernel = "fast"``): every entry within 1e-3 relative.

The same sums as :mod:`coloc.kernels.pf` (eqs. (25)-(27) of Brambilla et al.),

    out_j = log sum_s exp(logw_s) N(y_j - x_s; 0, R)

with a stated per-entry bound instead of the exact tree's 1e-6. With the kernel density messages
(``message_bandwidth = "prior"``, the default) almost every pair counts, so the exact tree cannot
prune (``docs/validation/pf.md``); what is left to gain is the cost of a pair. This kernel:

* evaluates every pair (no pruning), in **float32**: the whitened coordinates about the source set's
  mean, the squared distance q, exp(-(q - low) / 2) by a degree-5 polynomial after Cody-Waite range
  reduction (:func:`_exp32`, relative error 3.3e-6 measured: :data:`EXP_REL_ERROR`) and partial sums
  over at most 256 terms (totals in float64), 16 lanes a vector where the exact kernels' float64 has
  8; ``low`` is the target's squared distance to the sources' bounding box, so no term exceeds 1.
  Where float32 distances are not precise enough, i.e. sources more than 32 whitened units from their
  mean (the problem) or a target more than 20 from the sources' box (the row), the distances are
  float64 and the row is scaled by its nearest source. Together at most 4e-4 relative
  (:data:`ROUNDING_REL_ERROR`; 1.6e-4 measured at worst);
* keeps BPA-L's kernel matrices (:class:`FastRepeatedTransforms`) in **16 bits a pair** instead of
  32: the float32 value's exponent (2^-63 to 1) and the top 10 bits of its mantissa, rounded to
  nearest (relative error at most 2^-11 = 4.9e-4: :data:`CODE_REL_ERROR`), so every later BPA-L
  iteration reads half the memory of the exact path's float32 matrices;
* terms more than 43.5 below the row's scale (e^-43.5 = 1.3e-19) count as e^-43.5 (one-off sums) or
  2^-63 (the smallest code) times their weight: with the float32 weights that underflow, the mass so
  misstated is at most W 2^-61 per entry for source weight W (scaled to the largest); an entry whose
  sum is not that far above it for the rest of the budget is summed again exactly in log domain
  (:func:`coloc.kernels.pf._exact_log_sum`).

**Bound**: every entry is within :data:`FAST_REL_TOL` = 1e-3 of the brute-force sum, relatively,
tails included: 4.9e-4 (16-bit values; one-off sums, which keep no matrix, have none of it) + 4e-4
(float32 distances, exponential and partial sums) + the misstated tail mass, at most the rest of
the budget by the fallback (every term is positive, so relative errors of terms bound the sum's).
Tested against scipy on random problems (``tests/coloc/test_pf_fast.py``). A particle filter at
J = 5000 carries a Monte Carlo error of order 1/sqrt(J) = 1.4 %; what this bound does to the
estimates is measured by ``tools/pf_equivalence.py``.

Deterministic: every entry is one problem's sum in a fixed order (``prange`` over problems only),
so the result is the same bytes for any numba thread count.

With the bare V2F kernel (``message_bandwidth = "none"``) the exact tree skips most pairs and is
faster than this kernel, which never prunes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from coloc.kernels.pf import _chol_inverse, _exact_log_sum, _scaled_weights, _whiten

__all__ = ["FAST", "FAST_REL_TOL", "CODE_REL_ERROR", "EXP_REL_ERROR", "ROUNDING_REL_ERROR", "FAST_BYTES_PER_PAIR",
           "FastRepeatedTransforms", "fast_kept_problem_count", "fast_transform", "fast_transform_batch"]

FAST = "fast"
FAST_REL_TOL = 1e-3  # the per-entry relative bound of every sum of this module
CODE_REL_ERROR = 2.0 ** -11  # a kept 16-bit value: 10 mantissa bits, rounded to nearest
EXP_REL_ERROR = 1e-5  # _exp32 with its float32 argument (tested: below 3.4e-6 on a dense grid)
# float32 distances (sources within _EXTENT of their mean, targets within sqrt(_FAR) of their box) and exp
ROUNDING_REL_ERROR = 4e-4
FAST_BYTES_PER_PAIR = 2

_CUT = 43.5  # y = (q - q_min) / 2 from here on is coded as the smallest value, 2^-63 (e^-43.67)
_CODE_BASE = 64 << 10  # float32 bits >> 13 of 2^-63: code 0
# Bound of the misstated mass per unit of source weight (scaled to the largest): terms beyond _CUT
# (2^-62) and float32 source weights that underflow (below 2^-126 each, at most 2^-110 for 2^16 sources).
_TAIL = 2.0 ** -61
_CHUNK = 256  # float32 partial sums over at most this many terms (rounding <= 256 x 2^-24 = 1.5e-5)
_LOG2E32 = np.float32(1.4426950408889634)
_LN2_HI32 = np.float32(0.693145751953125)  # 0x3f317200: k * _LN2_HI32 exact for k < 2^11
_LN2_LO32 = np.float32(1.428606765330187e-06)


@intrinsic
def _f32_bits(typingctx, x):
    """The int32 IEEE-754 bit pattern of a float32 (an LLVM bitcast, vectorizes)."""
    sig = types.int32(types.float32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return sig, codegen


@intrinsic
def _f32_from_bits(typingctx, bits):
    """The float32 whose bit pattern is the int32 ``bits``."""
    sig = types.float32(types.int32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return sig, codegen


@nb.njit(cache=True, inline="always")
def _exp32_bits(y):
    """Bit pattern (int32) of float32 exp(-y) for float32 0 <= y <= _CUT (plain arithmetic: vectorizes).

    exp(-y) = 2^-k exp(r), k = round(y / ln 2), r = k ln 2 - y in [-ln2 / 2, ln2 / 2] (ln 2 in two
    float32 parts), exp(r) by its degree-5 Taylor polynomial (remainder |r|^6 / 720 < 2.5e-6), 2^-k
    by subtracting k from the exponent bits."""
    ki = np.int32(y * _LOG2E32 + np.float32(0.5))  # y >= 0: truncation is the floor
    k = np.float32(ki)
    r = (k * _LN2_HI32 - y) + k * _LN2_LO32
    p = np.float32(1.0 / 120.0)
    p = p * r + np.float32(1.0 / 24.0)
    p = p * r + np.float32(1.0 / 6.0)
    p = p * r + np.float32(0.5)
    p = p * r + np.float32(1.0)
    p = p * r + np.float32(1.0)
    return _f32_bits(p) - (ki << np.int32(23))


@nb.njit(cache=True, inline="always")
def _exp32(y):
    """float32 exp(-y), 0 <= y <= _CUT (relative error below EXP_REL_ERROR)."""
    return _f32_from_bits(_exp32_bits(y))


@nb.njit(cache=True, inline="always")
def _code(y):
    """16-bit code of exp(-min(y, _CUT)) (float32 y >= 0): exponent and 10 mantissa bits, rounded to nearest."""
    yc = y if y < np.float32(_CUT) else np.float32(_CUT)
    return np.uint16(((_exp32_bits(yc) + np.int32(0x1000)) >> np.int32(13)) - np.int32(_CODE_BASE))


@nb.njit(cache=True, inline="always")
def _decode(c):
    return _f32_from_bits((np.int32(c) + np.int32(_CODE_BASE)) << np.int32(13))


@nb.njit(cache=True, fastmath={"reassoc", "contract"})
def _row32(px, py, pvx, pvy, ws, u0, u1, u2, u3, low):
    """sum_s ws_s exp(-(|p_s - u|^2 - low) / 2), float32 throughout, terms beyond _CUT as e^-_CUT (whole
    arrays: the loop vectorizes, 16 lanes)."""
    acc = np.float32(0.0)
    for s in range(px.shape[0]):
        d0, d1, d2, d3 = px[s] - u0, py[s] - u1, pvx[s] - u2, pvy[s] - u3
        y = np.float32(0.5) * (d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3 - low)
        y = y if y < np.float32(_CUT) else np.float32(_CUT)
        y = y if y > np.float32(0.0) else np.float32(0.0)
        acc += ws[s] * _exp32(y)
    return acc


@nb.njit(cache=True, fastmath={"reassoc", "contract"})
def _code_row32(px, py, pvx, pvy, u0, u1, u2, u3, low, row):
    for s in range(px.shape[0]):
        d0, d1, d2, d3 = px[s] - u0, py[s] - u1, pvx[s] - u2, pvy[s] - u3
        y = np.float32(0.5) * (d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3 - low)
        y = y if y > np.float32(0.0) else np.float32(0.0)
        row[s] = _code(y)


@nb.njit(cache=True, fastmath={"reassoc", "contract"})
def _row_q(px, py, pvx, pvy, u0, u1, u2, u3, q):
    """q[s] = |p_s - u|^2 (float64, the guarded path); returns min q."""
    qmin = np.inf
    for s in range(px.shape[0]):
        d0, d1, d2, d3 = px[s] - u0, py[s] - u1, pvx[s] - u2, pvy[s] - u3
        q[s] = d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3
        qmin = min(qmin, q[s])
    return qmin


@nb.njit(cache=True)
def _code_row64(q, qmin, row):
    for s in range(q.shape[0]):
        row[s] = _code(np.float32(min(0.5 * (q[s] - qmin), _CUT)))


@nb.njit(cache=True, fastmath={"reassoc", "contract"})
def _coded_chunk_sum(row, ws32):
    acc = np.float32(0.0)
    for s in range(row.shape[0]):
        acc += _decode(row[s]) * ws32[s]
    return acc


@nb.njit(cache=True)
def _coded_row_sum(row, ws32):
    """sum_s value_s ws_s of a coded row: float32 products and partial sums over _CHUNK terms, float64 total."""
    acc = 0.0
    for s0 in range(0, row.shape[0], _CHUNK):
        s1 = min(s0 + _CHUNK, row.shape[0])
        acc += np.float64(_coded_chunk_sum(row[s0:s1], ws32[s0:s1]))
    return acc


_FAR = 400.0  # targets beyond 20 whitened units of the sources' box: the float64 path
_EXTENT = 32.0  # sources beyond 32 whitened units of their mean: the float64 path for the problem


@nb.njit(cache=True)
def _finish(acc, total, wmax, low, log_norm, src_w, src_logw, tgt_w, quantized, out):
    """out[t] = log of the sum from ``acc[t]`` (scaled by exp(-low[t] / 2) and exp(wmax)); summed exactly
    where the misstated tail mass (at most total 2^-61) could exceed what is left of the budget."""
    if wmax == -np.inf:
        out[:] = -np.inf
        return
    spare = FAST_REL_TOL - ROUNDING_REL_ERROR - (CODE_REL_ERROR if quantized else 0.0)
    floor = total * _TAIL / spare
    for t in range(acc.shape[0]):
        if acc[t] > floor:
            out[t] = math.log(acc[t]) - 0.5 * low[t] + wmax + log_norm
        else:
            out[t] = _exact_log_sum(src_w, src_logw, wmax, tgt_w[t]) + log_norm


@nb.njit(cache=True)
def _prepare(src, src_shift, tgt, tgt_shift, linv, src_w, tgt_w, low):
    """Whiten (float64), then float32 columns of the sources and rows of the targets about the sources'
    mean; low[t] = squared distance from target t to the sources' bounding box. Returns the float32
    columns, targets and whether the problem may take the float32 path (sources within _EXTENT)."""
    js, jt = src.shape[0], tgt.shape[0]
    for s in range(js):
        _whiten(src[s], src_shift, linv, src_w[s])
    for t in range(jt):
        _whiten(tgt[t], tgt_shift, linv, tgt_w[t])
    c = np.zeros(4)
    lo, hi = np.full(4, np.inf), np.full(4, -np.inf)
    for s in range(js):
        for d in range(4):
            c[d] += src_w[s, d] / js
            lo[d] = min(lo[d], src_w[s, d])
            hi[d] = max(hi[d], src_w[s, d])
    ok = True
    for d in range(4):
        ok = ok and hi[d] - c[d] <= _EXTENT and c[d] - lo[d] <= _EXTENT
    cols = np.empty((4, js), np.float32)
    for s in range(js):
        for d in range(4):
            cols[d, s] = np.float32(src_w[s, d] - c[d])
    t32 = np.empty((jt, 4), np.float32)
    for t in range(jt):
        d2 = 0.0
        for d in range(4):
            t32[t, d] = np.float32(tgt_w[t, d] - c[d])
            v = tgt_w[t, d]
            e = lo[d] - v if v < lo[d] else (v - hi[d] if v > hi[d] else 0.0)
            d2 += e * e
        low[t] = d2
    return cols, t32, ok


@nb.njit(cache=True)
def _direct_problem(src, src_logw, src_shift, tgt, tgt_shift, linv, log_norm, out):
    js, jt = src.shape[0], tgt.shape[0]
    src_w, tgt_w, low = np.empty((js, 4)), np.empty((jt, 4)), np.empty(jt)
    cols, t32, ok = _prepare(src, src_shift, tgt, tgt_shift, linv, src_w, tgt_w, low)
    ws = np.empty(js)
    wmax, total = _scaled_weights(src_logw, ws)
    acc = np.zeros(jt)
    if wmax > -np.inf:
        ws32 = ws.astype(np.float32)
        q = np.empty(js)
        for t in range(jt):
            if ok and low[t] <= _FAR:
                a = 0.0
                lo32 = np.float32(low[t])
                for s0 in range(0, js, _CHUNK):
                    s1 = min(s0 + _CHUNK, js)
                    a += np.float64(_row32(cols[0, s0:s1], cols[1, s0:s1], cols[2, s0:s1], cols[3, s0:s1],
                                           ws32[s0:s1], t32[t, 0], t32[t, 1], t32[t, 2], t32[t, 3], lo32))
                acc[t] = a
            else:  # float64 distances, scaled by the nearest source
                low[t] = _row_q(src_w[:, 0].copy(), src_w[:, 1].copy(), src_w[:, 2].copy(), src_w[:, 3].copy(),
                                tgt_w[t, 0], tgt_w[t, 1], tgt_w[t, 2], tgt_w[t, 3], q)
                a = 0.0
                for s in range(js):
                    y = 0.5 * (q[s] - low[t])
                    a += ws[s] * (np.float64(_exp32(np.float32(y))) if y < _CUT else 0.0)
                acc[t] = a
    _finish(acc, total, wmax, low, log_norm, src_w, src_logw, tgt_w, False, out)


@nb.njit(cache=True, parallel=True)
def _direct_batch(src_sets, src_logw, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, linv, log_norm, out):
    for p in nb.prange(src_index.shape[0]):
        _direct_problem(src_sets[src_index[p]], src_logw[p], src_shift[p], tgt_sets[tgt_index[p]], tgt_shift[p],
                        linv[p], log_norm[p], out[p])


def fast_transform_batch(src_sets, src_logw, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r
                         ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`coloc.kernels.pf.transform_batch` within :data:`FAST_REL_TOL` per entry (no matrix kept,
    so within 1e-5 plus the tail): ``(log_out (P, Jt), pair evaluations (P,))``."""
    src_index = np.ascontiguousarray(src_index, dtype=np.int64)
    tgt_index = np.ascontiguousarray(tgt_index, dtype=np.int64)
    p = src_index.size
    jt = tgt_sets.shape[1] if np.ndim(tgt_sets) == 3 else 0
    js = src_sets.shape[1] if np.ndim(src_sets) == 3 else 0
    out = np.empty((p, jt))
    if p == 0:
        return out, np.zeros(0, np.int64)
    linv, log_norm = _chol_inverse(np.asarray(r, dtype=float).reshape(p, 4, 4))
    _direct_batch(np.ascontiguousarray(src_sets, dtype=float), np.ascontiguousarray(src_logw, dtype=float), src_index,
                  np.ascontiguousarray(src_shift, dtype=float).reshape(p, 4),
                  np.ascontiguousarray(tgt_sets, dtype=float), tgt_index,
                  np.ascontiguousarray(tgt_shift, dtype=float).reshape(p, 4), linv, log_norm, out)
    return out, np.full(p, js * jt, np.int64)


def fast_transform(src, src_logw, tgt, r) -> np.ndarray:
    """One Gauss transform within :data:`FAST_REL_TOL`: log sum_s exp(logw_s) N(tgt_j - src_s; 0, r), (Jt,)."""
    out, _ = fast_transform_batch(np.asarray(src, float)[None], np.asarray(src_logw, float)[None],
                                  np.zeros(1, np.int64), np.zeros((1, 4)), np.asarray(tgt, float)[None],
                                  np.zeros(1, np.int64), np.zeros((1, 4)), np.asarray(r, float)[None])
    return out[0]


# ----------------------------------------------------------------------------- kept 16-bit matrices


@nb.njit(cache=True)
def _coded_problem(src, src_shift, tgt, tgt_shift, linv, codes, low, src_w, tgt_w, first_logw, log_norm, first_out):
    js, jt = src.shape[0], tgt.shape[0]
    cols, t32, ok = _prepare(src, src_shift, tgt, tgt_shift, linv, src_w, tgt_w, low)
    ws = np.empty(js)
    wmax, total = _scaled_weights(first_logw, ws)
    ws32 = ws.astype(np.float32)
    acc = np.zeros(jt)
    q = np.empty(js)
    for t in range(jt):
        if ok and low[t] <= _FAR:
            _code_row32(cols[0], cols[1], cols[2], cols[3], t32[t, 0], t32[t, 1], t32[t, 2], t32[t, 3],
                        np.float32(low[t]), codes[t])
        else:
            low[t] = _row_q(src_w[:, 0].copy(), src_w[:, 1].copy(), src_w[:, 2].copy(), src_w[:, 3].copy(),
                            tgt_w[t, 0], tgt_w[t, 1], tgt_w[t, 2], tgt_w[t, 3], q)
            _code_row64(q, low[t], codes[t])
        if wmax > -np.inf:
            acc[t] = _coded_row_sum(codes[t], ws32)
    _finish(acc, total, wmax, low, log_norm, src_w, first_logw, tgt_w, True, first_out)


@nb.njit(cache=True, parallel=True)
def _build_coded(src_sets, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, linv, codes, low, src_w, tgt_w,
                 first_logw, log_norm, first_out):
    for p in nb.prange(src_index.shape[0]):
        _coded_problem(src_sets[src_index[p]], src_shift[p], tgt_sets[tgt_index[p]], tgt_shift[p], linv[p], codes[p],
                       low[p], src_w[p], tgt_w[p], first_logw[p], log_norm[p], first_out[p])


@nb.njit(cache=True, parallel=True)
def _apply_coded(codes, low, log_norm, src_w, tgt_w, src_logw, problems, out):
    """out[q] = the kept problem ``problems[q]``'s sum for the weights ``src_logw[q]``."""
    for q in nb.prange(problems.shape[0]):
        p = problems[q]
        ws = np.empty(codes.shape[2])
        wmax, total = _scaled_weights(src_logw[q], ws)
        ws32 = ws.astype(np.float32)
        acc = np.zeros(codes.shape[1])
        if wmax > -np.inf:
            for t in range(codes.shape[1]):
                acc[t] = _coded_row_sum(codes[p, t], ws32)
        _finish(acc, total, wmax, low[p], log_norm[p], src_w[p], src_logw[q], tgt_w[p], True, out[q])


def fast_kept_problem_count(n_problems: int, js: int, jt: int, max_bytes: float) -> int:
    """How many of the problems (the first ones) keep their 16-bit matrices within ``max_bytes``."""
    if js == 0 or jt == 0:
        return 0
    return min(n_problems, int(max_bytes // (FAST_BYTES_PER_PAIR * js * jt)))


@dataclass
class FastRepeatedTransforms:
    """:class:`coloc.kernels.pf.RepeatedTransforms` within :data:`FAST_REL_TOL` per entry: the first
    :meth:`sum` builds the 16-bit matrices of the first problems that fit in ``max_bytes`` (summing
    each row while it is in cache), every later sum is their product with the new weights; problems
    beyond the budget are summed directly each time (:func:`fast_transform_batch`).
    ``storage``: a flat uint16 array of at least :func:`fast_kept_problem_count` x Jt x Js codes."""

    src_sets: np.ndarray
    src_index: np.ndarray
    src_shift: np.ndarray
    tgt_sets: np.ndarray
    tgt_index: np.ndarray
    tgt_shift: np.ndarray
    r: np.ndarray
    max_bytes: float = 0.0
    storage: np.ndarray | None = None

    def __post_init__(self):
        self.src_index = np.ascontiguousarray(self.src_index, dtype=np.int64)
        self.tgt_index = np.ascontiguousarray(self.tgt_index, dtype=np.int64)
        p = self.src_index.size
        self.src_shift = np.ascontiguousarray(np.asarray(self.src_shift, float).reshape(p, 4))
        self.tgt_shift = np.ascontiguousarray(np.asarray(self.tgt_shift, float).reshape(p, 4))
        self.r = np.asarray(self.r, float).reshape(p, 4, 4)
        self.js = self.src_sets.shape[1] if np.ndim(self.src_sets) == 3 else 0
        self.jt = self.tgt_sets.shape[1] if np.ndim(self.tgt_sets) == 3 else 0
        k = fast_kept_problem_count(p, self.js, self.jt, self.max_bytes)
        self.kept = np.arange(p) < k
        self._built = False

    def sum(self, src_logw: np.ndarray, problems: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(log_out (P, Jt), pair evaluations (P,))`` for source log-weights (P, Js); kept problems
        count their pairs once, at the build. ``problems``: sum only these (sorted indices; rows of
        ``src_logw`` and of the output in their order), after the first sum (which builds every kept
        problem); each problem's sum is the same, bit for bit, with or without the others."""
        src_logw = np.ascontiguousarray(src_logw, dtype=float)
        k = int(self.kept.sum())
        if problems is None:
            problems = np.arange(self.kept.size)
        elif not self._built:
            raise ValueError("the first sum builds the kept matrices of every problem")
        problems = np.asarray(problems, dtype=np.int64)
        p = problems.size
        out = np.empty((p, self.jt))
        pairs = np.zeros(p, np.int64)
        m = int(np.searchsorted(problems, k))  # problems[:m] are kept
        if m:
            kept_out = np.empty((m, self.jt))
            if not self._built:
                self._build(src_logw[:m], kept_out)
                pairs[:m] = self.js * self.jt
            else:
                _apply_coded(self.codes, self.low, self.log_norm, self.src_w, self.tgt_w, src_logw[:m], problems[:m],
                             kept_out)
            out[:m] = kept_out
        if m < p:
            rest = problems[m:]
            out[m:], pairs[m:] = fast_transform_batch(self.src_sets, src_logw[m:], self.src_index[rest],
                                                      self.src_shift[rest], self.tgt_sets, self.tgt_index[rest],
                                                      self.tgt_shift[rest], self.r[rest])
        self._built = True  # (also when nothing is kept)
        return out, pairs

    def _build(self, first_logw: np.ndarray, first_out: np.ndarray) -> None:
        k, js, jt = int(self.kept.sum()), self.js, self.jt
        if self.storage is None:
            self.codes = np.empty((k, jt, js), np.uint16)
        else:
            self.codes = self.storage[: k * jt * js].reshape(k, jt, js)
        self.low, self.src_w, self.tgt_w = np.empty((k, jt)), np.empty((k, js, 4)), np.empty((k, jt, 4))
        linv, self.log_norm = _chol_inverse(self.r[:k])
        _build_coded(np.ascontiguousarray(self.src_sets, dtype=float), self.src_index[:k], self.src_shift[:k],
                     np.ascontiguousarray(self.tgt_sets, dtype=float), self.tgt_index[:k], self.tgt_shift[:k], linv,
                     self.codes, self.low, self.src_w, self.tgt_w, first_logw, self.log_norm, first_out)
        self._built = True
