"""Gaussian BPA-L, eqs. (19)-(22), with the feature product (20) by consensus.

Without a V2X channel (``v2x`` None, the paper's assumption) the consensus of (20) is Metropolis
average consensus on the row graph, every message delivered, ``consensus_iterations`` rounds in
every BPA-L iteration. With one (``frame.v2x``, docs/architecture.md "The V2X channel") it runs over
the channel (:class:`coloc.inference.row_consensus.ChannelRowConsensus`): running-sum ratio
consensus, a row of vehicle i hearing the row of vehicle j for the same feature in round r only
when the V2V link j -> i delivered in round r; rounds are counted over the whole step, across the
BPA-L iterations. **Budget rule**: an iteration gets min(``consensus_iterations``, rounds left)
rounds, and BPA-L stops after the iteration that used the last round of ``rounds_per_step`` (0 =
unlimited), with ``converged`` False unless the stopping rule of Sec. V-A held in that iteration.
The participant count |V_k ∩ C| is the size of the row's component in the *intended* row graph
(V2V neighbours within Rc observing the same feature), which the vehicles know from their beacons;
a lossy channel does not change it. Each row's ratio y/z is always a convex combination of its
component's messages, reaching their plain average as packets get through; when too few do within
the budget, count x (y/z) is the vehicles' estimate of the product in (20), weighted towards the
messages that arrived.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit

from coloc.core.models import symmetrize
from coloc.core.v2x import V2xFrame
from coloc.inference.comm import GAUSSIAN_CONSENSUS_WORDS, CommCount, broadcast_rounds
from coloc.inference.consensus import _average_kernel
from coloc.inference.feature_store import FeatureStore
from coloc.inference.gaussian import _inv_spd, from_information, psd_clip, relative_message, to_information
from coloc.inference.params import IcpParams
from coloc.inference.row_consensus import ChannelRowConsensus, row_consensus_weights
from coloc.kernels.icp import (
    complete_component_consensus,
    extrinsic_kernel,
    feature_to_vehicle_kernel,
    relative_message_kernel,
    scatter_add,
    vehicle_to_feature_kernel,
)
from coloc.kernels import icp_fused
from coloc.kernels.bpa_rows import (
    LOOP_CONVERGED,
    LOOP_NEEDS_CLIP,
    bpa_forward_rows,
    information_rows,
    bpa_loop_rows,
    feature_to_vehicle_rows,
    vehicle_to_feature_rows,
)
from coloc.kernels.icp_fused import repeated_pair, step_beliefs_kernel, unique_inverse

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
    if icp_fused.FUSED:  # one pass (coloc.kernels.icp_fused.repeated_pair)
        if repeated_pair(np.ascontiguousarray(owner, dtype=np.int64), f):
            raise ValueError("a vehicle has two V2F rows associated with the same feature")
        return f
    used = f >= 0
    if used.any():
        key = np.asarray(owner, dtype=np.int64)[used] * (int(f.max()) + 1) + f[used]
        if unique_inverse(key)[0].size != key.size:
            raise ValueError("a vehicle has two V2F rows associated with the same feature")
    return f



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
    # What the step sent (coloc.inference.comm; rounds = consensus rounds of the step); None: not counted.
    comm: CommCount | None = None


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


def row_feature_means(lam: np.ndarray, eta: np.ndarray) -> np.ndarray:
    """MMSE mean of each row's feature belief b_k in information form (O, 4); NaN where Lambda is
    not positive definite (a track still at the uniform prior has no mean)."""
    out = np.full(eta.shape, np.nan)
    if eta.shape[0] == 0:
        return out
    sign, logdet = np.linalg.slogdet(lam)
    ok = (sign > 0) & np.isfinite(logdet)
    if ok.any():
        out[ok] = np.linalg.solve(lam[ok], eta[ok][..., None])[..., 0]
    return out


class _FeatureEstimates:
    """The feature part of the Sec. V-A stopping rule (``IcpParams.stop_on = "vehicles_and_features"``):
    every row's estimate of its feature (b_k of (20) at that vehicle), kept between BPA-L iterations."""

    def __init__(self, lam0: np.ndarray, eta0: np.ndarray):
        self.mean = row_feature_means(lam0, eta0)

    def settled(self, lam: np.ndarray, eta: np.ndarray, params: IcpParams) -> bool:
        """Take this iteration's estimates; True when none moved by stop_pos_m / stop_vel_mps or more.
        An estimate undefined now or before (NaN: a track at its uniform prior) has not settled."""
        new = row_feature_means(lam, eta)
        old, self.mean = self.mean, new
        if new.shape[0] == 0:
            return True
        dpos = np.nan_to_num(np.hypot(*(new[:, :2] - old[:, :2]).T), nan=np.inf)
        dvel = np.nan_to_num(np.hypot(*(new[:, 2:] - old[:, 2:]).T), nan=np.inf)
        return bool(dpos.max() < params.stop_pos_m and dvel.max() < params.stop_vel_mps)


#: The message a track keeps (``IcpParams.feature_message = "own"``) by the numba Cholesky kernel
#: :func:`coloc.kernels.icp.relative_message_kernel` instead of the numpy reference (LAPACK inverse and
#: BLAS products): the same formula, different rounding (relative differences ~1e-13, tests); off by
#: default so that the shipped configs' estimates stay byte for byte.
OWN_MESSAGE_KERNEL = False

#: Run the BPA-L iterations with the numba kernels of :mod:`coloc.kernels.icp` (False: the
#: numpy reference below; same algorithm, results equal up to rounding, see tests).
BPA_KERNELS = True


def _bpa_iterations_numpy(
    prior_mean, v_lam0, v_eta0, own_lam0, own_eta0, owner_u, z_u, r_u, r_inv, lam_f0_row, eta_f0_row, count,
    complete, weights, params, channel=None,
):
    """BPA-L iterations (19)-(22) with batched numpy (the reference of the kernels); ``channel``: a
    :class:`ChannelRowConsensus` for (20) over the V2X channel (None: lossless Metropolis)."""
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
    features = _FeatureEstimates(lam_f0_row, eta_f0_row) if params.stop_on == "vehicles_and_features" else None
    it = 0
    for it in range(1, params.bpa_max_iterations + 1):
        # (19): cavity (own belief x messages of the other features), integrated over x_V.
        cav_lam = own_lam0[owner_u] + in_lam[owner_u] - m_fv_lam
        cav_eta = own_eta0[owner_u] + in_eta[owner_u] - m_fv_eta
        m_vf_lam, m_vf_eta = relative_message(cav_lam, cav_eta, z_u, r_u, r_inv)
        # (20): product over V_k by average consensus among the participants, times |V_k ∩ C|
        # (the 10 distinct entries of the symmetric Lambda and the 4 of eta: every entry is
        # an independent consensus, so the symmetric copies need not be run twice).
        if channel is not None:
            granted = channel.grant(n_iter_cons, params.exchanges_left(it))
            avg_lam, avg_eta = _unpack_sym(channel.average(_pack_sym(m_vf_lam, m_vf_eta), granted))
        elif n_iter_cons:
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
        # Stopping rule of Sec. V-A (all vehicles; with stop_on = "vehicles_and_features" also
        # every row's estimate of its feature, b_k of (20) at that vehicle).
        settled = features is None or features.settled(loc_lam, loc_eta, params)
        if dpos.max() < params.stop_pos_m and dvel.max() < params.stop_vel_mps and settled:
            converged = True
            break
        if channel is not None and channel.exhausted:
            break  # the step's round budget is used up (module docstring)

    return v_lam, v_eta, m_vf_lam, m_vf_eta, it, converged, None


#: Run the BPA-L iterations of the fused path in one numba call (:func:`coloc.kernels.bpa_rows.bpa_loop_rows`;
#: False: one call per iteration and step, :func:`_bpa_iterations_kernels` below). Same numbers (tests).
LOOP_KERNEL = True

#: Symmetrised extrinsic matrices (flattened, float64) that :func:`psd_clip`'s eigh left unclipped (floor 0):
#: :func:`coloc.kernels.bpa_rows.bpa_loop_rows` skips the projection of a row bit for bit equal to one
#: (eigh is a deterministic function of the bits, so the projection would leave it as it is). A
#: process-wide cache: the estimates do not depend on what it holds. On the arterial they are a
#: handful of matrices, the birth information of a track that only one vehicle observes.
_UNCLIPPED: dict[bytes, np.ndarray] = {}
_UNCLIPPED_MAX = 64
_UNCLIPPED_ROWS = [np.empty((0, 16))]


def _learn_unclipped(lam: np.ndarray, sure: np.ndarray) -> None:
    """Add the rows of ``lam`` not proven positive definite (``~sure``) whose symmetrised matrix
    numpy's eigh leaves unclipped (no eigenvalue below 0, finite) to :data:`_UNCLIPPED`."""
    if len(_UNCLIPPED) >= _UNCLIPPED_MAX:
        return
    sym = symmetrize(lam[~sure])
    ok = np.isfinite(sym).all(axis=(1, 2))
    if not ok.any():
        return
    sym = sym[ok]
    unclipped = ~(np.linalg.eigh(sym)[0] < 0.0).any(axis=1)
    for m in sym[unclipped]:
        key = m.tobytes()
        if key not in _UNCLIPPED and len(_UNCLIPPED) < _UNCLIPPED_MAX:
            _UNCLIPPED[key] = m.reshape(16).copy()
    _UNCLIPPED_ROWS[0] = np.array(list(_UNCLIPPED.values())).reshape(-1, 16)


def _bpa_loop(owner_u, own_lam0, own_eta0, v_lam0, v_eta0, z_u, r_inv, w_indptr, w_indices, w_data, n_iter_cons,
              complete, count, lam_f0_row, eta_f0_row, in_lam, in_eta, m_fv_lam, m_fv_eta, mean, params):
    """The iterations of :func:`_bpa_iterations_kernels` (lossless consensus, stopping on the vehicles)
    in :func:`coloc.kernels.bpa_rows.bpa_loop_rows`; an iteration whose extrinsic information may need
    the PSD projection is finished here, as the per-iteration loop does, and the kernel resumes."""
    it, last = 1, params.bpa_max_iterations
    stop_pos, stop_vel = float(params.stop_pos_m), float(params.stop_vel_mps)
    while True:
        (status, it, m_vf_lam, m_vf_eta, v_lam, v_eta, in_lam, in_eta, m_fv_lam, m_fv_eta, mean, cov, ext_lam, ext_eta,
         sure) = bpa_loop_rows(owner_u, own_lam0, own_eta0, v_lam0, v_eta0, z_u, r_inv, w_indptr, w_indices, w_data,
                               n_iter_cons, complete, count, lam_f0_row, eta_f0_row, in_lam, in_eta, m_fv_lam, m_fv_eta,
                               mean, it, last, stop_pos, stop_vel, _UNCLIPPED_ROWS[0])
        if status != LOOP_NEEDS_CLIP:
            # the last iteration's beliefs (22) as moments: from_information(v_lam, v_eta), the same kernel
            return v_lam, v_eta, m_vf_lam, m_vf_eta, it, status == LOOP_CONVERGED, (mean, cov)
        _learn_unclipped(ext_lam, sure)
        ext_lam, ext_eta = psd_clip(ext_lam, ext_eta, sure=sure)
        m_fv_lam, m_fv_eta, in_lam, in_eta, v_lam, v_eta, mean, dpos, dvel = feature_to_vehicle_rows(
            owner_u, np.ascontiguousarray(ext_lam), np.ascontiguousarray(ext_eta), z_u, r_inv, v_lam0, v_eta0, mean)
        if dpos < params.stop_pos_m and dvel < params.stop_vel_mps:
            return v_lam, v_eta, m_vf_lam, m_vf_eta, it, True, None
        if it == last:
            return v_lam, v_eta, m_vf_lam, m_vf_eta, it, False, None
        it += 1


def _bpa_iterations_kernels(
    prior_mean, v_lam0, v_eta0, own_lam0, own_eta0, owner_u, z_u, r_u, r_inv, lam_f0_row, eta_f0_row, count,
    complete, weights, params, channel=None,
):
    """BPA-L iterations (19)-(22): each iteration is three numba passes over the rows
    (:mod:`coloc.kernels.icp`) around the consensus kernel."""
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
    features = _FeatureEstimates(lam_f0_row, eta_f0_row) if params.stop_on == "vehicles_and_features" else None
    # the same kernels computed across rows (coloc.kernels.bpa_rows: byte for byte, SIMD)
    v_to_f, f_to_v = ((vehicle_to_feature_rows, feature_to_vehicle_rows) if icp_fused.FUSED
                      else (vehicle_to_feature_kernel, feature_to_vehicle_kernel))
    if LOOP_KERNEL and icp_fused.FUSED and channel is None and features is None:
        return _bpa_loop(owner_u, own_lam0, own_eta0, v_lam0, v_eta0, z_u, r_inv, w_indptr, w_indices, w_data,
                         n_iter_cons, complete, count, lam_f0_row, eta_f0_row, in_lam, in_eta, m_fv_lam, m_fv_eta, mean,
                         params)
    it = 0
    for it in range(1, params.bpa_max_iterations + 1):
        if channel is None and icp_fused.FUSED:  # (19)-(21) below in one call (coloc.kernels.bpa_rows)
            m_vf_lam, m_vf_eta, avg, ext_lam, ext_eta, sure = bpa_forward_rows(
                owner_u, own_lam0, own_eta0, in_lam, in_eta, m_fv_lam, m_fv_eta, z_u, r_inv, w_indptr, w_indices,
                w_data, n_iter_cons, complete, count, lam_f0_row, eta_f0_row)
            ext_lam, ext_eta = psd_clip(ext_lam, ext_eta, sure=sure)
        else:
            # (19): cavity (own belief x messages of the other features), integrated over x_V.
            m_vf_lam, m_vf_eta, packed = v_to_f(
                owner_u, own_lam0, own_eta0, in_lam, in_eta, m_fv_lam, m_fv_eta, z_u, r_inv
            )
            # (20): product over V_k by average consensus among the participants, times |V_k ∩ C|.
            # (one round on complete components, where W = J/m is a projection: see the kernel)
            if channel is None:
                avg = complete_component_consensus(w_indptr, w_indices, w_data, packed, n_iter_cons, complete)
            else:  # over the V2X channel: ratio consensus on the links that delivered, within the budget
                avg = channel.average(packed, channel.grant(n_iter_cons, params.exchanges_left(it)))
            # (21): extrinsic b_k / m_{i->k} at vehicle i (PSD-projected), then integrate over x_F.
            ext_lam, ext_eta = psd_clip(*extrinsic_kernel(avg, count, lam_f0_row, eta_f0_row, m_vf_lam, m_vf_eta))
        # (21), second half; (22): b_i = b_i^(0) prod_k m_{k->i} and the new means.
        m_fv_lam, m_fv_eta, in_lam, in_eta, v_lam, v_eta, mean, dpos, dvel = f_to_v(
            owner_u, np.ascontiguousarray(ext_lam), np.ascontiguousarray(ext_eta), z_u, r_inv, v_lam0, v_eta0, mean
        )
        # Stopping rule of Sec. V-A (as in the numpy loop; b_k = b_k^(0) + |V_k ∩ C| x average).
        settled = True
        if features is not None:
            avg_lam, avg_eta = _unpack_sym(avg)
            settled = features.settled(lam_f0_row + count[:, None, None] * avg_lam,
                                       eta_f0_row + count[:, None] * avg_eta, params)
        if dpos < params.stop_pos_m and dvel < params.stop_vel_mps and settled:
            converged = True
            break
        if channel is not None and channel.exhausted:
            break  # the step's round budget is used up (module docstring)
    return v_lam, v_eta, m_vf_lam, m_vf_eta, it, converged, None


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
    v2x: V2xFrame | None = None,
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
    ``v2x``: the frame's V2X channel (``frame.v2x``, aligned with ``adjacency`` = ``frame.neighbors``):
    (20) over lossy links within the step's round budget (module docstring); None: lossless, as
    many rounds as ``params`` asks. ``comm`` of the result counts what the consensus sent
    (:mod:`coloc.inference.comm`: every vehicle with a row that has a consensus partner broadcasts
    once per round, :data:`coloc.inference.comm.GAUSSIAN_CONSENSUS_WORDS` words per such row).
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
        return BpaResult(prior_mean.copy(), prior_cov.copy(), used, np.empty((0, 4, 4)), np.empty((0, 4)), 0, True,
                         comm=CommCount.zeros(n))

    fids, fidx = unique_inverse(feat_u)
    if feature_prior_lam.shape != (fids.size, 4, 4) or feature_prior_eta.shape != (fids.size, 4):
        raise ValueError(f"feature priors must be given for the {fids.size} features of the used rows")
    lam_f0_row, eta_f0_row = feature_prior_lam[fidx], feature_prior_eta[fidx]

    # Row graph, Metropolis weights and |V_k ∩ C| in one numba pass (same numbers as
    # metropolis_weights(consensus_graph(...)) and row_components(...)); one graph for
    # every BPA-L iteration of this step.
    (w_indptr, w_indices, w_data), count, complete = row_consensus_weights(owner_u, fidx, fids.size, adjacency)
    n_iter_cons = int(params.consensus_iterations)
    r_inv = _inv_spd(r_u)

    if icp_fused.FUSED:  # both in one call (information_rows: row by row, the same numbers)
        lam2, eta2 = information_rows(np.concatenate([prior_mean, own_mean]).astype(np.float64, copy=False),
                                      np.concatenate([prior_cov, own_cov]).astype(np.float64, copy=False))
        v_lam0, v_eta0, own_lam0, own_eta0 = lam2[:n], eta2[:n], lam2[n:], eta2[n:]
    else:
        v_lam0, v_eta0 = to_information(prior_mean, prior_cov)
        own_lam0, own_eta0 = to_information(own_mean, own_cov)
    channel = None if v2x is None else ChannelRowConsensus(owner_u, fidx, fids.size, adjacency, v2x)
    loop = _bpa_iterations_kernels if BPA_KERNELS else _bpa_iterations_numpy
    v_lam, v_eta, m_vf_lam, m_vf_eta, it, converged, moments = loop(
        prior_mean, v_lam0, v_eta0, own_lam0, own_eta0, owner_u, z_u, r_u, r_inv, lam_f0_row, eta_f0_row,
        count, complete, (w_indptr, w_indices, w_data), params, channel,
    )
    rounds = it * n_iter_cons if channel is None else channel.rounds_used
    comm = broadcast_rounds(owner_u, count >= 2, n, rounds, GAUSSIAN_CONSENSUS_WORDS)

    keep_lam, keep_eta = m_vf_lam, m_vf_eta
    if params.feature_message == "own":
        # The message a track keeps: (19) on the vehicle's own-sensor belief alone (no other
        # feature in the cavity), so no vehicle's evidence reaches a track twice (IcpParams).
        if OWN_MESSAGE_KERNEL:
            keep_lam, keep_eta = relative_message_kernel(own_lam0[owner_u], own_eta0[owner_u],
                                                         np.ascontiguousarray(z_u), 1.0, r_inv)
        else:
            keep_lam, keep_eta = relative_message(own_lam0[owner_u], own_eta0[owner_u], z_u, r_u, r_inv)
    mean, cov = from_information(v_lam, v_eta) if moments is None else moments
    alone = np.bincount(owner_u, minlength=n) == 0
    mean[alone], cov[alone] = prior_mean[alone], prior_cov[alone]
    return BpaResult(mean, cov, used, keep_lam, keep_eta, it, converged, m_vf_lam, m_vf_eta, comm)


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
    if icp_fused.FUSED:  # one numba pass, same operations (coloc.kernels.icp_fused.step_beliefs_kernel)
        return step_beliefs_kernel(lam, eta, rows, res.final_lam, res.msg_lam, res.final_eta, res.msg_eta)
    scatter_add(lam, rows, res.final_lam - res.msg_lam)
    scatter_add(eta, rows, res.final_eta - res.msg_eta)
    return from_information(symmetrize(lam), eta)
