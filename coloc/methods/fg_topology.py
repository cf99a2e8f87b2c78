"""Factor-graph vehicle-infrastructure localization with topology factors (Gulati et al.).

Methods: ``fg_topology_old`` (topology factor (8) on the current positions),
``fg_topology_new`` (factor (11)-(13) on the previous positions moved by the
odometry, covariance (15)-(16)), and ``kf_gps_odom`` (the Kalman baseline with
GPS and odometry). The graphs are solved in batch over the whole run with
gtsam's Levenberg-Marquardt optimizer (Sec. III-D).

Model (Sec. IV-A), per vehicle i and step t, positions only (Point2 variables):

* GPS (6)-(7): g_t^i = p_t^i + n_g, n_g ~ N(0, gps_var I2): a unary PriorFactorPoint2.
* Odometry (4)-(5), (9)-(10): the displacement d_t^i = p_t^i - p_{t-1}^i + n_o,
  n_o ~ N(0, odom_var I2), in the global frame (as (10) adds it to the global
  position): a BetweenFactorPoint2 between consecutive states.
* Infrastructure sensor (radar) with unknown pose: unlabelled detections in its
  own frame, reduced to the topology pseudo-measurement z_t^2 of
  :mod:`coloc.inference.topology` (bias-corrected; variance (15) plus the second-order
  term, see there).
* Old factor (8): residual sum_{i<j} |p_t^i - p_t^j|^2 - z_t^2, on the N current states.
* New factor (11)-(13): residual sum_{i<j} |(p_{t-1}^i + d_t^i) - (p_{t-1}^j + d_t^j)|^2 - z_t^2.
  Eq. (11) (and the Jacobian (19)) involve only the previous states and the
  odometry; the current states listed in (12)-(13) enter with a zero Jacobian, so
  the factor is attached to the N previous states only. It exists for t >= 1.
  Its covariance is (15), the radar's noise only, as the paper writes it: the
  odometry noise in d_t, which the odometry factor also uses, is not counted.
* Noise of both topology factors (``topology_noise``): "z2" (default) is the
  variance of the squared quantity z_t^2 that (8) and (13) compare, i.e. (15)
  with M of (16) taken as the gradient of z^2, plus the second-order term
  (:mod:`coloc.inference.topology`). "eq16_literal" reads (16) as printed, M = d z_t^T / d(x, y)
  (z, not z^2), which gives sigma^2 = N radar_var whatever the geometry, and uses it
  as the noise of the squared residual (13): a topology factor too confident by
  about 4 z^2 (z^2 ~ 1e4..1e6 m^2 here), which LM needs tens to hundreds of
  iterations to satisfy, more for the old factor (on the current states, which
  the GPS and both odometry neighbours pull on) than for the new one. With the
  default max_iterations = 100 (also GTSAM 3.2's default) the old graph often
  stops at the cap; that reproduces the sign and size of Table II's time
  saving of the new factor, not Table I's ordering (README). Opt-in only: it is
  not a consistent noise model, and its RMSE depends on the iteration cap.

``kf_gps_odom``: the paper's Kalman filter (20) is a constant-velocity filter
whose use of the odometry is not stated. We use the filter that is exact for
the model above: position state, odometry as the known input
(p_t = p_{t-1} + d_t, process noise odom_var), GPS update; initialised by the
first GPS fix. With the topology factors removed the factor graph is the
Rauch-Tung-Striebel smoother of exactly this filter (its last state equals the
filter's), which the tests check.

:class:`FgTopologyInfra` is ``fg_topology_new`` run online at road-side units (a fixed-lag
smoother per RSU; the infrastructure mode of :mod:`coloc.methods.infra`, whose doc describes it).
gtsam is imported inside the functions that build a graph, so importing this module does not
load it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from coloc.inference.topology import (
    sum_sq_pairwise,
    sum_sq_pairwise_grad,
    topology_pseudo_measurement,
    topology_variance_eq16_literal,
)
from coloc.methods.fg_bias import chain_factor, fix_factor, start_factor
from coloc.methods.gnss_bias import GnssModelParams
from coloc.methods.infra import InfraMethodParams, _InfraBase
from coloc.methods.registry import FG_TOPOLOGY_NEW

if TYPE_CHECKING:  # annotations only; imported at run time inside the functions that use it
    import gtsam

TOPOLOGY_NOISES = ("z2", "eq16_literal")


@dataclass(frozen=True)
class FgTopologyParams:
    """Sensor variances (Gulati Sec. IV-A: odometry diag(1,1), GPS diag(9,9), radar diag(0.1,0.1)), LM settings
    and the topology factors' noise model (module doc: "z2" or "eq16_literal")."""

    odom_var: float = 1.0
    gps_var: float = 9.0
    radar_var: float = 0.1
    max_iterations: int = 100
    relative_error_tol: float = 1e-5
    absolute_error_tol: float = 1e-5
    topology_noise: str = "z2"

    def __post_init__(self):
        if self.topology_noise not in TOPOLOGY_NOISES:
            raise ValueError(f"topology_noise must be one of {TOPOLOGY_NOISES}, not {self.topology_noise!r}")


def state_key(vehicle: int, t: int, n_steps: int) -> int:
    """gtsam key of p_t^i."""
    return vehicle * n_steps + t


def _old_topology_error(z2: float):
    """Error function of factor (8): h(p_t^1..N) - z_t^2, Jacobians 2N (p_i - mean p) (eq. (19))."""

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
        keys = this.keys()
        p = np.array([values.atPoint2(k) for k in keys])
        if jacobians is not None:
            grad = sum_sq_pairwise_grad(p)
            for i in range(len(keys)):
                jacobians[i] = grad[i].reshape(1, 2)
        return np.array([sum_sq_pairwise(p) - z2])

    return error


def _new_topology_error(z2: float, odom: np.ndarray):
    """Error function of factor (11)-(13): h(p_{t-1}^i + d_t^i) - z_t^2 on the previous states."""

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
        keys = this.keys()
        p = np.array([values.atPoint2(k) for k in keys]) + odom
        if jacobians is not None:
            grad = sum_sq_pairwise_grad(p)  # d/dp_{t-1} of (11) = eq. (19)
            for i in range(len(keys)):
                jacobians[i] = grad[i].reshape(1, 2)
        return np.array([sum_sq_pairwise(p) - z2])

    return error


def build_graph(
    gps: np.ndarray, odom: np.ndarray, sensor: np.ndarray | None, params: FgTopologyParams, topology: str
) -> gtsam.NonlinearFactorGraph:
    """Factor graph of one run.

    gps (T, N, 2) each vehicle's own fix; odom (T, N, 2) with odom[t] the displacement
    t-1 -> t (odom[0] unused); sensor (T, N, 2) unlabelled infrastructure detections in
    the sensor frame; ``topology`` one of "old", "new", "none".
    """
    import gtsam  # imported when a factor graph is built

    n_steps, n_veh, _ = gps.shape
    graph = gtsam.NonlinearFactorGraph()
    gps_noise = gtsam.noiseModel.Isotropic.Sigma(2, float(np.sqrt(params.gps_var)))
    odom_noise = gtsam.noiseModel.Isotropic.Sigma(2, float(np.sqrt(params.odom_var)))
    for i in range(n_veh):
        for t in range(n_steps):
            graph.add(gtsam.PriorFactorPoint2(state_key(i, t, n_steps), gps[t, i], gps_noise))
            if t > 0:
                graph.add(gtsam.BetweenFactorPoint2(
                    state_key(i, t - 1, n_steps), state_key(i, t, n_steps), odom[t, i], odom_noise))
    if topology == "none" or n_veh < 2:
        return graph
    if topology not in ("old", "new"):
        raise ValueError(f"topology must be 'old', 'new' or 'none', not {topology!r}")
    for t in range(n_steps):
        if topology == "new" and t == 0:
            continue  # (11) needs a previous state and an odometry reading
        z2, var = topology_pseudo_measurement(sensor[t], params.radar_var)
        if params.topology_noise == "eq16_literal":
            var = topology_variance_eq16_literal(n_veh, params.radar_var)
        noise = gtsam.noiseModel.Isotropic.Sigma(1, float(np.sqrt(var)))
        if topology == "old":
            keys = [state_key(i, t, n_steps) for i in range(n_veh)]
            graph.add(gtsam.CustomFactor(noise, keys, _old_topology_error(z2)))
        else:
            keys = [state_key(i, t - 1, n_steps) for i in range(n_veh)]
            graph.add(gtsam.CustomFactor(noise, keys, _new_topology_error(z2, np.array(odom[t], dtype=float))))
    return graph


def initial_values(gps: np.ndarray) -> gtsam.Values:
    """LM starts from the GPS fixes (the paper does not state its initial estimate)."""
    import gtsam  # imported when a factor graph is built

    n_steps, n_veh, _ = gps.shape
    values = gtsam.Values()
    for i in range(n_veh):
        for t in range(n_steps):
            values.insert(state_key(i, t, n_steps), np.array(gps[t, i], dtype=float))
    return values


def solve_graph(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, n_steps: int, n_veh: int,
                params: FgTopologyParams) -> tuple[np.ndarray, int]:
    """Levenberg-Marquardt over the whole run; returns positions (T, N, 2) and the iteration count."""
    import gtsam  # imported when a factor graph is built

    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(params.max_iterations)
    lm.setRelativeErrorTol(params.relative_error_tol)
    lm.setAbsoluteErrorTol(params.absolute_error_tol)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, lm)
    result = optimizer.optimize()
    out = np.empty((n_steps, n_veh, 2))
    for i in range(n_veh):
        for t in range(n_steps):
            out[t, i] = result.atPoint2(state_key(i, t, n_steps))
    return out, int(optimizer.iterations())


def fg_localize(gps: np.ndarray, odom: np.ndarray, sensor: np.ndarray | None, params: FgTopologyParams,
                topology: str) -> tuple[np.ndarray, int]:
    """Smoothed positions (T, N, 2) of all vehicles over the run and the LM iteration count."""
    gps = np.asarray(gps, dtype=float)
    n_steps, n_veh, _ = gps.shape
    graph = build_graph(gps, np.asarray(odom, dtype=float), sensor, params, topology)
    return solve_graph(graph, initial_values(gps), n_steps, n_veh, params)


def kf_gps_odom(gps: np.ndarray, odom: np.ndarray, params: FgTopologyParams,
                smooth: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Kalman filter (optionally RTS-smoothed) of all vehicles at once.

    Position state per vehicle, predict p_t = p_{t-1} + d_t with covariance odom_var I2,
    update with the GPS fix (covariance gps_var I2); the first fix initialises. Returns
    means (T, N, 2) and covariances (T, N, 2, 2). Noises are isotropic and the model is
    the same on both axes, but the covariance is carried as 2x2 for clarity.
    """
    gps = np.asarray(gps, dtype=float)
    odom = np.asarray(odom, dtype=float)
    n_steps, n_veh, _ = gps.shape
    eye = np.eye(2)
    q = params.odom_var * eye
    r = params.gps_var * eye
    mean = np.empty((n_steps, n_veh, 2))
    cov = np.empty((n_steps, n_veh, 2, 2))
    pred_mean = np.empty_like(mean)
    pred_cov = np.empty_like(cov)
    mean[0] = gps[0]
    cov[0] = r
    for t in range(1, n_steps):
        m = mean[t - 1] + odom[t]
        p = cov[t - 1] + q
        pred_mean[t], pred_cov[t] = m, p
        s = p + r
        gain = p @ np.linalg.inv(s)
        mean[t] = m + np.einsum("nij,nj->ni", gain, gps[t] - m)
        ikh = eye - gain
        c = ikh @ p @ np.swapaxes(ikh, -1, -2) + gain @ r @ np.swapaxes(gain, -1, -2)  # Joseph form
        cov[t] = 0.5 * (c + np.swapaxes(c, -1, -2))
    if not smooth:
        return mean, cov
    # Rauch-Tung-Striebel backward pass (state transition = identity).
    sm, sc = mean.copy(), cov.copy()
    for t in range(n_steps - 2, -1, -1):
        g = cov[t] @ np.linalg.inv(pred_cov[t + 1])
        sm[t] = mean[t] + np.einsum("nij,nj->ni", g, sm[t + 1] - pred_mean[t + 1])
        c = cov[t] + g @ (sc[t + 1] - pred_cov[t + 1]) @ np.swapaxes(g, -1, -2)
        sc[t] = 0.5 * (c + np.swapaxes(c, -1, -2))
    return sm, sc


def run_rmse(est: np.ndarray, truth: np.ndarray) -> float:
    """Gulati eq. (21): sqrt( sum_t sum_i |p_est - p_true|^2 / n ), summed over vehicles, averaged over steps."""
    err = np.asarray(est) - np.asarray(truth)
    return float(np.sqrt(np.sum(err * err) / err.shape[0]))


# --------------------------------------------------------------------------- fg_topology_new online at RSUs


class FgTopologyInfra(_InfraBase):
    """``fg_topology_new`` per RSU with a fixed-lag smoother (the doc of :mod:`coloc.methods.infra`)."""

    name = FG_TOPOLOGY_NEW.name

    def __init__(self, params: InfraMethodParams, gnss_model: GnssModelParams | None = None):
        super().__init__(params, gnss_model)
        import gtsam  # only this method needs it

        self._gtsam = gtsam
        # topology_updates = _new (factor (11)) + _old (fallback (8)); _skipped: neither could be formed.
        self.stats = {"topology_updates": 0, "topology_updates_new": 0, "topology_updates_old": 0,
                      "topology_skipped": 0}
        self._smoother: dict[int, object] = {}
        self._keys: dict[int, dict[str, int]] = {}  # r -> vehicle id -> key of its state at the last step
        self._bias_keys: dict[int, dict[str, int]] = {}  # [gnss_model]: r -> vehicle id -> key of its bias
        self._next_key = 0

    def _new_smoother(self, dt):
        gtsam = self._gtsam
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(self.params.fg_max_iterations)
        return gtsam.BatchFixedLagSmoother(float(self.params.fg_window_steps * dt), lm)

    def _rsu_step(self, frame, r, rows, prev, fallback):
        if self.model is not None:
            return self._rsu_step_bias(frame, r, rows, prev, fallback)
        gtsam = self._gtsam
        infra = frame.infra
        keys_prev = self._keys.get(r, {})
        if rows.size == 0:
            self._keys[r] = {}
            return None
        smoother, graph, values, stamps, ids, entered, odom = self._open_step(frame, r, rows)
        keys_now = {}
        new_rows = [a for a, vid in enumerate(ids) if vid not in keys_prev or entered[a]]
        start_m, start_c, held = (self._start_beliefs(frame, rows[new_rows], prev) if new_rows
                                  else (np.empty((0, 4)), np.empty((0, 4, 4)), np.empty(0, dtype=bool)))
        start = {a: b for b, a in enumerate(new_rows)}
        est_prev = {}
        for a, vid in enumerate(ids):
            key = self._next_key
            self._next_key += 1
            keys_now[vid] = key
            z = frame.gnss_z[rows[a], :2]
            rz = frame.gnss_R[rows[a], :2, :2]
            if not (a in start and held[start[a]]):  # a start prior that is this step's fix is not added twice
                graph.add(gtsam.PriorFactorPoint2(key, z, gtsam.noiseModel.Gaussian.Covariance(rz)))
            if a in start:
                b = start[a]
                graph.add(gtsam.PriorFactorPoint2(key, start_m[b, :2],
                                                  gtsam.noiseModel.Gaussian.Covariance(start_c[b, :2, :2])))
                init = start_m[b, :2]
            else:
                kp = keys_prev[vid]
                d = self._add_odometry(graph, kp, key, odom[a], infra.odom_var)
                p_prev = self._estimate_point(smoother, kp)
                est_prev[vid] = p_prev
                init = p_prev + d
            values.insert(key, np.asarray(init, float))
            stamps[key] = float(frame.t)
        self._add_topology(graph, infra, r, rows.size, ids, new_rows, odom, keys_prev, keys_now)
        self._update(smoother, graph, values, stamps)
        self._keys[r] = keys_now
        result = smoother.calculateEstimate()
        m = fallback.mean[rows].copy()
        c = fallback.cov[rows].copy()
        for a, vid in enumerate(ids):
            key = keys_now[vid]
            m[a, :2] = result.atPoint2(key)
        return rows, m, c

    def _rsu_step_bias(self, frame, r, rows, prev, fallback):
        """The step under ``[gnss_model]``: the factors of :meth:`_rsu_step` with the receiver bias as a
        per-vehicle Gauss-Markov chain (:mod:`coloc.methods.fg_bias`); the start belief is the bias
        tracker's joint (p, b). A fix the vehicle's own tracker excluded (its chi-square rule,
        :mod:`coloc.methods.gnss_bias`) is not a factor. The reported position covariance is the
        smoother's marginal (gtsam.Marginals on its window); velocity as the tracker's, Cov(p, v) = 0."""
        gtsam = self._gtsam
        infra = frame.infra
        share = self.model.bias_share
        biased = share > 0.0
        decay = float(np.exp(-frame.dt / self.model.bias_tau_s))
        keys_prev = self._keys.get(r, {})
        bkeys_prev = self._bias_keys.get(r, {})
        if rows.size == 0:
            self._keys[r], self._bias_keys[r] = {}, {}
            return None
        smoother, graph, values, stamps, ids, entered, odom = self._open_step(frame, r, rows)
        excluded = self.gnss.last_excluded
        excluded = np.zeros(frame.n_vehicles, bool) if excluded is None else np.asarray(excluded, bool)
        keys_now, bkeys_now = {}, {}
        new_rows = [a for a, vid in enumerate(ids) if vid not in keys_prev or entered[a]]
        start_m, start_c, held = (self._start_beliefs6(frame, rows[new_rows], prev) if new_rows
                                  else (np.empty((0, 6)), np.empty((0, 6, 6)), np.empty(0, dtype=bool)))
        start = {a: b for b, a in enumerate(new_rows)}
        for a, vid in enumerate(ids):
            key, bkey = self._next_key, self._next_key + 1
            self._next_key += 2 if biased else 1
            keys_now[vid] = key
            z = frame.gnss_z[rows[a], :2]
            rz = np.asarray(frame.gnss_R[rows[a], :2, :2], float)
            own_fix = not (a in start and held[start[a]]) and not excluded[rows[a]]
            if biased:
                bkeys_now[vid] = bkey
                if own_fix:
                    graph.add(fix_factor(gtsam, key, bkey, z, rz, share))
            elif own_fix:
                graph.add(gtsam.PriorFactorPoint2(key, z, gtsam.noiseModel.Gaussian.Covariance(rz)))
            if a in start:
                b = start[a]
                if biased:
                    graph.add(start_factor(gtsam, key, bkey, start_m[b], start_c[b]))
                    values.insert(bkey, np.asarray(start_m[b, 4:], float))
                    stamps[bkey] = float(frame.t)
                else:
                    graph.add(gtsam.PriorFactorPoint2(key, start_m[b, :2],
                                                      gtsam.noiseModel.Gaussian.Covariance(start_c[b, :2, :2])))
                init = start_m[b, :2]
            else:
                kp = keys_prev[vid]
                d = self._add_odometry(graph, kp, key, odom[a], infra.odom_var)
                init = self._estimate_point(smoother, kp) + d
                if biased:
                    kb = bkeys_prev[vid]
                    graph.add(chain_factor(gtsam, kb, bkey, decay, rz, share))
                    values.insert(bkey, decay * self._estimate_point(smoother, kb))
                    stamps[bkey] = float(frame.t)
            values.insert(key, np.asarray(init, float))
            stamps[key] = float(frame.t)
        self._add_topology(graph, infra, r, rows.size, ids, new_rows, odom, keys_prev, keys_now)
        self._update(smoother, graph, values, stamps)
        self._keys[r], self._bias_keys[r] = keys_now, bkeys_now
        result = smoother.calculateEstimate()
        marginals = gtsam.Marginals(smoother.getFactors(), result)
        m = fallback.mean[rows].copy()
        c = fallback.cov[rows].copy()
        for a, vid in enumerate(ids):
            key = keys_now[vid]
            m[a, :2] = result.atPoint2(key)
            c[a, :2, :2] = marginals.marginalCovariance(key)
            c[a, :2, 2:] = 0.0
            c[a, 2:, :2] = 0.0
        return rows, m, c

    def _open_step(self, frame, r, rows):
        """RSU ``r``'s smoother (made at its first step), an empty graph, values and time stamps for the
        step's factors, and the ids, entered flags and odometry of its vehicles ``rows``."""
        if r not in self._smoother:
            self._smoother[r] = self._new_smoother(frame.dt)
        return (self._smoother[r], self._gtsam.NonlinearFactorGraph(), self._gtsam.Values(), {},
                frame.vehicle_ids[rows], np.asarray(frame.entered[rows], bool), frame.infra.odom[rows])

    def _add_odometry(self, graph, key_prev, key, odom, odom_var) -> np.ndarray:
        """The odometry factor p_t - p_{t-1} = d_t (variance ``odom_var`` per axis) between a vehicle's
        last and current state; returns d_t, zero when the step has no odometry."""
        d = odom if np.all(np.isfinite(odom)) else np.zeros(2)
        noise = self._gtsam.noiseModel.Isotropic.Sigma(2, float(np.sqrt(odom_var)))
        graph.add(self._gtsam.BetweenFactorPoint2(key_prev, key, np.asarray(d, float), noise))
        return d

    def _add_topology(self, graph, infra, r, n, ids, new_rows, odom, keys_prev, keys_now) -> None:
        """The topology factor of step t from RSU ``r``'s radar scan of its ``n`` vehicles ``ids``
        (pseudo-measurement z_t^2 and its variance (15)-(16), coloc.inference.topology)."""
        if n < 2:
            return
        pts = infra.radar_z[infra.radar_owner == r]
        if pts.shape[0] != n:
            # The scan's points are not the vehicles in range: neither (8) nor (11) holds.
            self.stats["topology_skipped"] += 1
            return
        gtsam = self._gtsam
        z2, var = topology_pseudo_measurement(pts, infra.radar_var)
        noise = gtsam.noiseModel.Isotropic.Sigma(1, float(np.sqrt(var)))
        if not new_rows and np.all(np.isfinite(odom)):
            # New factor (11)-(13): sum_{i<j} |(p_{t-1}^i + d_t^i) - (p_{t-1}^j + d_t^j)|^2 - z_t^2
            # on the N previous states (every vehicle in range has one here, and odometry d_t).
            kp = [keys_prev[vid] for vid in ids]
            graph.add(gtsam.CustomFactor(noise, kp, _new_topology_error(z2, np.array(odom, float))))
            self.stats["topology_updates_new"] += 1
        else:
            # Fallback, old factor (8): sum_{i<j} |p_t^i - p_t^j|^2 - z_t^2 on the N current
            # states, which every vehicle in range has (an entering one from its start belief).
            graph.add(gtsam.CustomFactor(noise, [keys_now[vid] for vid in ids], _old_topology_error(z2)))
            self.stats["topology_updates_old"] += 1
        self.stats["topology_updates"] += 1

    def _update(self, smoother, graph, values, stamps) -> None:
        """The fixed-lag smoother's update with the step's new factors, values and their time stamps."""
        ts = self._gtsam.FixedLagSmootherKeyTimestampMap()
        for k, t in stamps.items():
            ts.insert((k, t))
        smoother.update(graph, values, ts)

    @staticmethod
    def _estimate_point(smoother, key):
        return np.asarray(smoother.calculateEstimatePoint2(key), float)
