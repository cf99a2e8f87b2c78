"""What vehicles sense, given true states: the measurement side of Brambilla et al. Sec. II.

Pure numpy/scipy: used by the SUMO coupler and by the controlled scenarios, so
every source of frames synthesises measurements the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.spatial import cKDTree

from coloc.core.frame import Frame, Truth
from coloc.core.models import gnss_cov
from coloc.kernels.icp import rows_by_key
from couplers.sensing.gnss_error import FieldErrorProcess, GnssErrorParams, GnssErrorProcess
from coloc.core.inertial import ImuFrame
from couplers.sensing.inertial import InertialParams
from couplers.sensing.pedestrians import FeaturesParams
from couplers.sensing.perception import Detections, PerceptionParams
from couplers.sensing.rows import shuffle_within_owner
from couplers.sensing.v2x import V2xParams


@dataclass(frozen=True)
class SensorParams:
    """On-board sensing (docs/architecture.md "Models and default parameters", arterial column unless noted)."""

    accel_sigma: float = 0.05  # m/s^2, white noise per axis on the inertial input a_{t-1}
    v2f_range_m: float = 50.0  # Rs
    v2f_sigma_p: float = 0.1  # m, model (4)
    v2f_sigma_v: float = 0.1  # m/s
    v2v_range_m: float = 250.0  # Rc
    prior_sigma_p: float = 2.0  # m, fast-start prior (Sec. VI-A)
    prior_sigma_v: float = 0.1  # m/s
    # Opt-in realism (realistic sensing and V2X), from the [perception] / [gnss_error] / [v2x] / [inertial] config
    # tables; None (the default) is the paper's idealisation, synthesised exactly as before. SUMO coupler only.
    perception: PerceptionParams | None = None
    gnss_error: GnssErrorParams | None = None
    v2x: V2xParams | None = None
    inertial: InertialParams | None = None
    # [features]: SUMO pedestrians as moving features (couplers.sensing.pedestrians).
    features: "FeaturesParams | None" = None


class SensorNoise:
    """Independent, seeded random streams, one per sensor, so that adding a
    sensor or changing one's use does not shift the others' noise."""

    STREAMS = ("prior", "accel", "gnss", "v2f", "shuffle")

    def __init__(self, seed: int):
        children = np.random.SeedSequence([int(seed), 0xC0C]).spawn(len(self.STREAMS))
        for name, child in zip(self.STREAMS, children):
            setattr(self, name, np.random.default_rng(child))


def _diag_cov(n: int, sigma_p: float, sigma_v: float) -> np.ndarray:
    return gnss_cov(np.full(n, sigma_p), np.full(n, sigma_v))


# --- the per-step rows of models (3), (4) and the prior: numba kernels and their numpy references ----------


@njit(cache=True)
def _prior_rows(entered, x_true, w, sig):
    """Fast-start prior: rows of the entering vehicles x_true + w sig (w: one (4,) draw per entering vehicle,
    in row order), R = diag(sig^2); NaN rows for the others."""
    n = x_true.shape[0]
    z = np.full((n, 4), np.nan)
    R = np.full((n, 4, 4), np.nan)
    r = 0
    for i in range(n):
        if not entered[i]:
            continue
        R[i] = 0.0
        for j in range(4):
            z[i, j] = x_true[i, j] + w[r, j] * sig[j]
            R[i, j, j] = sig[j] * sig[j]
        r += 1
    return z, R


def _prior_rows_reference(entered, x_true, w, sig):
    """:func:`_prior_rows` in numpy."""
    n = x_true.shape[0]
    z, R = np.full((n, 4), np.nan), np.full((n, 4, 4), np.nan)
    if entered.any():
        z[entered] = x_true[entered] + w * sig
        R[entered] = _diag_cov(int(entered.sum()), sig[0], sig[2])
    return z, R


@njit(cache=True)
def _gnss_rows(x_true, w, sigma_p, sigma_v):
    """Model (3): z = x + w [sp, sp, sv, sv] and R = blockdiag(sp^2 I, sv^2 I) (``gnss_cov``) per vehicle."""
    n = x_true.shape[0]
    z = np.empty((n, 4))
    R = np.zeros((n, 4, 4))
    for i in range(n):
        sp, sv = sigma_p[i], sigma_v[i]
        z[i, 0] = x_true[i, 0] + w[i, 0] * sp
        z[i, 1] = x_true[i, 1] + w[i, 1] * sp
        z[i, 2] = x_true[i, 2] + w[i, 2] * sv
        z[i, 3] = x_true[i, 3] + w[i, 3] * sv
        R[i, 0, 0] = R[i, 1, 1] = sp * sp
        R[i, 2, 2] = R[i, 3, 3] = sv * sv
    return z, R


@njit(cache=True)
def _receiver_rows(gnss_z, gnss_R, x_true, err, cov, has_cov, verr, vcov, solved, doppler):
    """The receiver's rows written into model (3)'s, in place, the assignments of :func:`_receiver_rows_reference`:
    position x + err, its 2 x 2 block the reported ``cov`` (``has_cov``); under ``doppler`` the solved rows'
    velocity x + verr and its block ``vcov``."""
    for i in range(gnss_z.shape[0]):
        gnss_z[i, 0] = x_true[i, 0] + err[i, 0]
        gnss_z[i, 1] = x_true[i, 1] + err[i, 1]
        if has_cov:
            for r in range(2):
                for c in range(2):
                    gnss_R[i, r, c] = cov[i, r, c]
        if doppler and solved[i]:
            gnss_z[i, 2] = x_true[i, 2] + verr[i, 0]
            gnss_z[i, 3] = x_true[i, 3] + verr[i, 1]
            for r in range(2):
                for c in range(2):
                    gnss_R[i, 2 + r, 2 + c] = vcov[i, r, c]


def _receiver_rows_reference(gnss_z, gnss_R, x_true, err, cov, verr, vcov, solved):
    """:func:`_receiver_rows` in numpy (``cov`` / ``verr`` None: not set)."""
    gnss_z[:, :2] = x_true[:, :2] + err
    if cov is not None:
        gnss_R[:, :2, :2] = cov
    if verr is not None:
        gnss_z[solved, 2:4] = x_true[solved, 2:4] + verr[solved]
        gnss_R[solved, 2:, 2:] = vcov[solved]


_NO_COV = np.empty((0, 2, 2))
_NO_VELOCITY = (np.empty((0, 2)), np.empty((0, 2, 2)), np.zeros(0, dtype=np.bool_))


def _gnss_rows_reference(x_true, w, sigma_p, sigma_v):
    """:func:`_gnss_rows` in numpy."""
    return x_true + w * np.stack([sigma_p, sigma_p, sigma_v, sigma_v], axis=1), gnss_cov(sigma_p, sigma_v)


@njit(cache=True)
def _v2f_rows(perm, owner, feat, features_true, x_true, w, sig):
    """Model (4) for the pairs in the order ``perm``: owner, feature, z = (x_F - x_V) + w sig, R = diag(sig^2)."""
    o = perm.size
    own = np.empty(o, dtype=np.int64)
    ft = np.empty(o, dtype=np.int64)
    z = np.empty((o, 4))
    R = np.zeros((o, 4, 4))
    for r in range(o):
        i, f = owner[perm[r]], feat[perm[r]]
        own[r], ft[r] = i, f
        for j in range(4):
            z[r, j] = (features_true[f, j] - x_true[i, j]) + w[r, j] * sig[j]
            R[r, j, j] = sig[j] * sig[j]
    return own, ft, z, R


def _v2f_rows_reference(perm, owner, feat, features_true, x_true, w, sig):
    """:func:`_v2f_rows` in numpy."""
    owner, feat = owner[perm], feat[perm]
    return owner, feat, features_true[feat] - x_true[owner] + w * sig, _diag_cov(owner.size, sig[0], sig[2])


@njit(cache=True)
def _sweep_windows(xy, order, radius):
    """Sort and sweep along x over the points sorted by ``order``: point i pairs with the sorted positions
    [lo[i], hi[i]), those after it up to the first one more than ``radius`` further in x."""
    n = xy.shape[0]
    lo = np.empty(n, dtype=np.int64)
    hi = np.empty(n, dtype=np.int64)
    b = 0
    for a in range(n):
        i = order[a]
        lo[i] = a + 1
        b = max(b, a + 1)  # the window's end only moves forward: x is sorted
        while b < n and not xy[order[b], 0] - xy[i, 0] > radius:
            b += 1
        hi[i] = b
    return lo, hi


@njit(cache=True)
def _window_pairs(vxy, fxy, order, lo, hi, r2, owner, feat):
    """Pairs (i, order[q]) for q in [lo[i], hi[i]) with squared distance <= r2, written into
    ``owner``/``feat`` when they are large enough; returns the count."""
    store = owner.shape[0] > 0
    count = 0
    for i in range(vxy.shape[0]):
        for q in range(lo[i], hi[i]):
            j = order[q]
            dx = vxy[i, 0] - fxy[j, 0]
            dy = vxy[i, 1] - fxy[j, 1]
            if dx * dx + dy * dy <= r2:
                if store:
                    owner[count] = i
                    feat[count] = j
                count += 1
    return count


@njit(cache=True)
def _radius_graph_csr(xy, radius):
    """CSR (indptr, indices) of all pairs within ``radius``, rows sorted.

    Cost O(N log N + N k), k the vehicles within ``radius`` in x (:func:`_sweep_windows`). The sweep's pairs go into their
    rows unsorted; a transpose (columns visited in increasing order) then sorts every row without
    comparisons, the adjacency being symmetric (a per-row sort cost 4x the rest)."""
    n = xy.shape[0]
    order = np.argsort(xy[:, 0])
    lo, hi = _sweep_windows(xy, order, radius)
    empty = np.empty(0, dtype=np.int64)
    m = _window_pairs(xy, xy, order, lo, hi, radius * radius, empty, empty)
    first = np.empty(m, dtype=np.int64)
    second = np.empty(m, dtype=np.int64)
    _window_pairs(xy, xy, order, lo, hi, radius * radius, first, second)
    start = np.zeros(n + 1, dtype=np.int64)
    for k in range(m):
        start[first[k] + 1] += 1
        start[second[k] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    unsorted = np.empty(2 * m, dtype=np.int64)
    fill = start[:n].copy()
    for k in range(m):
        i, j = first[k], second[k]
        unsorted[fill[i]] = j
        fill[i] += 1
        unsorted[fill[j]] = i
        fill[j] += 1
    indices = np.empty(2 * m, dtype=np.int32)
    fill[:] = start[:n]
    for j in range(n):  # row i receives its neighbours j in increasing order
        for k in range(start[j], start[j + 1]):
            i = unsorted[k]
            indices[fill[i]] = j
            fill[i] += 1
    return start.astype(np.int32), indices


def _csr_attributes(data: np.ndarray, indices: np.ndarray, indptr: np.ndarray, shape: tuple[int, int],
                    maxprint: int) -> dict:
    """The instance attributes scipy's ``csr_matrix((data, indices, indptr), shape=shape)`` sets for int32
    index arrays within range, with sorted indices (the arrays themselves where scipy keeps views of them)."""
    return dict(_shape=shape, maxprint=maxprint, indices=indices, indptr=indptr, data=data,
                _has_sorted_indices=True)


def _csr_checked(data: np.ndarray, indices: np.ndarray, indptr: np.ndarray, shape: tuple[int, int]) -> sp.csr_matrix:
    """scipy's constructor (it checks the index dtype against the contents and the format), sorted indices."""
    adj = sp.csr_matrix((data, indices, indptr), shape=shape)
    adj.has_sorted_indices = True
    return adj


def _csr_probe() -> int | None:
    """scipy's default ``maxprint`` if its constructor sets exactly :func:`_csr_attributes` (else None: the
    fast path is off and :func:`_csr_checked` builds every graph)."""
    indptr, indices = np.array([0, 1, 2], dtype=np.int32), np.array([1, 0], dtype=np.int32)
    ref = _csr_checked(np.ones(2, dtype=bool), indices, indptr, (2, 2))
    keys = set(_csr_attributes(ref.data, indices, indptr, (2, 2), ref.maxprint))
    if set(vars(ref)) != keys or not all(np.shares_memory(getattr(ref, k), v) and getattr(ref, k).dtype == v.dtype
                                         for k, v in (("indices", indices), ("indptr", indptr))):
        return None
    return ref.maxprint


_CSR_MAXPRINT = _csr_probe()
_INT32_MAX = int(np.iinfo(np.int32).max)


def neighbor_graph(xy: np.ndarray, radius: float) -> sp.csr_matrix:
    """V2V links: symmetric boolean CSR of vehicle pairs within ``radius``, empty diagonal.

    A numba sort-and-sweep writes the CSR arrays directly: scipy's KD-tree pair
    query plus COO->CSR conversion was the coupler's largest cost at ~150 vehicles. The matrix is then
    assembled from its arrays without scipy's constructor, whose checks (index dtype against the contents,
    format) cost more than the sweep at ~120 vehicles: the arrays are int32 and valid by construction, and
    the attributes are those the constructor sets (``_csr_probe``; ``tests/couplers/test_sensors.py``)."""
    n = xy.shape[0]
    if n < 2:
        return sp.csr_matrix((n, n), dtype=bool)
    indptr, indices = _radius_graph_csr(np.ascontiguousarray(xy, dtype=np.float64), float(radius))
    data = np.ones(indices.size, dtype=bool)
    if _CSR_MAXPRINT is None or n > _INT32_MAX:
        return _csr_checked(data, indices, indptr, (n, n))
    adj = sp.csr_matrix.__new__(sp.csr_matrix)
    adj.__dict__.update(_csr_attributes(data, indices, indptr, (n, n), _CSR_MAXPRINT))
    return adj


@njit(cache=True)
def _pairs_within(vxy, fxy, radius):
    """(owner, feature) pairs with squared distance <= radius^2, sorted by owner then feature.

    Features sorted by x; each vehicle scans the features of its x window (widened by a slack so
    that the window never drops a pair the distance test keeps), then two stable counting sorts
    (by feature, then by owner) order the pairs without comparisons."""
    n, k = vxy.shape[0], fxy.shape[0]
    order = np.argsort(fxy[:, 0])
    fx = fxy[order, 0]
    lo = np.empty(n, dtype=np.int64)
    hi = np.empty(n, dtype=np.int64)
    for i in range(n):
        slack = 1e-9 * (abs(vxy[i, 0]) + radius) + 1e-9
        lo[i] = np.searchsorted(fx, vxy[i, 0] - radius - slack, side="left")
        hi[i] = np.searchsorted(fx, vxy[i, 0] + radius + slack, side="right")
    empty = np.empty(0, dtype=np.int64)
    m = _window_pairs(vxy, fxy, order, lo, hi, radius * radius, empty, empty)
    owner = np.empty(m, dtype=np.int64)
    feat = np.empty(m, dtype=np.int64)
    _window_pairs(vxy, fxy, order, lo, hi, radius * radius, owner, feat)
    by_feat = rows_by_key(feat, k)[1]
    by_owner = by_feat[rows_by_key(owner[by_feat], n)[1]]
    return owner[by_owner], feat[by_owner]


def features_in_range(vehicle_xy: np.ndarray, feature_tree: cKDTree | None, radius: float):
    """All (vehicle, feature) pairs within ``radius``: (owner (O,), feature (O,)) sorted by owner, feature.

    ``feature_tree``: the features' cKDTree (its ``data``); pairs at exactly zero distance and at exactly
    ``radius`` are kept, as the tree's ``sparse_distance_matrix`` keeps them (its reference in the tests)."""
    if feature_tree is None:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    return points_in_range(vehicle_xy, feature_tree.data, radius)


def points_in_range(vehicle_xy: np.ndarray, points_xy: np.ndarray, radius: float):
    """:func:`features_in_range` of the points ``points_xy`` (K, 2) themselves (a tree's ``data``), for
    points that change every step (no tree to build)."""
    if vehicle_xy.shape[0] == 0 or len(points_xy) == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    return _pairs_within(np.ascontiguousarray(vehicle_xy, dtype=np.float64),
                         np.ascontiguousarray(points_xy, dtype=np.float64), float(radius))


def synthesize_frame(
    *,
    t: float,
    dt: float,
    vehicle_ids: np.ndarray,
    entered: np.ndarray,
    x_true: np.ndarray,
    accel_true: np.ndarray,
    heading: np.ndarray,
    gnss_sigma_p: np.ndarray,
    gnss_sigma_v: np.ndarray,
    features_true: np.ndarray,
    feature_tree: cKDTree | None,
    params: SensorParams,
    noise: SensorNoise,
    zone: np.ndarray,
    area: np.ndarray,
    feature_ids: np.ndarray | None = None,
    detections: Detections | None = None,
    gnss_error: GnssErrorProcess | FieldErrorProcess | None = None,
    prev_row: np.ndarray | None = None,
    imu: ImuFrame | None = None,
    start: str = "fast_start",
    frame_fields: dict | None = None,
    truth_fields: dict | None = None,
) -> Frame:
    """Turn true states into one frame of measurements (models (1), (3), (4)).

    ``detections`` (couplers.sensing.perception.perceive) replaces the idealised V2F rows; ``gnss_error``
    replaces the white GNSS position error by its Gauss-Markov + NLOS error, driven by the same
    standard normal draws (both None: the paper's idealisation, byte for byte as before); a process with a
    ``reported_cov`` (``model = "satellites"``) also sets the position block of ``gnss_R`` to the covariance its
    receivers report, and with ``velocity = "doppler"`` the velocity and its block come from the receivers' range
    rates (vehicles without a fix keep the zone's Doppler error). ``prev_row``: the
    row of each vehicle in the previous step's ``vehicle_ids`` (-1 if new), handed to ``gnss_error`` (None: it
    matches the ids itself). ``imu`` (``couplers.sensing.inertial.InertialProcess``): the frame carries it and
    ``accel`` is NaN (the net-frame input would carry the true heading). ``start``: "fast_start" (the paper's
    prior N(x_true, diag(sp^2, sp^2, sv^2, sv^2)) for entering vehicles) or "gnss_fix" (an entering vehicle's
    prior is its receiver's fix of this step, ``gnss_z`` and ``gnss_R``: nothing of its truth; the frame's
    ``prior_has_fix`` says so, and the estimators do not update that prior with the same fix again).
    ``frame_fields`` / ``truth_fields``: further fields of the :class:`Frame` / :class:`Truth` (or values that
    replace the ones set here), so that a caller with more of the frame builds it once instead of replacing it."""
    n = x_true.shape[0]
    entered = np.asarray(entered, dtype=bool)

    xf = np.ascontiguousarray(x_true, dtype=np.float64)  # the kernels' view of x_true (the truth keeps the input)
    # Fast-start prior for vehicles entering now: N(x_true, diag(sp^2, sp^2, sv^2, sv^2)).
    k = int(np.count_nonzero(entered))
    gnss_fix = start == "gnss_fix"
    w = noise.prior.standard_normal((k, 4)) if k and not gnss_fix else np.zeros((k, 4))
    prior_z, prior_R = _prior_rows(entered, xf, w,
                                   np.array([params.prior_sigma_p] * 2 + [params.prior_sigma_v] * 2))

    accel_w = noise.accel.standard_normal((n, 2))  # drawn with or without the IMU (the stream's contract)
    accel = np.full((n, 2), np.nan) if imu is not None else accel_true + params.accel_sigma * accel_w

    # GNSS, model (3): z = x + n, zone-dependent R.
    gnss_w = noise.gnss.standard_normal((n, 4))
    gnss_z, gnss_R = _gnss_rows(xf, gnss_w, np.asarray(gnss_sigma_p, dtype=np.float64),
                                np.asarray(gnss_sigma_v, dtype=np.float64))
    if gnss_error is not None:
        err = gnss_error.step(t, vehicle_ids, entered, gnss_w[:, :2], gnss_sigma_p, zone, x_true[:, :2], idx=prev_row)
        # "satellites": the covariance the receiver reports; with velocity = "doppler" the range-rate solution
        cov = getattr(gnss_error, "reported_cov", None)
        doppler = bool(getattr(gnss_error, "doppler", False))
        verr, vcov, solved = gnss_error.velocity_error(x_true[:, 2:4]) if doppler else _NO_VELOCITY
        _receiver_rows(gnss_z, gnss_R, xf, np.ascontiguousarray(err, dtype=np.float64),
                       _NO_COV if cov is None else np.ascontiguousarray(cov, dtype=np.float64), cov is not None,
                       verr, vcov, solved, doppler)
    oracle_gnss = gnss_error.oracle_frame() if getattr(gnss_error, "oracle_channel", False) else None
    if gnss_fix:  # the receiver's first fix, its error included, and the covariance it reports
        prior_z[entered], prior_R[entered] = gnss_z[entered], gnss_R[entered]

    if detections is not None:
        v2f_z, owner, v2f_R, feat = detections.z, detections.owner, detections.R, detections.feature
    else:
        # V2F, model (4): z = x_F - x_V + n for every feature within Rs; rows shuffled per vehicle.
        owner, feat = features_in_range(x_true[:, :2], feature_tree, params.v2f_range_m)
        perm = shuffle_within_owner(owner, noise.shuffle)
        owner, feat, v2f_z, v2f_R = _v2f_rows(
            perm, owner, feat, np.ascontiguousarray(features_true, dtype=np.float64), xf,
            noise.v2f.standard_normal((owner.size, 4)),
            np.array([params.v2f_sigma_p] * 2 + [params.v2f_sigma_v] * 2))

    truth = dict(
        x_true=x_true,
        v2f_feature=feat,
        features_true=features_true,
        zone=zone,
        area=area,
        heading=heading,
        feature_ids=feature_ids,
    )
    if truth_fields:
        truth.update(truth_fields)
    fields = dict(
        t=float(t),
        dt=float(dt),
        vehicle_ids=vehicle_ids,
        entered=entered,
        prior_z=prior_z,
        prior_R=prior_R,
        accel=accel,
        gnss_z=gnss_z,
        gnss_R=gnss_R,
        v2f_z=v2f_z,
        v2f_owner=owner,
        v2f_R=v2f_R,
        neighbors=neighbor_graph(x_true[:, :2], params.v2v_range_m),
        truth=Truth(**truth),
        imu=imu,
        prior_has_fix=entered.copy() if gnss_fix else None,
        oracle_gnss=oracle_gnss,
    )
    if frame_fields:
        fields.update(frame_fields)
    return Frame(**fields)
