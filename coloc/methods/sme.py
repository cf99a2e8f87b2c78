"""``sme``: the symmetric measurement equation filter of Zhang et al. on an EKF.

Joint state of N vehicles, x = [p^1, v^1, ..., p^N, v^N] with each vehicle's
block in the project's order [px, py, vx, vy] (the paper's eq. (7) orders
[px, vx, py, vy]; the model is the same). Process model (3)-(4), (7)-(8):
constant velocity with white-acceleration noise of standard deviation delta,
Q = delta^2 B B^T, B = [T^2/2 I; T I]. This equals the paper's (8) for its T = 1
(for T != 1 the printed (8), with T^2/4, T^2/2, T, is not a covariance: its
determinant T^3 (1 - T) / 4 per axis is negative for T > 1).

Measurements of one step, both unlabelled:

* GPS fixes g_k (N, 2) in the global frame, noise gps_var I2 each, in unknown
  order. Pseudo-measurement (9): the sums of powers, per axis separately,
  y_x = [sum_i g_x^i, sum_i (g_x^i)^2, ..., sum_i (g_x^i)^N] and likewise y_y.
* Infrastructure detections (N, 2) in the sensor's unknown frame, noise
  sensor_var I2. Pseudo-measurement (10): the sum of squared pairwise distances
  (pose- and order-free), see :mod:`coloc.inference.topology`.

Numerical conditioning. The powers are taken of u = (g - c) / L with c the
mean of the predicted positions and L a length scale (both known at update time).
The sums of powers of u are an invertible linear map of those of g (binomial
expansion, with sum_i g^0 = N), and the EKF update is invariant under an
invertible linear map of the measurement when its noise covariance is mapped
with it, so this only changes rounding (a test checks the update against
c = 0, L = 1). Without it the third powers of 8 km positions reach 1e11.

Pseudo-measurement model and noise (the paper refers to [10], [17]; this is our
documented choice):

* Mean: the exact expectation under the Gaussian fix noise, h_k(x) = sum_i
  E[(mu_i + e)^k] with e ~ N(0, s^2), E[(mu + e)^k] = sum_{m even} C(k, m) mu^(k-m)
  s^m (m-1)!!. (For k = 2 this adds N s^2: without it the filter would be pulled
  outwards.) The topology mean is corrected the same way (coloc.inference.topology).
* Covariance, evaluated at the predicted positions mu_i (the EKF linearisation
  point), two options:
  ``pseudo_noise = "linearized"``: first-order (delta-method) linearisation of (9)
  in the fix noise, R = G diag(s^2) G^T with G_{k,i} = k mu_i^(k-1) per axis (the x
  and y blocks are independent).
  ``pseudo_noise = "moments"`` (default): the exact covariance of the power sums
  under Gaussian fix noise, Cov(s_k, s_l) = sum_i (M_{k+l}(mu_i) - M_k(mu_i) M_l(mu_i)),
  whose first-order term is the linearised R. Zhang's three vehicles start at one
  point, where G has zero rows for k >= 2 while the power sums still carry noise
  of order s^2; the linearised R is then far too small and the filter diverged in
  a few of 50 seeded runs (RMSE in the km), the exact one in none. The topology
  variance is (15) plus the second-order term (coloc.inference.topology), which is exact,
  evaluated at the predicted state.
* Jacobian of the mean with respect to the state: d/dmu E[(mu + e)^k] = k M_{k-1}(mu).

The x and y power sums are symmetric in x and y separately, so (9) does not
tie each x to its y: pairings that permute the y coordinates among vehicles
produce the same y_1. Nor does (10) help: sum_{i<j} |p_i - p_j|^2 =
sum_axes (N s_2 - s_1^2) is a function of the first two power sums per axis, so
such ghosts give exactly the same (9) and (10). Only the prior and the dynamics
disambiguate. In Zhang's own scenario (east, north-east, north from one point)
the ghost (80t, 0), (45t, 80t), (0, 45t) is one; 1 of 200 seeded runs of the
shipped study locks onto it and diverges (tests and study report). This is the
paper's construction and is kept; a pairing-aware SME (complex power sums
sum_i (x_i + j y_i)^k, Kamen's 2-D form) would remove it.

The baseline ``kf`` is the joint Kalman filter told the GPS association, which
cannot use the infrastructure sensor (Zhang Sec. IV). With N = 1 and no
topology the SME filter is exactly this Kalman filter (tests).
"""

from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from coloc.inference.topology import sum_sq_pairwise, sum_sq_pairwise_grad, topology_bias, topology_variance
from coloc.methods.registry import SME


@dataclass(frozen=True)
class SmeParams:
    """Zhang Sec. IV: GPS diag(50, 50), infrastructure sensor diag(10, 10), delta = 1/2, T = 1."""

    gps_var: float = 50.0
    sensor_var: float = 10.0
    process_sigma: float = 0.5
    dt: float = 1.0
    pseudo_noise: str = "moments"  # or "linearized" (module doc: the linearised one diverges at a common start)
    use_topology: bool = True

    def __post_init__(self):
        if self.pseudo_noise not in ("linearized", "moments"):
            raise ValueError(f"pseudo_noise must be 'linearized' or 'moments', not {self.pseudo_noise!r}")


def cv_transition(n_veh: int, dt: float) -> np.ndarray:
    """Block-diagonal A of (4), (7) for the joint state, per vehicle [px, py, vx, vy]."""
    a = np.eye(4)
    a[0, 2] = a[1, 3] = dt
    return np.kron(np.eye(n_veh), a)


def cv_process_cov(n_veh: int, dt: float, sigma: float) -> np.ndarray:
    """Q of (8): sigma^2 B B^T per vehicle, B = [T^2/2 I; T I] (equals the paper's (8) at T = 1)."""
    b = np.vstack([0.5 * dt * dt * np.eye(2), dt * np.eye(2)])
    return np.kron(np.eye(n_veh), sigma * sigma * (b @ b.T))


def gaussian_raw_moments(mu: np.ndarray, var: float, kmax: int) -> np.ndarray:
    """M[k] = E[(mu + e)^k], e ~ N(0, var), for k = 0..kmax; shape (kmax + 1,) + mu.shape."""
    mu = np.asarray(mu, dtype=float)
    out = np.zeros((kmax + 1,) + mu.shape)
    # Central moments of e: E[e^m] = (m-1)!! var^(m/2) for even m, 0 for odd m.
    central = np.zeros(kmax + 1)
    central[0] = 1.0
    for m in range(2, kmax + 1, 2):
        central[m] = central[m - 2] * (m - 1) * var
    for k in range(kmax + 1):
        for m in range(0, k + 1, 2):
            out[k] += comb(k, m) * central[m] * mu ** (k - m)
    return out


def power_sums(u: np.ndarray, n_pow: int) -> np.ndarray:
    """Eq. (9) for one axis: [sum_i u_i, sum_i u_i^2, ..., sum_i u_i^n_pow]."""
    return np.array([np.sum(u ** k) for k in range(1, n_pow + 1)])


def pseudo_measurement_model(
    positions: np.ndarray, var_u: float, pseudo_noise: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, Jacobian and noise covariance of (9) for one axis at positions ``positions`` (N,) (scaled units).

    Returns h (N,), dh/dmu (N, N) (row k-1 = power k, column = vehicle), R (N, N).
    """
    n = positions.shape[0]
    mom = gaussian_raw_moments(positions, var_u, 2 * n)  # (2N + 1, N)
    ks = np.arange(1, n + 1)
    h = mom[1 : n + 1].sum(axis=1)
    jac = ks[:, None] * mom[0:n]  # d/dmu E[(mu+e)^k] = k M_{k-1}
    if pseudo_noise == "linearized":
        g = ks[:, None] * positions[None, :] ** (ks[:, None] - 1)  # d s_k / d g_i at the predicted position
        r = var_u * g @ g.T
    else:
        r = np.empty((n, n))
        for a, k in enumerate(ks):
            for b, l in enumerate(ks):
                r[a, b] = np.sum(mom[k + l] - mom[k] * mom[l])
    return h, jac, 0.5 * (r + r.T)


def sme_predict(mean: np.ndarray, cov: np.ndarray, params: SmeParams) -> tuple[np.ndarray, np.ndarray]:
    """Prediction by (4) with (7)-(8)."""
    n = mean.shape[0] // 4
    a = cv_transition(n, params.dt)
    q = cv_process_cov(n, params.dt, params.process_sigma)
    p = a @ cov @ a.T + q
    return a @ mean, 0.5 * (p + p.T)


def sme_update(
    mean: np.ndarray,
    cov: np.ndarray,
    gps_fixes: np.ndarray,
    sensor_points: np.ndarray | None,
    params: SmeParams,
    centre: np.ndarray | None = None,
    scale: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """EKF update with the pseudo-measurements (9) and, if given, (10); see the module doc.

    ``gps_fixes`` (N, 2) and ``sensor_points`` (N, 2) in any order. ``centre`` and ``scale``
    default to the mean of the predicted positions and sqrt(max(gps_var, spread^2)).
    """
    n = mean.shape[0] // 4
    pos = mean.reshape(n, 4)[:, :2]
    if centre is None:
        centre = pos.mean(axis=0)
    if scale is None:
        spread2 = float(np.mean(np.sum((pos - centre) ** 2, axis=1)))
        scale = float(np.sqrt(max(params.gps_var, spread2)))
    var_u = params.gps_var / scale**2
    u_meas = (np.asarray(gps_fixes, dtype=float) - centre) / scale
    u_pred = (pos - centre) / scale

    use_topo = params.use_topology and sensor_points is not None and n >= 2
    m_dim = 2 * n + (1 if use_topo else 0)
    y = np.empty(m_dim)
    h = np.empty(m_dim)
    jac = np.zeros((m_dim, 4 * n))
    r = np.zeros((m_dim, m_dim))
    for axis in range(2):
        rows = slice(axis * n, (axis + 1) * n)
        y[rows] = power_sums(u_meas[:, axis], n)
        h_ax, j_ax, r_ax = pseudo_measurement_model(u_pred[:, axis], var_u, params.pseudo_noise)
        h[rows] = h_ax
        r[rows, rows] = r_ax
        # chain rule: d u / d p = 1 / scale; state column of vehicle i's axis is 4 i + axis
        jac[rows, 4 * np.arange(n) + axis] = j_ax / scale
    if use_topo:
        # (10) in scaled units (distances / scale): invariant to the sensor pose and the order.
        s2 = scale * scale
        var_s = params.sensor_var / s2
        y[-1] = sum_sq_pairwise(np.asarray(sensor_points, dtype=float) / scale) - topology_bias(n, var_s)
        topo_pred = float(sum_sq_pairwise(u_pred))
        h[-1] = topo_pred
        grad = sum_sq_pairwise_grad(u_pred) / scale  # (N, 2)
        jac[-1, 4 * np.arange(n)] = grad[:, 0]
        jac[-1, 4 * np.arange(n) + 1] = grad[:, 1]
        r[-1, -1] = topology_variance(topo_pred, n, var_s)

    s = jac @ cov @ jac.T + r
    s = 0.5 * (s + s.T)
    factor = cho_factor(s, lower=True)
    gain = cho_solve(factor, jac @ cov).T  # K = P H^T S^-1
    new_mean = mean + gain @ (y - h)
    ikh = np.eye(4 * n) - gain @ jac
    new_cov = ikh @ cov @ ikh.T + gain @ r @ gain.T  # Joseph form
    return new_mean, 0.5 * (new_cov + new_cov.T)


def kf_update_labelled(mean: np.ndarray, cov: np.ndarray, gps_fixes: np.ndarray, gps_var: float):
    """Kalman update of the joint state with the GPS fixes in vehicle order (the association known)."""
    n = mean.shape[0] // 4
    hmat = np.zeros((2 * n, 4 * n))
    for i in range(n):
        hmat[2 * i, 4 * i] = 1.0
        hmat[2 * i + 1, 4 * i + 1] = 1.0
    r = gps_var * np.eye(2 * n)
    s = hmat @ cov @ hmat.T + r
    factor = cho_factor(s, lower=True)
    gain = cho_solve(factor, hmat @ cov).T
    new_mean = mean + gain @ (np.asarray(gps_fixes, dtype=float).reshape(-1) - hmat @ mean)
    ikh = np.eye(4 * n) - gain @ hmat
    new_cov = ikh @ cov @ ikh.T + gain @ r @ gain.T
    return new_mean, 0.5 * (new_cov + new_cov.T)


@dataclass
class SmeFilter:
    """Recursive SME filter: ``step(gps_fixes, sensor_points)`` after construction with the joint prior.

    ``kind = "sme"`` or ``"kf"`` (the baseline: GPS in vehicle order, no sensor).
    """

    mean: np.ndarray
    cov: np.ndarray
    params: SmeParams = SmeParams()
    kind: str = SME.name

    def __post_init__(self):
        self.mean = np.array(self.mean, dtype=float)
        self.cov = np.array(self.cov, dtype=float)
        if self.kind not in (SME.name, "kf"):
            raise ValueError(f"kind must be {SME.name!r} or 'kf', not {self.kind!r}")

    def step(self, gps_fixes: np.ndarray, sensor_points: np.ndarray | None = None, predict: bool = True):
        """Predict (unless ``predict`` is False, for the first step) and update; returns (mean, cov) copies."""
        if predict:
            self.mean, self.cov = sme_predict(self.mean, self.cov, self.params)
        if self.kind == SME.name:
            self.mean, self.cov = sme_update(self.mean, self.cov, gps_fixes, sensor_points, self.params)
        else:
            self.mean, self.cov = kf_update_labelled(self.mean, self.cov, gps_fixes, self.params.gps_var)
        return self.mean.copy(), self.cov.copy()
