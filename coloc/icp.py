"""Gaussian ICP machinery shared by the ICP estimators (Brambilla et al. Secs. III, IV-B, IV-D).

With the association fixed (known, or decided by ICP-DA-LC's MAP rule (30)-(31)),
the V2F likelihood (18) of a row (vehicle i, feature k) is the single Gaussian
p(z_ik | x_Vi, x_Fk) = N(z_ik; x_Fk - x_Vi, R_ik) of model (4), every belief is
Gaussian and the BPA-L of eqs. (19)-(22) is Gaussian message passing, i.e. the
distributed Kalman filter of Soatti et al. [40] ("LC" implementation, Sec. IV-D).
Everything here works in information form (Lambda = P^-1, eta = P^-1 m),
batched over the O V2F rows with numpy (no per-vehicle Python loops).

Mapping of the equations to code (one BPA-L iteration n, :func:`bpa_localization`):

* (11)/(12) prior beliefs b^(0): supplied by the caller (GNSS-updated vehicle
  prediction; predicted feature tracks, uniform -- zero information -- for a
  feature nobody tracked before).
* (19) vehicle -> feature message. The cavity b_i^(n-1) / m_{k->i}^(n-1) is
  Lambda_i - Lambda_{k->i}; integrating the likelihood over x_Vi gives
  x_Fk ~ N(m_cav + z_ik, P_cav + R_ik)  (:func:`relative_message`, offset +z).
* (20) feature belief b_k = b_k^(0) prod_{i in V_k} m_{i->k}: the product is a
  sum of information, computed *by average consensus* among the vehicles that
  sense k, over the V2V links between them (:func:`consensus_graph`): every
  participant holds its own message, the consensus average is multiplied by
  the number of participants of its component |V_k ∩ C| and the prior
  information b_k^(0) (shared track, held by every participant) is added
  locally. Each participant ends with its own copy of b_k; with finitely many
  consensus rounds the copies differ.
* (21) feature -> vehicle message: vehicle i divides its copy of b_k by its own
  message (extrinsic information Lambda_k - Lambda_{i->k}) and integrates the
  likelihood over x_Fk: x_Vi ~ N(m_ext - z_ik, P_ext + R_ik).
* (22) vehicle belief b_i = b_i^(0) prod_k m_{k->i}: information sum over the
  vehicle's rows (a sparse (N, O) incidence product).

Iterations stop by the rule of Sec. V-A: every vehicle's position mean moved
by less than ``stop_pos_m`` and its velocity by less than ``stop_vel_mps``
(the global "all vehicles" test a max consensus would give), or after
``bpa_max_iterations``.

Across steps a track keeps one message per vehicle (:class:`FeatureStore`),
built on the vehicle's own-sensor belief (``IcpParams.feature_message``); the
step's feature estimate is (20) with BPA-L's final messages
(:func:`step_feature_beliefs`).

Consensus design: the per-feature groups are run in *one* consensus on a
graph whose nodes are the V2F rows: rows (i, k) and (j, k) are linked iff
vehicles i and j are V2V neighbours (:func:`consensus_graph`). Its Metropolis
weights are exactly those of each feature's participant-induced subgraph, so
one numba kernel runs every feature's consensus at once (cost
O(iterations * edges * 14): the 10 distinct entries of a symmetric Lambda and
the 4 of eta). The participant count |V_k ∩ C| is the size of the row's
connected component; a vehicle learns it exactly by flooding participant ids
for diameter-many rounds (a max consensus), which we compute directly.
Graph, weights and counts are built by one numba pass per time step
(:func:`row_consensus_weights`, equal bit for bit to
``metropolis_weights(consensus_graph(...))`` and :func:`row_components`). On a
component that is a complete graph (always the case when Rc >= 2 Rs) the
Metropolis matrix is J/m, a projection, so the consensus stops after its first
round there (:func:`coloc.icp_kernels.complete_component_consensus`).

Performance layout: the BPA-L iterations run as numba passes over the rows
(:mod:`coloc.icp_kernels`; ``BPA_KERNELS = False`` selects the batched numpy
reference, equal up to rounding); :class:`FeatureStore` caches what it derives
from its (immutable) arrays.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from numba import njit

from coloc.consensus import _average_kernel, connected_components
from coloc.icp_kernels import (
    complete_component_consensus,
    extrinsic_kernel,
    feature_to_vehicle_kernel,
    information_kernel,
    inverse_spd_kernel,
    predict_no_input_kernel,
    scatter_add,
    vehicle_to_feature_kernel,
)
from coloc.models import MotionParams, feature_noise_cov, symmetrize

__all__ = [
    "IcpParams",
    "BpaResult",
    "FeatureStore",
    "feature_track_q",
    "birth_information",
    "to_information",
    "from_information",
    "relative_message",
    "psd_clip",
    "consensus_graph",
    "row_components",
    "row_consensus_weights",
    "bpa_localization",
    "step_feature_beliefs",
    "validate_association",
]


#: What a vehicle's stored message to a feature track is built on (see :class:`IcpParams`).
FEATURE_MESSAGES = ("bpa", "own")


@dataclass(frozen=True)
class IcpParams:
    """Parameters of the Gaussian ICP (BPA-L with consensus).

    ``feature_sigma_par`` / ``feature_sigma_perp``: velocity random walk of
    model (2), m/s per step (Q_F = G diag(sv_par^2, sv_perp^2) G^T). Static
    features get a small default, sv_par = 0.01 m/s (the crossroad rule
    sv_par = vf/100 at vf = 1 m/s) so that tracks stay slightly open and their
    information does not grow without bound; sv_perp defaults to sv_par/2.
    A feature whose estimated speed is below ``feature_heading_min_speed``
    has no trusted heading and gets the isotropic Q_F (sv_par on both axes).

    A feature track no vehicle observed for more than
    ``feature_drop_after_s`` seconds is dropped (the paper resets an unobserved
    feature to a uniform belief; keeping it a while lets vehicles arriving
    later reuse what earlier vehicles learned).

    ``feature_velocity_prior_sigma``: a newborn track has a uniform position
    and, if set, a N(0, s^2 I) velocity (features known to be landmarks or
    slow objects); None or 0 is the paper's uniform belief.
    ``message_memory_s``: how long the latest message of a vehicle that
    stopped observing a track is kept apart (to be replaced if the vehicle
    observes the track again) before it is folded into the track
    (:class:`FeatureStore`).

    ``feature_message``: what each vehicle's message to a track is built on
    when it is *stored* in the track for later steps (within a step BPA-L
    always iterates the full messages (19)):

    * ``"own"`` (default): the vehicle's own-sensor belief (GNSS + inertial)
      integrated against this row's V2F likelihood, i.e. (19) with the
      other features' messages left out of the cavity. Own-sensor errors of
      different vehicles are independent, and each vehicle's message is kept
      once per track (latest message), so a track accumulates every vehicle's
      evidence exactly once and keeps converging as vehicles pass.
    * ``"bpa"``: the final message (19) of the step's BPA-L. Its cavity holds
      the other features' messages, which carry the other vehicles' evidence;
      storing and folding it counts that evidence again in every track the
      vehicle observes, step after step. Tracks become overconfident and stop
      absorbing new vehicles. Measured on the arterial TLR, first 600 s, LC:
      with Q_F sv_par = 0.001 m/s a block of 22 features locked onto a common
      ~2 m offset (vehicle RMSE 1.13 m, against 0.63 m with "own"); at
      0.0001 "own" gives 0.60 m, while "bpa" needs Q_F = 0.01 to forget fast
      enough (0.69 m). Kept to reproduce earlier results.
    """

    motion: MotionParams = field(default_factory=MotionParams)
    consensus_iterations: int = 20
    bpa_max_iterations: int = 10
    stop_pos_m: float = 0.1
    stop_vel_mps: float = 0.1
    feature_sigma_par: float = 0.01
    feature_sigma_perp: float | None = None
    feature_heading_min_speed: float = 0.5
    feature_drop_after_s: float = 10.0
    feature_velocity_prior_sigma: float | None = None
    message_memory_s: float = 10.0
    feature_message: str = "own"

    def __post_init__(self):
        if self.consensus_iterations < 0:
            raise ValueError("consensus_iterations must be >= 0")
        if self.bpa_max_iterations < 1:
            raise ValueError("bpa_max_iterations must be >= 1")
        if self.stop_pos_m < 0 or self.stop_vel_mps < 0:
            raise ValueError("stopping thresholds must be >= 0")
        if self.feature_sigma_par < 0 or (self.feature_sigma_perp is not None and self.feature_sigma_perp < 0):
            raise ValueError("feature driving noise must be >= 0")
        if self.feature_drop_after_s < 0:
            raise ValueError("feature_drop_after_s must be >= 0")
        if self.feature_velocity_prior_sigma is not None and self.feature_velocity_prior_sigma < 0:
            raise ValueError("feature_velocity_prior_sigma must be >= 0 (0 or None: uniform)")
        if self.message_memory_s < 0:
            raise ValueError("message_memory_s must be >= 0")
        if self.feature_message not in FEATURE_MESSAGES:
            raise ValueError(f"feature_message must be one of {FEATURE_MESSAGES}")

    @property
    def feature_sigma_perp_value(self) -> float:
        return self.feature_sigma_par / 2 if self.feature_sigma_perp is None else self.feature_sigma_perp


# ----------------------------------------------------------------------------- Gaussian algebra


def _inv_spd_numpy(m: np.ndarray) -> np.ndarray:
    return symmetrize(np.linalg.inv(m))


def _inv_spd(m: np.ndarray) -> np.ndarray:
    """Inverse of symmetric positive definite 4x4 matrices (numba Cholesky; numpy reference above)."""
    m = np.asarray(m, dtype=np.float64)
    if m.ndim < 2 or m.shape[-2:] != (4, 4):
        return _inv_spd_numpy(m)
    return inverse_spd_kernel(np.ascontiguousarray(m.reshape(-1, 4, 4))).reshape(m.shape)


def to_information(mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean (..,4), cov (..,4,4)) -> (Lambda, eta) = (P^-1, P^-1 m)."""
    mean = np.asarray(mean, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    if cov.shape[-2:] != (4, 4) or mean.shape != cov.shape[:-1]:
        lam = _inv_spd_numpy(cov)
        return lam, np.einsum("...ij,...j->...i", lam, mean)
    lam, eta = information_kernel(np.ascontiguousarray(mean.reshape(-1, 4)), np.ascontiguousarray(cov.reshape(-1, 4, 4)))
    return lam.reshape(cov.shape), eta.reshape(mean.shape)


def from_information(lam: np.ndarray, eta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Lambda, eta) -> (mean, cov); Lambda must be positive definite (same kernel as :func:`to_information`)."""
    cov, mean = to_information(eta, lam)
    return mean, cov


def psd_clip(lam: np.ndarray, eta: np.ndarray, floor: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Project information matrices on the PSD cone (eigenvalues < floor -> floor).

    Only needed for extrinsic information after *finite* consensus: count *
    average - own message can be slightly indefinite. The eta component along
    a clipped direction is removed too (no information -> no mean there).
    """
    if lam.shape[0] == 0:
        return lam, eta
    # Most calls clip nothing. Rows that a shifted Cholesky proves safely positive definite
    # (smallest eigenvalue far above the floor and the eigensolver's rounding) cannot be
    # clipped; only the others need the eigendecomposition. If none of them is clipped the
    # inputs are returned as they are, exactly as below.
    unsure = np.flatnonzero(~_surely_above_floor(np.ascontiguousarray(lam, dtype=np.float64), float(floor)))
    if unsure.size == 0 or not (np.linalg.eigh(symmetrize(lam[unsure]))[0] < floor).any():
        return lam, eta
    w, v = np.linalg.eigh(symmetrize(lam))
    bad = w < floor
    if not bad.any():
        return lam, eta
    keep = ~bad
    w = np.where(keep, w, floor)
    lam_c = np.einsum("...ik,...k,...jk->...ij", v, w, v)
    # Remove the part of eta in the clipped eigen-directions.
    coef = np.einsum("...ki,...k->...i", v, eta) * keep
    eta_c = np.einsum("...ik,...k->...i", v, coef)
    return symmetrize(lam_c), eta_c


@njit(cache=True)
def _surely_above_floor(lam, floor):
    """Per (4, 4) matrix: True when symmetrize(lam) - (floor + margin) I has a Cholesky
    factor with positive pivots, margin = 1e-8 * (largest |diagonal entry|). Cholesky is
    backward stable (error ~1e-15 of the entries), so such a matrix has every eigenvalue
    above ``floor`` by far more than a LAPACK eigensolver's rounding: it is never clipped.
    False means only "not proven" (singular or indefinite matrices, NaN)."""
    n = lam.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    a = np.empty((4, 4))
    for m in range(n):
        scale = 0.0
        for i in range(4):
            d = abs(lam[m, i, i])
            if d > scale:
                scale = d
        shift = floor + 1e-8 * scale
        for i in range(4):
            for j in range(4):
                a[i, j] = 0.5 * (lam[m, i, j] + lam[m, j, i])
            a[i, i] -= shift
        ok = scale > 0.0
        for j in range(4):
            if not ok:
                break
            d = a[j, j]
            for k in range(j):
                d -= a[j, k] * a[j, k]
            if not d > 0.0:  # also catches NaN
                ok = False
                break
            d = np.sqrt(d)
            a[j, j] = d
            for i in range(j + 1, 4):
                acc = a[i, j]
                for k in range(j):
                    acc -= a[i, k] * a[j, k]
                a[i, j] = acc / d
        out[m] = ok
    return out


def relative_message(
    lam: np.ndarray, eta: np.ndarray, offset: np.ndarray, r: np.ndarray, r_inv: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Information form of y = x + offset + n, x ~ (Lambda, eta), n ~ N(0, R), batched.

    This is the integral in (19) (offset +z: x_F = x_V + z) and (21)
    (offset -z: x_V = x_F - z) of a Gaussian belief against the V2F likelihood
    of model (4). Moments: N(m + offset, P + R). Computed without inverting
    Lambda so that a singular Lambda (uniform belief, e.g. a feature seen for
    the first time) gives the zero message:
        S = Lambda + R^-1,  Lambda_y = (P + R)^-1 = Lambda S^-1 R^-1,
        eta_y = R^-1 S^-1 eta + Lambda_y offset.
    """
    if r_inv is None:
        r_inv = _inv_spd_numpy(r)
    s = lam + r_inv
    s_inv = _inv_spd_numpy(s)
    lam_y = symmetrize(lam @ s_inv @ r_inv)
    eta_y = np.einsum("nij,nj->ni", r_inv @ s_inv, eta) + np.einsum("nij,nj->ni", lam_y, offset)
    return lam_y, eta_y


# ----------------------------------------------------------------------------- consensus groups


def consensus_graph(owner: np.ndarray, group: np.ndarray, adjacency: sp.spmatrix) -> sp.csr_matrix:
    """(O, O) graph on V2F rows: rows (i, k), (j, k) linked iff i, j are V2V neighbours.

    ``group`` (O,) is the feature each row is paired with (rows with group < 0
    take no part: no edges). One average consensus on this graph equals one
    consensus per feature restricted to the vehicles sensing it.
    """
    owner = np.asarray(owner, dtype=np.int64)
    group = np.asarray(group, dtype=np.int64)
    o = owner.size
    n = adjacency.shape[0]
    if o == 0:
        return sp.csr_matrix((0, 0), dtype=bool)
    used = group >= 0
    rows_idx = np.flatnonzero(used)
    own = sp.csr_matrix((np.ones(rows_idx.size), (rows_idx, owner[used])), shape=(o, n))
    _, g = np.unique(group[used], return_inverse=True)
    feat = sp.csr_matrix((np.ones(rows_idx.size), (rows_idx, g)), shape=(o, int(g.max()) + 1 if g.size else 0))
    adj = sp.csr_matrix(adjacency, dtype=np.float64)
    linked = (own @ adj @ own.T).multiply(feat @ feat.T)
    out = sp.csr_matrix(linked, dtype=bool)
    out.setdiag(False)
    out.eliminate_zeros()
    out.sort_indices()
    return out


def row_components(graph: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Component label and size (participant count |V_k ∩ C|) of every row."""
    n_comp, labels = connected_components(graph)
    sizes = np.bincount(labels, minlength=n_comp).astype(np.float64) if labels.size else np.zeros(0)
    return labels, sizes[labels] if labels.size else np.zeros(0)


@njit(cache=True)
def _pairwise_leaf(a, lo, n):
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True)
def _pairwise_sum(a, lo, n):
    """numpy's pairwise summation of a[lo:lo+n] (8 accumulators, halves above 128), bit for bit.

    The recursion is run on an explicit stack (numba's on-disk cache and recursion do not mix)."""
    if n <= 128:
        return _pairwise_leaf(a, lo, n)
    depth = 64
    w_lo = np.empty(depth * 3, dtype=np.int64)
    w_n = np.empty(depth * 3, dtype=np.int64)
    w_op = np.empty(depth * 3, dtype=np.int64)
    vals = np.empty(depth * 3)
    top, nv = 0, 0
    w_lo[0], w_n[0], w_op[0] = lo, n, 0
    top = 1
    while top > 0:
        top -= 1
        if w_op[top] == 1:  # combine the two last values: left + right
            vals[nv - 2] = vals[nv - 2] + vals[nv - 1]
            nv -= 1
            continue
        cl, cn = w_lo[top], w_n[top]
        if cn <= 128:
            vals[nv] = _pairwise_leaf(a, cl, cn)
            nv += 1
            continue
        n2 = cn // 2
        n2 -= n2 % 8
        w_op[top] = 1
        top += 1
        w_lo[top], w_n[top], w_op[top] = cl + n2, cn - n2, 0
        top += 1
        w_lo[top], w_n[top], w_op[top] = cl, n2, 0
        top += 1
    return vals[0]


@njit(cache=True)
def _row_consensus_kernel(owner, group, n_groups, adj_indptr, adj_indices, adj_data, n_vehicles):
    """Metropolis weights (CSR, diagonal included, columns sorted) of the row graph of
    :func:`consensus_graph` and each row's component size |V_k ∩ C| (:func:`row_components`).

    Same numbers as ``metropolis_weights(consensus_graph(...))``: off-diagonal
    w_rs = 1 / (1 + max(d_r, d_s)), w_rr = 1 - (sum of the row's off-diagonal
    weights in column order, summed as scipy's CSR row sum, i.e. numpy's add.reduceat).
    ``group`` (O,) in [0, n_groups) (every row used); rows of one group are
    linked iff their owners are V2V neighbours (a stored nonzero of the adjacency).
    """
    o = owner.size
    # Dense V2V lookup (N is a few hundred vehicles).
    adj = np.zeros((n_vehicles, n_vehicles), dtype=np.bool_)
    for i in range(n_vehicles):
        for p in range(adj_indptr[i], adj_indptr[i + 1]):
            if adj_data[p] != 0:
                adj[i, adj_indices[p]] = True
    # Rows of each group, ascending (counting sort keeps row order).
    g_count = np.zeros(n_groups + 1, dtype=np.int64)
    for r in range(o):
        g_count[group[r] + 1] += 1
    for g in range(n_groups):
        g_count[g + 1] += g_count[g]
    g_rows = np.empty(o, dtype=np.int64)
    fill = g_count[:n_groups].copy()
    for r in range(o):
        g_rows[fill[group[r]]] = r
        fill[group[r]] += 1
    # Degrees, and components by union-find (links never cross groups).
    deg = np.zeros(o, dtype=np.int64)
    parent = np.arange(o)
    for g in range(n_groups):
        for a in range(g_count[g], g_count[g + 1]):
            r = g_rows[a]
            for b in range(a + 1, g_count[g + 1]):
                s = g_rows[b]
                if adj[owner[r], owner[s]] and r != s:
                    deg[r] += 1
                    deg[s] += 1
                    x, y = r, s
                    while parent[x] != x:
                        x = parent[x]
                    while parent[y] != y:
                        y = parent[y]
                    if x != y:
                        if x < y:
                            parent[y] = x
                        else:
                            parent[x] = y
    root = np.empty(o, dtype=np.int64)
    size = np.zeros(o, dtype=np.int64)
    for r in range(o):
        x = r
        while parent[x] != x:
            x = parent[x]
        root[r] = x
        size[x] += 1
    count = np.empty(o)
    for r in range(o):
        count[r] = float(size[root[r]])
    # complete component: every row linked to all the others (sum of degrees = m (m - 1))
    deg_sum = np.zeros(o, dtype=np.int64)
    for r in range(o):
        deg_sum[root[r]] += deg[r]
    complete = np.empty(o, dtype=np.bool_)
    for r in range(o):
        m = size[root[r]]
        complete[r] = deg_sum[root[r]] == m * (m - 1)
    # CSR with the diagonal: row r has deg[r] + 1 entries, columns ascending.
    indptr = np.zeros(o + 1, dtype=np.int64)
    for r in range(o):
        indptr[r + 1] = indptr[r] + deg[r] + 1
    indices = np.empty(indptr[o], dtype=np.int64)
    data = np.empty(indptr[o])
    buf = np.empty(max(1, int(deg.max()) if o else 1))
    for r in range(o):
        g = group[r]
        p0 = indptr[r]
        # off-diagonal weights in column order, summed as numpy's add.reduceat does
        # (first element, then the pairwise sum of the rest): scipy's CSR row sum.
        nb = 0
        for a in range(g_count[g], g_count[g + 1]):
            s = g_rows[a]
            if s != r and adj[owner[r], owner[s]]:
                buf[nb] = 1.0 / (1.0 + float(max(deg[r], deg[s])))
                nb += 1
        acc = buf[0] + _pairwise_sum(buf, 1, nb - 1) if nb else 0.0
        diag = 1.0 - acc
        q = p0
        placed = False
        for a in range(g_count[g], g_count[g + 1]):
            s = g_rows[a]
            if not placed and s > r:
                indices[q] = r
                data[q] = diag
                q += 1
                placed = True
            if s != r and adj[owner[r], owner[s]]:
                indices[q] = s
                data[q] = 1.0 / (1.0 + float(max(deg[r], deg[s])))
                q += 1
        if not placed:
            indices[q] = r
            data[q] = diag
    return indptr, indices, data, count, complete


def _canonical_adjacency(adjacency: sp.spmatrix) -> sp.csr_matrix:
    a = adjacency if sp.isspmatrix_csr(adjacency) or isinstance(adjacency, sp.csr_array) else sp.csr_matrix(adjacency)
    if not a.has_canonical_format:
        a = sp.csr_matrix(a, copy=True)
        a.sum_duplicates()
    return a


def row_consensus_weights(
    owner: np.ndarray, group_index: np.ndarray, n_groups: int, adjacency: sp.spmatrix
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
    """Metropolis weights of :func:`consensus_graph` as CSR arrays (indptr, indices, data),
    the per-row participant count |V_k ∩ C| of :func:`row_components` and whether the row's
    component is a complete graph, in one numba pass.

    ``group_index`` (O,): every row's feature as an index in [0, n_groups) (all rows used).
    Equals ``metropolis_weights(consensus_graph(owner, group, adjacency))`` and
    ``row_components(...)[1]`` bit for bit (tests), without scipy.sparse on the small graphs.
    """
    a = _canonical_adjacency(adjacency)
    return _split4(
        _row_consensus_kernel(
            np.asarray(owner, dtype=np.int64), np.asarray(group_index, dtype=np.int64), int(n_groups),
            a.indptr.astype(np.int64), a.indices.astype(np.int64), np.asarray(a.data != 0), int(a.shape[0]),
        )
    )


def _split4(t):
    return (t[0], t[1], t[2]), t[3], t[4]


def validate_association(owner: np.ndarray, feature: np.ndarray, n_rows: int) -> np.ndarray:
    """Check a per-row feature id array; returns it as int64.

    Ids are stable integers (>= 0) across steps; -1 marks a row that is not
    used. A vehicle cannot measure the same feature twice in one step.
    """
    f = np.asarray(feature)
    if f.shape != (n_rows,):
        raise ValueError(f"association must have one entry per V2F row: shape ({n_rows},), got {f.shape}")
    if n_rows and not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"association must be integer feature ids, got dtype {f.dtype}")
    f = f.astype(np.int64)
    if (f < -1).any():
        raise ValueError("association ids must be >= 0 (or -1 for an unused row)")
    used = f >= 0
    if used.any():
        key = np.asarray(owner, dtype=np.int64)[used] * (int(f.max()) + 1) + f[used]
        if np.unique(key).size != key.size:
            raise ValueError("a vehicle has two V2F rows associated with the same feature")
    return f


# ----------------------------------------------------------------------------- feature tracks


def feature_track_q(mean: np.ndarray, dt: float, params: IcpParams) -> np.ndarray:
    """Q_F of model (2) for tracks with these means, isotropic below the heading speed."""
    v = np.array(mean[:, 2:], dtype=float)
    slow = np.hypot(v[:, 0], v[:, 1]) < params.feature_heading_min_speed
    v[slow] = 0.0
    return feature_noise_cov(v, dt, params.feature_sigma_par, params.feature_sigma_perp_value)


def birth_information(params: IcpParams) -> np.ndarray:
    """Information (4, 4) of a newborn track: uniform position; velocity N(0, s^2 I) if s is set."""
    lam = np.zeros((4, 4))
    s = params.feature_velocity_prior_sigma
    if s:  # None or 0: uniform
        lam[2, 2] = lam[3, 3] = 1.0 / (s * s)
    return lam


#: Process-wide integer code of every vehicle id seen (by its string form, as before): pair keys
#: become integer arithmetic instead of a sort of Python strings at every call.
_VEHICLE_CODES: dict[str, int] = {}


def vehicle_codes(vehicles) -> np.ndarray:
    """Process-wide integer code of each vehicle id (equal iff the id strings are equal)."""
    reg = _VEHICLE_CODES
    return np.fromiter(
        (reg.setdefault(v if type(v) is str else str(v), len(reg)) for v in vehicles), dtype=np.int64,
        count=len(vehicles),
    )


def _pair_keys(tracks_a, vehicles_a, tracks_b, vehicles_b, codes_a=None) -> tuple[np.ndarray, np.ndarray]:
    """Integer keys of (track, vehicle) pairs of two lists, comparable with each other
    (equal iff same track id and same vehicle id string)."""
    ca = vehicle_codes(vehicles_a) if codes_a is None else codes_a
    cb = vehicle_codes(vehicles_b)
    ka = np.asarray(tracks_a, dtype=np.int64) * (1 << 32) + ca
    kb = np.asarray(tracks_b, dtype=np.int64) * (1 << 32) + cb
    return ka, kb


@dataclass(frozen=True)
class FeatureStore:
    """Feature tracks shared over V2V, kept as *latest messages per vehicle*.

    The belief of track k is the product of
      * the birth prior (:func:`birth_information`),
      * a folded part: messages of vehicles that stopped observing k more than
        ``message_memory_s`` ago, multiplied into one Gaussian (info form),
      * the latest vehicle -> feature message of every vehicle that observed k
        recently (moment form, one per (track, vehicle)): by default (19)
        built on the vehicle's own-sensor belief alone, see
        ``IcpParams.feature_message``.
    A vehicle observing k again *replaces* its previous message instead of
    multiplying a new one in. Its own-sensor belief, from which the message is
    built, already contains all its earlier evidence (see
    :func:`bpa_localization`), so replacing avoids counting one vehicle's GNSS
    history once per step (the time-correlated double counting that otherwise
    makes tracks arbitrarily overconfident). Evidence of *different* vehicles
    (independent GNSS errors) accumulates. The paper's (20) treats every step
    anew; this is our documented choice for carrying tracks between steps.

    Messages and the folded part are predicted by model (2) separately, each
    with the track's Q_F (conservative for moving features: the noise enters
    every factor, not once; exact for static ones in the limit Q_F -> 0).
    """

    ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    last_seen: np.ndarray = field(default_factory=lambda: np.empty(0))
    folded_lam: np.ndarray = field(default_factory=lambda: np.empty((0, 4, 4)))
    folded_eta: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))
    msg_track: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    msg_vehicle: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=object))
    msg_mean: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))
    msg_cov: np.ndarray = field(default_factory=lambda: np.empty((0, 4, 4)))
    msg_time: np.ndarray = field(default_factory=lambda: np.empty(0))

    @property
    def size(self) -> int:
        return int(self.ids.size)

    def lookup(self, feature_ids: np.ndarray) -> np.ndarray:
        """Row of each id in the store (ids are sorted), -1 where absent."""
        feature_ids = np.asarray(feature_ids, dtype=np.int64)
        if self.ids.size == 0:
            return np.full(feature_ids.size, -1, dtype=np.int64)
        pos = np.minimum(np.searchsorted(self.ids, feature_ids), self.ids.size - 1)
        return np.where(self.ids[pos] == feature_ids, pos, -1)

    @cached_property
    def _message_information(self) -> tuple[np.ndarray, np.ndarray]:
        """(Lambda, eta) of every stored message, computed once per store (the store is immutable)."""
        return to_information(self.msg_mean, self.msg_cov)

    def information(self, params: IcpParams, exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(Lambda, eta) of every track: birth x folded x messages (those not excluded)."""
        lam = self.folded_lam + birth_information(params)
        eta = self.folded_eta.copy()
        use = np.ones(self.msg_track.size, bool) if exclude is None else ~exclude
        if use.any():
            ml, me = self._message_information
            rows = self.lookup(self.msg_track[use])
            scatter_add(lam, rows, ml[use])
            scatter_add(eta, rows, me[use])
        return symmetrize(lam), eta

    def moments(self, params: IcpParams) -> tuple[np.ndarray, np.ndarray]:
        """Track means and covariances (every stored track has had at least one message).

        Cached per store and params (the store is immutable); treat the arrays as read-only."""
        cache = self.__dict__.setdefault("_moments_cache", {})
        if params not in cache:
            if self.ids.size == 0:
                cache[params] = (np.empty((0, 4)), np.empty((0, 4, 4)))
            else:
                cache[params] = from_information(*self.information(params))
        return cache[params]

    def predict(self, dt: float, params: IcpParams) -> "FeatureStore":
        """Eq. (12): every factor of every track predicted by model (2) (no input)."""
        if self.ids.size == 0:
            return self
        mean, _ = self.moments(params)
        q = feature_track_q(mean, dt, params)
        folded_lam, folded_eta = self.folded_lam.copy(), self.folded_eta.copy()
        has = np.abs(folded_lam).sum(axis=(1, 2)) > 0
        if has.any():
            fm, fp = from_information(folded_lam[has], folded_eta[has])
            fm, fp = predict_no_input_kernel(fm, fp, np.ascontiguousarray(q[has]), float(dt))
            folded_lam[has], folded_eta[has] = to_information(fm, fp)
        msg_mean, msg_cov = self.msg_mean, self.msg_cov
        if self.msg_track.size:
            rows = self.lookup(self.msg_track)
            msg_mean, msg_cov = predict_no_input_kernel(
                np.ascontiguousarray(msg_mean), np.ascontiguousarray(msg_cov), np.ascontiguousarray(q[rows]), float(dt)
            )
        out = dataclasses.replace(
            self, folded_lam=folded_lam, folded_eta=folded_eta, msg_mean=msg_mean, msg_cov=msg_cov
        )
        return out._with_codes(self._msg_codes)

    def _with_codes(self, codes: np.ndarray) -> "FeatureStore":
        """Seed the cached vehicle codes of the messages (same vehicles as ``codes`` describe)."""
        self.__dict__["_msg_codes"] = codes
        return self

    @cached_property
    def _msg_codes(self) -> np.ndarray:
        return vehicle_codes(self.msg_vehicle)

    def _replaced(self, row_feature: np.ndarray, row_vehicle: np.ndarray, row_codes=None) -> np.ndarray:
        """Mask over stored messages whose (track, vehicle) pair appears in the rows."""
        if row_codes is None:
            row_codes = vehicle_codes(row_vehicle)
        row_feature = np.asarray(row_feature, dtype=np.int64)
        # prior_information and record ask the same (predicted) store about the same rows: keep the last answer.
        last = self.__dict__.get("_replaced_last")
        if last is not None and np.array_equal(last[0], row_feature) and np.array_equal(last[1], row_codes):
            return last[2]
        km = np.asarray(self.msg_track, dtype=np.int64) * (1 << 32) + self._msg_codes
        kr = row_feature * (1 << 32) + row_codes
        mask = np.isin(km, kr)
        self.__dict__["_replaced_last"] = (row_feature.copy(), np.array(row_codes, copy=True), mask)
        return mask

    def prior_information(
        self, feature_ids: np.ndarray, row_feature: np.ndarray, row_vehicle: np.ndarray, params: IcpParams,
        row_codes: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """b_k^(0) of (12) for ``feature_ids``, without the messages the rows' vehicles will replace.

        ``row_feature``/``row_vehicle``: the (track id, vehicle id) of every used
        V2F row of this step. New ids get the birth prior only. ``row_codes``:
        ``vehicle_codes(row_vehicle)`` if the caller has them.
        """
        k = len(feature_ids)
        lam = np.broadcast_to(birth_information(params), (k, 4, 4)).copy()
        eta = np.zeros((k, 4))
        idx = self.lookup(feature_ids)
        have = idx >= 0
        if have.any():
            tl, te = self.information(params, exclude=self._replaced(row_feature, row_vehicle, row_codes))
            lam[have], eta[have] = tl[idx[have]], te[idx[have]]
        return lam, eta

    def record(
        self,
        row_feature: np.ndarray,
        row_vehicle: np.ndarray,
        msg_lam: np.ndarray,
        msg_eta: np.ndarray,
        t: float,
        params: IcpParams,
        row_codes: np.ndarray | None = None,
    ) -> "FeatureStore":
        """Store this step's final messages (19), fold old ones, drop stale tracks.

        Each row's message replaces the previous message of its (track, vehicle)
        pair; new track ids are created; tracks observed now get last_seen = t.
        """
        row_feature = np.asarray(row_feature, dtype=np.int64)
        if row_codes is None:
            row_codes = vehicle_codes(row_vehicle)
        keep = ~self._replaced(row_feature, row_vehicle, row_codes)
        mm, mc = from_information(msg_lam, msg_eta) if row_feature.size else (np.empty((0, 4)), np.empty((0, 4, 4)))
        new_ids = np.setdiff1d(np.unique(row_feature), self.ids)
        ids = np.concatenate([self.ids, new_ids])
        order = np.argsort(ids, kind="stable")
        ids = ids[order]
        last_seen = np.concatenate([self.last_seen, np.full(new_ids.size, float(t))])[order]
        last_seen[np.searchsorted(ids, np.unique(row_feature))] = float(t)
        folded_lam = np.concatenate([self.folded_lam, np.zeros((new_ids.size, 4, 4))])[order]
        folded_eta = np.concatenate([self.folded_eta, np.zeros((new_ids.size, 4))])[order]
        msg_track = np.concatenate([self.msg_track[keep], row_feature])
        msg_vehicle = np.concatenate([self.msg_vehicle[keep], np.asarray(row_vehicle, dtype=object)])
        msg_codes = np.concatenate([self._msg_codes[keep], row_codes])
        msg_mean = np.concatenate([self.msg_mean[keep], mm])
        msg_cov = np.concatenate([self.msg_cov[keep], mc])
        msg_time = np.concatenate([self.msg_time[keep], np.full(row_feature.size, float(t))])
        # Messages of vehicles that stopped observing a track are folded into it.
        old = msg_time < t - params.message_memory_s
        if old.any():
            ol, oe = to_information(msg_mean[old], msg_cov[old])
            rows = np.searchsorted(ids, msg_track[old])
            scatter_add(folded_lam, rows, ol)
            scatter_add(folded_eta, rows, oe)
            msg_track, msg_vehicle, msg_codes, msg_mean, msg_cov, msg_time = (
                a[~old] for a in (msg_track, msg_vehicle, msg_codes, msg_mean, msg_cov, msg_time)
            )
        # Tracks nobody observed for longer than feature_drop_after_s are dropped
        # (the paper's reset of an unobserved feature to a uniform belief).
        live = (t - last_seen) <= params.feature_drop_after_s
        keep_msg = np.isin(msg_track, ids[live])
        return FeatureStore(
            ids=ids[live],
            last_seen=last_seen[live],
            folded_lam=symmetrize(folded_lam[live]),
            folded_eta=folded_eta[live],
            msg_track=msg_track[keep_msg],
            msg_vehicle=msg_vehicle[keep_msg],
            msg_mean=msg_mean[keep_msg],
            msg_cov=msg_cov[keep_msg],
            msg_time=msg_time[keep_msg],
        )._with_codes(msg_codes[keep_msg])

    def merge(self, absorbed: np.ndarray, into: np.ndarray) -> "FeatureStore":
        """Merge track ``absorbed[j]`` into track ``into[j]`` (ids; every absorbed id distinct, not a target).

        The merged track keeps the target id; folded parts multiply; of two
        messages of the same vehicle the more recent one is kept (the older
        is subsumed by it, as in :meth:`record`); last_seen is the later one.
        """
        absorbed = np.asarray(absorbed, dtype=np.int64)
        into = np.asarray(into, dtype=np.int64)
        if absorbed.size == 0:
            return self
        ra, ri = self.lookup(absorbed), self.lookup(into)
        if (ra < 0).any() or (ri < 0).any() or np.isin(into, absorbed).any():
            raise ValueError("merge: unknown track id, or a track both absorbed and absorbing")
        folded_lam, folded_eta, last_seen = self.folded_lam.copy(), self.folded_eta.copy(), self.last_seen.copy()
        scatter_add(folded_lam, ri, folded_lam[ra])
        scatter_add(folded_eta, ri, folded_eta[ra])
        np.maximum.at(last_seen, ri, last_seen[ra])
        msg_track = self.msg_track.copy()
        hit = self.lookup(msg_track)
        remap = np.arange(self.ids.size)
        remap[ra] = ri
        msg_track = self.ids[remap[hit]]
        # One message per (track, vehicle): keep the latest (stable order breaks ties).
        key, _ = _pair_keys(msg_track, self.msg_vehicle, np.empty(0, np.int64), np.empty(0, dtype=object), self._msg_codes)
        order = np.lexsort((-self.msg_time, key))
        first = np.ones(order.size, bool)
        first[1:] = key[order][1:] != key[order][:-1]
        keep = np.sort(order[first])
        live = np.ones(self.ids.size, bool)
        live[ra] = False
        return FeatureStore(
            ids=self.ids[live],
            last_seen=last_seen[live],
            folded_lam=symmetrize(folded_lam[live]),
            folded_eta=folded_eta[live],
            msg_track=msg_track[keep],
            msg_vehicle=self.msg_vehicle[keep],
            msg_mean=self.msg_mean[keep],
            msg_cov=self.msg_cov[keep],
            msg_time=self.msg_time[keep],
        )._with_codes(self._msg_codes[keep])

    def drop_stale(self, t: float, params: IcpParams) -> "FeatureStore":
        """Drop tracks nobody observed for longer than ``feature_drop_after_s`` (no new messages)."""
        empty = np.empty(0, dtype=np.int64)
        return self.record(empty, np.empty(0, dtype=object), np.empty((0, 4, 4)), np.empty((0, 4)), t, params)


# ----------------------------------------------------------------------------- BPA-L


@dataclass(frozen=True)
class BpaResult:
    mean: np.ndarray  # (N, 4) vehicle beliefs (22)
    cov: np.ndarray  # (N, 4, 4)
    used: np.ndarray  # (O,) bool: V2F rows that took part (feature id >= 0)
    msg_lam: np.ndarray  # (O_used, 4, 4) vehicle -> feature messages to store (IcpParams.feature_message)
    msg_eta: np.ndarray  # (O_used, 4)
    iterations: int
    converged: bool
    final_lam: np.ndarray | None = None  # (O_used, 4, 4) the final messages (19) of BPA-L; None: = msg_lam
    final_eta: np.ndarray | None = None


_SYM_I, _SYM_J = np.triu_indices(4)
_SYM_FULL = np.array([[int(np.flatnonzero((_SYM_I == min(a, b)) & (_SYM_J == max(a, b)))[0]) for b in range(4)] for a in range(4)])


def _pack_sym(lam: np.ndarray, eta: np.ndarray) -> np.ndarray:
    """(O, 14): the upper triangle of each (exactly symmetric) Lambda, then eta."""
    return np.ascontiguousarray(np.concatenate([lam[:, _SYM_I, _SYM_J], eta], axis=1))


def _unpack_sym(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return x[:, :10][:, _SYM_FULL], x[:, 10:]


@njit(cache=True)
def _sum_by_owner(owner, lam_flat, eta, n):
    """Per-vehicle sums of row values, rows added in ascending row order from 0 (eq. (22) product)."""
    out_l = np.zeros((n, lam_flat.shape[1]))
    out_e = np.zeros((n, eta.shape[1]))
    for r in range(owner.size):
        i = owner[r]
        for c in range(lam_flat.shape[1]):
            out_l[i, c] += lam_flat[r, c]
        for c in range(eta.shape[1]):
            out_e[i, c] += eta[r, c]
    return out_l, out_e


def _pack(lam: np.ndarray, eta: np.ndarray) -> np.ndarray:
    return np.concatenate([lam.reshape(lam.shape[0], 16), eta], axis=1)


def _unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return symmetrize(x[:, :16].reshape(-1, 4, 4)), x[:, 16:]


#: Run the BPA-L iterations with the numba kernels of :mod:`coloc.icp_kernels` (False: the
#: numpy reference below; same algorithm, results equal up to rounding, see tests).
BPA_KERNELS = True


def _bpa_iterations_numpy(
    prior_mean, v_lam0, v_eta0, own_lam0, own_eta0, owner_u, z_u, r_u, r_inv, lam_f0_row, eta_f0_row, count,
    complete, weights, params,
):
    """BPA-L iterations (19)-(22) with batched numpy (the reference of the kernels)."""
    w_indptr, w_indices, w_data = weights
    n, o = prior_mean.shape[0], owner_u.size
    n_iter_cons = int(params.consensus_iterations)
    v_lam, v_eta = v_lam0.copy(), v_eta0.copy()
    mean = prior_mean.copy()
    # m_{k->i}^(0) = 1 (zero information).
    m_fv_lam = np.zeros((o, 4, 4))
    m_fv_eta = np.zeros((o, 4))
    in_lam = np.zeros((n, 4, 4))
    in_eta = np.zeros((n, 4))
    converged = False
    it = 0
    for it in range(1, params.bpa_max_iterations + 1):
        # (19): cavity (own belief x messages of the other features), integrated over x_V.
        cav_lam = own_lam0[owner_u] + in_lam[owner_u] - m_fv_lam
        cav_eta = own_eta0[owner_u] + in_eta[owner_u] - m_fv_eta
        m_vf_lam, m_vf_eta = relative_message(cav_lam, cav_eta, z_u, r_u, r_inv)
        # (20): product over V_k by average consensus among the participants, times |V_k ∩ C|
        # (the 10 distinct entries of the symmetric Lambda and the 4 of eta: every entry is
        # an independent consensus, so the symmetric copies need not be run twice).
        if n_iter_cons:
            avg = _average_kernel(w_indptr, w_indices, w_data, _pack_sym(m_vf_lam, m_vf_eta), n_iter_cons)
            avg_lam, avg_eta = _unpack_sym(avg)
        else:
            avg_lam, avg_eta = m_vf_lam.copy(), m_vf_eta.copy()
        loc_lam = lam_f0_row + count[:, None, None] * avg_lam
        loc_eta = eta_f0_row + count[:, None] * avg_eta
        # (21): extrinsic b_k / m_{i->k} at vehicle i, then integrate over x_F.
        ext_lam, ext_eta = psd_clip(loc_lam - m_vf_lam, loc_eta - m_vf_eta)
        m_fv_lam, m_fv_eta = relative_message(ext_lam, ext_eta, -z_u, r_u, r_inv)
        # (22): b_i = b_i^(0) prod_k m_{k->i} (rows summed in row order, as the sparse incidence product did).
        in_lam, in_eta = _sum_by_owner(owner_u, m_fv_lam.reshape(o, 16), m_fv_eta, n)
        in_lam = in_lam.reshape(n, 4, 4)
        v_lam = symmetrize(v_lam0 + in_lam)
        v_eta = v_eta0 + in_eta
        new_mean = np.linalg.solve(v_lam, v_eta[..., None])[..., 0]
        dpos = np.hypot(*(new_mean[:, :2] - mean[:, :2]).T)
        dvel = np.hypot(*(new_mean[:, 2:] - mean[:, 2:]).T)
        mean = new_mean
        # Stopping rule of Sec. V-A (all vehicles).
        if dpos.max() < params.stop_pos_m and dvel.max() < params.stop_vel_mps:
            converged = True
            break

    return v_lam, v_eta, m_vf_lam, m_vf_eta, it, converged


def _bpa_iterations_kernels(
    prior_mean, v_lam0, v_eta0, own_lam0, own_eta0, owner_u, z_u, r_u, r_inv, lam_f0_row, eta_f0_row, count,
    complete, weights, params,
):
    """BPA-L iterations (19)-(22): each iteration is three numba passes over the rows
    (:mod:`coloc.icp_kernels`) around the consensus kernel."""
    w_indptr, w_indices, w_data = weights
    n, o = prior_mean.shape[0], owner_u.size
    n_iter_cons = int(params.consensus_iterations)
    z_u = np.ascontiguousarray(z_u)
    r_inv = np.ascontiguousarray(r_inv)
    lam_f0_row = np.ascontiguousarray(lam_f0_row)
    eta_f0_row = np.ascontiguousarray(eta_f0_row)
    v_lam, v_eta = v_lam0.copy(), v_eta0.copy()
    mean = np.ascontiguousarray(prior_mean, dtype=np.float64)
    # m_{k->i}^(0) = 1 (zero information).
    m_fv_lam = np.zeros((o, 4, 4))
    m_fv_eta = np.zeros((o, 4))
    in_lam = np.zeros((n, 4, 4))
    in_eta = np.zeros((n, 4))
    converged = False
    it = 0
    for it in range(1, params.bpa_max_iterations + 1):
        # (19): cavity (own belief x messages of the other features), integrated over x_V.
        m_vf_lam, m_vf_eta, packed = vehicle_to_feature_kernel(
            owner_u, own_lam0, own_eta0, in_lam, in_eta, m_fv_lam, m_fv_eta, z_u, r_inv
        )
        # (20): product over V_k by average consensus among the participants, times |V_k ∩ C|.
        # (one round on complete components, where W = J/m is a projection: see the kernel)
        avg = complete_component_consensus(w_indptr, w_indices, w_data, packed, n_iter_cons, complete)
        # (21): extrinsic b_k / m_{i->k} at vehicle i (PSD-projected), then integrate over x_F;
        # (22): b_i = b_i^(0) prod_k m_{k->i} and the new means.
        ext_lam, ext_eta = psd_clip(*extrinsic_kernel(avg, count, lam_f0_row, eta_f0_row, m_vf_lam, m_vf_eta))
        m_fv_lam, m_fv_eta, in_lam, in_eta, v_lam, v_eta, mean, dpos, dvel = feature_to_vehicle_kernel(
            owner_u, np.ascontiguousarray(ext_lam), np.ascontiguousarray(ext_eta), z_u, r_inv, v_lam0, v_eta0, mean
        )
        # Stopping rule of Sec. V-A (all vehicles).
        if dpos < params.stop_pos_m and dvel < params.stop_vel_mps:
            converged = True
            break
    return v_lam, v_eta, m_vf_lam, m_vf_eta, it, converged


def bpa_localization(
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    own_mean: np.ndarray,
    own_cov: np.ndarray,
    owner: np.ndarray,
    feature: np.ndarray,
    z: np.ndarray,
    r: np.ndarray,
    adjacency: sp.spmatrix,
    feature_prior_lam: np.ndarray,
    feature_prior_eta: np.ndarray,
    params: IcpParams,
) -> BpaResult:
    """Gaussian BPA-L, eqs. (19)-(22), with the feature product (20) by consensus.

    ``prior_mean``/``prior_cov`` (N, ...): b_i^(0) of (11), the GNSS-updated
    prediction of the vehicle's previous belief. ``own_mean``/``own_cov``: the
    vehicle's own-sensor belief (GNSS + inertial only, no feature evidence),
    used in place of b_i^(0) inside the cavity of (19): a vehicle tells a
    feature what its *own sensors* say, plus this step's messages of its other
    features. Using b_i^(0) there (as the paper's recursion does) feeds a
    feature's past information back to it through the vehicle at every step;
    on SUMO traffic this locks features and vehicles onto early GNSS errors
    (measured on the arterial TLR, first 600 s: RMSE 4.3 m against GNSS 2.2 m;
    with the own-sensor cavity and :class:`FeatureStore` 0.69 m). Passing
    ``own = prior`` gives the paper's (19) exactly.
    ``owner``/``feature``/``z``/``r`` (O, ...): the V2F rows with stable
    feature ids (-1 = row not used). ``feature_prior_lam``/``_eta`` (K, ...):
    b_k^(0) of (12) in information form for the K = unique(feature[used])
    ids in sorted order (zeros = uniform).
    Vehicles without used rows keep b^(0) exactly. The returned messages are the
    ones the feature tracks will store (``params.feature_message``).
    """
    n = prior_mean.shape[0]
    feature = np.asarray(feature, dtype=np.int64)
    used = feature >= 0
    owner_u = np.asarray(owner, dtype=np.int64)[used]
    feat_u = feature[used]
    z_u = np.asarray(z, dtype=float)[used]
    r_u = np.asarray(r, dtype=float)[used]
    o = owner_u.size
    if o == 0 or n == 0:
        return BpaResult(prior_mean.copy(), prior_cov.copy(), used, np.empty((0, 4, 4)), np.empty((0, 4)), 0, True)

    fids, fidx = np.unique(feat_u, return_inverse=True)
    if feature_prior_lam.shape != (fids.size, 4, 4) or feature_prior_eta.shape != (fids.size, 4):
        raise ValueError(f"feature priors must be given for the {fids.size} features of the used rows")
    lam_f0_row, eta_f0_row = feature_prior_lam[fidx], feature_prior_eta[fidx]

    # Row graph, Metropolis weights and |V_k ∩ C| in one numba pass (same numbers as
    # metropolis_weights(consensus_graph(...)) and row_components(...)); one graph for
    # every BPA-L iteration of this step.
    (w_indptr, w_indices, w_data), count, complete = row_consensus_weights(owner_u, fidx, fids.size, adjacency)
    n_iter_cons = int(params.consensus_iterations)
    r_inv = _inv_spd(r_u)

    v_lam0, v_eta0 = to_information(prior_mean, prior_cov)
    own_lam0, own_eta0 = to_information(own_mean, own_cov)
    loop = _bpa_iterations_kernels if BPA_KERNELS else _bpa_iterations_numpy
    v_lam, v_eta, m_vf_lam, m_vf_eta, it, converged = loop(
        prior_mean, v_lam0, v_eta0, own_lam0, own_eta0, owner_u, z_u, r_u, r_inv, lam_f0_row, eta_f0_row,
        count, complete, (w_indptr, w_indices, w_data), params,
    )

    keep_lam, keep_eta = m_vf_lam, m_vf_eta
    if params.feature_message == "own":
        # The message a track keeps: (19) on the vehicle's own-sensor belief alone (no other
        # feature in the cavity), so no vehicle's evidence reaches a track twice (IcpParams).
        keep_lam, keep_eta = relative_message(own_lam0[owner_u], own_eta0[owner_u], z_u, r_u, r_inv)
    mean, cov = from_information(v_lam, v_eta)
    alone = np.bincount(owner_u, minlength=n) == 0
    mean[alone], cov[alone] = prior_mean[alone], prior_cov[alone]
    return BpaResult(mean, cov, used, keep_lam, keep_eta, it, converged, m_vf_lam, m_vf_eta)


def step_feature_beliefs(
    store: FeatureStore, params: IcpParams, row_track: np.ndarray, res: BpaResult
) -> tuple[np.ndarray, np.ndarray] | None:
    """Eq. (20) after this step's BPA-L, for every track of ``store`` (the store after
    :meth:`FeatureStore.record` and any merge; ``row_track`` (O_used,) the rows' track ids in it).

    The store holds this step's *kept* messages (``IcpParams.feature_message``); the feature
    estimate of the step is b_k = b_k^(0) prod_i m_{i->k} with the *final* messages of BPA-L.
    Merging keeps each vehicle's latest message, so every row's kept message is in the store
    and swapping it for the final one gives (20) exactly. None when the two are the same
    (then the store's moments are the beliefs)."""
    if res.final_lam is None or res.final_lam is res.msg_lam or store.size == 0:
        return None
    lam, eta = store.information(params)
    rows = store.lookup(row_track)
    scatter_add(lam, rows, res.final_lam - res.msg_lam)
    scatter_add(eta, rows, res.final_eta - res.msg_eta)
    return from_information(symmetrize(lam), eta)
