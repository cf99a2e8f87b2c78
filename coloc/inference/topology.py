"""Topology pseudo-measurement of an infrastructure sensor with unknown pose.

Zhang et al. (SME) eq. (10) and Gulati et al. eq. (8): the sum of squared
pairwise distances of the N detected vehicles,

    z^2 = sum_{i<j} |q_i - q_j|^2 = N * sum_i |q_i - mean(q)|^2,

is the same in the sensor's local frame and in the global frame (distances are
invariant to rotation and translation) and the same for any order of the
detections, so neither the sensor pose nor the association is needed.

The sensor measures q_i = R(theta) (p_i - s) + n_i, n_i ~ N(0, var I2). Per axis
z^2 = u^T L u with L = N I - 1 1^T (the Laplacian of the complete graph:
eigenvalues 0 and N, tr L = N (N - 1), L^2 = N L). For Gaussian noise this gives
in closed form

    E[z^2]   = z_true^2 + 2 var N (N - 1)                              (mean bias)
    Var[z^2] = 4 N var z_true^2 + 4 (N - 1) N^2 var^2.

The first variance term is exactly Gulati et al.'s linearised covariance (15)
with M of (16) taken as the gradient of z^2 with respect to the 2N sensor
coordinates (grad_i = 2 N (q_i - mean q), so M Cov M' = 4 N var z^2); the second
is the Gaussian second-order term, which keeps the variance positive when the
vehicles (nearly) coincide, where (15) alone is zero. Neither paper states the
bias; we subtract it (it is 120 m^2 for Zhang's three vehicles and var 10 m^2).
"""

from __future__ import annotations

import numpy as np


def sum_sq_pairwise(points: np.ndarray) -> np.ndarray:
    """sum_{i<j} |p_i - p_j|^2 over the vehicle axis -2 of ``points`` (..., N, 2); eqs. (8) / (10)."""
    p = np.asarray(points, dtype=float)
    n = p.shape[-2]
    centred = p - p.mean(axis=-2, keepdims=True)
    return n * np.sum(centred * centred, axis=(-2, -1))


def sum_sq_pairwise_grad(points: np.ndarray) -> np.ndarray:
    """Gradient of :func:`sum_sq_pairwise` with respect to each point, (..., N, 2): 2 N (p_i - mean p).

    The per-axis sums of Gulati et al.'s Jacobian (19), written per vehicle."""
    p = np.asarray(points, dtype=float)
    n = p.shape[-2]
    return 2.0 * n * (p - p.mean(axis=-2, keepdims=True))


def topology_bias(n: int, var: float) -> float:
    """E[z^2] - z_true^2 for N detections with isotropic noise variance ``var`` per axis."""
    return 2.0 * var * n * (n - 1)


def topology_variance(z2_true: float | np.ndarray, n: int, var: float) -> float | np.ndarray:
    """Var[z^2] given the true z^2: Gulati (15)-(16) plus the Gaussian second-order term (module doc)."""
    return 4.0 * n * var * np.maximum(z2_true, 0.0) + 4.0 * (n - 1) * n * n * var * var


def topology_variance_eq16_literal(n: int, var: float) -> float:
    """Gulati (15) with M of (16) read literally: the gradient of z_t^T itself, not of (z_t^T)^2.

    z = sqrt(S) with S = sum_{i<j} |q_i - q_j|^2, grad z = grad S / (2 z) and |grad S|^2 = 4 N S, so
    M Cov M' = var |grad z|^2 = N var for any configuration (S > 0): the variance of the distance-like
    z, not of the squared quantity that factor (13) compares. Used only by the opt-in
    ``topology_noise = "eq16_literal"`` of :mod:`coloc.methods.fg_topology`.
    """
    return float(n * var)


def topology_pseudo_measurement(sensor_points: np.ndarray, var: float) -> tuple[float, float]:
    """Bias-corrected topology pseudo-measurement of one scan (N, 2) and its variance.

    The variance is evaluated at the bias-corrected value (clipped at zero): the
    derived covariance (15) at the measurement, as Gulati et al. do.
    """
    q = np.asarray(sensor_points, dtype=float)
    n = q.shape[0]
    value = float(sum_sq_pairwise(q)) - topology_bias(n, var)
    return value, float(topology_variance(max(value, 0.0), n, var))
