"""``gnss`` with a receiver error model of its own (config ``[gnss_model]``): a Gauss-Markov bias state
per vehicle and the exclusion of faulty (NLOS) fixes.

The integrator's model, never the world's (docs: DESIGN "Two models, never one"): it reads only the
covariance the receiver reports (``frame.gnss_R``) and the ``[gnss_model]`` values.

State per vehicle ``[px, py, vx, vy, bx, by]``:

* kinematics: model (1), as :class:`coloc.methods.gnss.GnssTracker` (the driving noise Q oriented by
  the prior velocity estimate);
* bias: ``b_k = a b_{k-1} + w_b``, ``a = exp(-Ts / tau)``, ``Var(w_b) = (1 - a^2) s R_pos,k`` with
  ``s = bias_share`` and ``R_pos,k`` the position block of the covariance the receiver reports at
  step k. The bias variance therefore relaxes towards the stationary ``s R_pos`` of the zone the
  vehicle is in, with the bias's own correlation time (a zone change does not jump the variance: the
  bias is the same physical error before and after);
* fix: ``z_pos = p + b + n``, ``Var(n) = (1 - s) R_pos``; ``z_vel = v + n_v`` with the reported
  velocity block (and the reported cross blocks).

A new (or re-entered) vehicle: the kinematic part from ``frame.prior_z`` / ``prior_R`` as the white
tracker, the bias at 0 with its stationary covariance ``s R_pos``, uncorrelated with the kinematics;
it is only updated in its first step. Where that prior is the step's fix itself (``Frame.prior_has_fix``,
``start = "gnss_fix"``), the fix is not applied again: the state is the exact posterior of that one fix
from a flat position prior, position = fix with the reported covariance, bias N(0, s R_pos) and
Cov(p, b) = -s R_pos (p = z - b - n).

Fault exclusion (``innovation_gate`` = level alpha > 0): a fix whose position innovation has a
normalized innovation squared ``nu^T S_pos^-1 nu`` above the chi-square quantile of 2 degrees of freedom
at alpha is excluded: its position is skipped and only its velocity updates the state. Two degrees of
freedom: the faults meant (NLOS reception) bias the position; gating the 4-D innovation would add two
healthy velocity components that dilute the test. The velocity is kept because skipping the whole fix
(predict only) let trackers diverge on the realistic arterial: with an IMU bias the predicted
velocity drifts, the position error outgrows the predicted covariance and the gate never reopens
(docs/validation/gnss_benchmark.md). For the same reason, after ``max_exclusions`` consecutive
exclusions the next fix is taken. A fresh vehicle's first fix is never gated (its prior comes from it).

Robust velocity (``velocity_gate`` = level > 0; opt-in, both models): a velocity whose innovation fails the
2-dof chi-square test at that level is taken with its noise scaled by d^2 / threshold
(:func:`coloc.methods.gnss_bias2.velocity_deweight`; Chang, J. Geodesy 88, 2014): range-rate velocities carry
reflected signals' path rates the receiver's report does not know. Scaled rather than excluded: excluding the
velocity let trackers whose predicted velocity had drifted diverge (tuning seeds 101-103:
docs/validation/consistency.md, "The receiver model of the satellite world").

The bias follows the report (``bias_follows_report``; opt-in): where a vehicle's reported position
covariance changes between steps (a zone change: a new geometry and environment), the bias is mapped,
``b_k = a T_k b_{k-1}``, ``T_k = L_k L_{k-1}^-1`` with ``L`` the Cholesky factor of the report, so that
the bias's stationary covariance ``s R`` becomes ``s R_k`` at once (the white tracker's noise does the same).
Why: a position error is the range errors mapped by the geometry (sigma_pos = DOP x sigma_UERE: Kaplan and
Hegarty, "Understanding GPS/GNSS", 3rd ed., 2017, Sec. 7.3); what is slow is in the ranges, so a
position bias scales with the reported sigma. Without it (the default), a vehicle entering a zone whose
report is five times larger keeps its small bias variance for about ``bias_tau_s``, and a long
``bias_tau_s`` carries the variance of the zones before into the next (measured, tuning seeds 101-103:
docs/validation/consistency.md).

Adaptive receiver covariance (``adaptive_window_s`` = T > 0; opt-in, off by default): the covariance the
receiver reports is taken as ``alpha_k R_pos`` for the step's white fix noise and the bias's driving noise,
with ``alpha_k = m_k`` where ``m_k`` exceeds its 99 % quantile under consistency (:func:`fading_threshold`:
the excess is significant), 1 elsewhere; ``m_k = beta m_{k-1} + (1 - beta) min(NIS_k, thr) / 2`` is the
vehicle's exponentially weighted average of its position innovations' NIS per degree of freedom, each
computed with the reported (unscaled) covariance (``beta = exp(-Ts / T)``, ``m = 1`` for a fresh vehicle,
``thr`` the gate's threshold: an excluded fault counts as at most a fix at the gate). The rule is
innovation-based adaptive estimation of the measurement covariance (Mehra, IEEE TAC 17(5), 1972;
Mohamed and Schwarz, "Adaptive Kalman filtering for INS/GPS", J. Geodesy 73, 1999: R estimated from the
innovations over a window), here as a scale on the reported covariance and in the normalized form
E[NIS] = 2 of a consistent filter (Bar-Shalom et al., "Estimation with Applications to Tracking and
Navigation", 2001, Sec. 5.4). Why: receiver errors the model does not carry (NLOS episodes of seconds,
errors common to many receivers) make the innovations larger than predicted for many steps in a row; a
single fix's gate sees only the largest, the average sees the lasting excess. With a consistent model the
average rarely passes the test (1 % of steps). Scaling the predicted state covariance instead (the
fading factor of Xia et al., Automatica 30(8), 1994) was tried first: it compounds through the recursion,
and on the realistic arterial (tuning seeds 101-103) it let the trackers follow the fixes' noise (RMSE
26-42 m against 9 m; docs/validation/consistency.md). The gate tests the innovation against the scaled
covariance.

Outputs are the 4-D kinematic marginal (mean and covariance). All vehicles of a frame as one numpy
batch. With ``bias_share = 0`` and no gate it is the white tracker (tests: to 1e-12).

``bias_model = "two_state"``: a common-mode bias slow in time and a local bias decorrelating with the distance
travelled, an 8-D state (:mod:`coloc.methods.gnss_bias2`); ``gnss`` and the cooperative methods of
:mod:`coloc.methods.coop_fusion` (the infrastructure methods keep this module's single bias:
:meth:`GnssModelParams.single_model`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.stats import chi2

from coloc.core.frame import Frame, StepEstimate
from coloc.core.inertial import estimator_input
from coloc.core.models import MotionParams, driving_noise_cov
from coloc.core.vehicles import fresh_rows, keep_entry_fix, match_ids
from coloc.inference.comm import CommCount
from coloc.methods.gnss_bias2 import (gate_nis, gated_joseph_update, two_state_entry_posterior, two_state_predict_update,
                                      two_state_start, velocity_deweight)
from coloc.methods.registry import GNSS

#: H of the fix for the state [p, v, b]: z_pos = p + b, z_vel = v.
H = np.zeros((4, 6))
H[0, 0] = H[1, 1] = H[2, 2] = H[3, 3] = H[0, 4] = H[1, 5] = 1.0

#: ``[gnss_model] bias_model`` values; ``common_update`` values (coloc.methods.gnss_bias2).
BIAS_MODELS = ("single", "two_state")
#: ``[gnss_model] gate_on`` values (GnssModelParams.gate_on)
GATE_ON = ("calibrated", "report")
VELOCITY_INFLATIONS = ("noise", "innovation")
COMMON_UPDATES = ("augmented", "consider")


@dataclass(frozen=True)
class GnssModelParams:
    """The ``[gnss_model]`` table: what the integrator believes about the receiver's error."""

    # Share of the reported position variance that is a slowly varying bias; the rest is white.
    # Assumption: the code-phase noise of a carrier-smoothed single-frequency fix is decimetres,
    # while the reported 1-sigma is metres (atmosphere, orbit/clock, multipath): most of it is slow.
    bias_share: float = 0.8
    # Correlation time of the bias (s). Assumption: tens of seconds (multipath) to minutes
    # (atmospheric residuals) for single-frequency position errors; 60 s in between.
    bias_tau_s: float = 60.0
    # Level of the chi-square gate (2 dof) on the position innovation; 0: no exclusion.
    innovation_gate: float = 0.999
    # Consecutive excluded fixes after which the next one is taken whatever its innovation: a
    # discrepancy that lasts is more likely the tracker's own drift (e.g. an IMU bias) than a fault,
    # and a gate that never reopens would let it diverge. Assumption: NLOS episodes last seconds.
    max_exclusions: int = 10
    # Time constant (s) of the average of normalized innovations that scales the reported covariance
    # (module docstring; Mohamed and Schwarz, J. Geodesy 1999). 0: off (the plain filter).
    adaptive_window_s: float = 0.0
    # The bias follows the reported covariance: when the report changes (a zone change: the receiver's
    # geometry and environment), the bias is mapped by the change of its square root (module docstring).
    # False: the bias carries over unchanged and its variance relaxes with bias_tau_s.
    bias_follows_report: bool = False
    # The receiver's error as one bias ("single": bias_share, bias_tau_s above) or two
    # ("two_state": a common-mode bias slow in time and a local one decorrelating with the distance
    # travelled; coloc.methods.gnss_bias2). `gnss` and, with [fusion], icp_known_da, icp_da_lc and icp_da_pf
    # take "two_state" (coloc.methods.coop_fusion); the infrastructure methods keep the single model
    # (bias_share, bias_tau_s).
    bias_model: str = "single"
    # Two-state model, common-mode bias (atmosphere, orbit, clock): its share of the reported position
    # variance and its correlation time. Assumption: the slow error is most of the reported variance
    # (decimetre code noise against metres), about half of it common-mode; residuals of the broadcast
    # ionosphere, troposphere and orbit/clock models change over tens of minutes (Kaplan and Hegarty,
    # "Understanding GPS/GNSS", 3rd ed., 2017, Sec. 7.2). Shares 0.5 / 0.45 chosen over 0.4 / 0.4 and
    # 0.6 / 0.35 on the tuning seeds 101-103 (docs/validation/consistency.md, "Two bias states").
    common_share: float = 0.5
    common_tau_s: float = 1800.0
    # Two-state model: a common-mode part of known size (m, per axis), added to the common-mode bias's
    # stationary covariance, s_c R_pos + common_sigma_m^2 I. The receiver's report cannot carry the error its
    # residuals do not show (what every satellite's range shares with the other receivers' moves the fix, not
    # the residuals), so this part is what the integrator takes from the receiver's open-sky accuracy instead
    # (coloc.methods.gnss_bias2). 0: the common-mode bias is the share of the report alone.
    common_sigma_m: float = 0.0
    # Level of a chi-square test (2 dof) on the velocity innovation; 0: none. A velocity
    # from range rates carries a reflected signal's path rate (metres per second where a vehicle drives toward
    # the facade that reflects it) that the receiver's report does not know; a velocity that fails the test
    # is taken with its noise scaled by d^2 / threshold (coloc.methods.gnss_bias2.velocity_deweight).
    velocity_gate: float = 0.0
    # What the velocity gate inflates: "noise", R_vv by d^2 / threshold (the one-step form); "innovation", S_vv
    # by d^2 / threshold (R_vv grows by (d^2 / threshold - 1) S_vv), so that the inflated statistic is the
    # threshold even where the predicted velocity's covariance dominates S (a range-rate velocity 1-2 m/s off at
    # a start from a stop, reported at 0.07 m/s, is followed with a gain near one under "noise"). Measured on the
    # tuning seeds and not adopted: an outlier's pull then falls as 1/d, so a prediction that has drifted is not
    # pulled back by correct velocities either (TLR icp_da_lc 1.64 -> 3.03 m; docs/validation/consistency.md,
    # "A start from a stop").
    velocity_inflation: str = "noise"
    # Two-state model, local bias (multipath): its share, its correlation length in distance travelled
    # (m; multipath decorrelates over metres to tens of metres of travel: Braasch, in Parkinson and
    # Spilker, "Global Positioning System: Theory and Applications" Vol. I, 1996, ch. 14; 30 m chosen over
    # 10 m on the tuning seeds) and its correlation time at rest (s; static multipath changes with the
    # satellites' motion over minutes, ibid.).
    local_share: float = 0.45
    local_length_m: float = 30.0
    local_tau_s: float = 120.0
    # Two-state model: the common-mode bias as a state of the filter ("augmented") or a Schmidt consider
    # state ("consider": carried, never updated; coloc.methods.gnss_bias2). Consider: the more consistent
    # in every candidate on the tuning seeds (a single receiver cannot tell its common-mode error from its
    # position).
    common_update: str = "consider"
    # The receiver's report calibrated against a reference trajectory (coloc.methods.report_calibration):
    # above a reported per-axis position std of degraded_above_m (m; 0: the report as it is) the position
    # covariance is taken degraded_position_scale^2 and the velocity covariance degraded_velocity_scale^2
    # times larger. Applies to every method that takes [gnss_model], through coloc.methods.registry.
    degraded_above_m: float = 0.0
    degraded_position_scale: float = 1.0
    degraded_velocity_scale: float = 1.0
    # The fault exclusion's statistic on the calibrated report ("calibrated") or on the report as the receiver
    # gives it ("report": the receiver's own claim, the integrity reading of RAIM), the update on the calibrated
    # one either way (coloc.methods.report_calibration.gate_noise_scale). Needs degraded_position_scale >= 1.
    gate_on: str = "calibrated"

    @property
    def calibrates_report(self) -> bool:
        """The estimators get the calibrated report (coloc.methods.report_calibration)."""
        return self.degraded_above_m > 0 and (self.degraded_position_scale != 1.0
                                              or self.degraded_velocity_scale != 1.0)

    @property
    def two_state(self) -> bool:
        return self.bias_model == "two_state"

    @property
    def state_dim(self) -> int:
        """6 ([p, v, b]) or 8 ([p, v, c, l])."""
        return 8 if self.two_state else 6

    def single_model(self) -> "GnssModelParams":
        """The model for the methods that take the single bias only: this one with ``bias_model = "single"``."""
        return self if not self.two_state else replace(self, bias_model="single")

    def __post_init__(self):
        if self.bias_model not in BIAS_MODELS:
            raise ValueError(f"must be one of {', '.join(map(repr, BIAS_MODELS))}, got {self.bias_model!r}")
        if self.common_update not in COMMON_UPDATES:
            raise ValueError(f"must be one of {', '.join(map(repr, COMMON_UPDATES))}, got {self.common_update!r}")
        for name, what in (("common_tau_s", "the common-mode bias's correlation time, s"),
                           ("local_length_m", "the local bias's correlation length, m"),
                           ("local_tau_s", "the local bias's correlation time at rest, s")):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
                raise ValueError(f"must be positive and finite ({what}), got {v!r}")
        if not (isinstance(self.common_sigma_m, (int, float)) and not isinstance(self.common_sigma_m, bool)
                and math.isfinite(self.common_sigma_m) and self.common_sigma_m >= 0):
            raise ValueError(f"must be >= 0 and finite (the common-mode bias's own std per axis, m), "
                             f"got {self.common_sigma_m!r}")
        if not (isinstance(self.degraded_above_m, (int, float)) and not isinstance(self.degraded_above_m, bool)
                and math.isfinite(self.degraded_above_m) and self.degraded_above_m >= 0):
            raise ValueError(f"must be >= 0 and finite (a reported per-axis position std, m; 0: off), "
                             f"got {self.degraded_above_m!r}")
        for name in ("degraded_position_scale", "degraded_velocity_scale"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
                raise ValueError(f"must be positive and finite (a factor on the reported std), got {v!r}")
        if self.velocity_inflation not in VELOCITY_INFLATIONS:
            raise ValueError(f"must be one of {', '.join(map(repr, VELOCITY_INFLATIONS))}, "
                             f"got {self.velocity_inflation!r}")
        if self.gate_on not in GATE_ON:
            raise ValueError(f"must be one of {', '.join(map(repr, GATE_ON))}, got {self.gate_on!r}")
        if self.gate_on == "report" and self.degraded_position_scale < 1.0:
            raise ValueError("gate_on = \"report\" needs degraded_position_scale >= 1 (the calibration is then "
                             f"invertible from the calibrated report), got {self.degraded_position_scale!r}")
        if not (isinstance(self.velocity_gate, (int, float)) and not isinstance(self.velocity_gate, bool)
                and 0.0 <= self.velocity_gate < 1.0):
            raise ValueError(f"must be in [0, 1) (a chi-square level; 0: no velocity test), "
                             f"got {self.velocity_gate!r}")
        for name in ("common_share", "local_share"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 <= v < 1.0):
                raise ValueError(f"must be in [0, 1) (a share of the reported variance), got {v!r}")
        if self.two_state and not self.common_share + self.local_share < 1.0:
            raise ValueError(f"common_share + local_share must be below 1 (the rest is the white noise), got "
                             f"{self.common_share!r} + {self.local_share!r}")
        if self.two_state and self.adaptive_window_s > 0:
            raise ValueError("adaptive_window_s applies to the single model only (bias_model = \"single\")")
        if not (isinstance(self.bias_share, (int, float)) and 0.0 <= self.bias_share < 1.0):
            raise ValueError(f"must be in [0, 1) (the share of the reported variance that is a bias), "
                             f"got {self.bias_share!r}")
        if not (isinstance(self.bias_tau_s, (int, float)) and math.isfinite(self.bias_tau_s) and self.bias_tau_s > 0):
            raise ValueError(f"must be positive and finite (the bias correlation time, s), got {self.bias_tau_s!r}")
        if not (isinstance(self.max_exclusions, int) and self.max_exclusions >= 0):
            raise ValueError(f"must be a non-negative integer (consecutive excluded fixes), got {self.max_exclusions!r}")
        if not (isinstance(self.adaptive_window_s, (int, float)) and math.isfinite(self.adaptive_window_s)
                and self.adaptive_window_s >= 0):
            raise ValueError(f"must be >= 0 and finite (the adaptive covariance time constant, s; 0: off), "
                             f"got {self.adaptive_window_s!r}")
        if not isinstance(self.bias_follows_report, bool):
            raise ValueError(f"must be true or false, got {self.bias_follows_report!r}")
        if not (isinstance(self.innovation_gate, (int, float)) and 0.0 <= self.innovation_gate < 1.0):
            raise ValueError(f"must be in [0, 1) (the chi-square gate's level; 0: no exclusion), "
                             f"got {self.innovation_gate!r}")

    @property
    def gate_threshold(self) -> float:
        """The chi-square quantile of 2 dof at the gate's level: -2 ln(1 - alpha) (inf: no gate)."""
        return math.inf if self.innovation_gate == 0 else -2.0 * math.log1p(-self.innovation_gate)

    @property
    def velocity_gate_threshold(self) -> float:
        """The chi-square quantile of 2 dof at the velocity gate's level (inf: no gate)."""
        return math.inf if self.velocity_gate == 0 else -2.0 * math.log1p(-self.velocity_gate)


def entry_fix_posterior(mean: np.ndarray, cov: np.ndarray, frame, fresh: np.ndarray, r: np.ndarray,
                        bias_share: float) -> np.ndarray:
    """In place, after the step's GNSS update of 6-state [p, v, b] beliefs: the rows whose entry prior is this
    step's fix (:func:`coloc.core.vehicles.entry_fix_rows`) get the one-fix posterior instead of a second
    update by it. With a flat prior on p, z = p + b + w, b ~ N(0, s R), w ~ N(0, (1 - s) R): p | z ~ N(z, R),
    b | z ~ N(0, s R), Cov(p, b) = -s R (s = ``bias_share``). Returns the rows."""
    once = keep_entry_fix(mean, cov, frame, fresh)
    if once.any():
        cross = -bias_share * r[once, :2, :2]
        cov[once, :4, 4:] = 0.0
        cov[once, 4:, :4] = 0.0
        cov[once, :2, 4:], cov[once, 4:, :2] = cross, np.swapaxes(cross, -1, -2)
        mean[once, 4:] = 0.0
        cov[once, 4:, 4:] = bias_share * r[once, :2, :2]
    return once


#: Level of the test that starts the scaling: the average normalized innovation must exceed what a
#: consistent filter exceeds with probability 1 - FADING_LEVEL (a conventional 1 % false-alarm level).
FADING_LEVEL = 0.99


def fading_threshold(beta: float) -> float:
    """The FADING_LEVEL quantile of the exponentially weighted average m = sum (1 - beta) beta^j x_j of
    independent x_j = NIS_j / 2 ~ Exp(1) (a consistent filter's 2-dof innovations): mean 1, variance
    (1 - beta) / (1 + beta), approximated by chi2(2 n) / (2 n) with n = (1 + beta) / (1 - beta) the
    effective number of averaged innovations."""
    n = (1.0 + beta) / (1.0 - beta)
    return float(chi2.ppf(FADING_LEVEL, 2.0 * n) / (2.0 * n))


def report_map(r_prev: np.ndarray, r_now: np.ndarray) -> np.ndarray:
    """(N, 2, 2) maps T = L_now L_prev^-1 of the bias between two reported position covariances (L the
    lower Cholesky factors): T r_prev T^T = r_now; the identity (exactly) where the two are equal."""
    l_prev = np.linalg.cholesky(r_prev)
    l_now = np.linalg.cholesky(r_now)
    t = np.swapaxes(np.linalg.solve(np.swapaxes(l_prev, -1, -2), np.swapaxes(l_now, -1, -2)), -1, -2)
    same = np.all(r_prev == r_now, axis=(-1, -2))
    t[same] = np.eye(2)
    return t


def bias_predict_update(mean, cov, accel, z, r, predict_mask, dt, motion: MotionParams, model: GnssModelParams,
                        streak=None, nis_avg=None, r_prev=None):
    """One step for a batch of 6-D states (N, 6), (N, 6, 6): predict where ``predict_mask``, then the
    update by each fix that passes the gate (a fresh row, ``~predict_mask``, is never gated; nor is a
    row whose ``streak`` of consecutive exclusions has reached ``model.max_exclusions``); an excluded
    fix updates the velocity only. With ``model.adaptive_window_s`` > 0, ``nis_avg`` (N,) is each row's
    average normalized innovation before this step (1 for a fresh row) and the predicted rows' reported
    position covariance is scaled by the adaptive factor (module docstring). With
    ``model.bias_follows_report``, ``r_prev`` (N, 2, 2) is each row's reported position covariance of its
    previous step (any value for a fresh row) and the bias is mapped to this step's report. Returns (mean, cov, excluded (N,)
    bool), and the rows' new ``nis_avg`` as a fourth item when the adaptive covariance is on."""
    n = mean.shape[0]
    s = model.bias_share
    r = np.asarray(r, dtype=float)
    r_pos = r[:, :2, :2]
    m = mean.copy()
    p = cov.copy()
    if predict_mask.any():
        a, f, mp, q = bias_transition(m, accel, r_pos, dt, motion, model)
        if model.bias_follows_report and r_prev is not None:
            # b_k = a T_k b_{k-1}: T_k = L_k L_{k-1}^-1, L the Cholesky factor of the reported position
            # covariance (module docstring); T = I where the report did not change
            fr = np.broadcast_to(f, (n, 6, 6)).copy()
            fr[:, 4:, 4:] = a * report_map(r_prev, r_pos)
            mp = np.einsum("nij,nj->ni", fr, m)
            mp[:, 0:2] += 0.5 * dt * dt * accel
            mp[:, 2:4] += dt * accel
            pp = fr @ p @ np.swapaxes(fr, -1, -2) + q
        else:
            pp = f @ p @ f.T + q
        pp = 0.5 * (pp + np.swapaxes(pp, -1, -2))
        m[predict_mask] = mp[predict_mask]
        p[predict_mask] = pp[predict_mask]
    rn = r.copy()
    rn[:, :2, :2] *= 1.0 - s
    ph = p @ H.T  # (N, 6, 4)
    sm = H @ ph + rn  # (N, 4, 4)
    innov = z - m @ H.T
    adaptive = model.adaptive_window_s > 0
    if adaptive:
        nis_avg = np.ones(n) if nis_avg is None else np.asarray(nis_avg, dtype=float).copy()
        nu = innov[:, :2]
        nis0 = np.einsum("ni,ni->n", nu, np.linalg.solve(sm[:, :2, :2], nu[..., None])[..., 0])
        beta = math.exp(-dt / model.adaptive_window_s)
        upd = beta * nis_avg + (1.0 - beta) * 0.5 * np.minimum(nis0, model.gate_threshold)
        nis_avg = np.where(predict_mask, upd, 1.0)
        alpha = np.where(predict_mask & (nis_avg > fading_threshold(beta)), nis_avg, 1.0)
        if (alpha > 1.0).any():
            # R_pos -> alpha R_pos: the white part of the fix and the bias's driving noise of this step
            extra = (alpha - 1.0)[:, None, None]
            rn[:, :2, :2] += extra * (1.0 - s) * r_pos
            a = math.exp(-dt / model.bias_tau_s)
            p[:, 4:, 4:] += extra * (1.0 - a * a) * s * r_pos
            ph = p @ H.T
            sm = H @ ph + rn
    velocity_deweight(innov, sm, rn, predict_mask, model)
    excluded = np.zeros(n, dtype=bool)
    if model.innovation_gate > 0:
        nis = gate_nis(innov, sm, rn, r, model)
        excluded = predict_mask & (nis > model.gate_threshold)
        if streak is not None:
            excluded &= streak < model.max_exclusions
    # A full update where the fix passes, a velocity-only update (rows 2-3 of H) where it is excluded.
    gated_joseph_update(m, p, ph, sm, rn, innov, excluded, H)
    if adaptive:
        return m, p, excluded, nis_avg
    return m, p, excluded


@dataclass
class GnssBiasTracker:
    """``gnss`` with ``[gnss_model]``: keeps each vehicle's 6-D (two-state model: 8-D) posterior between frames
    and reports the 4-D kinematic marginal."""

    motion: MotionParams = field(default_factory=MotionParams)
    model: GnssModelParams = field(default_factory=GnssModelParams)
    name: str = GNSS.name
    _ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=object))
    _mean: np.ndarray = field(default_factory=lambda: np.empty((0, 6)))
    _cov: np.ndarray = field(default_factory=lambda: np.empty((0, 6, 6)))
    last_comm: CommCount | None = None  # non-cooperative: sends nothing
    last_excluded: np.ndarray | None = None  # (N,) bool: fixes skipped by the gate this step
    _heading: np.ndarray | None = None  # kept heading per vehicle row ([inertial] only)
    _streak: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))  # consecutive exclusions
    _nis: np.ndarray = field(default_factory=lambda: np.empty(0))  # average normalized innovation (adaptive)
    _rpos: np.ndarray = field(default_factory=lambda: np.empty((0, 2, 2)))  # last reported position covariance

    def __post_init__(self):
        if self.model.two_state and self._mean.shape[1] != 8:
            self._mean, self._cov = np.empty((0, 8)), np.empty((0, 8, 8))

    def step(self, frame: Frame) -> StepEstimate:
        idx = match_ids(self._ids, frame.vehicle_ids)
        accel, self._heading = estimator_input(frame, idx, self._mean[:, 2:4], self._heading,
                                               self.motion.heading_min_speed,
                                               self.motion.holds_heading)
        prior_z = np.asarray(frame.prior_z, dtype=float)
        fresh = fresh_rows(idx, frame.entered, prior_z)
        r = np.asarray(frame.gnss_R, dtype=float)
        n = len(frame.vehicle_ids)
        d = self.model.state_dim
        mean = np.zeros((n, d))
        cov = np.zeros((n, d, d))
        keep = ~fresh
        mean[keep] = self._mean[idx[keep]]
        cov[keep] = self._cov[idx[keep]]
        if fresh.any():
            mean[fresh, :4] = prior_z[fresh]
            cov[fresh, :4, :4] = np.asarray(frame.prior_R, dtype=float)[fresh]
            if self.model.two_state:
                two_state_start(cov, fresh, r[:, :2, :2], self.model)
            else:
                cov[fresh, 4:, 4:] = self.model.bias_share * r[fresh, :2, :2]
        streak = np.zeros(n, dtype=np.int64)
        streak[keep] = self._streak[idx[keep]]
        nis = None
        if self.model.adaptive_window_s > 0:
            nis = np.ones(n)
            nis[keep] = self._nis[idx[keep]]
        r_prev = None
        if self.model.bias_follows_report:
            r_prev = r[:, :2, :2].copy()
            r_prev[keep] = self._rpos[idx[keep]]
            self._rpos = r[:, :2, :2].copy()
        if self.model.two_state:
            out = two_state_predict_update(
                mean, cov, np.asarray(accel, dtype=float), np.asarray(frame.gnss_z, dtype=float), r, keep,
                float(frame.dt), self.motion, self.model, streak, r_prev)
        else:
            out = bias_predict_update(
                mean, cov, np.asarray(accel, dtype=float), np.asarray(frame.gnss_z, dtype=float), r, keep,
                float(frame.dt), self.motion, self.model, streak, nis, r_prev)
        mean, cov, self.last_excluded = out[:3]
        if nis is not None:
            self._nis = out[3]
        if self.model.two_state:
            two_state_entry_posterior(mean, cov, frame, fresh, r, self.model)
        else:
            entry_fix_posterior(mean, cov, frame, fresh, r, self.model.bias_share)
        self._streak = np.where(self.last_excluded, streak + 1, 0)
        self._ids, self._mean, self._cov = frame.vehicle_ids, mean, cov
        self.last_comm = CommCount.zeros(frame.n_vehicles)
        return StepEstimate(mean=mean[:, :4].copy(), cov=cov[:, :4, :4].copy())


def bias_predict(mean, cov, accel, r_pos, dt, motion: MotionParams, model: GnssModelParams):
    """The prediction of :func:`bias_predict_update` alone, for a batch of 6-D states (N, 6), (N, 6, 6):
    model (1) on [p, v] (velocity-oriented driving noise) and ``b' = a b + w_b``, ``Var(w_b) = (1 - a^2) s
    R_pos`` with ``R_pos`` (N, 2, 2) the reported position covariance. Returns new (mean, cov)."""
    _a, f, m, q = bias_transition(mean, accel, np.asarray(r_pos, dtype=float), dt, motion, model)
    p = f @ cov @ f.T + q
    return m, 0.5 * (p + np.swapaxes(p, -1, -2))


def bias_transition(mean, accel, r_pos, dt, motion: MotionParams, model: GnssModelParams):
    """The 6-state model's pieces for a batch (N, 6): ``a = exp(-dt / tau)``, the transition F (6, 6), the
    predicted means F x + B accel (N, 6), and Q (N, 6, 6): model (1)'s velocity-oriented driving noise on [p, v]
    and ``Var(w_b) = (1 - a^2) s R_pos`` on the bias (``R_pos`` (N, 2, 2) the reported position covariance).
    Shared by :func:`bias_predict_update`, :func:`bias_predict` and the split filters of
    :mod:`coloc.methods.coop_fusion`."""
    n = mean.shape[0]
    a = math.exp(-dt / model.bias_tau_s)
    f = np.eye(6)
    f[0, 2] = f[1, 3] = dt
    f[4, 4] = f[5, 5] = a
    q = np.zeros((n, 6, 6))
    q[:, :4, :4] = driving_noise_cov(mean[:, 2:4], dt, motion)
    q[:, 4:, 4:] = (1.0 - a * a) * model.bias_share * r_pos
    m = mean @ f.T
    m[:, 0:2] += 0.5 * dt * dt * accel
    m[:, 2:4] += dt * accel
    return a, f, m, q
