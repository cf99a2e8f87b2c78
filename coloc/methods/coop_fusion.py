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
the 4-D kinematic marginal.

The two-state receiver model (``[gnss_model] bias_model = "two_state"``, :mod:`coloc.methods.gnss_bias2`): both
filters on the 8-D state [p, v, c, l] (c the common-mode bias, l the local one; numba kernel
:func:`coloc.kernels.gnss8.gnss8_step`, equal to the numpy references to 1e-12). The common-mode bias is, by the
model's own assumption, shared by the receivers around: the other vehicles' own-sensor messages carry the same
c, so the features they place, and the evidence their messages give this vehicle, are in the frame shifted by
c. The rule: **the feature evidence observes the kinematics in the common-mode frame**, [p + c, v], and **c is a
consider state of the fusion** (zero gain rows): the evidence cannot move c's estimate nor shrink its
variance; it refines p + c, and p only as far as c allows (with perfect evidence, Var(p) -> Var(c)). Since
nothing of the evidence is then correlated with c, what c puts in a belief is in the independent part (its
prior, its driving noise, and the part of the one-fix entry posterior it drives: s_c R on p and c, -s_c R
between them), so the fusion's covariance intersection never inflates c either: under ``common_update =
"consider"`` the cooperative belief's common-mode covariance is the own track's, the consider bound, at
every step (tests). With ``common_mode_gnss`` the local bias's driving noise and the fix's noise go to the
dependent part, as the 6-state bias and fix do. What is sent to the features is the own track's position
marginal (its covariance holds Var(c): conservative for the common-mode frame), or with
``common_frame_messages`` its marginal in the common-mode frame, [p + c, v]: the features are then placed in
the frame their evidence is taken in, as precise as the vehicles' own errors apart from c allow, and the
cooperation refines p + c by what the receivers do not share (multipath, NLOS, noise) while Var(p) stays at or
above Var(c). ``bias_follows_report`` maps
both biases of both filters as :func:`coloc.methods.gnss_bias2.two_state_predict_update` does (the 6-state
filters do not apply it). Nothing here reads the world: only the covariance the receiver reports,
the V2F rows and the ``[gnss_model]`` / ``[fusion]`` values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from coloc.core.frame import Frame
from coloc.core.models import MotionParams
from coloc.core.vehicles import fresh_rows
from coloc.inference.bpa import BpaResult
from coloc.inference.params import IcpParams
from coloc.inference.split_ci import SEARCH_ITERATIONS, feature_evidence, split_ci_update
from coloc.kernels.gnss6 import gnss6_step
from coloc.kernels.gnss8 import gnss8_step
from coloc.methods.gnss_bias import H, GnssModelParams, bias_transition, entry_fix_posterior, report_map
from coloc.methods.gnss_bias2 import (H8, common_cov, gate_nis, mapped_two_state_transition,
                                      two_state_entry_posterior, two_state_start, velocity_deweight)
from coloc.methods.report_calibration import gate_noise_scale

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
    # Two-state model: what a vehicle sends to the features (and what ICP-DA-LC's tracks keep) is its own track
    # in the common-mode frame, [p + c, v] with that covariance, the frame in which the feature evidence is
    # taken (module docstring). False: the position marginal [p, v], whose covariance holds Var(c), so that
    # every feature is at least as uncertain as the common-mode error the features cannot see.
    common_frame_messages: bool = False
    # The cooperative belief's own fault exclusion of the receiver's fix, where it differs from the own-sensor
    # track's ([gnss_model] innovation_gate and max_exclusions, which the own track and the `gnss` benchmark
    # keep): the belief is predicted from a step that had the landmarks' evidence, so a run of reflected fixes
    # can be excluded for longer than a receiver alone may without losing the road (after max_exclusions the
    # own track takes the next fix, its only way back). -1: [gnss_model]'s value.
    belief_innovation_gate: float = -1.0
    belief_max_exclusions: int = -1
    # With common_frame_messages the features are placed in the common-mode frame, which moves as the
    # common-mode bias does. True: the part of every track's belief that came from vehicles no longer observing
    # it (the folded messages of (12)) drifts with it, by the bias's Gauss-Markov driving noise
    # common_sigma_m^2 (1 - exp(-2 dt / common_tau_s)) per axis and step ([gnss_model]), so a map kept over
    # the run follows the frame the vehicles see now. False: model (2) alone (the map keeps the frame of the
    # minutes it was built in).
    map_drift: bool = False

    def __post_init__(self):
        if self.rule not in FUSION_RULES:
            raise ValueError(f"must be one of {', '.join(FUSION_RULES)}, got {self.rule!r}")
        g = self.belief_innovation_gate
        if not (isinstance(g, (int, float)) and not isinstance(g, bool) and (g == -1 or 0.0 <= g < 1.0)):
            raise ValueError(f"must be in [0, 1) (the chi-square gate's level; 0: no exclusion) or -1 "
                             f"([gnss_model]'s), got {g!r}")
        k = self.belief_max_exclusions
        if not (isinstance(k, int) and not isinstance(k, bool) and k >= -1):
            raise ValueError(f"must be a non-negative integer (consecutive excluded fixes) or -1 ([gnss_model]'s), "
                             f"got {k!r}")


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
        model = gnss_model if (params.bias_state and gnss_model is not None) else WHITE_RECEIVER
        return CoopFusion(params, model)

    def map_drift(self, dt: float) -> float:
        """The folded map's position noise of a step (m^2 per axis; :attr:`FusionParams.map_drift`): the
        common-mode bias's driving noise of the two-state model, sigma_c^2 (1 - exp(-2 dt / tau_c)) with sigma_c =
        ``common_sigma_m``, tau_c = ``common_tau_s`` (its report-scaled share has no fixed size and is left
        out). 0 when the key is off, the messages are not in the common-mode frame, or the model has no
        common-mode size."""
        p = self.params
        if not (p.map_drift and p.common_frame_messages) or self.model.bias_model != "two_state":
            return 0.0
        return self.model.common_sigma_m ** 2 * -math.expm1(-2.0 * dt / self.model.common_tau_s)

    @property
    def belief_model(self) -> GnssModelParams:
        """The receiver model of the cooperative belief's fix: ``model`` with ``[fusion]``'s belief gate and
        exclusion run where they are set (the model itself where neither is)."""
        p, changes = self.params, {}
        if p.belief_innovation_gate != -1:
            changes["innovation_gate"] = float(p.belief_innovation_gate)
        if p.belief_max_exclusions != -1:
            changes["max_exclusions"] = int(p.belief_max_exclusions)
        return replace(self.model, **changes) if changes else self.model


@dataclass(frozen=True)
class SplitState:
    """The 6-D (two-state model: 8-D) filters of every vehicle (rows in the method's ``ids`` order)."""

    mean: np.ndarray = field(default_factory=lambda: np.empty((0, 6)))  # cooperative belief
    cov: np.ndarray = field(default_factory=lambda: np.empty((0, 6, 6)))  # its total covariance
    ind: np.ndarray = field(default_factory=lambda: np.empty((0, 6, 6)))  # its independent part
    streak: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))  # consecutive exclusions
    own_mean: np.ndarray = field(default_factory=lambda: np.empty((0, 6)))  # own-sensor track
    own_cov: np.ndarray = field(default_factory=lambda: np.empty((0, 6, 6)))
    own_streak: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    # each row's reported position covariance of its last step (two-state model with bias_follows_report)
    rpos: np.ndarray | None = None

    @staticmethod
    def empty(d: int) -> "SplitState":
        """No vehicle, states of dimension ``d``."""
        e, ee = np.empty((0, d)), np.empty((0, d, d))
        z = np.empty(0, dtype=np.int64)
        return SplitState(e, ee, ee, z, e, ee, z, np.empty((0, 2, 2)))

    def reset_to_own(self, rows: np.ndarray) -> "SplitState":
        """The cooperative belief of ``rows`` (bool) replaced by the own-sensor track (ICP-DA-LC's step 10)."""
        mean, cov, ind = self.mean.copy(), self.cov.copy(), self.ind.copy()
        mean[rows], cov[rows], ind[rows] = self.own_mean[rows], self.own_cov[rows], self.own_cov[rows]
        return SplitState(mean, cov, ind, self.streak, self.own_mean, self.own_cov, self.own_streak, self.rpos)


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
    rpos: np.ndarray | None = None  # this step's reported position covariances (SplitState.rpos)
    common_frame_messages: bool = False  # FusionParams.common_frame_messages

    def marginal(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(b0_mean, b0_cov, own_mean, own_cov): the 4-D kinematic marginals, the own track's as
        :meth:`own_marginal`."""
        return (self.mean[:, :4].copy(), self.cov[:, :4, :4].copy(), *self.own_marginal())

    def own_marginal(self) -> tuple[np.ndarray, np.ndarray]:
        """The own track's 4-D marginal: [p, v], or with ``common_frame_messages`` and 8-D states the
        common-mode frame's [p + c, v] (mean T x, covariance T P T^T of :func:`common_frame`)."""
        if self.common_frame_messages and self.own_mean.shape[1] == 8:
            t, _ = common_frame(8)
            return (self.own_mean @ t.T)[:, :4], (t @ self.own_cov @ t.T)[:, :4, :4]
        return self.own_mean[:, :4].copy(), self.own_cov[:, :4, :4].copy()


def _carry(prev, match, fresh, n, shape, fill=0.0):
    out = np.full((n, *shape), fill, dtype=prev.dtype)
    keep = ~fresh
    out[keep] = prev[match[keep]]
    return out


def _split_gnss_step(mean, cov, ind, accel, z, r, predict_mask, dt, motion: MotionParams, model: GnssModelParams,
                     streak, common_mode: bool = False, r_prev=None):
    """The cooperative belief's model (1) prediction and fix (3), with the independent part carried
    along: P' = F P F^T + Q and P_i' = F P_i F^T + Q (the driving and bias noise are the vehicle's own),
    then the fix in Joseph form on both, K from the total (the fix's noise is independent; with
    ``common_mode`` the fix's noise and the bias's driving noise go to the dependent part). The fix's
    position is excluded by :class:`GnssModelParams`'s chi-square rule on this belief's innovation
    (velocity-only update, at most ``max_exclusions`` in a row; a fresh row is never gated), as
    :func:`coloc.methods.gnss_bias.bias_predict_update` does for the own track. The two-state model (8-D
    states): as :func:`coloc.methods.gnss_bias2.two_state_predict_update` (consider: zero common-mode gain
    rows; ``r_prev``: the biases mapped to this step's report, ``bias_follows_report``), the common-mode bias's
    driving noise always independent (module docstring), with ``common_mode`` the local bias's and the fix's
    noise dependent."""
    n = mean.shape[0]
    r_pos = r[:, :2, :2]
    m, p, pi = mean.copy(), cov.copy(), ind.copy()
    fixed = None
    if model.two_state:
        h, white = H8, 1.0 - model.common_share - model.local_share
        fixed = slice(4, 6) if model.common_update == "consider" else None
        if predict_mask.any():
            f, mp, q = mapped_two_state_transition(m, accel, r_pos, r_prev, dt, motion, model)
            sel = predict_mask
            ft = np.swapaxes(f[sel], -1, -2)
            m[sel] = mp[sel]
            p[sel] = f[sel] @ p[sel] @ ft + q[sel]
            q_ind = q[sel].copy()
            if common_mode:
                q_ind[:, 6:, 6:] = 0.0
            pi[sel] = f[sel] @ pi[sel] @ ft + q_ind
    else:
        h, white = H, 1.0 - model.bias_share
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
    rn[:, :2, :2] *= white
    innov = z - m @ h.T
    sm = h @ p @ h.T + rn
    velocity_deweight(innov, sm, rn, predict_mask, model)
    excluded = np.zeros(n, dtype=bool)
    if model.innovation_gate > 0:
        nis = gate_nis(innov, sm, rn, r, model)
        excluded = predict_mask & (nis > model.gate_threshold) & (streak < model.max_exclusions)
    for rows, sel in ((slice(0, 4), ~excluded), (slice(2, 4), excluded)):
        if not sel.any():
            continue
        hs = h[rows]
        rs = rn[sel][:, rows, rows]
        gain = np.swapaxes(np.linalg.solve(sm[sel][:, rows, rows], hs @ p[sel]), -1, -2)  # P H^T S^-1
        if fixed is not None:
            gain[:, fixed, :] = 0.0
        m[sel] = m[sel] + np.einsum("nij,nj->ni", gain, innov[sel][:, rows])
        ikh = np.eye(h.shape[1]) - gain @ hs
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
                      int(model.max_exclusions), bool(common_mode), bool(with_ind), not with_ind,
                      float(model.velocity_gate_threshold), gate_noise_scale(r, model),
                      model.velocity_inflation == "innovation")


def _gnss8(mean, cov, ind, accel, z, r, predict_mask, dt, motion: MotionParams, model: GnssModelParams, streak,
           common_mode: bool = False, with_ind: bool = True, r_prev=None):
    """The numba kernel :func:`coloc.kernels.gnss8.gnss8_step` of the two-state model: ``with_ind`` the
    cooperative belief as :func:`_split_gnss_step`, else the own track as
    :func:`coloc.methods.gnss_bias2.two_state_predict_update` (equal to 1e-12; tests; ``r_prev`` as there).
    Returns (mean, cov, ind, excluded)."""
    c = np.ascontiguousarray
    ind = c(ind, dtype=float) if with_ind else np.empty((0, 8, 8))
    mapped = bool(model.bias_follows_report and r_prev is not None)
    r = np.asarray(r, dtype=float)
    tmap = report_map(np.asarray(r_prev, dtype=float), r[:, :2, :2]) if mapped else np.empty((0, 2, 2))
    return gnss8_step(c(mean, dtype=float), c(cov, dtype=float), ind, c(accel, dtype=float), c(z, dtype=float),
                      c(r, dtype=float), c(predict_mask, dtype=np.bool_), c(streak, dtype=np.int64), float(dt),
                      float(motion.sigma_along), float(motion.sigma_cross), float(motion.heading_min_speed),
                      float(model.common_share), float(model.local_share), math.exp(-dt / model.common_tau_s),
                      float(model.local_tau_s), float(model.local_length_m), model.common_update == "consider",
                      float(model.gate_threshold), int(model.max_exclusions), bool(common_mode), bool(with_ind),
                      not with_ind, c(tmap), mapped, float(model.common_sigma_m) ** 2,
                      float(model.velocity_gate_threshold), gate_noise_scale(r, model),
                      model.velocity_inflation == "innovation")


def common_frame(d: int) -> tuple[np.ndarray, np.ndarray]:
    """(T, T^-1) for 8-D states: y = T x = [p + c, v, c, l], the kinematics in the common-mode frame
    (module docstring); identities for ``d`` = 6."""
    t = np.eye(d)
    if d == 8:
        t[0, 4] = t[1, 5] = 1.0
    ti = 2.0 * np.eye(d) - t
    return t, ti


def _common_part(r_pos: np.ndarray, model: GnssModelParams) -> np.ndarray:
    """(K, 8, 8): the covariance of the common-mode-driven error of the one-fix posterior (p = z: e_p = c + ...,
    e_c = -c): C = s_c R (+ ``common_sigma_m``^2 I) on the position and on c, -C between them."""
    k = r_pos.shape[0]
    out = np.zeros((k, 8, 8))
    b = common_cov(r_pos, model)
    out[:, :2, :2] = out[:, 4:6, 4:6] = b
    out[:, :2, 4:6] = out[:, 4:6, :2] = -b
    return out


def split_prior(state: SplitState | None, frame: Frame, match: np.ndarray, accel: np.ndarray, motion: MotionParams,
                model: GnssModelParams, common_mode: bool = False, common_frame_messages: bool = False,
                belief_model: GnssModelParams | None = None) -> SplitPrior:
    """Both filters carried to this frame (``match`` = ``match_ids(previous ids, frame.vehicle_ids)``),
    predicted with the input ``accel`` (frame order) and updated by the step's fix (``common_mode``:
    :attr:`FusionParams.common_mode_gnss`; ``common_frame_messages``: :attr:`FusionParams.common_frame_messages`).
    The two-state model: 8-D filters (module docstring). ``belief_model`` (:attr:`CoopFusion.belief_model`):
    the cooperative belief's fault exclusion where it differs from ``model``'s; None: ``model``."""
    d = model.state_dim
    two = model.two_state
    state = state if state is not None else SplitState.empty(d)
    prior_z = np.asarray(frame.prior_z, dtype=float)
    fresh = fresh_rows(match, frame.entered, prior_z)
    r = np.asarray(frame.gnss_R, dtype=float)
    z = np.asarray(frame.gnss_z, dtype=float)
    accel = np.asarray(accel, dtype=float)
    n = len(frame.vehicle_ids)
    init_m = np.zeros((n, d))
    init_p = np.zeros((n, d, d))
    if fresh.any():
        init_m[fresh, :4] = prior_z[fresh]
        init_p[fresh, :4, :4] = np.asarray(frame.prior_R, dtype=float)[fresh]
        if two:
            two_state_start(init_p, fresh, r[:, :2, :2], model)
        else:
            init_p[fresh, 4:, 4:] = model.bias_share * r[fresh, :2, :2]
    r_prev = None
    if two and model.bias_follows_report:
        # the report of each row's previous step; a fresh row's is this one's (no map)
        r_prev = r[:, :2, :2].copy()
        if state.rpos is not None and len(state.rpos) == len(state.mean):
            r_prev[~fresh] = state.rpos[match[~fresh]]

    def step(*args, **kw):
        return _gnss8(*args, **kw, r_prev=r_prev) if two else _gnss6(*args, **kw)

    def entry(mean, cov):
        if two:
            return two_state_entry_posterior(mean, cov, frame, fresh, r, model)
        return entry_fix_posterior(mean, cov, frame, fresh, r, model.bias_share)

    def carried(prev_m, prev_p):
        m, p = _carry(prev_m, match, fresh, n, (d,)), _carry(prev_p, match, fresh, n, (d, d))
        m[fresh], p[fresh] = init_m[fresh], init_p[fresh]
        return m, p

    keep = ~fresh
    own_m, own_p = carried(state.own_mean, state.own_cov)
    own_streak = _carry(state.own_streak, match, fresh, n, ())
    own_m, own_p, _, own_ex = step(own_m, own_p, None, accel, z, r, keep, float(frame.dt), motion, model,
                                   own_streak, with_ind=False)
    entry(own_m, own_p)  # the entry protocol, as gnss_bias
    m, p = carried(state.mean, state.cov)
    pi = _carry(state.ind, match, fresh, n, (d, d))
    # A new vehicle's prior is its own receiver's: independent (dependent with common-mode errors; the
    # two-state model's common-mode bias stays independent: module docstring).
    if common_mode:
        pi[fresh] = 0.0
        if two:
            pi[fresh, 4:6, 4:6] = init_p[fresh, 4:6, 4:6]
    else:
        pi[fresh] = init_p[fresh]
    streak = _carry(state.streak, match, fresh, n, ())
    m, p, pi, ex = step(m, p, pi, accel, z, r, keep, float(frame.dt), motion,
                        model if belief_model is None else belief_model, streak, common_mode)
    once = entry(m, p)
    # the receiver's fix, once: independent unless errors are shared (then only its common-mode-driven part)
    if common_mode:
        pi[once] = _common_part(r[once, :2, :2], model) if two else 0.0
    else:
        pi[once] = p[once]
    return SplitPrior(m, p, pi, np.where(ex, streak + 1, 0), own_m, own_p, np.where(own_ex, own_streak + 1, 0),
                      r[:, :2, :2].copy() if r_prev is not None else None, common_frame_messages)


def fuse_evidence(mean, cov, ind, y_f, p_f, r_f, has):
    """Split CI of the beliefs (mean (n, d), total ``cov``, independent part ``ind``) with the step's feature
    evidence (:func:`coloc.inference.split_ci.combine_messages`), where ``has``. 6-D states:
    :func:`coloc.inference.split_ci.split_ci_update` as it is. 8-D (two-state model): the evidence observes
    the kinematics in the common-mode frame, y = T x = [p + c, v, c, l], and the common-mode bias is a
    consider state of the fusion (its gain rows zero): its estimate and its variance leave the fusion as they
    came (module docstring). Returns (mean, cov, ind)."""
    c = np.ascontiguousarray
    if mean.shape[1] != 8:
        out = split_ci_update(c(mean), c(cov), c(ind), y_f, p_f, r_f, has, SEARCH_ITERATIONS)
        return out[0], out[1], out[2]
    t, ti = common_frame(8)
    my, py, iy, _ = split_ci_update(c(mean @ t.T), c(t @ cov @ t.T), c(t @ ind @ t.T), y_f, p_f, r_f, has,
                                    SEARCH_ITERATIONS, 4, 6)
    cov, ind = ti @ py @ ti.T, ti @ iy @ ti.T
    return my @ ti.T, 0.5 * (cov + np.swapaxes(cov, -1, -2)), 0.5 * (ind + np.swapaxes(ind, -1, -2))


def split_localization(prior: SplitPrior, owner: np.ndarray, feature: np.ndarray, z: np.ndarray, r: np.ndarray,
                       adjacency, feature_prior_lam: np.ndarray, feature_prior_eta: np.ndarray, params: IcpParams,
                       v2x=None, feature_ci: bool = False) -> tuple[BpaResult, SplitState]:
    """The step's localization under split CI, in place of :func:`coloc.inference.bpa.bpa_localization`
    (same row arguments): the feature evidence of :func:`coloc.inference.split_ci.feature_evidence` fused
    into each observing vehicle's b^(0); vehicles without evidence keep b^(0). The result's messages are
    the own-sensor ones the tracks keep (so the step's feature beliefs are the store's moments)."""
    own_mean, own_cov = prior.own_marginal()
    msg_lam, msg_eta, y_f, p_f, r_f, has, comm = feature_evidence(
        np.ascontiguousarray(own_mean), np.ascontiguousarray(own_cov), owner, feature, z, r, adjacency,
        feature_prior_lam, feature_prior_eta, params, v2x, feature_ci)
    mean, cov, ind = fuse_evidence(prior.mean, prior.cov, prior.ind, y_f, p_f, r_f, has)
    used = np.asarray(feature, dtype=np.int64) >= 0
    res = BpaResult(mean[:, :4].copy(), cov[:, :4, :4].copy(), used, msg_lam, msg_eta, 1, True, comm=comm)
    return res, SplitState(mean, cov, ind, prior.streak, prior.own_mean, prior.own_cov, prior.own_streak, prior.rpos)
