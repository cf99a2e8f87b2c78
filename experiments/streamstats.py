"""Statistics of a run's rows read in batches, in memory that does not grow with the rows.

What summary.json reports (RMSE, mean NEES, percentiles, medians) is computed here from the rows read
twice, batch by batch, and equals, bit for bit, the numpy computation over the whole array:

* sums: numpy adds a contiguous float64 array by pairwise summation (blocks of at most 128 values
  summed with 8 accumulators, split at n/2 rounded down to a multiple of 8; numpy's
  ``pairwise_sum`` in ``loops_utils.h``). The split points depend on n only, so with n known from the
  first pass :class:`PairwiseSum` adds the same numbers in the same order as the values stream in,
  holding one partial sum per level of the tree (about 20 for a day);
* percentiles (``np.quantile``, method "linear") and medians: the first pass fills a histogram of
  fixed relative resolution (:data:`BINS_PER_OCTAVE` bins per power of two, from 2^-30 to 2^30, an
  underflow and an overflow bin: 7682 counts); the order statistics numpy interpolates between fall
  in known bins, and the second pass keeps only the values of those bins, from which they are taken
  exactly. Memory: the histogram plus the rows of at most four bins per percentile (a bin of a
  1 m error is 5.4 mm wide: about 0.5 % of the rows of a group).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from experiments.scoring import CHI2_2_95, _nan_to_none

#: Histogram bins per power of two of the value (the float64 exponent and its 7 leading mantissa bits:
#: a bin is at most 2^-7 = 0.78 % of its lower edge wide).
BINS_PER_OCTAVE = 128
_RANGE = 30  # octaves either side of 1: bins from 2^-30 to 2^30


def _edges(bits: int) -> tuple[int, int, int]:
    shift = 52 - bits
    lo = int(np.array(2.0 ** -_RANGE).view(np.int64)) >> shift
    hi = int(np.array(2.0 ** _RANGE).view(np.int64)) >> shift
    return shift, lo, hi


def n_bins(bits: int = 7) -> int:
    """Bins of :func:`bin_index`: underflow (values below 2^-30, zero and negatives), 60 octaves of
    2^bits bins each, overflow (2^30 and more, inf)."""
    _shift, lo, hi = _edges(bits)
    return hi - lo + 2


N_BINS = n_bins()


def bin_index(x: np.ndarray, bits: int = 7) -> np.ndarray:
    """Histogram bin of each (non-NaN) value, 2^bits bins per octave: monotonic in the value (the bit
    pattern of a non-negative float64 orders as an integer)."""
    shift, lo, hi = _edges(bits)
    x = np.asarray(x, dtype=np.float64)
    key = np.where(x > 0.0, x, 0.0).view(np.int64) >> shift
    return (np.clip(key, lo - 1, hi) - (lo - 1)).astype(np.int64)


def bin_edges(bits: int = 7) -> np.ndarray:
    """The n_bins(bits) + 1 edges of :func:`bin_index`'s bins (the first 0, the last inf)."""
    shift, lo, hi = _edges(bits)
    inner = (np.arange(lo, hi + 1, dtype=np.int64) << shift).view(np.float64)
    return np.concatenate([[0.0], inner, [np.inf]])


_LEAF = 128  # numpy's PW_BLOCKSIZE


@njit(cache=True)
def _leaf_sums(values, lengths):
    """numpy's pairwise_sum of each of the consecutive blocks ``lengths`` (each at most 128) of ``values``."""
    out = np.empty(lengths.size)
    pos = 0
    r = np.empty(8)
    for k in range(lengths.size):
        n = lengths[k]
        a = values[pos:pos + n]
        if n < 8:
            res = 0.0
            for i in range(n):
                res += a[i]
        else:
            for j in range(8):
                r[j] = a[j]
            i = 8
            while i < n - (n % 8):
                for j in range(8):
                    r[j] += a[i + j]
                i += 8
            res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
            while i < n:
                res += a[i]
                i += 1
        out[k] = res
        pos += n
    return out


def _program(n: int):
    """numpy's pairwise summation tree of n values in post-order: a leaf's length (> 0) or 0 = add the
    two last partial sums."""
    if n <= _LEAF:
        yield n
        return
    n2 = n // 2
    n2 -= n2 % 8
    yield from _program(n2)
    yield from _program(n - n2)
    yield 0


class PairwiseSum:
    """``np.sum`` of n float64 values that arrive in pieces, equal to the sum of their concatenation."""

    def __init__(self, n: int):
        self.n = int(n)
        self._ops = _program(self.n) if self.n else iter(())
        self._next = next(self._ops, None)
        self._stack: list[float] = []
        self._buf = np.empty(0)
        self.seen = 0

    def add(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=np.float64)
        self.seen += x.size
        if self.seen > self.n:
            raise ValueError(f"PairwiseSum: {self.seen} values, {self.n} announced")
        buf = np.concatenate([self._buf, x]) if self._buf.size else np.ascontiguousarray(x)
        pos = 0
        while True:
            # the leaves that the values at hand complete, with the additions between them
            ops, lengths, take = [], [], 0
            op = self._next
            while op is not None and (op == 0 or take + op <= buf.size - pos):
                ops.append(op)
                if op:
                    lengths.append(op)
                    take += op
                op = next(self._ops, None)
            self._next = op
            if not ops:
                break
            sums = iter(_leaf_sums(buf[pos:pos + take], np.array(lengths, dtype=np.int64)).tolist())
            stack = self._stack
            for o in ops:
                if o:
                    stack.append(next(sums))
                else:
                    b = stack.pop()
                    stack.append(stack.pop() + b)
            pos += take
        self._buf = buf[pos:].copy()

    @property
    def value(self) -> float:
        if self.seen != self.n:
            raise ValueError(f"PairwiseSum: {self.seen} of {self.n} values seen")
        return self._stack[0] if self._stack else 0.0


def _lerp(a: float, b: float, t: float) -> float:
    """numpy's _lerp (numpy/lib/_function_base_impl.py) on scalars."""
    diff = b - a
    return b - diff * (1.0 - t) if t >= 0.5 else a + diff * t


class Sample:
    """One group's values in row order, seen twice (:meth:`first` for every batch, then :meth:`second`
    for the same batches in the same order): ``mean``, ``rmse`` (of the values, or of their squares
    summed: ``squares``), ``quantile`` for the ``quantiles`` asked at construction, ``median``."""

    def __init__(self, squares: bool = True, quantiles: tuple[float, ...] = (), median: bool = False):
        self.squares = squares
        self.qs = tuple(quantiles)
        self.with_median = median
        self.n = 0
        self.nan = 0
        self.hist = np.zeros(N_BINS, dtype=np.int64) if (self.qs or median) else None
        self._sum: PairwiseSum | None = None
        self._ranks: list[int] = []
        self._bins: np.ndarray = np.empty(0, dtype=np.int64)
        self._below: dict[int, int] = {}
        self._kept: dict[int, list] = {}

    # ---------------------------------------------------------------- pass 1
    def first(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=np.float64)
        self.n += x.size
        if self.hist is not None:
            isnan = np.isnan(x)
            self.nan += int(isnan.sum())
            self.hist += np.bincount(bin_index(x[~isnan]), minlength=N_BINS)

    def _order_stats(self) -> list[int]:
        """0-based ranks of the order statistics the quantiles and the median need."""
        n = self.n
        ranks = []
        for q in self.qs:
            v = (n - 1) * np.float64(q)
            k = n - 1 if v >= n - 1 else int(np.floor(v))
            ranks += [k, min(k + 1, n - 1)]
        if self.with_median:
            ranks += [(n - 1) // 2, n // 2]
        return sorted(set(ranks))

    # ---------------------------------------------------------------- pass 2
    def second(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=np.float64)
        if self._sum is None:
            self._start()
        self._sum.add(x * x if self.squares else x)
        if self._bins.size:
            b = bin_index(np.where(np.isnan(x), 0.0, x))
            for k in self._bins.tolist():
                self._kept[k].append(x[(b == k) & ~np.isnan(x)])

    def _start(self) -> None:
        self._sum = PairwiseSum(self.n)
        if self.hist is not None and self.n and not self.nan:
            self._ranks = self._order_stats()
            ends = np.cumsum(self.hist)
            bins = np.searchsorted(ends, np.array(self._ranks), side="right")
            self._bins = np.unique(bins)
            for k in self._bins.tolist():
                self._below[k] = int(ends[k] - self.hist[k])
                self._kept[k] = []

    def finish(self) -> None:
        if self._sum is None:
            self._start()
        sorted_bins = {k: np.sort(np.concatenate(v)) if v else np.empty(0) for k, v in self._kept.items()}
        self._kept = {}
        self._stat = {}
        for r in self._ranks:
            k = int(np.searchsorted(np.cumsum(self.hist), r, side="right"))
            self._stat[r] = float(sorted_bins[k][r - self._below[k]])

    # ---------------------------------------------------------------- results
    def mean(self) -> float:
        """``np.mean`` of the values (of their squares with ``squares``): NaN when there are none."""
        return float(self._sum.value / self.n) if self.n else float("nan")

    def rmse(self) -> float:
        return float(np.sqrt(self.mean()))

    def quantile(self, q: float) -> float:
        """``np.quantile(values, q)`` (NaN when empty or when a value is NaN)."""
        if not self.n or self.nan:
            return float("nan")
        n = self.n
        v = (n - 1) * np.float64(q)
        if v >= n - 1:  # numpy: both neighbours the largest value, gamma = v + 1 (inf -> nan, as numpy)
            a = self._stat[n - 1]
            return float(_lerp(a, a, float(v + 1.0)))
        k = int(np.floor(v))
        return float(_lerp(self._stat[k], self._stat[k + 1], float(v - np.floor(v))))

    def median(self) -> float:
        """``np.median(values)``."""
        if not self.n or self.nan:
            return float("nan")
        n = self.n
        a, b = self._stat[(n - 1) // 2], self._stat[n // 2]
        return a if n % 2 else float(np.mean(np.array([a, b])))


class EstimateStats:
    """The summary blocks of one method's estimates (:func:`experiments.scoring.method_summary`,
    :func:`experiments.scoring.nees_summary` and, under ``[infra]``, :func:`experiments.scoring.coverage_summary`),
    from its scored rows fed batch by batch: every batch to :meth:`feed` with ``second=False``, then the
    same batches in the same order with ``second=True``, then :meth:`blocks`. Columns of a batch:
    err_pos, err_vel, err_along, err_cross, nees (float64), zone, area (int codes of ``names``), and with
    ``infra`` covered (bool) and rsu (int codes)."""

    def __init__(self, infra: bool = False):
        self.infra = infra
        self.pos = Sample(quantiles=(0.5, 0.95))
        self.vel = Sample()
        self.by: dict[str, dict[int, tuple[Sample, Sample, Sample]]] = {"area": {}, "zone": {}}
        self.nees = Sample(squares=False, median=True)
        self.nees_zone: dict[int, Sample] = {}
        self.inside: dict[int, int] = {}
        self.cov_pos = Sample(quantiles=(0.95,))
        self.cov_area: dict[int, Sample] = {}
        self.rsu: dict[int, int] = {}

    @staticmethod
    def _groups(codes: np.ndarray):
        for c in np.unique(codes).tolist():
            yield c, codes == c

    def feed(self, b: dict, second: bool) -> None:
        step = "second" if second else "first"
        getattr(self.pos, step)(b["err_pos"])
        getattr(self.vel, step)(b["err_vel"])
        for key in ("area", "zone"):
            groups = self.by[key]
            for c, sel in self._groups(b[key]):
                if c not in groups:
                    groups[c] = (Sample(quantiles=(0.5, 0.95)), Sample(), Sample())
                for s, col in zip(groups[c], ("err_pos", "err_along", "err_cross")):
                    getattr(s, step)(b[col][sel])
        ok = np.isfinite(b["nees"])
        nees, zone = b["nees"][ok], b["zone"][ok]
        getattr(self.nees, step)(nees)
        for c, sel in self._groups(zone):
            if c not in self.nees_zone:
                self.nees_zone[c] = Sample(squares=False, median=True)
            getattr(self.nees_zone[c], step)(nees[sel])
            if not second:
                self.inside[c] = self.inside.get(c, 0) + int(np.count_nonzero(nees[sel] <= CHI2_2_95))
        if self.infra:
            cov = b["covered"]
            getattr(self.cov_pos, step)(b["err_pos"][cov])
            area = b["area"][cov]
            for c, sel in self._groups(area):
                if c not in self.cov_area:
                    self.cov_area[c] = Sample(quantiles=(0.95,))
                getattr(self.cov_area[c], step)(b["err_pos"][cov][sel])
            if not second:
                for c, sel in self._groups(b["rsu"][cov]):
                    self.rsu[c] = self.rsu.get(c, 0) + int(sel.sum())

    def _samples(self):
        yield self.pos
        yield self.vel
        for groups in self.by.values():
            for trio in groups.values():
                yield from trio
        yield self.nees
        yield from self.nees_zone.values()
        yield self.cov_pos
        yield from self.cov_area.values()

    def blocks(self, zones: list[str], areas: list[str], rsus: list[str]) -> tuple[dict, dict | None, dict | None]:
        """(method_summary block with ``nees_pos``, the method's within_rsu_coverage block, rsu vehicle-steps)
        (the last two None without ``infra``); ``zones``, ``areas``, ``rsus``: the names of the codes."""
        for s in self._samples():
            s.finish()
        names = {"zone": zones, "area": areas}
        out = {"rmse_pos_m": self.pos.rmse(), "rmse_vel_mps": self.vel.rmse(), "p50_pos_m": self.pos.quantile(0.5),
               "p95_pos_m": self.pos.quantile(0.95), "n": int(self.pos.n)}
        for key in ("area", "zone"):
            groups = self.by[key]
            out[f"by_{key}"] = {
                names[key][c]: {"rmse_pos_m": p.rmse(), "p50_pos_m": p.quantile(0.5), "p95_pos_m": p.quantile(0.95),
                                "rmse_along_m": a.rmse(), "rmse_cross_m": x.rmse(), "n": int(p.n)}
                for c, (p, a, x) in sorted(groups.items(), key=lambda kv: names[key][kv[0]])}
        out = _nan_to_none(out)
        if self.nees.n:
            nees = self._nees_stats(self.nees, sum(self.inside.values()))
        else:
            nees = {"mean": None, "median": None, "inside_95": None, "n": 0}
        nees["by_zone"] = {zones[c]: self._nees_stats(s, self.inside[c])
                           for c, s in sorted(self.nees_zone.items(), key=lambda kv: zones[kv[0]])}
        out["nees_pos"] = nees
        if not self.infra:
            return out, None, None
        cov = {"rmse_pos_m": self.cov_pos.rmse(), "p95_pos_m": self.cov_pos.quantile(0.95), "n": int(self.cov_pos.n),
               "by_area": {areas[c]: {"rmse_pos_m": s.rmse(), "p95_pos_m": s.quantile(0.95), "n": int(s.n)}
                           for c, s in sorted(self.cov_area.items(), key=lambda kv: areas[kv[0]])}}
        steps = {rsus[c]: n for c, n in sorted(self.rsu.items(), key=lambda kv: rsus[kv[0]])}
        return out, _nan_to_none(cov), steps

    @staticmethod
    def _nees_stats(s: Sample, inside: int) -> dict:
        """:func:`experiments.scoring._nees_stats`: float(nees.mean()), np.median, np.mean(nees <= chi2)."""
        return {"mean": s.mean(), "median": s.median(), "inside_95": inside / s.n, "n": int(s.n)}
