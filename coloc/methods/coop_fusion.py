"""Consistent fusion in the cooperative methods (config ``[fusion]``; ``icp_known_da``, ``icp_da_lc``, and the
vehicles of ``icp_da_pf`` through :mod:`coloc.methods.pf_fusion`): split covariance intersection (:mod:`coloc.inference.split_ci`, where the rule and its
sources are) and the receiver error model ``[gnss_model]`` (:mod:`coloc.methods.gnss_bias`).

Per vehicle two filters run on the state [px, py, vx, vy, bx, by] (b: the receiver's Gauss-Markov bias;
without a bias model its variance is 0 and the filters are the white ones of the paper's model):

* the **own-sensor track**: GNSS and inertial only, :func:`coloc.methods.gnss_bias.bias_predict_update`
  (the ``gnss`` benchmark's filter, fault exclusion included; here as the numba kernel
  :func:`coloc.kernels.gnss6.gnss6_step`, equal to it to 1e-12); it is what the vehicle sends to
  features (19) and what converts its sensor-frame detections;
* the **cooperative belief**: the same prediction and fix (its fault exclusion by the same chi-square
  rule on its own innovation, with its own streak count), its covariance kept as a total and an
  independent part (what the vehicle's own sensors and its own V2F noise put in: the prediction noise,
  the fixes, the prior of a new vehicle), then fused with the step's feature evidence by split CI
  (:func:`coloc.inference.split_ci.split_ci_update`).

A fresh vehicle starts both from ``frame.prior_z`` / ``prior_R`` with the bias at 0 and its stationary
covariance (as :class:`coloc.methods.gnss_bias.GnssBiasTracker`), all of it independent. Reports use
the 4-D kinematic marginal. Nothing here reads the world: only the covariance the receiver reports,
the V2F rows and the ``[gnss_model]`` / ``[fusion]`` values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from coloc.core.frame import Frame
from coloc.core.models import MotionParams
from coloc.core.vehicles import fresh_rows
from coloc.inference.bpa import BpaResult
from coloc.inference.params import IcpParams
from coloc.inference.split_ci import SEARCH_ITERATIONS, feature_evidence, split_ci_update
from coloc.kernels.gnss6 import gnss6_step
from coloc.methods.gnss_bias import H, GnssModelParams, bias_transition, entry_fix_posterior

__all__ = ["FUSION_RULES", "FusionParams", "CoopFusion", "SplitState", "SplitPrior", "split_prior",
           "split_localization", "WHITE_RECEIVER"]

#: ``[fusion] rule`` values: "bp" is the paper's Gaussian BP propagation (Brambilla et al., Sec. IV), as
#: without the table (a sweep level can switch the fusion off with it).
FUSION_RULES = ("split_ci", "bp")

#: The receiver model without a bias or a gate: the white tracker of the paper's model (3).
WHITE_RECEIVER = GnssModelParams(bias_share=0.0, innovation_gate=0.0)


@dataclass(frozen=True)
class FusionParams:
    """The ``[fusion]`` table."""

    # How the cooperative methods fuse what they receive: "split_ci" (coloc.inference.split_ci), or "bp":
    # the paper's BP propagation, as without [fusion] (the other keys are then unused).
    rule: str = "split_ci"
    # Give the cooperative methods the receiver error model of [gnss_model] (a bias state and fault
    # exclusion) when the config has that table; false (or no [gnss_model]): the white receiver.
    bias_state: bool = True
    # The receivers' errors may be shared between nearby vehicles (the atmospheric, orbit and clock terms
    # of single-frequency receivers are common-mode over kilometres): then what a vehicle's fixes put in
    # its belief is of unknown correlation with the other vehicles' messages, and split CI counts it in
    # the dependent part (its prior from the receiver and the bias's driving noise too). False: the
    # paper's model (3), every receiver's error its own.
    common_mode_gnss: bool = False
    # The feature evidence as the covariance intersection (equal weights) of this step's other observers'
    # messages instead of the sum of every stored message (coloc.inference.split_ci.feature_evidence):
    # the other vehicles' messages may share their receivers' errors.
    feature_ci: bool = False

    def __post_init__(self):
        if self.rule not in FUSION_RULES:
            raise ValueError(f"must be one of {', '.join(FUSION_RULES)}, got {self.rule!r}")


@dataclass(frozen=True)
class CoopFusion:
    """What a cooperative method needs for the consistent fusion: the rule and its receiver model."""

    params: FusionParams = field(default_factory=FusionParams)
    model: GnssModelParams = WHITE_RECEIVER

    @staticmethod
    def from_config(params: FusionParams | None, gnss_model: GnssModelParams | None) -> "CoopFusion | None":
        """None without ``[fusion]``; the receiver model of ``[gnss_model]`` when ``bias_state``."""
        if params is None or params.rule == "bp":
            return None
        # the single bias of [gnss_model] (bias_share, bias_tau_s): the two-state model is gnss's only
        model = gnss_model.single_model() if (params.bias_state and gnss_model is not None) else WHITE_RECEIVER
        return CoopFusion(params, model)


@dataclass(frozen=True)
class SplitState:
    """The 6-D filters of every vehicle (rows in the method's ``ids`` order)."""

    mean: np.ndarray = field(default_factory=lambda: np.empty((0, 6)))  # cooperative belief
    cov: np.ndarray = field(default_factory=lambda: np.empty((0, 6, 6)))  # its total covariance
    ind: np.ndarray = field(default_factory=lambda: np.empty((0, 6, 6)))  # its independent part
    streak: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))  # consecutive exclusions
    own_mean: np.ndarray = field(default_factory=lambda: np.empty((0, 6)))  # own-sensor track
    own_cov: np.ndarray = field(default_factory=lambda: np.empty((0, 6, 6)))
    own_streak: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))

    def reset_to_own(self, rows: np.ndarray) -> "SplitState":
        """The cooperative belief of ``rows`` (bool) replaced by the own-sensor track (ICP-DA-LC's step 10)."""
        mean, cov, ind = self.mean.copy(), self.cov.copy(), self.ind.copy()
        mean[rows], cov[rows], ind[rows] = self.own_mean[rows], self.own_cov[rows], self.own_cov[rows]
        return SplitState(mean, cov, ind, self.streak, self.own_mean, self.own_cov, self.own_streak)


@dataclass(frozen=True)
class SplitPrior:
    """The step's priors: the cooperative b^(0) of (11) (predicted, fix applied) with its split, and
    the own-sensor track after its fix (6-D), in frame order."""

    mean: np.ndarray
    cov: np.ndarray
    ind: np.ndarray
    streak: np.ndarray
    own_mean: np.ndarray
    own_cov: np.ndarray
    own_streak: np.ndarray

    def marginal(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(b0_mean, b0_cov, own_mean, own_cov): the 4-D kinematic marginals."""
        return (self.mean[:, :4].copy(), self.cov[:, :4, :4].copy(), self.own_mean[:, :4].copy(),
                self.own_cov[:, :4, :4].copy())


def _carry(prev, match, fresh, n, shape, fill=0.0):
    out = np.full((n, *shape), fill, dtype=prev.dtype)
    keep = ~fresh
    out[keep] = prev[match[keep]]
    return out


def _split_gnss_step(mean, cov, ind, accel, z, r, predict_mask, dt, motion: MotionParams, model: GnssModelParams,
                     streak, common_mode: bool = False):
    """The cooperative belief's model (1) prediction and fix (3), with the independent part carried
    along: P' = F P F^T + Q and P_i' = F P_i F^T + Q (the driving and bias noise are the vehicle's own),
    then the fix in Joseph form on both, K from the total (the fix's noise is independent; with
    ``common_mode`` the fix's noise and the bias's driving noise go to the dependent part). The fix's
    position is excluded by :class:`GnssModelParams`'s chi-square rule on this belief's innovation
    (velocity-only update, at most ``max_exclusions`` in a row; a fresh row is never gated), as
    :func:`coloc.methods.gnss_bias.bias_predict_update` does for the own track."""
    n = mean.shape[0]
    s = model.bias_share
    r_pos = r[:, :2, :2]
    m, p, pi = mean.copy(), cov.copy(), ind.copy()
    if predict_mask.any():
        _a, f, mp, q = bias_transition(m, accel, r_pos, dt, motion, model)
        sel = predict_mask
        m[sel] = mp[sel]
        p[sel] = f @ p[sel] @ f.T + q[sel]
        q_ind = q[sel].copy()
        if common_mode:
            q_ind[:, 4:, 4:] = 0.0
        pi[sel] = f @ pi[sel] @ f.T + q_ind
    rn = r.copy()
    rn[:, :2, :2] *= 1.0 - s
    innov = z - m @ H.T
    sm = H @ p @ H.T + rn
    excluded = np.zeros(n, dtype=bool)
    if model.innovation_gate > 0:
        nu = innov[:, :2]
        nis = np.einsum("ni,ni->n", nu, np.linalg.solve(sm[:, :2, :2], nu[..., None])[..., 0])
        excluded = predict_mask & (nis > model.gate_threshold) & (streak < model.max_exclusions)
    for rows, sel in ((slice(0, 4), ~excluded), (slice(2, 4), excluded)):
        if not sel.any():
            continue
        hs = H[rows]
        rs = rn[sel][:, rows, rows]
        gain = np.swapaxes(np.linalg.solve(sm[sel][:, rows, rows], hs @ p[sel]), -1, -2)  # P H^T S^-1
        m[sel] = m[sel] + np.einsum("nij,nj->ni", gain, innov[sel][:, rows])
        ikh = np.eye(6) - gain @ hs
        noise = gain @ rs @ np.swapaxes(gain, -1, -2)
        for arr in (p, pi):
            u = ikh @ arr[sel] @ np.swapaxes(ikh, -1, -2) + (0.0 if common_mode and arr is pi else noise)
            arr[sel] = 0.5 * (u + np.swapaxes(u, -1, -2))
    return m, p, pi, excluded


def _gnss6(mean, cov, ind, accel, z, r, predict_mask, dt, motion: MotionParams, model: GnssModelParams, streak,
           common_mode: bool = False, with_ind: bool = True):
    """The numba kernel :func:`coloc.kernels.gnss6.gnss6_step`: ``with_ind`` the cooperative belief as
    :func:`_split_gnss_step`, else the own track as :func:`coloc.methods.gnss_bias.bias_predict_update`
    (equal to 1e-12; tests). Returns (mean, cov, ind, excluded)."""
    c = np.ascontiguousarray
    ind = c(ind, dtype=float) if with_ind else np.empty((0, 6, 6))
    return gnss6_step(c(mean, dtype=float), c(cov, dtype=float), ind, c(accel, dtype=float), c(z, dtype=float),
                      c(r, dtype=float), c(predict_mask, dtype=np.bool_), c(streak, dtype=np.int64), float(dt),
                      float(motion.sigma_along), float(motion.sigma_cross), float(motion.heading_min_speed),
                      float(model.bias_share), math.exp(-dt / model.bias_tau_s), float(model.gate_threshold),
                      int(model.max_exclusions), bool(common_mode), bool(with_ind), not with_ind)


def split_prior(state: SplitState | None, frame: Frame, match: np.ndarray, accel: np.ndarray, motion: MotionParams,
                model: GnssModelParams, common_mode: bool = False) -> SplitPrior:
    """Both filters carried to this frame (``match`` = ``match_ids(previous ids, frame.vehicle_ids)``),
    predicted with the input ``accel`` (frame order) and updated by the step's fix (``common_mode``:
    :attr:`FusionParams.common_mode_gnss`)."""
    state = state or SplitState()
    prior_z = np.asarray(frame.prior_z, dtype=float)
    fresh = fresh_rows(match, frame.entered, prior_z)
    r = np.asarray(frame.gnss_R, dtype=float)
    z = np.asarray(frame.gnss_z, dtype=float)
    accel = np.asarray(accel, dtype=float)
    n = len(frame.vehicle_ids)
    init_m = np.zeros((n, 6))
    init_p = np.zeros((n, 6, 6))
    if fresh.any():
        init_m[fresh, :4] = prior_z[fresh]
        init_p[fresh, :4, :4] = np.asarray(frame.prior_R, dtype=float)[fresh]
        init_p[fresh, 4:, 4:] = model.bias_share * r[fresh, :2, :2]

    def carried(prev_m, prev_p):
        m, p = _carry(prev_m, match, fresh, n, (6,)), _carry(prev_p, match, fresh, n, (6, 6))
        m[fresh], p[fresh] = init_m[fresh], init_p[fresh]
        return m, p

    keep = ~fresh
    own_m, own_p = carried(state.own_mean, state.own_cov)
    own_streak = _carry(state.own_streak, match, fresh, n, ())
    own_m, own_p, _, own_ex = _gnss6(own_m, own_p, None, accel, z, r, keep, float(frame.dt), motion, model,
                                     own_streak, with_ind=False)
    entry_fix_posterior(own_m, own_p, frame, fresh, r, model.bias_share)  # the entry protocol, as gnss_bias
    m, p = carried(state.mean, state.cov)
    pi = _carry(state.ind, match, fresh, n, (6, 6))
    # A new vehicle's prior is its own receiver's: independent (dependent with common-mode errors).
    pi[fresh] = 0.0 if common_mode else init_p[fresh]
    streak = _carry(state.streak, match, fresh, n, ())
    m, p, pi, ex = _gnss6(m, p, pi, accel, z, r, keep, float(frame.dt), motion, model, streak, common_mode)
    once = entry_fix_posterior(m, p, frame, fresh, r, model.bias_share)
    pi[once] = 0.0 if common_mode else p[once]  # the receiver's fix, once: independent unless errors are shared
    return SplitPrior(m, p, pi, np.where(ex, streak + 1, 0), own_m, own_p, np.where(own_ex, own_streak + 1, 0))


def split_localization(prior: SplitPrior, owner: np.ndarray, feature: np.ndarray, z: np.ndarray, r: np.ndarray,
                       adjacency, feature_prior_lam: np.ndarray, feature_prior_eta: np.ndarray, params: IcpParams,
                       v2x=None, feature_ci: bool = False) -> tuple[BpaResult, SplitState]:
    """The step's localization under split CI, in place of :func:`coloc.inference.bpa.bpa_localization`
    (same row arguments): the feature evidence of :func:`coloc.inference.split_ci.feature_evidence` fused
    into each observing vehicle's b^(0); vehicles without evidence keep b^(0). The result's messages are
    the own-sensor ones the tracks keep (so the step's feature beliefs are the store's moments)."""
    own_mean, own_cov = prior.own_mean[:, :4], prior.own_cov[:, :4, :4]
    msg_lam, msg_eta, y_f, p_f, r_f, has, comm = feature_evidence(
        np.ascontiguousarray(own_mean), np.ascontiguousarray(own_cov), owner, feature, z, r, adjacency,
        feature_prior_lam, feature_prior_eta, params, v2x, feature_ci)
    mean, cov, ind, _ = split_ci_update(np.ascontiguousarray(prior.mean), np.ascontiguousarray(prior.cov),
                                        np.ascontiguousarray(prior.ind), y_f, p_f, r_f, has, SEARCH_ITERATIONS)
    used = np.asarray(feature, dtype=np.int64) >= 0
    res = BpaResult(mean[:, :4].copy(), cov[:, :4, :4].copy(), used, msg_lam, msg_eta, 1, True, comm=comm)
    return res, SplitState(mean, cov, ind, prior.streak, prior.own_mean, prior.own_cov, prior.own_streak)
