"""The two-state receiver model of ``[gnss_model]`` (``bias_model = "two_state"``): the 8-D state
``[px, py, vx, vy, cx, cy, lx, ly]`` per vehicle, for :class:`coloc.methods.gnss_bias.GnssBiasTracker`.

The position error of a single-frequency fix has parts with different correlation structure (Kaplan and
Hegarty, "Understanding GPS/GNSS", 3rd ed., 2017, Sec. 7.2-7.3 and 7.4): the atmospheric, orbit and clock
residuals change over tens of minutes and are shared by receivers kilometres apart; multipath depends on the
reflecting surroundings, so it decorrelates over the metres to tens of metres a moving receiver travels
(Braasch, "Multipath effects", in Parkinson and Spilker, "Global Positioning System: Theory and
Applications" Vol. I, 1996, ch. 14) and over minutes at rest, as the satellites move. One Gauss-Markov state
with one time constant cannot carry both: with a short one the filter forgets the slow part, with a long one
it trusts the local part to stay (docs/validation/consistency.md, "Under realism").

Model (s_c = ``common_share``, s_l = ``local_share``, R_pos,k the position block the receiver reports):

* kinematics: model (1), as the 6-state tracker;
* common-mode bias: ``c_k = a_c c_{k-1} + w_c``, ``a_c = exp(-Ts / common_tau_s)``,
  ``Var(w_c) = (1 - a_c^2) (s_c R_pos,k + sigma_c^2 I)``, sigma_c = ``common_sigma_m`` (0 by default). The
  common-mode error of a single-point fix is what every range shares with other receivers' (broadcast clock
  and orbit, ionosphere, troposphere): it moves the fix and leaves the least-squares residuals alone, so a
  covariance the receiver scales from its residuals does not carry it (Kaplan and Hegarty, Sec. 7.3: the
  position error is DOP x UERE whatever the residuals). ``common_sigma_m`` is the integrator's size for it,
  from the receiver's open-sky accuracy, which is that error (a static open-sky receiver has little
  multipath and averages its noise);
* local bias: ``l_k = a_l l_{k-1} + w_l``, ``a_l = exp(-Ts / local_tau_s - |v| Ts / local_length_m)`` with
  |v| the estimator's OWN speed estimate (the prior mean's velocity, never the truth): a first-order
  Gauss-Markov process in the distance travelled, with a time constant at rest; ``Var(w_l) = (1 - a_l^2)
  s_l R_pos,k``;
* fix: ``z_pos = p + c + l + n``, ``Var(n) = (1 - s_c - s_l) R_pos``; ``z_vel = v + n_v``.

``common_update`` chooses how the common-mode state is estimated:

* ``"augmented"``: a state of the Kalman filter like any other;
* ``"consider"``: a Schmidt (consider) state (Schmidt, "Application of state-space methods to navigation
  problems", Advances in Control Systems 3, 1966; Simon, "Optimal State Estimation", 2006, Sec. 7.5): its
  correlations with the other states are carried and enter every gain, but its own estimate is never updated
  (its gain rows are zero; the covariance update is the Joseph form of that gain, exact for any gain). A
  single receiver cannot tell its common-mode error from its position; the consider state keeps the filter
  from believing it did.

A fresh vehicle: the kinematic part from its prior, both biases at 0 with their stationary covariances;
the entry protocol (prior = this step's fix) gives the one-fix posterior: p = z with the reported covariance
(plus sigma_c^2 I), Cov(p, c) = -(s_c R + sigma_c^2 I), Cov(p, l) = -s_l R, c and l uncorrelated. Fault
exclusion, ``max_exclusions`` and ``bias_follows_report`` (both biases mapped) as in the 6-state model. With
``local_share = 0`` it is the 6-state model with ``bias_share = common_share``, ``bias_tau_s = common_tau_s``
when ``common_update = "augmented"`` (tests: to 1e-12).
"""

from __future__ import annotations

import math

import numpy as np

from coloc.core.models import MotionParams, driving_noise_cov
from coloc.core.vehicles import keep_entry_fix
from coloc.methods.report_calibration import gate_noise_scale

#: H of the fix for the state [p, v, c, l]: z_pos = p + c + l, z_vel = v.
H8 = np.zeros((4, 8))
H8[0, 0] = H8[1, 1] = H8[2, 2] = H8[3, 3] = 1.0
H8[0, 4] = H8[1, 5] = H8[0, 6] = H8[1, 7] = 1.0


def common_cov(r_pos: np.ndarray, model) -> np.ndarray:
    """(K, 2, 2): the common-mode bias's stationary covariance, s_c R_pos + ``common_sigma_m``^2 I."""
    out = model.common_share * r_pos
    if model.common_sigma_m > 0:
        out = out + model.common_sigma_m ** 2 * np.eye(2)
    return out


def two_state_start(cov: np.ndarray, rows: np.ndarray, r_pos: np.ndarray, model) -> None:
    """In place: the rows' bias blocks of an (N, 8, 8) covariance at their stationary values."""
    cov[rows, 4:6, 4:6] = common_cov(r_pos[rows], model)
    cov[rows, 6:8, 6:8] = model.local_share * r_pos[rows]


def two_state_transition(mean, accel, r_pos, dt, motion: MotionParams, model):
    """The 8-state model's pieces for a batch (N, 8): the transitions F (N, 8, 8) (the local bias's decay
    depends on each row's own speed estimate), the predicted means (N, 8) and Q (N, 8, 8)."""
    n = mean.shape[0]
    a_c = math.exp(-dt / model.common_tau_s)
    speed = np.hypot(mean[:, 2], mean[:, 3])
    a_l = np.exp(-dt / model.local_tau_s - speed * dt / model.local_length_m)
    f = np.broadcast_to(np.eye(8), (n, 8, 8)).copy()
    f[:, 0, 2] = f[:, 1, 3] = dt
    f[:, 4, 4] = f[:, 5, 5] = a_c
    f[:, 6, 6] = f[:, 7, 7] = a_l
    q = np.zeros((n, 8, 8))
    q[:, :4, :4] = driving_noise_cov(mean[:, 2:4], dt, motion)
    q[:, 4:6, 4:6] = (1.0 - a_c * a_c) * model.common_share * r_pos
    if model.common_sigma_m > 0:
        q[:, 4:6, 4:6] += (1.0 - a_c * a_c) * model.common_sigma_m ** 2 * np.eye(2)
    q[:, 6:8, 6:8] = ((1.0 - a_l * a_l) * model.local_share)[:, None, None] * r_pos
    m = np.einsum("nij,nj->ni", f, mean)
    m[:, 0:2] += 0.5 * dt * dt * accel
    m[:, 2:4] += dt * accel
    return f, m, q


def mapped_two_state_transition(mean, accel, r_pos, r_prev, dt, motion: MotionParams, model):
    """:func:`two_state_transition`, with both biases mapped by the report's change (``bias_follows_report``
    and a previous report ``r_prev``: c' = a_c T c, l' = a_l T l, T from
    :func:`coloc.methods.gnss_bias.report_map`)."""
    from coloc.methods.gnss_bias import report_map

    f, mp, q = two_state_transition(mean, accel, r_pos, dt, motion, model)
    if model.bias_follows_report and r_prev is not None:
        t = report_map(r_prev, r_pos)
        f[:, 4:6, 4:6] = f[:, 4:6, 4:6] @ t
        f[:, 6:8, 6:8] = f[:, 6:8, 6:8] @ t
        mp = np.einsum("nij,nj->ni", f, mean)
        mp[:, 0:2] += 0.5 * dt * dt * accel
        mp[:, 2:4] += dt * accel
    return f, mp, q


def two_state_predict_update(mean, cov, accel, z, r, predict_mask, dt, motion: MotionParams, model,
                             streak=None, r_prev=None):
    """:func:`coloc.methods.gnss_bias.bias_predict_update` for the 8-D states (N, 8), (N, 8, 8). Returns
    (mean, cov, excluded (N,) bool)."""
    n = mean.shape[0]
    white = 1.0 - model.common_share - model.local_share
    r = np.asarray(r, dtype=float)
    r_pos = r[:, :2, :2]
    m = mean.copy()
    p = cov.copy()
    if predict_mask.any():
        f, mp, q = mapped_two_state_transition(m, accel, r_pos, r_prev, dt, motion, model)
        pp = f @ p @ np.swapaxes(f, -1, -2) + q
        pp = 0.5 * (pp + np.swapaxes(pp, -1, -2))
        m[predict_mask] = mp[predict_mask]
        p[predict_mask] = pp[predict_mask]
    rn = r.copy()
    rn[:, :2, :2] *= white
    ph = p @ H8.T  # (N, 8, 4)
    sm = H8 @ ph + rn
    innov = z - m @ H8.T
    velocity_deweight(innov, sm, rn, predict_mask, model)
    excluded = np.zeros(n, dtype=bool)
    if model.innovation_gate > 0:
        nis = gate_nis(innov, sm, rn, r, model)
        excluded = predict_mask & (nis > model.gate_threshold)
        if streak is not None:
            excluded &= streak < model.max_exclusions
    fixed = slice(4, 6) if model.common_update == "consider" else None
    gated_joseph_update(m, p, ph, sm, rn, innov, excluded, H8, fixed)
    return m, p, excluded


def gate_nis(innov: np.ndarray, sm: np.ndarray, rn: np.ndarray, r: np.ndarray, model) -> np.ndarray:
    """(N,) the fault exclusion's statistic nu_p^T S_g^-1 nu_p on the position innovation: S_g = S's position
    block, with the fix's noise ``rn`` (its position block the white share of the report ``r``) taken at the
    receiver's own report where ``model.gate_on = "report"``: S_g = S - (1 - g) R_n,pos, g from
    :func:`coloc.methods.report_calibration.gate_noise_scale` (1 everywhere otherwise, and then S_g is S's
    block itself, bit for bit)."""
    nu = innov[:, :2]
    sg = sm[:, :2, :2]
    g = gate_noise_scale(r, model)
    if (g != 1.0).any():
        sg = sg - (1.0 - g)[:, None, None] * rn[:, :2, :2]
    return np.einsum("ni,ni->n", nu, np.linalg.solve(sg, nu[..., None])[..., 0])


def velocity_deweight(innov: np.ndarray, sm: np.ndarray, rn: np.ndarray, predict_mask: np.ndarray, model) -> None:
    """In place on the fix's noise ``rn`` and innovation covariance ``sm`` (N, 4, 4): where a predicted row's
    velocity innovation fails the 2-dof chi-square test ``velocity_gate`` (nu_v^T S_vv^-1 nu_v = d^2 above the
    threshold t), its velocity noise is scaled by d^2 / t, R_vv -> (d^2 / t) R_vv (and S_vv with it): the
    Mahalanobis-distance rule of a robust Kalman filter (G. Chang, "Robust Kalman filtering based on
    Mahalanobis distance as outlier judging criterion", J. Geodesy 88, 2014), in its one-step form. With
    ``velocity_inflation = "innovation"`` S_vv itself is scaled by d^2 / t (R_vv grows by (d^2 / t - 1) S_vv), so
    that the inflated statistic is t whatever the prediction's share of S: where the predicted velocity's
    covariance dominates S, scaling R_vv alone leaves the gain near one and the outlier is followed. Not an
    exclusion: excluding the velocity let trackers diverge where the predicted velocity had drifted (the gate
    never reopened); a scaled fix keeps pulling back, and an outlier's pull is bounded."""
    if model.velocity_gate <= 0:
        return
    nu = innov[:, 2:4]
    d2 = np.einsum("ni,ni->n", nu, np.linalg.solve(sm[:, 2:4, 2:4], nu[..., None])[..., 0])
    thr = model.velocity_gate_threshold
    out = predict_mask & (d2 > thr)
    if out.any():
        base = sm if model.velocity_inflation == "innovation" else rn
        extra = (d2[out] / thr - 1.0)[:, None, None] * base[out, 2:4, 2:4]
        rn[out, 2:4, 2:4] += extra
        sm[out, 2:4, 2:4] += extra


def gated_joseph_update(m, p, ph, sm, rn, innov, excluded, h, fixed=None) -> None:
    """In place on a batch of states m (N, d), P (N, d, d): the fix's update of every row, the full fix
    (rows 0-3 of ``h``, [z_pos, z_vel]) where not ``excluded``, the velocity only (rows 2-3) where it is.
    ``ph`` = P H^T (N, d, 4), ``sm`` = H P H^T + R_n (N, 4, 4), ``rn`` the fix's noise R_n, ``innov`` z - H m.
    K = P H_s^T S_s^-1; ``fixed`` (a slice of states, or None): their gain rows are zero, a Schmidt consider
    state (module docstring). Joseph form, P = (I - K H) P (I - K H)^T + K R K^T (exact for any gain: Simon,
    "Optimal State Estimation", 2006, Sec. 5.2), then symmetrized. Shared by the 6-state
    (:func:`coloc.methods.gnss_bias.bias_predict_update`) and the 8-state model."""
    d = p.shape[-1]
    for rows, sel in ((slice(0, 4), ~excluded), (slice(2, 4), excluded)):
        if not sel.any():
            continue
        hs = h[rows]
        rs = rn[sel][:, rows, rows]
        phs = ph[sel][:, :, rows]
        ss = sm[sel][:, rows, rows]
        gain = np.swapaxes(np.linalg.solve(ss, np.swapaxes(phs, -1, -2)), -1, -2)  # (U, d, k)
        if fixed is not None:
            gain[:, fixed, :] = 0.0
        m[sel] = m[sel] + np.einsum("nij,nj->ni", gain, innov[sel][:, rows])
        ikh = np.eye(d) - gain @ hs
        pu = ikh @ p[sel] @ np.swapaxes(ikh, -1, -2) + gain @ rs @ np.swapaxes(gain, -1, -2)
        p[sel] = 0.5 * (pu + np.swapaxes(pu, -1, -2))


def two_state_entry_posterior(mean: np.ndarray, cov: np.ndarray, frame, fresh: np.ndarray, r: np.ndarray,
                              model) -> np.ndarray:
    """:func:`coloc.methods.gnss_bias.entry_fix_posterior` for the 8-D states (module docstring)."""
    once = keep_entry_fix(mean, cov, frame, fresh)
    if once.any():
        rp = r[once, :2, :2]
        cov[once, :4, 4:] = 0.0
        cov[once, 4:, :4] = 0.0
        cov[once, 4:, 4:] = 0.0
        mean[once, 4:] = 0.0
        for sl, block in ((slice(4, 6), common_cov(rp, model)), (slice(6, 8), model.local_share * rp)):
            cross = -block
            cov[once, :2, sl], cov[once, sl, :2] = cross, np.swapaxes(cross, -1, -2)
            cov[once, sl, sl] = block
        if model.common_sigma_m > 0:  # the part the report does not carry: p = z - c - l - n
            cov[once, :2, :2] += model.common_sigma_m ** 2 * np.eye(2)
    return once
