"""Centralized joint Kalman filter over all vehicles and features (a reference, not a method).

One state vector theta_t = [x_V (4N); x_F (4K)] as in Brambilla et al. Sec. III
(Table I), with the *known* association: linear-Gaussian prediction by models
(1) (vehicles, inertial input) and (2) (features), and a joint update by every
GNSS fix (3) and every V2F row (4), z_ik = x_Fk - x_Vi + n. This is the MMSE
estimator (5) a road-side unit with all data would run when the association is
known; with static features and connected vehicles the distributed
``icp_known_da`` approaches it.

Two modes:

* ``decorrelate=False`` (default): the exact joint KF; vehicle-feature and
  vehicle-vehicle cross-covariances are carried from step to step.
* ``decorrelate=True``: after each update the cross-covariance blocks are
  zeroed, so the next prior is the product of the marginal beliefs -- exactly
  the prior BPA-L uses in (11)-(12). Gaussian BP gives the exact marginal means
  of that one-step joint at convergence, so this is the reference against
  which ``icp_known_da`` must agree to numerical precision (with exhaustive
  consensus); the gap to the exact joint KF measures what the BP time
  recursion loses by not carrying correlations.

The update is in information form so that a feature seen for the first time
can enter with zero information (uniform prior, as in ``icp_known_da``);
prediction is in covariance form. Cost O((4(N+K))^3) per step: a reference
for tests and small scenarios.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from coloc.core.frame import Frame, StepEstimate
from coloc.core.models import driving_noise_cov, input_matrix, symmetrize, transition_matrix
from coloc.core.vehicles import entry_fix_rows, match_ids
from coloc.inference.bpa import validate_association
from coloc.inference.feature_store import feature_track_q
from coloc.inference.params import IcpParams

__all__ = ["JointState", "centralized_step", "one_step_joint", "CentralizedKF"]


@dataclass(frozen=True)
class JointState:
    """Joint Gaussian: vehicles (frame order) then features (sorted ids)."""

    vehicle_ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=object))
    feature_ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    feature_last_seen: np.ndarray = field(default_factory=lambda: np.empty(0))
    mean: np.ndarray = field(default_factory=lambda: np.empty(0))
    cov: np.ndarray = field(default_factory=lambda: np.empty((0, 0)))

    @property
    def n_vehicles(self) -> int:
        return int(self.vehicle_ids.shape[0])


def _blocks(idx: np.ndarray) -> np.ndarray:
    """State indices of 4-blocks ``idx``."""
    return (4 * np.asarray(idx, dtype=np.int64)[:, None] + np.arange(4)).ravel()


def _block_diag_add(p: np.ndarray, blocks: np.ndarray, offset: int = 0) -> None:
    """p[block b, block b] += blocks[b] for consecutive 4-blocks starting at block ``offset``."""
    m = blocks.shape[0]
    if m == 0:
        return
    pv = p.reshape(p.shape[0] // 4, 4, p.shape[1] // 4, 4)
    b = np.arange(offset, offset + m)
    pv[b, :, b, :] += blocks


def centralized_step(
    state: JointState, frame: Frame, v2f_feature: np.ndarray, params: IcpParams, decorrelate: bool = False
) -> JointState:
    """One predict + joint update step of the centralized KF."""
    assoc = validate_association(frame.v2f_owner, v2f_feature, frame.v2f_z.shape[0])
    dt = frame.dt
    n_prev = state.n_vehicles
    k_prev = state.feature_ids.size

    # --- survivors: marginalize departed / re-entered vehicles, predict by (1) and (2).
    idx = match_ids(state.vehicle_ids, frame.vehicle_ids)
    fresh = (idx < 0) | np.asarray(frame.entered, dtype=bool)
    surv_cur = np.flatnonzero(~fresh)
    surv_prev = idx[surv_cur]
    keep_blocks = np.concatenate([surv_prev, n_prev + np.arange(k_prev)])
    si = _blocks(keep_blocks)
    x = state.mean[si]
    p = state.cov[np.ix_(si, si)]
    ns = surv_cur.size
    if keep_blocks.size:
        a = transition_matrix(dt)
        xb = x.reshape(-1, 4) @ a.T
        xb[:ns] += frame.accel[surv_cur] @ input_matrix(dt).T
        m = keep_blocks.size
        pv = p.reshape(m, 4, m, 4)
        p = np.einsum("ij,ajbk,lk->aibl", a, pv, a).reshape(4 * m, 4 * m)
        # Q of model (1) oriented by the previous posterior velocity, as in the GNSS tracker.
        q_v = driving_noise_cov(x.reshape(-1, 4)[:ns, 2:], dt, params.motion)
        q_f = feature_track_q(x.reshape(-1, 4)[ns:], dt, params)
        _block_diag_add(p, q_v, 0)
        _block_diag_add(p, q_f, ns)
        x = xb.ravel()
        p = symmetrize(p)

    # --- layout of the updated state: current vehicles (frame order), old features, new features.
    n = frame.n_vehicles
    used = assoc >= 0
    seen_ids = np.unique(assoc[used])
    new_ids = np.setdiff1d(seen_ids, state.feature_ids)
    feature_ids = np.concatenate([state.feature_ids, new_ids])
    k = feature_ids.size
    d = 4 * (n + k)
    lam = np.zeros((d, d))
    eta = np.zeros(d)
    # Prior information: survivors + old features jointly, fresh vehicles from their prior,
    # new features uniform (zero information).
    pos_keep = np.concatenate([surv_cur, n + np.arange(k_prev)])
    if pos_keep.size:
        li = symmetrize(np.linalg.inv(p))
        ki = _blocks(pos_keep)
        lam[np.ix_(ki, ki)] = li
        eta[ki] = li @ x
    fr = np.flatnonzero(fresh)
    if fr.size:
        lp = symmetrize(np.linalg.inv(frame.prior_R[fr]))
        lv = lam.reshape(n + k, 4, n + k, 4)
        lv[fr, :, fr, :] += lp
        eta.reshape(-1, 4)[fr] += np.einsum("nij,nj->ni", lp, frame.prior_z[fr])

    # GNSS (3): H = I on each vehicle block (not on a fresh vehicle whose prior is this step's fix:
    # coloc.core.vehicles.entry_fix_rows, the entry protocol).
    if n:
        rg = symmetrize(np.linalg.inv(frame.gnss_R))
        once = entry_fix_rows(frame, fresh)
        if once.any():
            rg[once] = 0.0
        _block_diag_add(lam, rg, 0)
        eta[: 4 * n] += np.einsum("nij,nj->ni", rg, frame.gnss_z).ravel()

    # V2F (4): z = x_F - x_V + n, H = [-I (vehicle), +I (feature)].
    _add_v2f_information(lam, eta, n, feature_ids, frame.v2f_owner, assoc, frame.v2f_z, frame.v2f_R)

    lam = symmetrize(lam)
    cov = symmetrize(np.linalg.inv(lam)) if d else np.zeros((0, 0))
    mean = cov @ eta if d else np.zeros(0)

    last_seen = np.concatenate([state.feature_last_seen, np.full(new_ids.size, float(frame.t))])
    last_seen[_positions(feature_ids, seen_ids)] = float(frame.t)

    # Drop features no vehicle observed for too long (marginalize), then sort features by id.
    keep_f = np.flatnonzero((frame.t - last_seen) <= params.feature_drop_after_s)
    keep_f = keep_f[np.argsort(feature_ids[keep_f], kind="stable")]
    sel = _blocks(np.concatenate([np.arange(n), n + keep_f]))
    mean = mean[sel]
    cov = cov[np.ix_(sel, sel)]
    if decorrelate and cov.size:
        m = cov.shape[0] // 4
        cv = cov.reshape(m, 4, m, 4)
        diag = cv[np.arange(m), :, np.arange(m), :].copy()
        cov = np.zeros_like(cov)
        _block_diag_add(cov, diag, 0)
    return JointState(
        vehicle_ids=np.asarray(frame.vehicle_ids),
        feature_ids=feature_ids[keep_f],
        feature_last_seen=last_seen[keep_f],
        mean=mean,
        cov=cov,
    )


def _add_v2f_information(lam, eta, n, feature_ids, owner, assoc, z, r) -> None:
    """Add H^T R^-1 H and H^T R^-1 z of every used V2F row (model (4)) in place."""
    used = assoc >= 0
    if not used.any():
        return
    m = lam.shape[0] // 4
    own = np.asarray(owner, dtype=np.int64)[used]
    fpos = n + _positions(feature_ids, assoc[used])
    rv = symmetrize(np.linalg.inv(r[used]))
    zr = np.einsum("nij,nj->ni", rv, z[used])
    lv = lam.reshape(m, 4, m, 4)
    np.add.at(lv, (own, slice(None), own, slice(None)), rv)
    np.add.at(lv, (fpos, slice(None), fpos, slice(None)), rv)
    np.add.at(lv, (own, slice(None), fpos, slice(None)), -rv)
    np.add.at(lv, (fpos, slice(None), own, slice(None)), -rv)
    ev = eta.reshape(m, 4)
    np.add.at(ev, own, -zr)
    np.add.at(ev, fpos, zr)


def one_step_joint(
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    feature_prior_lam: np.ndarray,
    feature_prior_eta: np.ndarray,
    owner: np.ndarray,
    assoc: np.ndarray,
    z: np.ndarray,
    r: np.ndarray,
):
    """Exact marginals of b^(0)_V x b^(0)_F x prod of V2F likelihoods (one time step).

    The product prior is the one BPA-L starts from in (11)-(12) (independent
    vehicle and feature beliefs; ``feature_prior_*`` in information form for the
    sorted unique ids of the used rows, zeros = uniform), so
    converged Gaussian BP with exact consensus must reproduce these means.
    Returns (vehicle mean (N,4), vehicle cov (N,4,4), feature ids (K,), feature
    mean (K,4), feature cov (K,4,4)) for the features observed in the step.
    """
    assoc = np.asarray(assoc, dtype=np.int64)
    n = prior_mean.shape[0]
    fids = np.unique(assoc[assoc >= 0])
    k = fids.size
    m = n + k
    lam = np.zeros((4 * m, 4 * m))
    eta = np.zeros(4 * m)
    lv0 = symmetrize(np.linalg.inv(prior_cov))
    _block_diag_add(lam, lv0, 0)
    eta[: 4 * n] = np.einsum("nij,nj->ni", lv0, prior_mean).ravel()
    _block_diag_add(lam, feature_prior_lam, n)
    eta[4 * n :] = feature_prior_eta.ravel()
    _add_v2f_information(lam, eta, n, fids, owner, assoc, z, r)
    cov = symmetrize(np.linalg.inv(symmetrize(lam)))
    mean = (cov @ eta).reshape(m, 4)
    cv = cov.reshape(m, 4, m, 4)
    blocks = cv[np.arange(m), :, np.arange(m), :]
    return mean[:n], blocks[:n], fids, mean[n:], blocks[n:]


def _positions(sorted_or_not: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Position of each id in ``sorted_or_not`` (all ids must be present)."""
    order = np.argsort(sorted_or_not, kind="stable")
    pos = order[np.searchsorted(sorted_or_not[order], ids)]
    return pos


@dataclass
class CentralizedKF:
    """Stateful wrapper around :func:`centralized_step` (reference; needs the association)."""

    params: IcpParams = field(default_factory=IcpParams)
    decorrelate: bool = False
    name: str = "centralized_kf"
    state: JointState = field(default_factory=JointState)

    def step(self, frame: Frame) -> StepEstimate:
        raise TypeError("the centralized reference needs the association: call step_with_association(frame, v2f_feature)")

    def step_with_association(self, frame: Frame, v2f_feature: np.ndarray) -> StepEstimate:
        self.state = centralized_step(self.state, frame, v2f_feature, self.params, self.decorrelate)
        s = self.state
        n, k = s.n_vehicles, s.feature_ids.size
        m = n + k
        cv = s.cov.reshape(m, 4, m, 4)
        blocks = cv[np.arange(m), :, np.arange(m), :]
        means = s.mean.reshape(m, 4)
        return StepEstimate(
            mean=means[:n].copy(),
            cov=blocks[:n].copy(),
            feature_mean=means[n:].copy(),
            feature_cov=blocks[n:].copy(),
            feature_track_ids=s.feature_ids.copy(),
            v2f_assignment=np.asarray(v2f_feature, dtype=np.int64).copy(),
        )
