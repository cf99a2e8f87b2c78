"""The linear algebra and the measurement rows of ``joint_oracle`` (:mod:`coloc.methods.joint_oracle`): the SPD
inverse, the scatter of a batch of row information into the joint information, the front-bumper slip of the
prediction, and the sensor-frame rows with the heading shared or taken from the velocity state
(docs/validation/oracle.md)."""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

from coloc.core.frame import Frame
from coloc.core.models import symmetrize
from coloc.methods.joint_oracle_world import OracleWorld

def spd_inverse(a: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix by Cholesky (LAPACK potrf / potri), symmetric."""
    if a.shape[0] == 0:
        return a.copy()
    c, info = lapack.dpotrf(a, lower=1, clean=0, overwrite_a=0)
    if info != 0:
        raise np.linalg.LinAlgError(f"joint_oracle: matrix not positive definite (potrf info {info})")
    inv, info = lapack.dpotri(c, lower=1, overwrite_c=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"joint_oracle: potri info {info}")
    low = np.tril(inv)
    return low + np.tril(inv, -1).T


def _idx(starts: np.ndarray, width: int) -> np.ndarray:
    """(len(starts), width) state indices of blocks starting at ``starts``."""
    return np.asarray(starts, dtype=np.int64)[:, None] + np.arange(width)


def _left_multiply(p: np.ndarray, nv: int, vdim: int, fv: np.ndarray, k: int, fa: np.ndarray, a_c) -> np.ndarray:
    """F p for block-diagonal F: ``fv`` (nv, vdim, vdim) vehicle blocks, ``fa`` (4, 4) every feature block,
    ``a_c`` (one per row, or a scalar) on the shared block (the rest of the rows)."""
    out = np.empty_like(p)
    cols = p.shape[1]
    nvr = nv * vdim
    if nv:
        out[:nvr] = np.einsum("nij,njc->nic", fv, p[:nvr].reshape(nv, vdim, cols)).reshape(nvr, cols)
    if k:
        out[nvr:nvr + 4 * k] = np.einsum("ij,njc->nic", fa, p[nvr:nvr + 4 * k].reshape(k, 4, cols)).reshape(4 * k, cols)
    out[nvr + 4 * k:] = np.asarray(a_c, dtype=float).reshape(-1, 1) * p[nvr + 4 * k:]
    return out


def _scatter(lam: np.ndarray, eta: np.ndarray, ind: np.ndarray, hth: np.ndarray, htz: np.ndarray) -> None:
    """lam[ind_r, ind_r] += hth[r], eta[ind_r] += htz[r] for every row-group r (duplicates add up)."""
    if ind.shape[0] == 0:
        return
    w = ind.shape[1]
    rr = np.broadcast_to(ind[:, :, None], (ind.shape[0], w, w))
    cc = np.broadcast_to(ind[:, None, :], (ind.shape[0], w, w))
    np.add.at(lam, (rr, cc), hth)
    np.add.at(eta, ind, htz)


def _information(h: np.ndarray, rinv: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """H^T R^-1 H and H^T R^-1 z for a batch: h (M, m, w), rinv (M, m, m), z (M, m)."""
    htr = np.swapaxes(h, -1, -2) @ rinv
    return htr @ h, np.einsum("nij,nj->ni", htr, z)


def _front_slip(w: OracleWorld, frame: Frame, surv: np.ndarray, v0: np.ndarray, heading, accel: np.ndarray,
                dt: float, min_speed: float, yaw_rate: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(mean (ns, 2), covariance (ns, 2, 2)) the survivors' positions move across their heading in a step besides
    model (1): the world reports the front bumper's position and the body axis as the heading (SUMO), so a
    vehicle turning at yaw rate w has its bumper moving sideways at about l w, l = ``front_lever_m`` (half the
    vehicle's length). w: the IMU's measured yaw rate, or without the IMU the rate the net-frame input turns
    the velocity at t-1, (v x a) / |v|^2 (0 below ``min_speed``). The direction: the normal of the mid-step
    heading. Residual std ``front_slip_sigma_per_rad`` |w| Ts (at most ``front_slip_sigma_max_m``) across.
    ``yaw_rate``: the IMU's rate as the oracle uses it (all vehicles; default the frame's)."""
    if frame.imu is not None:
        om = np.asarray(frame.imu.yaw_rate if yaw_rate is None else yaw_rate, dtype=float)[surv]
        psi_mid = np.asarray(heading, dtype=float)[surv] - 0.5 * om * dt
    else:
        a = np.asarray(accel, dtype=float)[surv]
        s2 = v0[:, 0] ** 2 + v0[:, 1] ** 2
        fast = s2 >= min_speed * min_speed
        om = np.where(fast, (v0[:, 0] * a[:, 1] - v0[:, 1] * a[:, 0]) / np.maximum(s2, 1e-300), 0.0)
        psi_mid = np.arctan2(v0[:, 1], v0[:, 0]) + 0.5 * om * dt
    nrm = np.stack([-np.sin(psi_mid), np.cos(psi_mid)], axis=1)
    turn = np.abs(om) * dt
    sd = np.minimum(w.front_slip_sigma_per_rad * turn, w.front_slip_sigma_max_m)
    return ((w.front_lever_m * om * dt)[:, None] * nrm,
            (sd * sd)[:, None, None] * nrm[:, :, None] * nrm[:, None, :])


def _heading_gradient(det, psi_row) -> np.ndarray:
    """(m, 4) d z / d psi of sensor-frame rows converted with heading ``psi_row``
    (:func:`coloc.core.detections.to_net_frame`): [mount u_perp(psi) + r u_perp(phi); rdot u_perp(phi)]."""
    phi = psi_row + np.asarray(det.yaw, dtype=float) + np.asarray(det.bearing, dtype=float)
    n_perp = np.stack([-np.sin(phi), np.cos(phi)], axis=1)
    g = (np.asarray(det.mount_x, dtype=float)[:, None] * np.stack([-np.sin(psi_row), np.cos(psi_row)], axis=1)
         + np.asarray(det.range, dtype=float)[:, None] * n_perp)
    return np.concatenate([g, np.asarray(det.range_rate, dtype=float)[:, None] * n_perp], axis=1)


def _heading_state_information(lam, eta, ind, det, psi_row, v_row, z, r0, range_rate: bool = True) -> None:
    """Sensor-frame rows with the heading a function of the owner's velocity state, psi = atan2(vy, vx):
    z(psi_hat) = x_F - x_V + gz (psi_hat - psi) + noise, psi - psi_hat = g_v^T (v - v_hat), g_v = [-vy, vx] / |v|^2
    at the predicted velocity, so H = [-I - gz g_v^T on v | +I] and, as g_v^T v_hat = 0, the row's z is
    unchanged; ``r0`` is the row covariance without the heading's term."""
    gz = _heading_gradient(det, psi_row)
    s2 = np.maximum(np.einsum("ni,ni->n", v_row, v_row), 1e-12)
    gv = np.stack([-v_row[:, 1], v_row[:, 0]], axis=1) / s2[:, None]
    h = np.zeros((psi_row.shape[0], 4, 8))
    h[:, :, :4] = -np.eye(4)
    h[:, :, 4:] = np.eye(4)
    h[:, :, 2:4] -= gz[:, :, None] * gv[:, None, :]
    if not range_rate:
        h, r0, z = h[:, :2], r0[:, :2, :2], z[:, :2]
    hth, htz = _information(h, symmetrize(np.linalg.inv(r0)), z)
    _scatter(lam, eta, ind, hth, htz)


def _shared_heading_information(lam, eta, ind, det, psi_row, var, own, z, r) -> None:
    """Sensor-frame rows with one heading error per vehicle and step, shared by all its rows.

    Every row of vehicle i is rotated by the same estimated heading, so its error dpsi_i ~ N(0, var_i) enters
    each row j as gz_j dpsi_i, gz_j = d z_j / d psi = [mount u_perp(psi) + r u_perp(phi); rdot u_perp(phi)]
    (:func:`coloc.core.detections.to_net_frame`, whose R_j holds var_i gz_j gz_j^T). The rows of one vehicle
    then have the joint covariance D + var_i G G^T (D block-diagonal, R_j without that term), whose inverse
    by the matrix inversion lemma is D^-1 - alpha_i (D^-1 G)(D^-1 G)^T, alpha_i = 1 / (1 / var_i + sum_j
    gz_j^T D_j^-1 gz_j): the information of the rows as independent, less one rank-one term per vehicle.
    H_j = [-I (vehicle) | +I (feature)] as model (4)."""
    phi = psi_row + np.asarray(det.yaw, dtype=float) + np.asarray(det.bearing, dtype=float)
    n_perp = np.stack([-np.sin(phi), np.cos(phi)], axis=1)
    mount = np.asarray(det.mount_x, dtype=float)
    rr = np.asarray(det.range, dtype=float)
    g = mount[:, None] * np.stack([-np.sin(psi_row), np.cos(psi_row)], axis=1) + rr[:, None] * n_perp
    gz = np.concatenate([g, np.asarray(det.range_rate, dtype=float)[:, None] * n_perp], axis=1)  # (m, 4)
    v_row = var[own]
    d_rows = symmetrize(r - v_row[:, None, None] * gz[:, :, None] * gz[:, None, :])
    dinv = symmetrize(np.linalg.inv(d_rows))
    h = np.zeros((own.size, 4, 8))
    h[:, :, :4] = -np.eye(4)
    h[:, :, 4:] = np.eye(4)
    hth, htz = _information(h, dinv, z)
    _scatter(lam, eta, ind, hth, htz)
    a = np.einsum("nij,nj->ni", dinv, gz)  # D_j^-1 gz_j
    u = np.concatenate([-a, a], axis=1)  # H_j^T D_j^-1 gz_j on ind_j
    c = np.einsum("ni,ni->n", gz, a)
    e = np.einsum("ni,ni->n", a, z)
    nv = var.shape[0]
    csum = np.bincount(own, weights=c, minlength=nv)
    esum = np.bincount(own, weights=e, minlength=nv)
    alpha = 1.0 / (1.0 / np.maximum(var, 1e-300) + csum)
    # every ordered pair (j, j') of rows of one vehicle: - alpha_i u_j u_j'^T on (ind_j, ind_j')
    order = np.argsort(own, kind="stable")
    counts = np.bincount(own, minlength=nv)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    m_row = counts[own[order]]
    left = np.repeat(order, m_row)
    offs = np.arange(left.size) - np.repeat(np.cumsum(m_row) - m_row, m_row)
    right = order[starts[own[order]].repeat(m_row) + offs]
    wgt = alpha[own[left]]
    blk = -wgt[:, None, None] * u[left][:, :, None] * u[right][:, None, :]
    np.add.at(lam, (ind[left][:, :, None], ind[right][:, None, :]), blk)
    np.add.at(eta, ind, -(alpha * esum)[own][:, None] * u)


def _positions(ids: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Position of each of ``wanted`` in ``ids`` (all present)."""
    order = np.argsort(ids, kind="stable")
    return order[np.searchsorted(ids[order], wanted)]


def _course_information(lam, eta, mean_lin, n, vd, ho, sigma) -> None:
    """The velocity along the heading: 0 = u_perp(psi)^T v + noise (std ``sigma``) for every vehicle, linearized at
    ``mean_lin`` (psi_hat, v_hat): H = [-sin psi_hat, cos psi_hat on v | -u(psi_hat)^T v_hat on psi],
    z = H x_hat - u_perp(psi_hat)^T v_hat = -(u(psi_hat)^T v_hat) psi_hat."""
    blk = mean_lin[:vd * n].reshape(n, vd)
    psi = blk[:, ho]
    c, s = np.cos(psi), np.sin(psi)
    along = c * blk[:, 2] + s * blk[:, 3]
    h = np.stack([-s, c, -along], axis=1)  # (n, 3)
    z = -along * psi
    ind = vd * np.arange(n)[:, None] + np.array([2, 3, ho])
    w = 1.0 / (sigma * sigma)
    _scatter(lam, eta, ind, w * h[:, :, None] * h[:, None, :], (w * z)[:, None] * h)


def _heading_linearization(w: OracleWorld, p_pred: np.ndarray, xv: np.ndarray, surv: np.ndarray, fresh: np.ndarray,
                           zg: np.ndarray, rg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the heading state is linearized, and whose sensor-frame rows stay out (``heading_row_max_std_deg``).

    The constraint and the rows are linear in the heading only near the linearization point: a vehicle that entered
    standing (its fix's course is noise) or stopped since has a heading known to tens of degrees, and rows
    linearized there put wrong information into the map. Returns (psi_lin (N,), NaN where the predicted mean is
    kept; out (N,) bool, rows left out). The linearization point's std: the predicted heading's (survivors), the
    fix's course, g R_v g^T (fresh vehicles, whose mean is that course). A survivor whose predicted heading is
    wider than the gate but whose predicted velocity's direction is narrower is linearized at that direction
    (an EKF may linearize anywhere; the prior mean is unchanged). Rows of a vehicle whose linearization point is
    wider than the gate are left out."""
    from coloc.core.detections import heading_from_velocity

    n = fresh.size
    ho, vd = w.heading_offset, w.vehicle_dim
    gate = np.radians(w.heading_row_max_std_deg) ** 2
    psi_lin = np.full(n, np.nan)
    var = np.empty(n)
    fr = np.flatnonzero(fresh)
    if fr.size:
        var[fr] = heading_from_velocity(zg[fr, 2:4], rg[fr, 2:, 2:])[1]
    if surv.size:
        ii = vd * np.arange(surv.size)
        var_psi = p_pred[ii + ho, ii + ho]
        vv = _idx(ii + 2, 2)
        dirn, var_dir = heading_from_velocity(xv[:, 2:4], p_pred[vv[:, :, None], vv[:, None, :]])
        relin = (var_psi > gate) & (var_dir < var_psi)
        psi_lin[surv[relin]] = dirn[relin]
        var[surv] = np.where(relin, var_dir, var_psi)
    return psi_lin, var > gate


def _field_read_share(w: OracleWorld, p_pred: np.ndarray, surv: np.ndarray, sig: np.ndarray, common_share: float,
                      ) -> np.ndarray:
    """(N,) the fix's extra white variance, as a share of sigma_i^2, for reading the field at the predicted position
    rather than the true one (``field_read_noise``): the world's field has an exponential correlation, so it is not
    smooth and its increment over a distance r has variance 2 (1 - exp(-r / L)) (unit field; on the world's random
    Fourier features, 64 frequencies, L = 50 m: 0.074 at 2 m, 0.13 at 3 m, against 0.078, 0.116), not of the
    gradient's r^2 order. In the fix it is scaled by (1 - s) f; r is the predicted position's RMS error,
    sqrt(trace P_pp) (survivors), or the fix's own, sqrt(2) sigma_i (an entering vehicle is linearized at its fix)."""
    vd = w.vehicle_dim
    r = np.sqrt(2.0) * np.asarray(sig, dtype=float)
    if surv.size:
        ii = vd * np.arange(surv.size)
        r[surv] = np.sqrt(np.maximum(p_pred[ii, ii] + p_pred[ii + 1, ii + 1], 0.0))
    return (1.0 - common_share) * w.field_share * 2.0 * (1.0 - np.exp(-r / w.field_corr_length_m))
