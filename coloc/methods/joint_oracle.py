"""``joint_oracle``: a centralized joint filter told the true association and the world's error structure.

An explicitly labelled **oracle** (docs/validation/oracle.md): the reference the cooperative methods are
drawn against. It is the one estimator allowed to read the world's configuration (``[gnss_error]``,
``[scenario] start``; the runner turns them into :class:`OracleWorld`); it never reads truth positions
or headings. It is told, like ``icp_known_da``, the true feature of every V2F row (the runner passes
``truth.v2f_feature``; clutter and other road users carry -1 and are left out).

State (one joint Gaussian, covariance form between steps), extending :mod:`coloc.methods.centralized`:

* per vehicle (frame order) ``[px, py, vx, vy]`` of model (1), and with a correlated GNSS world a unit
  error state ``u`` (2, per axis) for the receiver's local error (below);
* per feature (sorted ids) ``[px, py, vx, vy]`` of model (2);
* with ``common_share > 0``, one unit common-mode state ``c`` (2) shared by every receiver.

GNSS (world ``couplers/sensing/gnss_error.py``): per axis the world's position error is
``sigma_p(zone) (sqrt(s) c + sqrt(1 - s) (sqrt(f) F(p_i) + sqrt(1 - f) u_i)) + b_nlos``. The oracle's
fix model is ``z_pos = p_i + sigma_i (sqrt(s) c + sqrt(1 - s) l_i) + n`` with ``sigma_i`` the reported
position std (``frame.gnss_R``: the zone's sigma_p, so the zone rescaling of the world is exact) and:

* ``c``: the common Gauss-Markov process, ``a_c = exp(-Ts / common_tau_s)`` (exact);
* field: with the world's field frequencies given (``OracleWorld.field_omega``, the runner copies the world's
  draw), F(p_i) = phi(p_i)^T theta with theta the 4 M unit Gauss-Markov coefficients (``field_tau_s``) as
  shared states, phi the random Fourier basis at the vehicle's predicted position (linearized: the field's
  gradient times the position error is left out; 5 m against a 50 m correlation length), and ``l_i`` the
  receiver's own part u_i alone, a_l = exp(-d / L_local - Ts / tau_s) (exact up to that linearization);
* ``l_i`` without ``field_omega``: the vehicle's local unit process, standing for the field part F(p_i) and the
  receiver's own part u_i together. **Approximation**: the field is shared by vehicles within tens of metres; the
  oracle treats each vehicle's field part as its own (no cross-vehicle correlation) and merges the two
  parts into one Gauss-Markov state whose one-step correlation is the world's,
  ``a_l = f exp(-d / L_field - Ts / tau_field) + (1 - f) exp(-d / L_local - Ts / tau_s)`` with ``d`` the
  distance the vehicle moved in the step **as the oracle estimates it** (|v| Ts of its previous
  posterior). The "per_vehicle" world is the case s = f = 0, L_local = inf (exact);
* ``n``: white, variance ``fix_noise_share`` sigma_i^2 (1e-4: 1 % of the std). The world has no white
  position noise; this regularizes the information form and is negligible;
* velocity ``z_vel = v_i + n_v``, the reported velocity block (the world's white Doppler error, exact);
* NLOS episodes (bias of uniform direction, exponential magnitude, random start and length) are not
  structure an estimator can know in advance: a fix whose position innovation on the predicted state
  has ``nu^T S^-1 nu`` above the chi-square quantile of 2 dof at ``gate_level`` is left out (its
  velocity kept), as in ``coloc.methods.gnss_bias``; after ``max_exclusions`` in a row the next fix is
  taken.
* "white" world (no ``[gnss_error]``): no error states, ``R = gnss_R`` as in the centralized KF.

Entering vehicles: a prior that is the step's own fix (``Frame.prior_has_fix``, the entry protocol of
:func:`coloc.core.vehicles.entry_fix_rows`) -> zero prior information on the kinematics (the fix is used
once, in the update); else the frame's prior (``prior_z``, ``prior_R``). Their ``l`` starts stationary, N(0, I), independent.

Sensor rows: net-frame rows (``v2f_z``, ``v2f_R``) as model (4), H = [-I (vehicle) | +I (feature)], with
the frame's row covariance (the world's sensor noise). Sensor-frame rows (``frame.v2f_sensor``: range,
bearing, range rate with the world's sigmas) are converted by :func:`coloc.core.detections.to_net_frame`
with the oracle's heading, the direction of its predicted velocity at t with variance g P_vv g^T from its
joint covariance (:func:`coloc.core.detections.vehicle_headings`; the world's heading is the direction of
the velocity, couplers/traffic/sumo.py). One heading error per vehicle and step is shared by all its rows:
they enter with their joint covariance (``shared_heading``, :func:`_shared_heading_information`), not as
independent rows; ``heading_from_state`` instead makes the heading the direction of the velocity state
(EKF, :func:`_heading_state_information`), so its error is carried across steps. Rows of a vehicle below ``heading_min_speed`` are left out: the
heading a stopped vehicle keeps has the same error at every step of its stop, and counting its rows
again at each step made the landmark map overconfident (docs/validation/oracle.md). An EKF taking the
heading as a function of the velocity state was tried and did worse on the realistic arterial (same page).
With ``heading_state`` (and the gyroscope's model told, ``[inertial]``) the heading psi and the gyroscope's bias b_g
are states of every vehicle instead: psi_t = psi_{t-1} + (r - b_g) Ts + white (density^2 Ts), b_g a random walk of
the drift's one-step variance, prior N(0, turn_on^2 + drift^2); the velocity is held along the heading by
0 = u_perp(psi)^T v + n (std ``course_sigma_mps``, :func:`_course_information`; the world's velocity is the speed
along the body axis); the sensor-frame rows are converted with the predicted psi and linearized in it
(H = [-I | +I | -dz/dpsi]), rows of slow vehicles kept (the heading's error across a stop is the state's); the IMU
input is rotated by psi_{t-1} + (r - b_g) Ts / 2 and linearized in psi and b_g. An entering vehicle's heading
starts unknown (pi^2 / 3) about its fix's course. ``heading_row_max_std_deg`` (opt-in) leaves out the sensor-frame
rows of a vehicle whose heading is too uncertain to linearize at, and ``field_read_noise`` (opt-in) gives each fix
the field's increment between the predicted and the true position as white noise (docs/validation/oracle.md).

Inertial input (``[inertial]``, couplers/sensing/inertial.py): the body-frame acceleration rotated by the
oracle's heading at t-1 (its velocity's direction, or while slow the heading the rows keep, held rather
than dead-reckoned by the biased gyroscope) plus half the step's measured yaw rate. The accelerometer
bias is a state per vehicle (body frame, 2): prior N(0, turn_on^2 + drift^2) when the vehicle enters;
each step b_k = b_{k-1} + w, Var(w) = (1 - a^2) drift^2, a = exp(-Ts / tau) (**approximation**: the
world's turn-on part is constant and its drift Gauss-Markov; the oracle's random walk has the drift's
one-step variance and grows by about one drift variance per tau). The accelerometer's white noise
(density^2 / Ts) and the heading's error (|a|^2 var(psi) across the input) add to model (1)'s driving
noise from ``[motion]``; the gyroscope's biases are not states. With ``imu_heading_from_state`` (default) a
vehicle whose heading at t-1 is its velocity's direction has the input's dependence on that velocity in the
transition instead (EKF, g_v^T v_hat = 0 so the mean is unchanged) and no heading term in Q.

World kinematics (``front_lever_m`` > 0; the runner sets it for SUMO traffic): the world's position is the front
bumper and its heading the body axis, so a turning vehicle's bumper moves across the heading at about
``front_lever_m`` times the yaw rate; :func:`_front_slip` adds that to the position prediction with a residual
in Q (docs/validation/oracle.md, "Kinematics of the world").

Satellite world (``gnss = "satellites"``, couplers/sensing/gnss_satellites.py): the frame's ``oracle_gnss`` gives each
receiver's WLS gain K_i over the constellation, its satellites and which came by reflection. Shared states: per
satellite its clock/orbit and vertical ionospheric errors, and the net's zenith troposphere (2 S + 1 unit
Gauss-Markov states, ``sv_tau_s``); the vehicle's error state l_i is its fix's multipath part in metres (Gauss-Markov
over the distance travelled, stationary covariance K_i diag((m / sin el)^2) K_i^T). Fix: z_i = p_i + l_i + K_i A(el)
c + v_i, Var(v_i) = K_i diag(code noise + a reflected signal's extra-path variance) K_i^T, z less K_i times the extra
paths' mean (:func:`_satellite_information`; no NLOS gate: the reflected signals are told). Velocity: v_i +
K_v,i (Doppler noise + a reflected signal's path rate).

Fix-level satellite world (``gnss = "fix"``, ``[oracle] gnss_channel = "fix"``): no ``oracle_gnss``; the oracle
sees the fixes, their reported covariance and velocity as every method does and is told the world's fix-level error
structure (:class:`OracleWorld`, "fix"): z_i = p_i + l_i + sigma_c c + n, c one unit 2-D common state, l_i + n the
local error in metres (covariance C_i: the report calibrated; n its white share ``fix_noise_share``, l_i the rest,
Gauss-Markov over the distance travelled and time), the NLOS gate as above.

Features unseen for ``feature_keep_s`` are marginalized (dropped). Cost: two Cholesky inversions of the
joint information and covariance (dimension (4 + 2 + 2) N + 4 K + 2 + 4 M with every option) per step, O(d^3);
the rest O(d^2) (the fixes' information is dense over the field states: O(N d^2) with a small constant).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from coloc.core.detections import HeadingMemory, to_net_frame, vehicle_headings
from coloc.core.frame import Frame, StepEstimate
from coloc.core.inertial import wrap_angle
from coloc.core.models import driving_noise_cov, input_matrix, symmetrize, transition_matrix
from coloc.core.vehicle_rows import expand_rows, without_vehicle_rows
from coloc.core.vehicles import entry_fix_rows, match_ids
from coloc.inference.bpa import validate_association
from coloc.inference.feature_store import feature_track_q
from coloc.inference.params import IcpParams
from coloc.methods.joint_oracle_rows import (  # noqa: F401  (_front_slip .. _information: imported from here by tests)
    _course_information,
    _field_read_share,
    _front_slip,
    _heading_gradient,
    _heading_linearization,
    _heading_state_information,
    _idx,
    _information,
    _left_multiply,
    _positions,
    _scatter,
    _shared_heading_information,
    spd_inverse,
)
from coloc.methods.joint_oracle_world import GNSS_WORLDS, OracleWorld  # noqa: F401
from coloc.methods.registry import JOINT_ORACLE

__all__ = ["OracleWorld", "JointOracle", "OracleState", "spd_inverse"]


@dataclass(frozen=True)
class OracleState:
    """Joint Gaussian: vehicles (blocks of ``vehicle_dim``, frame order), features (4, sorted ids), common."""

    vehicle_ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=object))
    feature_ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    feature_last_seen: np.ndarray = field(default_factory=lambda: np.empty(0))
    mean: np.ndarray | None = None  # None: not started (the common state is set at the first step)
    cov: np.ndarray | None = None
    heading: np.ndarray | None = None  # [inertial]: kept heading per vehicle row
    sensor_heading: HeadingMemory | None = None
    streak: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    v_first: np.ndarray | None = None  # (N, 2) each vehicle's velocity as first estimated (predicted) at its step


@dataclass
class JointOracle:
    """The oracle (module docstring): a :class:`coloc.core.protocol.KnownAssociationEstimator`."""

    params: IcpParams = field(default_factory=IcpParams)
    world: OracleWorld = field(default_factory=OracleWorld)
    name: str = JOINT_ORACLE.name
    state: OracleState = field(default_factory=OracleState)
    last_excluded: np.ndarray | None = None  # (N,) fixes left out by the NLOS gate this step
    last_dim: int = 0  # the joint dimension of the last step

    def step_with_association(self, frame: Frame, v2f_feature: np.ndarray) -> StepEstimate:
        n_rows = frame.v2f_z.shape[0]
        frame, kept = without_vehicle_rows(frame)
        assoc = np.asarray(v2f_feature)[kept] if kept is not None else np.asarray(v2f_feature)
        assoc = validate_association(frame.v2f_owner, assoc, frame.v2f_z.shape[0])
        self.state = self._step(self.state, frame, assoc)
        s, w = self.state, self.world
        n, vd = s.vehicle_ids.shape[0], w.vehicle_dim
        vi = _idx(vd * np.arange(n), 4)
        fi = _idx(vd * n + 4 * np.arange(s.feature_ids.size), 4)
        cov = s.cov
        return StepEstimate(
            mean=s.mean[vi].copy(), cov=cov[vi[:, :, None], vi[:, None, :]].copy(),
            feature_mean=s.mean[fi].copy(), feature_cov=cov[fi[:, :, None], fi[:, None, :]].copy(),
            feature_track_ids=s.feature_ids.copy(),
            v2f_assignment=expand_rows(assoc.astype(np.int64), kept, n_rows) if kept is not None
            else assoc.astype(np.int64).copy(),
        )

    # --- one step -------------------------------------------------------------------------------------

    def _step(self, st: OracleState, frame: Frame, assoc: np.ndarray) -> OracleState:
        w, p_icp = self.world, self.params
        vd, cd = w.vehicle_dim, w.tail_dim  # cd: every shared state (common, field)
        dt = float(frame.dt)
        n_prev = st.vehicle_ids.shape[0]
        k_prev = st.feature_ids.size
        if st.mean is None:  # first step: the common state starts stationary
            st = OracleState(mean=np.zeros(cd), cov=np.eye(cd))
            n_prev, k_prev = 0, 0
        idx = match_ids(st.vehicle_ids, frame.vehicle_ids)
        fresh = (idx < 0) | np.asarray(frame.entered, dtype=bool)
        idx_c = np.where(fresh, -1, idx)
        yaw = None  # the yaw rate the prediction uses: the gyroscope's, less the bias state's mean (heading_state)
        if frame.imu is None:
            accel, heading = np.asarray(frame.accel, dtype=float), None
        else:
            accel, heading, psi_var, yaw = self._imu_input(frame, idx, fresh, st)

        # --- predict survivors, old features and the common state (block-diagonal F, Q).
        surv = np.flatnonzero(~fresh)
        sp = idx[surv]
        keep = np.concatenate([_idx(vd * sp, vd).ravel(), vd * n_prev + np.arange(4 * k_prev + cd)]).astype(np.int64)
        x = st.mean[keep]
        p = st.cov[np.ix_(keep, keep)]
        ns = surv.size
        a4 = transition_matrix(dt)
        xv = x[:vd * ns].reshape(ns, vd)
        fv_mean = None
        fv = np.zeros((ns, vd, vd))
        fv[:, :4, :4] = a4
        qv = np.zeros((ns, vd, vd))
        qv[:, :4, :4] = driving_noise_cov(xv[:, 2:4], dt, p_icp.motion)
        if w.gnss == "satellites":
            # the receiver's multipath in metres: Gauss-Markov over the distance travelled (the oracle's |v| Ts),
            # stationary covariance K diag((m / sin el)^2) K^T of this step's gain
            a_l = np.exp(-np.hypot(xv[:, 2], xv[:, 3]) * dt / w.multipath_corr_length_m) if w.multipath_state \
                else np.zeros(ns)
            fv[:, 4, 4] = fv[:, 5, 5] = a_l
            qv[:, 4:6, 4:6] = (1.0 - a_l * a_l)[:, None, None] * _multipath_cov(w, frame)[surv]
        elif w.gnss == "fix":  # the local error in metres, stationary covariance from this step's report
            a_l = w.local_coefficient(np.hypot(xv[:, 2], xv[:, 3]) * dt, dt)
            fv[:, 4, 4] = fv[:, 5, 5] = a_l
            qv[:, 4:6, 4:6] = ((1.0 - a_l * a_l) * (1.0 - w.fix_noise_share))[:, None, None] * \
                w.fix_local_cov(frame.gnss_R)[surv]
        elif w.correlated:
            a_l = w.local_coefficient(np.hypot(xv[:, 2], xv[:, 3]) * dt, dt)
            fv[:, 4, 4] = fv[:, 5, 5] = a_l
            qv[:, 4, 4] = qv[:, 5, 5] = 1.0 - a_l * a_l
        if w.imu:
            # accelerometer bias b (body frame): a_net = R(psi_mid) (a_body - b), psi_mid the heading the input
            # was rotated by; b constant (turn-on) plus a drift whose increments are taken as a random walk of
            # the drift's one-step variance (module docstring).
            bo = w.bias_offset
            fv[:, bo, bo] = fv[:, bo + 1, bo + 1] = 1.0
            if frame.imu is not None:  # a frame without the IMU leaves the bias out of the input
                r = yaw[surv]
                psi_mid = wrap_angle(np.asarray(heading, dtype=float)[surv] - 0.5 * r * dt)
                c, s_ = np.cos(psi_mid), np.sin(psi_mid)
                rot = np.stack([np.stack([c, -s_], -1), np.stack([s_, c], -1)], -2)  # (ns, 2, 2)
                fv[:, 0:2, bo:bo + 2] = -0.5 * dt * dt * rot
                fv[:, 2:4, bo:bo + 2] = -dt * rot
            a_b = math.exp(-dt / w.accel_bias_tau_s)
            qv[:, bo, bo] = qv[:, bo + 1, bo + 1] = (1.0 - a_b * a_b) * w.accel_bias_sigma ** 2
            bm = input_matrix(dt)
            qv[:, :4, :4] += (w.accel_noise_density ** 2 / dt) * (bm @ bm.T)
        if frame.imu is not None:
            # the input rotated by a heading of variance psi_var: an error |a| dpsi across it (first order)
            ab = np.asarray(frame.imu.accel_body, dtype=float)[surv]
            amag2 = ab[:, 0] ** 2 + ab[:, 1] ** 2
            hh = wrap_angle(np.asarray(heading, dtype=float)[surv]
                            - 0.5 * yaw[surv] * dt)  # psi_mid
            u = np.stack([-np.sin(hh), np.cos(hh)], axis=1)
            bu = np.einsum("ij,nj->ni", input_matrix(dt), u)  # (ns, 4)
            pvar = psi_var[surv]
            if w.imu_heading_from_state:
                # a_net = Rot(psi(v) + r Ts / 2) a_body with psi(v) = atan2(vy, vx) of the velocity at t-1: the
                # transition gets B d a_net / d psi g_v^T on that velocity (g_v = [-vy, vx] / |v|^2; g_v^T v = 0,
                # so the predicted mean is unchanged); the heading's variance leaves Q for those vehicles.
                fast = self._imu_fast[surv]
                v0 = xv[:, 2:4]
                ang = np.asarray(heading, dtype=float)[surv] - 0.5 * yaw[surv] * dt
                if w.first_estimate_jacobians and st.v_first is not None:
                    # FEJ: the Jacobian at the velocity the rows of t-1 were linearized at (mean: the posterior)
                    v0 = st.v_first[sp]
                    ang = ang - np.arctan2(xv[:, 3], xv[:, 2]) + np.arctan2(v0[:, 1], v0[:, 0])
                s2 = np.maximum(v0[:, 0] ** 2 + v0[:, 1] ** 2, 1e-12)
                gv = np.stack([-v0[:, 1], v0[:, 0]], axis=1) / s2[:, None]
                c2, s2_ = np.cos(ang), np.sin(ang)
                da = np.stack([-s2_ * ab[:, 0] - c2 * ab[:, 1], c2 * ab[:, 0] - s2_ * ab[:, 1]], axis=1)
                jac = np.einsum("ij,nj->ni", input_matrix(dt), da)[:, :, None] * gv[:, None, :]  # (ns, 4, 2)
                fv[fast, 0:4, 2:4] += jac[fast]
                if w.first_estimate_jacobians:  # g_v^T v_hat != 0 at another point: the mean without the Jacobian
                    fv_mean = fv.copy()
                    fv_mean[fast, 0:4, 2:4] -= jac[fast]
                pvar = np.where(fast, 0.0, pvar)
            qv[:, :4, :4] += (amag2 * pvar)[:, None, None] * bu[:, :, None] * bu[:, None, :]
        if w.heading_dim:
            # heading psi and gyroscope bias b_g: psi_t = psi_{t-1} + (r - b_g) Ts + white (density^2 Ts), b_g a
            # random walk of the drift's one-step variance; the input a_net = Rot(psi_{t-1} + (r - b_g) Ts / 2) a_body
            # (the world's psi_mid, couplers/sensing/inertial.py) linearized in psi and b_g (its mean: the state's).
            ho = w.heading_offset
            fv[:, ho, ho] = fv[:, ho + 1, ho + 1] = 1.0
            a_g = math.exp(-dt / w.gyro_bias_tau_s)
            qv[:, ho + 1, ho + 1] = (1.0 - a_g * a_g) * math.radians(w.gyro_bias_sigma) ** 2
            if frame.imu is not None:
                fv[:, ho, ho + 1] = -dt
                qv[:, ho, ho] = math.radians(w.gyro_noise_density) ** 2 * dt
                ab = np.asarray(frame.imu.accel_body, dtype=float)[surv]
                ang = np.asarray(heading, dtype=float)[surv] - 0.5 * yaw[surv] * dt
                c2, s2_ = np.cos(ang), np.sin(ang)
                da = np.stack([-s2_ * ab[:, 0] - c2 * ab[:, 1], c2 * ab[:, 0] - s2_ * ab[:, 1]], axis=1)
                jac = np.einsum("ij,nj->ni", input_matrix(dt), da)  # (ns, 4) d x / d psi_mid
                fv_mean = fv.copy()  # the mean: the input at the state's mean (above), not through the Jacobian
                fv[:, 0:4, ho] = jac
                fv[:, 0:4, ho + 1] = -0.5 * dt * jac
        a_c = w.tail_coefficients(dt)
        xf = x[vd * ns:vd * ns + 4 * k_prev].reshape(k_prev, 4)
        p = _left_multiply(p, ns, vd, fv, k_prev, a4, a_c)
        p = _left_multiply(np.ascontiguousarray(p.T), ns, vd, fv, k_prev, a4, a_c)
        xv = np.einsum("nij,nj->ni", fv if fv_mean is None else fv_mean, xv)
        xv[:, :4] += accel[surv] @ input_matrix(dt).T
        if w.heading_dim and frame.imu is not None:
            xv[:, w.heading_offset] += np.asarray(frame.imu.yaw_rate, dtype=float)[surv] * dt
        if w.front_lever_m > 0 and ns:
            slip, q_slip = _front_slip(w, frame, surv, x[:vd * ns].reshape(ns, vd)[:, 2:4], heading, accel, dt,
                                       p_icp.motion.heading_min_speed, yaw)
            xv[:, :2] += slip
            qv[:, :2, :2] += q_slip
        xf = xf @ a4.T
        xc = a_c * x[vd * ns + 4 * k_prev:]
        pv = p[:vd * ns, :vd * ns].reshape(ns, vd, ns, vd)
        pv[np.arange(ns), :, np.arange(ns), :] += qv
        if k_prev:
            qf = feature_track_q(xf, dt, p_icp)
            pf = p[vd * ns:vd * ns + 4 * k_prev, vd * ns:vd * ns + 4 * k_prev].reshape(k_prev, 4, k_prev, 4)
            pf[np.arange(k_prev), :, np.arange(k_prev), :] += qf
        if cd:
            cc = np.arange(p.shape[0] - cd, p.shape[0])
            p[cc, cc] += 1.0 - a_c * a_c
        p = symmetrize(p)

        # Sensor-frame rows of a vehicle below heading_min_speed (predicted speed; fresh: its fix's) are left
        # out: the heading it keeps while slow has the same error at every step of a stop, and counting its rows
        # again each step made the map overconfident (docs/validation/oracle.md).
        n = frame.n_vehicles
        zg = np.asarray(frame.gnss_z, dtype=float)
        if frame.v2f_sensor is not None and assoc.size and not w.heading_dim:
            speed = np.hypot(zg[:, 2], zg[:, 3])
            speed[surv] = np.hypot(xv[:, 2], xv[:, 3])
            slow = speed < p_icp.motion.heading_min_speed
            assoc = np.where(slow[np.asarray(frame.v2f_owner, dtype=np.int64)], -1, assoc)
        psi_lin = None  # heading_state: where the heading is linearized, when not at its predicted mean
        if w.heading_dim and n and math.isfinite(w.heading_row_max_std_deg):
            psi_lin, row_out = _heading_linearization(w, p, xv, surv, fresh, zg, np.asarray(frame.gnss_R, dtype=float))
            if frame.v2f_sensor is not None and assoc.size:
                assoc = np.where(row_out[np.asarray(frame.v2f_owner, dtype=np.int64)], -1, assoc)

        # --- layout after the update: vehicles (frame order), old features, new features, common.
        used = assoc >= 0
        seen = np.unique(assoc[used])
        new_ids = np.setdiff1d(seen, st.feature_ids)
        fids = np.concatenate([st.feature_ids, new_ids]).astype(np.int64)
        k = fids.size
        d = vd * n + 4 * k + cd
        c0 = vd * n + 4 * k  # first index of the common state
        # predicted means in the new layout (fresh vehicles: filled below, only as linearization points)
        mean_pred = np.zeros(d)
        mean_pred[:vd * n].reshape(n, vd)[surv] = xv
        mean_pred[vd * n:vd * n + 4 * k_prev] = xf.ravel()
        mean_pred[c0:] = xc
        pos_keep = np.concatenate([_idx(vd * surv, vd).ravel(), vd * n + np.arange(4 * k_prev), c0 + np.arange(cd)])
        pos_keep = pos_keep.astype(np.int64)
        # predicted covariance blocks needed by the gate and the headings, in the new layout
        rg = np.asarray(frame.gnss_R, dtype=float)
        sig = np.sqrt(rg[:, 0, 0]) if n else np.empty(0)

        lam = np.zeros((d, d))
        eta = np.zeros(d)
        if pos_keep.size:
            li = spd_inverse(p)
            lam[np.ix_(pos_keep, pos_keep)] = li
            eta[pos_keep] = li @ mean_pred[pos_keep]
        fr = np.flatnonzero(fresh)
        if fr.size:
            pr = fr[~entry_fix_rows(frame, fresh)[fr]]  # a prior that is the step's fix is not counted twice
            if pr.size:
                prior_z = np.asarray(frame.prior_z, dtype=float)[pr]
                lp = np.linalg.inv(np.asarray(frame.prior_R, dtype=float)[pr])
                ind = _idx(vd * pr, 4)
                _scatter(lam, eta, ind, symmetrize(lp), np.einsum("nij,nj->ni", lp, prior_z))
            if w.gnss == "satellites":  # the multipath state starts stationary
                ind = _idx(vd * fr + 4, 2)
                _scatter(lam, eta, ind, symmetrize(np.linalg.inv(_multipath_cov(w, frame)[fr])), np.zeros((fr.size, 2)))
            elif w.gnss == "fix":  # the local error starts stationary
                ind = _idx(vd * fr + 4, 2)
                lc = (1.0 - w.fix_noise_share) * w.fix_local_cov(rg)[fr]
                _scatter(lam, eta, ind, symmetrize(np.linalg.inv(lc)), np.zeros((fr.size, 2)))
            elif w.correlated:  # the local error state starts stationary
                ind = _idx(vd * fr + 4, 2)
                _scatter(lam, eta, ind, np.broadcast_to(np.eye(2), (fr.size, 2, 2)), np.zeros((fr.size, 2)))
            if w.imu:  # the bias of an IMU just switched on: turn-on plus stationary drift
                ind = _idx(vd * fr + w.bias_offset, 2)
                ib = np.eye(2) / (w.accel_turn_on_sigma ** 2 + w.accel_bias_sigma ** 2)
                _scatter(lam, eta, ind, np.broadcast_to(ib, (fr.size, 2, 2)), np.zeros((fr.size, 2)))
            # linearization points of fresh vehicles: their fix
            mean_pred[:vd * n].reshape(n, vd)[fr, :4] = zg[fr]
            if w.heading_dim:  # heading: unknown (pi^2 / 3), about the fix's course; the gyroscope's bias switched on
                from coloc.core.detections import HEADING_VAR_UNKNOWN

                ho = w.heading_offset
                psi0 = np.arctan2(zg[fr, 3], zg[fr, 2])
                mean_pred[:vd * n].reshape(n, vd)[fr, ho] = psi0
                ib = 1.0 / (math.radians(w.gyro_turn_on_sigma) ** 2 + math.radians(w.gyro_bias_sigma) ** 2)
                ih = np.zeros((fr.size, 2, 2))
                ih[:, 0, 0], ih[:, 1, 1] = 1.0 / HEADING_VAR_UNKNOWN, ib
                _scatter(lam, eta, _idx(vd * fr + ho, 2), ih,
                         np.stack([psi0 / HEADING_VAR_UNKNOWN, np.zeros(fr.size)], axis=1))
        if new_ids.size and p_icp.feature_velocity_prior_sigma:
            ind = _idx(vd * n + 4 * np.arange(k_prev, k) + 2, 2)
            iv = np.eye(2) / p_icp.feature_velocity_prior_sigma ** 2
            _scatter(lam, eta, ind, np.broadcast_to(iv, (new_ids.size, 2, 2)), np.zeros((new_ids.size, 2)))

        # --- GNSS (3) with the error states; the NLOS gate on the predicted state.
        excluded = np.zeros(n, dtype=bool)
        streak = np.zeros(n, dtype=np.int64)
        if n:
            have = idx_c >= 0
            streak[have] = st.streak[idx_c[have]] if st.streak.size else 0
            excluded = self._gnss_information(lam, eta, p, frame, fresh, surv, mean_pred, sig, zg, rg, streak)
        self.last_excluded = excluded
        lin = mean_pred  # the linearization point of the constraint and the sensor-frame rows
        if psi_lin is not None:
            lin = mean_pred.copy()
            lin[vd * np.arange(n) + w.heading_offset] = np.where(np.isfinite(psi_lin), psi_lin,
                                                                 mean_pred[vd * np.arange(n) + w.heading_offset])
        if w.heading_dim and n:
            _course_information(lam, eta, lin, n, vd, w.heading_offset, w.course_sigma_mps)

        # --- V2F (4) rows with the true association.
        iterate = w.heading_iterations > 0 and frame.v2f_sensor is not None and w.heading_from_state
        if iterate:
            lam0, eta0 = lam.copy(), eta.copy()
        sensor_heading = self._v2f_information(lam, eta, frame, assoc, fids, idx_c, lin, p, surv, st)

        lam = symmetrize(lam)
        cov = spd_inverse(lam)
        mean = cov @ eta
        for _ in range(w.heading_iterations if iterate else 0):
            # iterated EKF (Gauss-Newton on the rows): the sensor-frame rows relinearized at the posterior velocity;
            # z = C(psi(v_i)) with H at v_i is the Gauss-Newton step of 0 = x_F - x_V - C(psi(v)) (g_v^T v_i = 0)
            lin = mean_pred.copy()
            vi = _idx(vd * np.arange(n) + 2, 2)
            lin[vi] = mean[vi]
            lam, eta = lam0.copy(), eta0.copy()
            self._v2f_information(lam, eta, frame, assoc, fids, idx_c, lin, p, surv, st)
            lam = symmetrize(lam)
            cov = spd_inverse(lam)
            mean = cov @ eta
        last_seen = np.concatenate([st.feature_last_seen, np.full(new_ids.size, float(frame.t))])
        if seen.size:
            last_seen[_positions(fids, seen)] = float(frame.t)
        keep_f = np.flatnonzero((frame.t - last_seen) <= w.feature_keep_s)
        keep_f = keep_f[np.argsort(fids[keep_f], kind="stable")]
        sel = np.concatenate([np.arange(vd * n), (vd * n + 4 * keep_f[:, None] + np.arange(4)).ravel(),
                              c0 + np.arange(cd)]).astype(np.int64)
        if sel.size != d or np.any(sel != np.arange(d)):
            mean, cov = mean[sel], cov[np.ix_(sel, sel)]
        self.last_dim = d
        return OracleState(
            vehicle_ids=np.asarray(frame.vehicle_ids), feature_ids=fids[keep_f], feature_last_seen=last_seen[keep_f],
            mean=mean, cov=cov, heading=heading, sensor_heading=sensor_heading,
            streak=np.where(excluded, streak + 1, 0), v_first=mean_pred[:vd * n].reshape(n, vd)[:, 2:4].copy(),
        )

    def _imu_input(self, frame: Frame, idx: np.ndarray, fresh: np.ndarray, st: OracleState):
        """The input a_{t-1} of model (1) from the body-frame IMU, the heading at t kept, the variance
        of the heading used and the yaw rate used (the gyroscope's; less the bias state with
        ``heading_state``). The heading at t-1 is the direction of the oracle's velocity at t-1 when the
        vehicle was above ``heading_min_speed`` (variance g P_vv g^T), else the heading the sensor-frame rows
        keep for it (:class:`coloc.core.detections.HeadingMemory`: held, not dead-reckoned by the gyroscope,
        whose turn-on bias would turn a queued vehicle by tens of degrees a minute); unknown (pi^2 / 3) without
        one. Rotated at mid-step by the measured yaw rate (:mod:`coloc.core.inertial`)."""
        from coloc.core.detections import HEADING_VAR_UNKNOWN, heading_from_velocity
        from coloc.core.inertial import rotate, wrap_angle

        vd = self.world.vehicle_dim
        n = frame.n_vehicles
        n_prev = st.vehicle_ids.shape[0]
        have = ~fresh
        pv = np.zeros((n, 2))
        pvv = np.tile(np.eye(2) * HEADING_VAR_UNKNOWN, (n, 1, 1))
        if n_prev and have.any():
            rows = idx[have]
            blk = st.mean[:vd * n_prev].reshape(n_prev, vd)
            pv[have] = blk[rows, 2:4]
            ii = vd * rows[:, None] + np.array([2, 3])
            pvv[have] = st.cov[ii[:, :, None], ii[:, None, :]]
        psi, var = heading_from_velocity(pv, pvv)
        slow = np.hypot(pv[:, 0], pv[:, 1]) < self.params.motion.heading_min_speed
        if st.sensor_heading is not None and n_prev:
            kh, kv = st.sensor_heading.carry(np.where(fresh, -1, idx))
            use = slow & np.isfinite(kh)
            psi = np.where(use, kh, psi)
            var = np.where(use, kv, var)
            slow = slow & ~use
        var = np.where(slow, HEADING_VAR_UNKNOWN, var)
        # heading from the velocity at t-1 (not held, not unknown): the EKF input of imu_heading_from_state
        self._imu_fast = have & (np.hypot(pv[:, 0], pv[:, 1]) >= self.params.motion.heading_min_speed)
        r = np.asarray(frame.imu.yaw_rate, dtype=float)
        if self.world.heading_dim:  # the heading and the gyroscope bias states at t-1 (variance: in the Jacobian)
            ho = self.world.heading_offset
            if n_prev and have.any():
                blk = st.mean[:vd * n_prev].reshape(n_prev, vd)
                psi = np.where(have, 0.0, psi)
                psi[have] = blk[idx[have], ho]
                r = r.copy()
                r[have] = r[have] - blk[idx[have], ho + 1]
            var = np.where(have, 0.0, var)
            self._imu_fast = np.zeros(n, dtype=bool)
        step = np.where(fresh, 0.0, r * float(frame.dt))
        accel = rotate(np.asarray(frame.imu.accel_body, dtype=float).reshape(-1, 2), psi + 0.5 * step)
        return accel, wrap_angle(psi + step), var, r

    def _gnss_information(self, lam, eta, p_pred, frame, fresh, surv, mean_pred, sig, zg, rg, streak) -> np.ndarray:
        """Add every fix's information; returns which fixes' positions the gate left out."""
        w = self.world
        if w.gnss == "satellites":
            _satellite_information(w, lam, eta, frame, mean_pred, zg, rg)
            return np.zeros(frame.n_vehicles, dtype=bool)
        vd, cd, fd = w.vehicle_dim, w.common_dim, w.field_dim
        n = frame.n_vehicles
        d = lam.shape[0]
        c0 = d - cd - fd
        # H of the position rows on [p (2), l (2), c (2), field coefficients (fd)]: I, sigma sqrt(1 - s) I (times
        # sqrt(1 - f) with the exact field), sigma sqrt(s) I, sigma sqrt(1 - s) sqrt(f) dF/dcoef at the predicted
        # position (linearized: the field's gradient times the position error is left out).
        s = w.common_share if cd else 0.0
        if w.gnss == "fix":  # z = p + l + sigma_c c + n (module docstring), l in metres
            pcols = np.concatenate([vd * np.arange(n)[:, None] + np.array([0, 1, 4, 5]),
                                    np.broadcast_to(c0 + np.arange(cd), (n, cd))], axis=1)
            hp = np.zeros((n, 2, 6))
            hp[:, :, :2] = hp[:, :, 2:4] = np.eye(2)
            hp[:, :, 4:] = w.fix_common_sigma_m * np.eye(2)
            rp = w.fix_noise_share * w.fix_local_cov(rg)
        elif w.correlated:
            own = math.sqrt(1.0 - w.field_share) if fd else 1.0
            cols = [vd * np.arange(n)[:, None] + np.array([0, 1, 4, 5])]
            hp = np.zeros((n, 2, 4 + cd + fd))
            hp[:, :, :2] = np.eye(2)
            hp[:, :, 2:4] = (sig * math.sqrt(1.0 - s) * own)[:, None, None] * np.eye(2)
            if cd:
                cols.append(np.broadcast_to(c0 + np.arange(cd), (n, cd)))
                hp[:, :, 4:4 + cd] = (sig * math.sqrt(s))[:, None, None] * np.eye(2)
            if fd:
                cols.append(np.broadcast_to(c0 + cd + np.arange(fd), (n, fd)))
                xy = mean_pred[:vd * n].reshape(n, vd)[:, :2]
                hp[:, :, 4 + cd:] = ((sig * math.sqrt((1.0 - s) * w.field_share))[:, None, None]
                                     * w.field_basis(xy))
            pcols = np.concatenate(cols, axis=1)
            share = np.full(n, w.fix_noise_share)
            if fd and w.field_read_noise:
                share = share + _field_read_share(w, p_pred, surv, sig, s)
            rp = (share * sig * sig)[:, None, None] * np.eye(2)
        else:
            pcols = vd * np.arange(n)[:, None] + np.array([0, 1])
            hp = np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
            rp = rg[:, :2, :2]
        zp = zg[:, :2]
        excluded = np.zeros(n, dtype=bool)
        thr = w.gate_threshold
        if math.isfinite(thr) and surv.size:
            # innovation covariance on the predicted joint: the survivors' rows of p_pred (old layout)
            ns = surv.size
            old = pcols[surv].copy()
            ov = old < vd * n
            veh = old // vd
            rank = np.empty(n, dtype=np.int64)
            rank[surv] = np.arange(ns)
            old[ov] = vd * rank[veh[ov]] + old[ov] % vd
            old[~ov] = p_pred.shape[0] - (d - old[~ov])
            pp = p_pred[old[:, :, None], old[:, None, :]]
            hs = hp[surv]
            sm = hs @ pp @ np.swapaxes(hs, -1, -2) + rp[surv]
            nu = zp[surv] - np.einsum("nij,nj->ni", hs, mean_pred[pcols[surv]])
            nis = np.einsum("ni,ni->n", nu, np.linalg.solve(sm, nu[..., None])[..., 0])
            excluded[surv] = (nis > thr) & (streak[surv] < w.max_exclusions)
        take = ~excluded
        if take.any() and fd:  # wide rows (every fix reads the shared field): dense H^T R^-1 H, R diagonal here
            tk = np.flatnonzero(take)
            hd = np.zeros((tk.size, 2, d))
            np.put_along_axis(hd, np.broadcast_to(pcols[tk][:, None, :], hd.shape[:2] + (pcols.shape[1],)),
                              hp[tk], axis=2)
            hd = hd.reshape(2 * tk.size, d)
            wts = 1.0 / np.repeat(share[tk] * sig[tk] ** 2, 2)
            lam += hd.T @ (wts[:, None] * hd)
            eta += hd.T @ (wts * zp[tk].ravel())
        elif take.any():
            hth, htz = _information(hp[take], np.linalg.inv(rp[take]), zp[take])
            _scatter(lam, eta, pcols[take], hth, htz)
        # velocity rows: v + white noise with the reported block
        vcols = vd * np.arange(n)[:, None] + np.array([2, 3])
        rv_inv = np.linalg.inv(w.fix_velocity_cov(rg) if w.gnss == "fix" else rg[:, 2:, 2:])
        _scatter(lam, eta, vcols, symmetrize(rv_inv), np.einsum("nij,nj->ni", rv_inv, zg[:, 2:]))
        return excluded

    def _v2f_information(self, lam, eta, frame, assoc, fids, idx_c, mean_pred, p_pred, surv, st):
        """Add every associated V2F row's information; returns the heading memory to keep."""
        vd = self.world.vehicle_dim
        n = frame.n_vehicles
        used = np.flatnonzero(assoc >= 0)
        det = frame.v2f_sensor
        memory = None
        owner = np.asarray(frame.v2f_owner, dtype=np.int64)
        if det is not None:
            # each vehicle's predicted velocity and its covariance (fresh: the fix's velocity block)
            vmean = mean_pred[:vd * n].reshape(n, vd)[:, :4]
            vcov = np.zeros((n, 4, 4))
            vcov[:] = np.asarray(frame.gnss_R, dtype=float)
            if surv.size:
                ii = _idx(vd * np.arange(surv.size), 4)
                vcov[surv] = p_pred[ii[:, :, None], ii[:, None, :]]
            psi, var, memory = vehicle_headings(frame, vmean, vcov, idx_c, st.sensor_heading,
                                                self.params.motion.heading_min_speed)
            if self.world.heading_dim:  # the heading state, its error in H (below)
                psi = mean_pred[:vd * n].reshape(n, vd)[:, self.world.heading_offset].copy()
                var = np.zeros(n)
        if used.size == 0:
            return memory
        own = owner[used]
        fpos = _positions(fids, assoc[used])
        m = used.size
        h = np.zeros((m, 4, 8))
        h[:, :, :4] = -np.eye(4)
        h[:, :, 4:] = np.eye(4)
        if det is None:
            z = np.asarray(frame.v2f_z, dtype=float)[used]
            r = np.asarray(frame.v2f_R, dtype=float)[used]
        else:
            from dataclasses import replace as _replace

            sub = _replace(det, **{f: np.asarray(getattr(det, f))[used] for f in (
                "range", "bearing", "range_rate", "mount_x", "yaw", "sigma_range", "sigma_bearing", "sigma_range_rate")})
            z, r = to_net_frame(sub, psi[own], var[own])
        ind = np.concatenate([_idx(vd * own, 4), _idx(vd * n + 4 * fpos, 4)], axis=1)
        if det is not None and self.world.heading_dim:
            # z(psi_hat) = x_F - x_V + gz (psi_hat - psi) + noise: H = [-I | +I | -gz on psi], z' = z - gz psi_hat
            gz = _heading_gradient(sub, psi[own])
            h9 = np.concatenate([h, -gz[:, :, None]], axis=2)
            z9 = z - gz * psi[own][:, None]
            ind9 = np.concatenate([ind, (vd * own + self.world.heading_offset)[:, None]], axis=1)
            if not self.world.range_rate_rows:  # diagnostic: the position half only
                h9, z9, r = h9[:, :2], z9[:, :2], r[:, :2, :2]
            hth, htz = _information(h9, symmetrize(np.linalg.inv(r)), z9)
            _scatter(lam, eta, ind9, hth, htz)
            return memory
        if det is not None and self.world.heading_from_state:
            hvar = var[own] if self.world.heading_row_inflation else np.zeros(m)
            _heading_state_information(lam, eta, ind, sub, psi[own], mean_pred[:vd * n].reshape(n, vd)[own, 2:4], z,
                                       to_net_frame(sub, psi[own], hvar)[1], self.world.range_rate_rows)
            return memory
        if det is not None and self.world.shared_heading:
            _shared_heading_information(lam, eta, ind, sub, psi[own], var, own, z, r)
            return memory
        rinv = symmetrize(np.linalg.inv(r))
        hth, htz = _information(h, rinv, z)
        _scatter(lam, eta, ind, hth, htz)
        return memory


# --- the satellite world ([gnss_error] model = "satellites"; Frame.oracle_gnss) ------------------------------------

MULTIPATH_FLOOR_M2 = 1e-6  # keeps the multipath state's covariance invertible for a receiver without a fix


def _channel(w: OracleWorld, frame: Frame):
    """(gain (N, 2, S), reflected (N, S), elevation (S,), fix (N,)) of the frame's OracleGnss; without one (a frame
    of a world without the channel) no receiver has a gain: every fix is taken with its reported covariance."""
    n, s = frame.n_vehicles, w.sv_count
    ch = frame.oracle_gnss
    if ch is None:
        return np.zeros((n, 2, s)), np.zeros((n, s), dtype=bool), np.full(s, 0.5 * math.pi), np.zeros(n, dtype=bool)
    if ch.gain.shape[2] != s:
        raise ValueError(f"the frame's satellites ({ch.gain.shape[2]}) are not the oracle's ({s})")
    return (np.asarray(ch.gain, dtype=float), np.asarray(ch.reflected, dtype=bool),
            np.asarray(ch.elevation, dtype=float), np.asarray(ch.fix, dtype=bool))


def _multipath_cov(w: OracleWorld, frame: Frame) -> np.ndarray:
    """(N, 2, 2) stationary covariance of each fix's multipath part, K diag((m / sin el)^2) K^T (with
    ``multipath_state``; the floor alone without it or without a fix)."""
    gain, _, el, _ = _channel(w, frame)
    _, mp = w.own_variances(el)
    cov = np.einsum("nis,s,njs->nij", gain, mp, gain) if w.multipath_state else np.zeros((frame.n_vehicles, 2, 2))
    return cov + MULTIPATH_FLOOR_M2 * np.eye(2)


def _satellite_information(w: OracleWorld, lam, eta, frame: Frame, mean_pred, zg, rg) -> None:
    """Every fix as z_i = p_i + l_i + K_i (A(el) c) + v_i (docs/validation/oracle.md, "Satellite world"): K_i the
    receiver's WLS gain, c the 2 S + 1 unit satellite states (A: :meth:`OracleWorld.satellite_columns`), l_i its
    multipath state, v_i white with Var = K_i diag(code noise (+ multipath without its state) + the extra path's
    variance of a reflected signal) K_i^T, z less K_i times the extra paths' mean. The Doppler velocity: v_i +
    K_v,i (white range-rate noise + a reflected signal's path rate), Var = K_v diag(...) K_v^T. A receiver without a
    fix (or velocity) of its own: the reported block, no error state."""
    n = frame.n_vehicles
    if not n:
        return
    vd, sd = w.vehicle_dim, w.satellite_dim
    d = lam.shape[0]
    t0 = d - sd
    gain, refl, el, fix = _channel(w, frame)
    cos_el = np.cos(el)
    white, _ = w.own_variances(el)
    own = white[None, :] + refl * (2.0 * cos_el * w.nlos_d_std_m)[None, :] ** 2
    r = np.einsum("nis,ns,njs->nij", gain, own, gain)
    r[~fix] = rg[~fix, :2, :2]
    z = zg[:, :2] - np.einsum("nis,ns->ni", gain, refl * (2.0 * cos_el * w.nlos_d_mean_m)[None, :])
    ht = gain @ w.satellite_columns(el)  # (N, 2, 2S+1)
    hv = np.zeros((n, 2, 4))
    hv[:, :, :2] = np.eye(2)
    hv[fix, :, 2:] = np.eye(2)
    wi = symmetrize(np.linalg.inv(r))
    vcols = vd * np.arange(n)[:, None] + np.array([0, 1, 4, 5])
    hvw = np.swapaxes(hv, 1, 2) @ wi  # (N, 4, 2)
    _scatter(lam, eta, vcols, hvw @ hv, np.einsum("nij,nj->ni", hvw, z))
    cross = hvw @ ht  # (N, 4, T)
    rows = vcols.ravel()
    lam[rows, t0:] += cross.reshape(4 * n, sd)
    lam[t0:, rows] += cross.reshape(4 * n, sd).T
    htw = np.swapaxes(ht, 1, 2) @ wi  # (N, T, 2)
    lam[t0:, t0:] += np.einsum("nti,niu->tu", htw, ht)
    eta[t0:] += np.einsum("nti,ni->t", htw, z)
    # velocity rows
    ch = frame.oracle_gnss
    rv = np.array(rg[:, 2:, 2:], dtype=float)
    if ch is not None and ch.velocity_gain is not None:
        kv = np.asarray(ch.velocity_gain, dtype=float)
        ok = np.asarray(ch.velocity_solved, dtype=bool)
        s_el = np.maximum(np.sin(el), 0.05)
        speed = np.hypot(*mean_pred[:vd * n].reshape(n, vd)[:, 2:4].T)
        var_v = (w.doppler_noise_mps ** 2 * (1.0 + 1.0 / s_el))[None, :] + (
            (refl & np.asarray(ch.velocity_used, dtype=bool)) * (2.0 * cos_el[None, :] * speed[:, None]
                                                                  * w.nlos_rate_share) ** 2)
        rv_ch = np.einsum("nis,ns,njs->nij", kv, var_v, kv)
        rv[ok] = rv_ch[ok]
    vc = vd * np.arange(n)[:, None] + np.array([2, 3])
    rv_inv = symmetrize(np.linalg.inv(rv))
    _scatter(lam, eta, vc, rv_inv, np.einsum("nij,nj->ni", rv_inv, zg[:, 2:]))
