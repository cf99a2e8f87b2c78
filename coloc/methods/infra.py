"""Infrastructure-mode estimators: ``rsu_bp``, ``sme`` and ``fg_topology_new`` run online at
road-side units (RSUs) on the vehicles within their range.

Each method reads ``frame.infra`` (:class:`coloc.core.frame.InfraFrame`): the V2I links, the RSU
positions and the unlabelled radar detections in the radar's unknown frame, plus the vehicles'
own GNSS (and V2F, odometry) measurements. Common rules:

* Every method runs an internal GNSS tracker (:class:`coloc.methods.gnss.GnssTracker`) on all vehicles.
  A vehicle within range of no RSU gets the tracker's estimate and ``covered = False``.
* A vehicle in range of several RSUs is reported by the one with the lowest index (each RSU
  still uses it, since its radar sees it).
* A vehicle entering an RSU's range starts from its tracker's belief *without* the current fix:
  the posterior of the previous step predicted by model (1) with the inertial input (or the
  fast-start prior if it entered the net now). The RSU then applies this step's GNSS fix itself,
  so no fix is counted twice. Its state at an RSU is dropped when it leaves the range.

Per-method decisions (the papers describe a fixed set of vehicles):

* ``rsu_bp`` (Fröhle et al.): particle beliefs per vehicle, Gaussian between steps: the product
  phi_s chi_s of the prediction (10) and the GNSS message is formed in closed form (model (1) with
  the inertial input, which the paper's CV model (28) lacks, then the Kalman update with the fix)
  and represented by Np equally weighted draws; the V2F messages (23) weight these draws and the
  weighted moments of b_s (26) are carried to the next step. (Weighting prediction particles by the
  4-D fix instead degenerated: the fix's 0.1 m/s velocity noise against the 0.26 m/s predicted spread
  left ~15 % effective particles, and the filter without any feature was 10 % worse than the
  tracker on the arterial; with the closed-form product it equals the tracker up to Monte Carlo
  error, see the tests.) Features
  are RSU-held particle clouds of static landmarks (position random walk of
  ``feature_walk_sigma`` per step, zero velocity). Association with missed detections and
  new/clutter measurements: :func:`coloc.methods.rsu_bp.rsu_bp_step_open`. Feature birth: a V2F row whose
  probability of "new" exceeds 0.5 starts a track at (vehicle posterior mean + z) unless a track
  or an earlier birth of this step lies within ``feature_birth_gate_m`` or the vehicle's position
  standard deviation exceeds ``feature_birth_max_std_m`` (measured on the arterial, 120 s TLR:
  births from zone-C vehicles gave vague tracks that attracted wrong rows, p95 5.0 m against
  the tracker's 3.5 m); a track drops when no
  row has been associated to it (total probability < 0.5) for ``feature_drop_s``, or when it is
  farther than range + Rs from the RSU.
* ``sme`` (Zhang et al.): one joint EKF per RSU over the vehicles in radar range (at most
  ``sme_max_vehicles``, nearest to the RSU by their estimate). The GNSS fixes are labelled (each
  vehicle sends its own; the joint update is the labelled Kalman update, as Zhang's KF baseline),
  so the power-sum pseudo-measurement (9) is not needed; the radar enters by the pose- and
  order-free topology pseudo-measurement (10) (:mod:`coloc.inference.topology`, bias-corrected, variance (15)
  plus the second-order term). When the vehicle set changes the joint state is rebuilt from the
  carried per-vehicle marginals (cross-covariances dropped) plus entering vehicles. When the
  number of detections differs from the number of vehicles in the state (the cap) the topology
  update is skipped and counted (``topology_skipped``). Prediction: model (1), as the tracker.
  With one vehicle it is exactly the GNSS tracker (tests).
* ``fg_topology_new`` (Gulati et al.): per RSU a gtsam ``BatchFixedLagSmoother`` (LM) over the
  last ``fg_window_steps`` steps; states leave the window by the smoother's marginalisation (a
  Gaussian prior on the remaining states, not a plain drop). Factors: GPS unary (the position part
  of the fix, covariance from the frame), odometry between factors (Gulati (4)-(5)), one
  topology factor per step and RSU from its radar scan (pseudo-measurement and variance
  (15)-(16), :mod:`coloc.inference.topology`), and, for the first state of a vehicle, its tracker's
  predicted position belief (above). The topology factor of step t is the new factor (11)-(13)
  on the previous states moved by the odometry (:func:`coloc.methods.fg_topology._new_topology_error`)
  when every vehicle in range has a state at t-1 at this RSU and finite odometry
  (``topology_updates_new``). Otherwise (a vehicle just entered the range) it is Gulati's old
  factor (8) on the current states of all vehicles in range
  (:func:`coloc.methods.fg_topology._old_topology_error`; ``topology_updates_old``), which needs no
  previous state: an entering vehicle's current state has its start belief and its fix. The
  paper, with a fixed set of vehicles, does not have this case; mixing the two (11 on the
  vehicles that have a previous state, 8 on the others) is not a factor of the paper either.
  ``topology_updates`` counts both; a scan whose point count differs from the number of
  vehicles in range gives neither (``topology_skipped``; never with the coupler's radar, which
  detects every vehicle in range). On the arterial (seed 1, 600 s, README) a third of the
  RSU-steps with two or more vehicles have an entering vehicle: 730 of 2257 (TLR), 802 of 2224
  (VSR), which (11) alone skipped. Velocity is not in the graph: the reported velocity is the
  tracker's, and so is the reported covariance (the batch fixed-lag smoother does not expose
  marginals cheaply; the scores use the means only).

Receiver model and consistent fusion (opt-in; docs/validation/consistency.md, "Infrastructure methods"):

* ``[gnss_model]`` (``fg_topology_new``, ``sme``): the internal tracker is the bias-state tracker of
  :mod:`coloc.methods.gnss_bias` and an entering vehicle starts from its 6-D belief
  (:meth:`_InfraBase._start_beliefs6`). ``sme`` carries [p, v, b] blocks in the joint EKF
  (:func:`joint_predict_bias`, :func:`joint_fix_update_bias`); ``fg_topology_new`` the bias as a
  Gauss-Markov chain of factors (:mod:`coloc.methods.fg_bias`) and reports the smoother's position
  marginal. A fix the vehicle's own tracker excluded (its chi-square rule) is not used.
* ``[fusion]`` in ``sme``: a vehicle whose earlier information a topology update of this RSU spread into
  the others' states re-enters with its tracker's belief, correlated with theirs by an unknown amount:
  covariance intersection of the carried block and the re-entering beliefs (:func:`ci_reentry`). A
  vehicle never in the set enters exactly (zero cross-covariance).
* ``[fusion]`` in ``rsu_bp``: the rule of :mod:`coloc.methods.pf_fusion` at the RSU
  (:meth:`RsuBpInfra._rsu_step_fused`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from coloc.core.detections import with_net_detections
from coloc.core.frame import Frame, StepEstimate
from coloc.core.models import (
    MotionParams,
    driving_noise_cov,
    input_matrix,
    kalman_update,
    predict,
    symmetrize,
    transition_matrix,
)
from coloc.core.vehicles import carry_states, entry_fix_rows, fresh_rows, match_ids
from coloc.inference.topology import sum_sq_pairwise, sum_sq_pairwise_grad, topology_bias, topology_variance
from coloc.methods.gnss import GnssTracker
from coloc.methods.gnss_bias import GnssBiasTracker, GnssModelParams, bias_predict
from coloc.methods.registry import RSU_BP, SME
from coloc.methods.rsu_bp import RsuBpParams, init_particles, rsu_bp_step_open

@dataclass(frozen=True)
class InfraMethodParams:
    """Settings of the infrastructure methods (config ``[infra]``; see the module doc)."""

    motion: MotionParams = field(default_factory=MotionParams)
    seed: int = 1
    rsu_bp_particles: int = 200
    detection_prob: float = 0.9  # P_D of a visible feature
    v2f_range_m: float = 50.0  # Rs: the clutter density is 1 / (pi Rs^2), the visibility gate Rs + margin
    visibility_margin_m: float = 5.0
    feature_walk_sigma: float = 0.02  # m per step, static landmarks
    feature_birth_gate_m: float = 3.0
    feature_birth_max_std_m: float = 1.5  # only vehicles localised at least this well (per-axis rms) start tracks
    feature_drop_s: float = 5.0
    feature_keep_radius_m: float = 150.0  # an RSU drops a track farther than this from it (range + Rs + margin)
    sme_max_vehicles: int = 12
    fg_window_steps: int = 8
    fg_max_iterations: int = 20


def home_rsu(v2i) -> np.ndarray:
    """(N,) the lowest-index RSU covering each vehicle, -1 for none."""
    n_rsu, n = v2i.shape
    home = np.full(n, -1, dtype=np.int64)
    for r in range(n_rsu - 1, -1, -1):
        home[v2i.indices[v2i.indptr[r]:v2i.indptr[r + 1]]] = r
    return home


class _InfraBase:
    """GNSS fallback, per-RSU bookkeeping and the entering-vehicle belief."""

    name = "infra"

    def __init__(self, params: InfraMethodParams, gnss_model: GnssModelParams | None = None):
        self.params = params
        # [gnss_model]: the internal tracker is the gnss benchmark's bias-state tracker (6-D states).
        self.model = gnss_model
        self.gnss = (GnssTracker(motion=params.motion) if gnss_model is None
                     else GnssBiasTracker(motion=params.motion, model=gnss_model))
        self.stats = {"topology_updates": 0, "topology_skipped": 0}
        self._sensor_heading = None  # sensor-frame detections: coloc.core.detections.HeadingMemory

    def _start_beliefs(self, frame: Frame, rows: np.ndarray, prev) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Belief at t without this step's fix: tracker posterior of t-1 predicted by model (1), or the prior.
        Returns (mean, cov, held): ``held`` (rows,) bool marks priors that are this step's fix already
        (the entry protocol, :func:`coloc.core.vehicles.entry_fix_rows`): the RSU does not apply the fix
        to those again."""
        ids, mean, cov = prev
        m, c, fresh = carry_states(ids, mean, cov, frame.vehicle_ids[rows], frame.entered[rows],
                                   frame.prior_z[rows], frame.prior_R[rows])
        old = ~fresh
        if old.any():
            q = driving_noise_cov(m[old, 2:], frame.dt, self.params.motion)
            m[old], c[old] = predict(m[old], c[old], frame.accel[rows[old]], frame.dt, q)
        return m, c, entry_fix_rows(frame, fresh, rows)

    def _start_beliefs6(self, frame: Frame, rows: np.ndarray, prev) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_start_beliefs` on the 6-D states [p, v, b] of the ``[gnss_model]`` tracker
        (:class:`coloc.methods.gnss_bias.GnssBiasTracker`): its posterior of t-1 predicted
        (:func:`coloc.methods.gnss_bias.bias_predict`), or the prior with the bias at 0 and its
        stationary covariance s R_pos. A prior that is this step's fix (``held``) gets the one-fix
        posterior's Cov(p, b) = -s R_pos (:func:`coloc.methods.gnss_bias.entry_fix_posterior`)."""
        ids, mean, cov = prev
        s = self.model.bias_share
        idx = match_ids(ids, frame.vehicle_ids[rows])
        prior_z = np.asarray(frame.prior_z, dtype=float)[rows]
        fresh = fresh_rows(idx, frame.entered[rows], prior_z)
        r_pos = np.asarray(frame.gnss_R, dtype=float)[rows, :2, :2]
        n = rows.size
        m = np.zeros((n, 6))
        c = np.zeros((n, 6, 6))
        old = ~fresh
        m[old], c[old] = mean[idx[old]], cov[idx[old]]
        m[fresh, :4] = prior_z[fresh]
        c[fresh, :4, :4] = np.asarray(frame.prior_R, dtype=float)[rows][fresh]
        c[fresh, 4:, 4:] = s * r_pos[fresh]
        if old.any():
            m[old], c[old] = bias_predict(m[old], c[old], np.asarray(frame.accel, dtype=float)[rows[old]],
                                          r_pos[old], float(frame.dt), self.params.motion, self.model)
        held = entry_fix_rows(frame, fresh, rows)
        if held.any():
            cross = -s * r_pos[held]
            c[held, :2, 4:], c[held, 4:, :2] = cross, np.swapaxes(cross, -1, -2)
        return m, c, held

    def step(self, frame: Frame) -> StepEstimate:
        prev = (self.gnss._ids, self.gnss._mean, self.gnss._cov)
        fallback = self.gnss.step(frame)
        if frame.v2f_sensor is not None:  # model (4)'s rows by the heading of the vehicle's own GNSS track at t
            frame, self._sensor_heading = with_net_detections(
                frame, fallback.mean, fallback.cov, match_ids(prev[0], frame.vehicle_ids), self._sensor_heading,
                self.params.motion.heading_min_speed)
        mean, cov = fallback.mean.copy(), fallback.cov.copy()
        n = frame.n_vehicles
        covered = np.zeros(n, dtype=bool)
        infra = frame.infra
        if infra is None:
            raise ValueError(f"{self.name} needs infrastructure frames (frame.infra)")
        home = home_rsu(infra.v2i) if n else np.empty(0, dtype=np.int64)
        for r in range(infra.n_rsu):
            rows = infra.v2i.indices[infra.v2i.indptr[r]:infra.v2i.indptr[r + 1]].astype(np.int64)
            res = self._rsu_step(frame, r, rows, prev, fallback)
            if res is None:
                continue
            used, m, c = res
            mine = home[used] == r
            mean[used[mine]], cov[used[mine]] = m[mine], c[mine]
            covered[used[mine]] = True
        return StepEstimate(mean=mean, cov=cov, covered=covered)

    def _rsu_step(self, frame, r, rows, prev, fallback):  # pragma: no cover - abstract
        raise NotImplementedError


# --------------------------------------------------------------------------- sme


def joint_predict(mean: np.ndarray, cov: np.ndarray, accel: np.ndarray, dt: float, motion: MotionParams,
                  moving: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Model (1) on a joint state (4n,) / (4n, 4n); blocks with ``moving`` False stay (already at t)."""
    n = mean.shape[0] // 4
    a1, b1 = transition_matrix(dt), input_matrix(dt)
    blocks = [a1 if mv else np.eye(4) for mv in moving]
    a = np.zeros((4 * n, 4 * n))
    q = np.zeros((4 * n, 4 * n))
    x = mean.reshape(n, 4)
    qs = driving_noise_cov(x[:, 2:], dt, motion)
    out = np.empty_like(x)
    for i in range(n):
        sl = slice(4 * i, 4 * i + 4)
        a[sl, sl] = blocks[i]
        if moving[i]:
            q[sl, sl] = qs[i]
            out[i] = a1 @ x[i] + b1 @ accel[i]
        else:
            out[i] = x[i]
    return out.reshape(-1), symmetrize(a @ cov @ a.T + q)


def joint_labelled_update(mean, cov, z, r_blocks, use=None):
    """Kalman update of the joint state with each vehicle's own position-velocity fix (H = I, model (3)).
    ``use`` (n,) bool: only these vehicles' fixes (None: all)."""
    n = mean.shape[0] // 4
    if use is not None and not np.all(use):
        keep = np.flatnonzero(use)
        if keep.size == 0:
            return mean, cov
        sel = (4 * keep[:, None] + np.arange(4)).ravel()
        r = np.zeros((sel.size, sel.size))
        for a, i in enumerate(keep):
            r[4 * a:4 * a + 4, 4 * a:4 * a + 4] = r_blocks[i]
        s = cov[np.ix_(sel, sel)] + r
        gain = np.linalg.solve(s, cov[sel, :]).T  # P H^T S^-1
        new_mean = mean + gain @ (np.asarray(z, float)[keep].reshape(-1) - mean[sel])
        ikh = np.eye(4 * n)
        ikh[:, sel] -= gain
        return new_mean, symmetrize(ikh @ cov @ ikh.T + gain @ r @ gain.T)
    r = np.zeros((4 * n, 4 * n))
    for i in range(n):
        r[4 * i:4 * i + 4, 4 * i:4 * i + 4] = r_blocks[i]
    s = cov + r
    gain = np.linalg.solve(s, cov).T  # P S^-1 (S, P symmetric)
    new_mean = mean + gain @ (np.asarray(z, float).reshape(-1) - mean)
    ikh = np.eye(4 * n) - gain
    return new_mean, symmetrize(ikh @ cov @ ikh.T + gain @ r @ gain.T)


def topology_update(mean, cov, radar_points, radar_var, dim: int = 4):
    """Scalar EKF update with Zhang's (10) / Gulati's (8): sum of squared pairwise distances of the
    detections (pose- and order-free), bias-corrected; variance (15) + second-order term at the prediction.
    ``dim``: entries per vehicle in the joint state, its position first (4: [p, v]; 6: [p, v, b])."""
    n = mean.shape[0] // dim
    pos = mean.reshape(n, dim)[:, :2]
    y = float(sum_sq_pairwise(radar_points)) - topology_bias(n, radar_var)
    h = float(sum_sq_pairwise(pos))
    jac = np.zeros(dim * n)
    grad = sum_sq_pairwise_grad(pos)
    jac[dim * np.arange(n)] = grad[:, 0]
    jac[dim * np.arange(n) + 1] = grad[:, 1]
    r = float(topology_variance(h, n, radar_var))
    ph = cov @ jac
    s = float(jac @ ph) + r
    gain = ph / s
    new_mean = mean + gain * (y - h)
    ikh = np.eye(dim * n) - np.outer(gain, jac)
    return new_mean, symmetrize(ikh @ cov @ ikh.T + r * np.outer(gain, gain))


def joint_predict_bias(mean, cov, accel, r_pos, dt, motion: MotionParams, model: GnssModelParams, moving):
    """:func:`joint_predict` on 6-D blocks [p, v, b] (``[gnss_model]``): model (1) on [p, v] and the
    Gauss-Markov bias ``b' = a b + w``, ``Var(w) = (1 - a^2) s R_pos`` (:func:`coloc.methods.gnss_bias.bias_predict`);
    blocks with ``moving`` False stay."""
    n = mean.shape[0] // 6
    x = mean.reshape(n, 6)
    out, qs = bias_predict(x, np.zeros((n, 6, 6)), accel, r_pos, dt, motion, model)  # qs: Q of each block
    a1 = np.eye(6)
    a1[0, 2] = a1[1, 3] = dt
    a1[4, 4] = a1[5, 5] = np.exp(-dt / model.bias_tau_s)
    a = np.zeros((6 * n, 6 * n))
    q = np.zeros((6 * n, 6 * n))
    for i in range(n):
        sl = slice(6 * i, 6 * i + 6)
        a[sl, sl] = a1 if moving[i] else np.eye(6)
        if moving[i]:
            q[sl, sl] = qs[i]
    out = np.where(np.asarray(moving, bool)[:, None], out, x)
    return out.reshape(-1), symmetrize(a @ cov @ a.T + q)


def joint_fix_update_bias(mean, cov, z, r_blocks, share, use, pos_ok):
    """Kalman update of the 6-D-block joint state by each used vehicle's fix: z_pos = p + b (noise (1 - s)
    R_pos), z_vel = v; ``pos_ok`` (n,) False: the fix's position is excluded (velocity rows only)."""
    n = mean.shape[0] // 6
    rows, blocks = [], []
    for i in np.flatnonzero(use):
        comp = np.arange(4) if pos_ok[i] else np.arange(2, 4)
        rows.append((i, comp))
        rb = np.array(r_blocks[i], dtype=float)
        rb[:2, :2] *= 1.0 - share
        blocks.append(rb[np.ix_(comp, comp)])
    if not rows:
        return mean, cov
    m = sum(c.size for _, c in rows)
    h = np.zeros((m, 6 * n))
    r = np.zeros((m, m))
    y = np.empty(m)
    k = 0
    for (i, comp), rb in zip(rows, blocks):
        for a, c in enumerate(comp):
            h[k + a, 6 * i + c] = 1.0
            if c < 2:
                h[k + a, 6 * i + 4 + c] = 1.0
            y[k + a] = z[i][c]
        r[k:k + comp.size, k:k + comp.size] = rb
        k += comp.size
    s = h @ cov @ h.T + r
    gain = np.linalg.solve(s, h @ cov).T
    new_mean = mean + gain @ (y - h @ mean)
    ikh = np.eye(6 * n) - gain @ h
    return new_mean, symmetrize(ikh @ cov @ ikh.T + gain @ r @ gain.T)


def ci_reentry(cov, dim, carried, dependent):
    """Covariance intersection of the joint state's carried block with the start beliefs of ``dependent``
    entering vehicles (their cross-covariances unknown, set to 0): the blocks scaled by 1 / w_k with
    sum w_k = 1 bound every cross-covariance (Julier & Uhlmann 2001); w_k proportional to the square root
    of each block's position trace, which minimises sum tr_k / w_k (the trace of the positions' bound, m^2).
    Returns the new covariance."""
    groups = [np.concatenate([dim * i + np.arange(dim) for i in carried])] + [dim * i + np.arange(dim) for i in dependent]
    tr = np.array([sum(cov[j, j] for j in g if j % dim < 2) for g in groups])
    w = np.sqrt(tr) / np.sum(np.sqrt(tr))
    out = cov.copy()
    for g, wk in zip(groups, w):
        out[np.ix_(g, g)] /= wk
    return out


class SmeInfra(_InfraBase):
    """``sme`` per RSU (module doc). ``gnss_model`` ([gnss_model]): 6-D blocks [p, v, b] with the receiver's
    Gauss-Markov bias and the own tracker's fault exclusion; ``fusion`` ([fusion]): covariance intersection
    for a vehicle that re-enters the joint state (:func:`ci_reentry`)."""

    name = SME.name

    def __init__(self, params: InfraMethodParams, gnss_model: GnssModelParams | None = None, fusion=None):
        super().__init__(params, gnss_model)
        self.fusion = fusion
        self._state: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # r -> (ids, mean (dn,), cov)
        self._seen: dict[int, set] = {}  # [fusion]: r -> ids whose information a topology update spread

    def _rsu_step(self, frame, r, rows, prev, fallback):
        infra = frame.infra
        d = 4 if self.model is None else 6
        if rows.size == 0:
            self._state.pop(r, None)
            return None
        if rows.size > self.params.sme_max_vehicles:
            dist = np.hypot(*(fallback.mean[rows, :2] - infra.rsu_xy[r]).T)
            rows = np.sort(rows[np.argsort(dist, kind="stable")[: self.params.sme_max_vehicles]])
        ids = frame.vehicle_ids[rows]
        n = rows.size
        old_ids, old_mean, old_cov = self._state.get(r, (np.empty(0, dtype=object), np.empty(0), np.empty((0, 0))))
        idx = match_ids(old_ids, ids)
        idx[np.asarray(frame.entered[rows], bool)] = -1
        fixed = np.ones(n, dtype=bool)  # vehicles this step's fix updates
        if idx.size == old_ids.size and np.array_equal(idx, np.arange(n)):
            mean, cov = old_mean, old_cov  # same vehicles, same order: keep the joint covariance
            moving = np.ones(n, dtype=bool)
        else:
            mean = np.empty(d * n)
            cov = np.zeros((d * n, d * n))
            moving = idx >= 0
            carried = np.flatnonzero(moving)
            for i in carried:
                j = idx[i]
                mean[d * i:d * i + d] = old_mean[d * j:d * j + d]
                for i2 in carried:
                    j2 = idx[i2]
                    cov[d * i:d * i + d, d * i2:d * i2 + d] = old_cov[d * j:d * j + d, d * j2:d * j2 + d]
            new = np.flatnonzero(~moving)
            if new.size:
                start = self._start_beliefs if self.model is None else self._start_beliefs6
                m0, c0, held = start(frame, rows[new], prev)  # already at t
                for a, i in enumerate(new):
                    mean[d * i:d * i + d] = m0[a]
                    cov[d * i:d * i + d, d * i:d * i + d] = c0[a]
                fixed[new[held]] = False  # their prior is this step's fix
                if self.fusion is not None and carried.size:
                    seen = self._seen.get(r, set())
                    dependent = [i for i in new if ids[i] in seen]
                    if dependent:
                        cov = ci_reentry(cov, d, carried, dependent)
                        self.stats["ci_reentries"] = self.stats.get("ci_reentries", 0) + len(dependent)
        if self.model is None:
            mean, cov = joint_predict(mean, cov, frame.accel[rows], frame.dt, self.params.motion, moving)
            mean, cov = joint_labelled_update(mean, cov, frame.gnss_z[rows], frame.gnss_R[rows], fixed)
        else:
            r_pos = np.asarray(frame.gnss_R, dtype=float)[rows, :2, :2]
            mean, cov = joint_predict_bias(mean, cov, np.asarray(frame.accel, dtype=float)[rows], r_pos, frame.dt,
                                           self.params.motion, self.model, moving)
            ex = self.gnss.last_excluded
            pos_ok = np.ones(n, dtype=bool) if ex is None else ~np.asarray(ex, bool)[rows]
            mean, cov = joint_fix_update_bias(mean, cov, frame.gnss_z[rows], frame.gnss_R[rows],
                                              self.model.bias_share, fixed, pos_ok)
        if n >= 2:
            pts = infra.radar_z[infra.radar_owner == r]
            if pts.shape[0] == n:
                mean, cov = topology_update(mean, cov, pts, infra.radar_var, d)
                self.stats["topology_updates"] += 1
                if self.fusion is not None:
                    self._seen.setdefault(r, set()).update(ids)
            else:
                self.stats["topology_skipped"] += 1
        self._state[r] = (ids, mean, cov)
        m = mean.reshape(n, d)[:, :4]
        c = np.stack([cov[d * i:d * i + 4, d * i:d * i + 4] for i in range(n)])
        return rows, m.copy(), c


# --------------------------------------------------------------------------- rsu_bp


@dataclass
class _RsuFeatures:
    particles: np.ndarray  # (K, Np, 4)
    track_ids: np.ndarray  # (K,) int
    last_hit: np.ndarray  # (K,) time of the last associated row


class RsuBpInfra(_InfraBase):
    """``rsu_bp`` online per RSU (module doc)."""

    name = RSU_BP.name

    def __init__(self, params: InfraMethodParams, fusion=None):
        # [fusion] (coloc.methods.coop_fusion.CoopFusion): the own track is the 6-D filter of its receiver model.
        super().__init__(params, None if fusion is None else fusion.model)
        self.fusion = fusion
        self._split: dict[int, dict] = {}  # [fusion]: r -> id -> (mean, cov, independent part, streak), 6-D
        self.bp = RsuBpParams(n_particles=params.rsu_bp_particles)
        self.rng = np.random.default_rng(np.random.SeedSequence([int(params.seed), 0x25B]))
        self._veh: dict[int, dict[str, np.ndarray]] = {}  # r -> id -> particles (Np, 4)
        self._feat: dict[int, _RsuFeatures] = {}
        self._next_track = 0
        self.stats.update({"features_born": 0, "features_dropped": 0})
        self._extra = None

    def _begin(self, frame):
        o = frame.v2f_z.shape[0]
        return {"assign": np.full(o, -1, dtype=np.int64), "fm": [], "fc": [], "fid": []}

    def _rsu_step(self, frame, r, rows, prev, fallback):
        if self.fusion is not None:
            return self._rsu_step_fused(frame, r, rows, prev)
        p = self.params
        infra = frame.infra
        store = self._veh.setdefault(r, {})
        feats = self._feat.get(r)
        if feats is None:
            feats = _RsuFeatures(np.empty((0, self.bp.n_particles, 4)), np.empty(0, dtype=np.int64), np.empty(0))
        ids = frame.vehicle_ids[rows]
        if rows.size == 0:
            self._veh[r] = {}
            self._feat[r] = self._drop_features(feats, frame, r)
            return None
        entered = np.asarray(frame.entered[rows], bool)
        old = np.array([(vid in store) and not entered[a] for a, vid in enumerate(ids)], dtype=bool)
        # phi_s chi_s in closed form: model (1) prediction of the carried Gaussian belief (or the
        # entering vehicle's start belief), Kalman update with the GNSS fix (3); then Np draws.
        m = np.empty((rows.size, 4))
        c = np.empty((rows.size, 4, 4))
        if old.any():
            m_old = np.stack([store[v][0] for v in ids[old]])
            c_old = np.stack([store[v][1] for v in ids[old]])
            q = driving_noise_cov(m_old[:, 2:], frame.dt, p.motion)
            m[old], c[old] = predict(m_old, c_old, frame.accel[rows[old]], frame.dt, q)
        held = np.zeros(rows.size, dtype=bool)
        if (~old).any():
            m[~old], c[~old], held[~old] = self._start_beliefs(frame, rows[~old], prev)
        m0, c0 = m[held], c[held]
        m, c = kalman_update(m, c, frame.gnss_z[rows], frame.gnss_R[rows])
        m[held], c[held] = m0, c0  # a prior that is this step's fix is not updated by it again
        z = self.rng.standard_normal((rows.size, self.bp.n_particles, 4))
        xs = m[:, None, :] + np.einsum("sij,spj->spi", np.linalg.cholesky(c + 1e-12 * np.eye(4)), z)
        fs = feats.particles.copy()
        if fs.shape[0]:
            fs[:, :, :2] += p.feature_walk_sigma * self.rng.standard_normal(fs[:, :, :2].shape)
        # V2F rows of the vehicles in range, owner as local index.
        local = np.full(frame.n_vehicles, -1, dtype=np.int64)
        local[rows] = np.arange(rows.size)
        sel = np.flatnonzero(local[frame.v2f_owner] >= 0) if frame.v2f_owner.size else np.empty(0, dtype=np.int64)
        owner = local[frame.v2f_owner[sel]]
        vz = frame.v2f_z[sel, :2]
        vr = frame.v2f_R[sel, :2, :2]
        vmean = xs[:, :, :2].mean(axis=1)
        fmean0 = fs[:, :, :2].mean(axis=1) if fs.shape[0] else np.empty((0, 2))
        d = np.hypot(*(vmean[:, None, :] - fmean0[None, :, :]).transpose(2, 0, 1)) if fs.shape[0] else np.empty((rows.size, 0))
        visible = d <= p.v2f_range_m + p.visibility_margin_m
        res = rsu_bp_step_open(xs, fs, None, None, vz, vr, owner, visible,
                               p.detection_prob, 1.0 / (np.pi * p.v2f_range_m**2), self.bp, self.rng)
        # A vehicle without V2F information keeps the exact Gaussian phi_s chi_s (no Monte Carlo error):
        # with no features the method is exactly the GNSS tracker.
        informed = visible.any(axis=1) & (np.bincount(owner, minlength=rows.size) > 0)
        vmean_out = np.where(informed[:, None], res.vehicle_mean, m)
        vcov_out = np.where(informed[:, None, None], res.vehicle_cov, c)
        self._upkeep(frame, r, feats, res, fs, owner, vz, vr, sel, vmean_out, vcov_out)
        self._veh[r] = {vid: (vmean_out[a], vcov_out[a]) for a, vid in enumerate(ids)}
        return rows, vmean_out, vcov_out

    def _rsu_step_fused(self, frame, r, rows, prev):
        """The step under ``[fusion]``, by the rule of :mod:`coloc.methods.pf_fusion`: per vehicle at the RSU the
        cooperative 6-D belief with its independent part (:mod:`coloc.methods.coop_fusion`; an entering vehicle
        from its own track's predicted belief, :meth:`_start_beliefs6`), predicted and updated by the fix; the
        particle step (association, feature clouds) runs on draws from the vehicles' own tracks, so the
        clouds hold own-sensor messages only; the belief is b^(0) fused by split CI with the evidence of this
        step's other observers of the tracks its rows were paired with (the row's most probable existing
        track), the tracks' earlier content left out (:func:`coloc.methods.pf_fusion.track_prior_information`)."""
        from coloc.inference.params import IcpParams
        from coloc.methods.coop_fusion import SplitPrior, _gnss6, split_localization
        from coloc.methods.pf_fusion import track_prior_information

        p, fu, model = self.params, self.fusion.params, self.model
        infra = frame.infra
        feats = self._feat.get(r)
        if feats is None:
            feats = _RsuFeatures(np.empty((0, self.bp.n_particles, 4)), np.empty(0, dtype=np.int64), np.empty(0))
        if rows.size == 0:
            self._split[r] = {}
            self._feat[r] = self._drop_features(feats, frame, r)
            return None
        store = self._split.get(r, {})
        ids = frame.vehicle_ids[rows]
        n = rows.size
        entered = np.asarray(frame.entered[rows], bool)
        old = np.array([(vid in store) and not entered[a] for a, vid in enumerate(ids)], dtype=bool)
        m, c, ci = np.zeros((n, 6)), np.zeros((n, 6, 6)), np.zeros((n, 6, 6))
        streak = np.zeros(n, dtype=np.int64)
        for a in np.flatnonzero(old):
            m[a], c[a], ci[a], streak[a] = store[ids[a]]
        held = np.zeros(n, dtype=bool)
        if (~old).any():
            m[~old], c[~old], held[~old] = self._start_beliefs6(frame, rows[~old], prev)
            ci[~old] = 0.0 if fu.common_mode_gnss else c[~old]  # the own receiver's (dependent if shared)
        m1, c1, ci1, ex = _gnss6(m, c, ci, np.asarray(frame.accel, float)[rows], frame.gnss_z[rows], frame.gnss_R[rows],
                                 old, float(frame.dt), p.motion, model, streak, fu.common_mode_gnss)
        m1[held], c1[held], ci1[held] = m[held], c[held], ci[held]  # a prior that is the step's fix: not again
        own_m, own_c = self.gnss._mean[rows], self.gnss._cov[rows]  # own tracks at t (after their fixes)
        z = self.rng.standard_normal((n, self.bp.n_particles, 4))
        chol = np.linalg.cholesky(own_c[:, :4, :4] + 1e-12 * np.eye(4))
        xs = own_m[:, None, :4] + np.einsum("sij,spj->spi", chol, z)
        fs = feats.particles.copy()
        if fs.shape[0]:
            fs[:, :, :2] += p.feature_walk_sigma * self.rng.standard_normal(fs[:, :, :2].shape)
        local = np.full(frame.n_vehicles, -1, dtype=np.int64)
        local[rows] = np.arange(n)
        sel = np.flatnonzero(local[frame.v2f_owner] >= 0) if frame.v2f_owner.size else np.empty(0, dtype=np.int64)
        owner = local[frame.v2f_owner[sel]]
        vz, vr = frame.v2f_z[sel, :2], frame.v2f_R[sel, :2, :2]
        vmean = xs[:, :, :2].mean(axis=1)
        fmean0 = fs[:, :, :2].mean(axis=1) if fs.shape[0] else np.empty((0, 2))
        d = np.hypot(*(vmean[:, None, :] - fmean0[None, :, :]).transpose(2, 0, 1)) if fs.shape[0] else np.empty((n, 0))
        visible = d <= p.v2f_range_m + p.visibility_margin_m
        res = rsu_bp_step_open(xs, fs, None, None, vz, vr, owner, visible,
                               p.detection_prob, 1.0 / (np.pi * p.v2f_range_m**2), self.bp, self.rng)
        k = fs.shape[0]
        assoc = res.v2f_association
        best = assoc.argmax(axis=1) if assoc.shape[0] else np.empty(0, dtype=np.int64)
        row_track = np.where(best < k, feats.track_ids[np.minimum(best, max(k - 1, 0))] if k else -1, -1)
        icp = IcpParams(motion=p.motion)
        fids = np.unique(row_track[row_track >= 0])
        lam0, eta0 = track_prior_information(fids, icp)
        adjacency = sp.csr_matrix(~np.eye(n, dtype=bool))  # every vehicle in range talks to the RSU
        prior = SplitPrior(m1, c1, ci1, np.where(ex, streak + 1, 0), own_m, own_c, np.zeros(n, dtype=np.int64))
        out, split = split_localization(prior, owner, row_track, frame.v2f_z[sel], frame.v2f_R[sel], adjacency,
                                        lam0, eta0, icp, feature_ci=fu.feature_ci)
        vmean_out, vcov_out = out.mean, out.cov
        self._upkeep(frame, r, feats, res, fs, owner, vz, vr, sel, vmean_out, vcov_out)
        self._split[r] = {vid: (split.mean[a], split.cov[a], split.ind[a], split.streak[a]) for a, vid in enumerate(ids)}
        return rows, vmean_out, vcov_out

    def _upkeep(self, frame, r, feats, res, fs, owner, vz, vr, sel, vmean_out, vcov_out):
        """Association output and feature upkeep (births from ``vmean_out`` / ``vcov_out``, drops)."""
        p = self.params
        assoc = res.v2f_association  # (O_r, K + 1)
        k = fs.shape[0]
        last_hit = feats.last_hit.copy()
        if k:
            hits = assoc[:, :k].sum(axis=0)
            last_hit[hits >= 0.5] = frame.t
        best = assoc.argmax(axis=1) if assoc.shape[0] else np.empty(0, dtype=np.int64)
        extra = self._extra
        if extra is None:
            extra = self._extra = self._begin(frame)
        assigned = np.where(best < k, feats.track_ids[np.minimum(best, max(k - 1, 0))] if k else -1, -1)
        new_rows = np.flatnonzero(assoc[:, -1] > 0.5) if assoc.shape[0] else np.empty(0, dtype=np.int64)
        fparts, tids, lh = res.feature_particles, feats.track_ids, last_hit
        born_xy = []
        fmean = res.feature_mean[:, :2]
        for i in new_rows:
            s = owner[i]
            if np.sqrt(np.trace(vcov_out[s, :2, :2]) / 2.0) > p.feature_birth_max_std_m:
                continue  # a poorly localised vehicle would start a vague track that attracts wrong rows
            pos = vmean_out[s, :2] + vz[i]
            if fmean.shape[0] and np.min(np.hypot(*(fmean - pos).T)) < p.feature_birth_gate_m:
                continue
            if born_xy and np.min(np.hypot(*(np.array(born_xy) - pos).T)) < p.feature_birth_gate_m:
                continue
            born_xy.append(pos)
            cov = 2.0 * (vcov_out[s, :2, :2] + vr[i])
            newp = init_particles(pos[None], cov[None], self.bp, self.rng, velocity_cov=1e-12 * np.eye(2)[None])
            newp[:, :, 2:] = 0.0
            fparts = np.concatenate([fparts, newp])
            tids = np.append(tids, self._next_track)
            assigned[i] = self._next_track
            self._next_track += 1
            lh = np.append(lh, frame.t)
            self.stats["features_born"] += 1
        extra["assign"][sel] = assigned
        self._feat[r] = self._drop_features(_RsuFeatures(fparts, tids, lh), frame, r)
        f = self._feat[r]
        if f.track_ids.size:
            extra["fm"].append(f.particles.mean(axis=1))
            extra["fc"].append(np.stack([np.cov(x.T) for x in f.particles]))
            extra["fid"].append(f.track_ids)

    def _drop_features(self, f: _RsuFeatures, frame, r) -> _RsuFeatures:
        if f.track_ids.size == 0:
            return f
        p = self.params
        xy = f.particles[:, :, :2].mean(axis=1)
        far = np.hypot(*(xy - frame.infra.rsu_xy[r]).T) > p.feature_keep_radius_m
        stale = frame.t - f.last_hit > p.feature_drop_s
        keep = ~(far | stale)
        self.stats["features_dropped"] += int((~keep).sum())
        return _RsuFeatures(f.particles[keep], f.track_ids[keep], f.last_hit[keep])

    def step(self, frame: Frame) -> StepEstimate:
        self._extra = self._begin(frame)
        est = super().step(frame)
        e = self._extra
        if e["fid"]:
            fm = np.concatenate(e["fm"])
            fmean = np.hstack([fm, np.zeros_like(fm)])
            fcov = np.zeros((fm.shape[0], 4, 4))
            fcov[:, :2, :2] = np.concatenate(e["fc"])[:, :2, :2]
            fid = np.concatenate(e["fid"])
        else:
            fmean, fcov, fid = np.empty((0, 4)), np.empty((0, 4, 4)), np.empty(0, dtype=np.int64)
        return StepEstimate(mean=est.mean, cov=est.cov, covered=est.covered, feature_mean=fmean, feature_cov=fcov,
                            feature_track_ids=fid, v2f_assignment=e["assign"])
