"""summary.json's ``gnss_world`` block: what the simulated receivers got wrong, scored from truth.

For a run with ``[gnss_error]``: the raw receiver position error (the frame's GNSS fix minus the true
position, before any estimator) by GNSS zone, and the correlation of two receivers' errors against their
separation. This is the world's side (docs/outputs.md), never an estimator's input.

Correlation per separation bin and axis: over every pair of vehicles (i, j) present at the same step with
separation in the bin (and, by zone, over the pairs whose two vehicles are both in that zone: the open sky
of zone A apart from the canyons), rho = mean(e_i e_j) / mean((e_i^2 + e_j^2) / 2), the correlation about zero (an
error's expected value is zero) of the pairs' error components, symmetric in the order of a pair. Not about
the sample mean: a common error that stays nearly constant through a run (a slow common part) is error the
receivers share, and subtracting the run's mean would remove it. Steps with more than :data:`MAX_VEHICLES` vehicles use every k-th row (k the
smallest giving at most that many), which keeps the pair count per step below ~MAX_VEHICLES^2 / 2.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Separation bins (m), [lo, hi).
SEPARATION_BINS = ((10.0, 50.0), (50.0, 200.0), (200.0, 1000.0))
MAX_VEHICLES = 600


class GnssWorldTally:
    """Raw receiver errors and pair sums over a run; :meth:`summary` is the ``gnss_world`` block."""

    def __init__(self):
        self._zone_err: dict[str, list[np.ndarray]] = {}
        # per bin: pairs, then per axis sum of e_i e_j, of e_i + e_j, of e_i^2 + e_j^2
        self._sums = np.zeros((len(SEPARATION_BINS), 7))
        self._zone_sums: dict[str, np.ndarray] = {}  # the same over the pairs within one zone

    def add(self, frame) -> None:
        xy = np.asarray(frame.truth.x_true, dtype=float)[:, :2]
        err = np.asarray(frame.gnss_z, dtype=float)[:, :2] - xy
        zone = np.asarray(frame.truth.zone, dtype=object).reshape(-1)
        norm = np.hypot(err[:, 0], err[:, 1])
        for z in np.unique(zone).tolist():
            self._zone_err.setdefault(str(z), []).append(norm[zone == z])
        n = len(xy)
        if n < 2:
            return
        if n > MAX_VEHICLES:
            stride = -(-n // MAX_VEHICLES)
            xy, err, zone = xy[::stride], err[::stride], zone[::stride]
        pairs = cKDTree(xy).query_pairs(SEPARATION_BINS[-1][1], output_type="ndarray")
        if not len(pairs):
            return
        i, j = pairs[:, 0], pairs[:, 1]
        d = np.hypot(*(xy[i] - xy[j]).T)
        _add_pairs(self._sums, d, err[i], err[j])
        same = zone[i] == zone[j]
        for z in np.unique(zone[i[same]]).tolist():
            sel = same & (zone[i] == z)
            _add_pairs(self._zone_sums.setdefault(str(z), np.zeros((len(SEPARATION_BINS), 7))), d[sel],
                       err[i[sel]], err[j[sel]])

    def summary(self) -> dict:
        by_zone = {}
        parts = {z: np.concatenate(v) for z, v in sorted(self._zone_err.items())}
        if parts:
            parts["all"] = np.concatenate(list(parts.values()))
        for z, e in parts.items():
            by_zone[z] = {"rms_2d_m": float(np.sqrt(np.mean(e * e))) if e.size else None,
                          "p95_2d_m": float(np.percentile(e, 95)) if e.size else None, "n": int(e.size)}
        return {"receiver_error_by_zone": by_zone, "error_correlation_by_separation": _correlations(self._sums),
                "error_correlation_by_zone_and_separation": {z: _correlations(s)
                                                             for z, s in sorted(self._zone_sums.items())}}


def _add_pairs(sums: np.ndarray, d: np.ndarray, ei: np.ndarray, ej: np.ndarray) -> None:
    """Add the pairs (separations ``d``, errors ``ei``, ``ej``) to ``sums`` (bins x 7), bin by bin."""
    for b, (lo, hi) in enumerate(SEPARATION_BINS):
        sel = (d >= lo) & (d < hi)
        a, c = ei[sel], ej[sel]
        sums[b, 0] += sel.sum()
        sums[b, 1:3] += (a * c).sum(axis=0)
        sums[b, 3:5] += (a + c).sum(axis=0)
        sums[b, 5:7] += (a * a + c * c).sum(axis=0)


def _correlations(sums: np.ndarray) -> dict:
    """Per separation bin: the pair count and rho per axis (None without pairs or power)."""
    corr = {}
    for (lo, hi), s in zip(SEPARATION_BINS, sums):
        n = int(s[0])
        block = {"pairs": n}
        for k, axis in enumerate("xy"):
            if n == 0:
                block[axis] = None
                continue
            power = s[5 + k] / (2 * n)
            block[axis] = float((s[1 + k] / n) / power) if power > 0 else None
        corr[f"{lo:g}-{hi:g}m"] = block
    return corr
