"""The births and merges of ICP-DA-LC's feature tracks (:mod:`coloc.methods.icp_da_lc`, module docstring
steps 6 and 8): the rows of different vehicles implying one new feature clustered into one new track, and the
pairs of tracks merged."""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from coloc.inference.feature_store import FeatureStore
from coloc.inference.gaussian import chi2_ppf
from coloc.inference.params import IcpParams, LcParams
from coloc.kernels import icp_fused
from coloc.kernels.birth import birth_greedy_kernel
from coloc.kernels.icp_fused import any_pair_within

__all__ = ["PRUNE_MARGIN", "birth_pairs", "birth_clusters", "merge_candidates"]


#: Relative margin of the trace bound (coloc.kernels.birth): a pair is dropped only if |d|^2 exceeds
#: gate * trace * (1 + PRUNE_MARGIN), far beyond the rounding of the solve and of |d|^2.
PRUNE_MARGIN = 1e-6


def birth_pairs(xy: np.ndarray, cov: np.ndarray, gate_d2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pairs (i, j), j < i, that may pass the gate, with their squared Mahalanobis distance.

    Returns ``(indptr, cand_j, cand_d2)``: row i's candidates are ``cand_j[indptr[i]:indptr[i+1]]``,
    sorted by d2 (NaN last, as ``np.argsort``), then by j. Non-finite input: every pair j < i.
    """
    b = xy.shape[0]
    if np.isfinite(xy).all() and np.isfinite(cov).all():
        tr = cov[:, 0, 0] + cov[:, 1, 1]
        reach2 = gate_d2 * 2.0 * float(tr.max()) * (1.0 + PRUNE_MARGIN)
        pairs = cKDTree(xy).query_pairs(math.sqrt(max(reach2, 0.0)) * (1.0 + PRUNE_MARGIN), output_type="ndarray")
        j, i = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)  # query_pairs: first < second
        dd = xy[j] - xy[i]
        keep = (dd * dd).sum(axis=1) <= gate_d2 * (tr[i] + tr[j]) * (1.0 + PRUNE_MARGIN)
        j, i = j[keep], i[keep]
    else:
        i, j = np.tril_indices(b, -1)
        i, j = i.astype(np.int64), j.astype(np.int64)
    # The expressions of the per-row loop, batched (d = seed - row, S = S_seed + S_row).
    d = xy[j] - xy[i]
    s = cov[j] + cov[i]
    d2 = np.einsum("ni,ni->n", d, np.linalg.solve(s, d[..., None])[..., 0]) if i.size else np.empty(0)
    order = np.lexsort((j, d2, i))
    indptr = np.zeros(b + 1, dtype=np.int64)
    np.cumsum(np.bincount(i, minlength=b), out=indptr[1:])
    return indptr, np.ascontiguousarray(j[order]), np.ascontiguousarray(d2[order])


def birth_clusters(owner: np.ndarray, implied_xy: np.ndarray, implied_cov: np.ndarray, gate_d2: float) -> np.ndarray:
    """Cluster label of each birth row: rows of different vehicles implying the same feature share a new track.

    ``implied_xy``/``implied_cov`` (B, 2), (B, 2, 2): the feature position a row
    implies, m_i + z_l, and its covariance P_i + R_l. Greedy in row order
    (deterministic): a row joins the nearest earlier cluster (squared
    Mahalanobis distance to the cluster's first row, summed covariances, at
    most ``gate_d2``) that holds no row of the same vehicle -- one vehicle's
    rows are distinct features -- or opens a new cluster.
    """
    owner = np.ascontiguousarray(owner, dtype=np.int64)
    if owner.size == 0:
        return np.empty(0, dtype=np.int64)
    # Only the pairs that can pass the gate (coloc.kernels.birth: exact pruning, the same d2 bit for bit).
    indptr, cand_j, cand_d2 = birth_pairs(np.asarray(implied_xy, dtype=float), np.asarray(implied_cov, dtype=float),
                                          float(gate_d2))
    return birth_greedy_kernel(owner, indptr, cand_j, cand_d2, float(gate_d2))


def merge_candidates(
    store: FeatureStore, params: IcpParams, lc: LcParams, row_owner: np.ndarray, row_track: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (absorbed, into) of tracks to merge (module docstring, step 8); into = the older (lower) id.

    ``row_owner``/``row_track``: this step's paired rows; two tracks one vehicle
    observed at this step are distinct features and never merged.
    """
    if store.size < 2 or lc.merge_gate_m <= 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    mean, cov = store.moments(params)
    if icp_fused.FUSED and not any_pair_within(np.ascontiguousarray(mean[:, :2]), float(lc.merge_gate_m)):
        return np.empty(0, np.int64), np.empty(0, np.int64)  # no two tracks within the gate: no pair below
    pairs = cKDTree(mean[:, :2]).query_pairs(lc.merge_gate_m, output_type="ndarray")
    if pairs.size == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    a, b = pairs[:, 0], pairs[:, 1]
    d = mean[a, :2] - mean[b, :2]
    s = cov[a, :2, :2] + cov[b, :2, :2]
    d2 = np.einsum("ni,ni->n", d, np.linalg.solve(s, d[..., None])[..., 0])
    ok = d2 <= chi2_ppf(0.99, 2)
    if store.klass is not None:  # a pedestrian track and a landmark track are different objects
        ok &= store.klass[a] == store.klass[b]
    if row_owner.size and ok.any():
        n_v = int(row_owner.max()) + 1
        inc = sp.csr_matrix((np.ones(row_owner.size), (store.lookup(row_track), row_owner)), shape=(store.size, n_v))
        together = np.asarray((inc[a[ok]].multiply(inc[b[ok]])).sum(axis=1)).ravel() > 0
        ok[np.flatnonzero(ok)[together]] = False
    absorbed, into = [], []
    taken: set = set()
    order = np.argsort(d2[ok], kind="stable")  # closest pairs first
    for i, j in zip(a[ok][order].tolist(), b[ok][order].tolist()):
        lo, hi = sorted((int(store.ids[i]), int(store.ids[j])))
        if lo in taken or hi in taken:
            continue
        absorbed.append(hi)
        into.append(lo)
        taken.update((lo, hi))
    return np.array(absorbed, dtype=np.int64), np.array(into, dtype=np.int64)
