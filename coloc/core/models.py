"""Motion and measurement models of Brambilla et al., Sec. II.

Model (1): x_t = A x_{t-1} + B a_{t-1} + w_t, x = [px, py, vx, vy],
A = [[I, Ts I], [0, I]], B = [Ts^2/2 I; Ts I], w ~ N(0, Q), where the driving
noise is specified along and across the direction of travel:
Q = B R(theta) diag(s_along^2, s_cross^2) R(theta)^T B^T.
Model (2), features: x_F,t = A x_F,t-1 + w_F, Q_F = G diag(sv_par^2, sv_perp^2) G^T,
G = [Ts I; I] (a random walk on velocity, rotated to the feature heading).
Model (3), GNSS: z = x + n, R = blockdiag(sp^2 I, sv^2 I).
Model (4), V2F: z = x_F - x_V + n.
Constant-velocity model (28)-(29) of Fröhle et al. (the rsu_bp estimator and its scenario):
:func:`cv_transition`, :func:`cv_process_cov`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MotionParams:
    """Driving noise of model (1), m/s^2 (docs/architecture.md "Models and default parameters":
    crossroad 0.35 / 0.001)."""

    sigma_along: float = 0.35
    sigma_cross: float = 0.001
    # Below this speed the heading of the estimate is not trusted and the
    # driving noise is taken isotropic with sigma_along on both axes.
    heading_min_speed: float = 1.0
    # The heading an estimator rotates its body-frame IMU input with while the vehicle is slower than
    # heading_min_speed (coloc.core.inertial): "dead_reckoned" integrates the gyroscope's yaw rate from the
    # heading it kept; "held" keeps that heading unchanged, as the sensor-frame detections' heading does
    # (coloc.core.detections.vehicle_headings): a slow vehicle is mostly standing in a queue, where a
    # gyroscope's bias alone (0.5 deg/s turn-on, RotorS) turns the integrated heading by 30 deg a minute.
    imu_heading: str = "dead_reckoned"

    @property
    def holds_heading(self) -> bool:
        """``imu_heading == "held"``: what :func:`coloc.core.inertial.estimator_input` takes as ``hold``."""
        return self.imu_heading == "held"


IMU_HEADINGS = ("dead_reckoned", "held")


def transition_matrix(dt: float) -> np.ndarray:
    """A of model (1)."""
    a = np.eye(4)
    a[0, 2] = a[1, 3] = dt
    return a


def input_matrix(dt: float) -> np.ndarray:
    """B of model (1): maps the acceleration a_{t-1} (2,) to the state increment."""
    return np.vstack([0.5 * dt * dt * np.eye(2), dt * np.eye(2)])


def rotated_diag(headings: np.ndarray, s_par: float, s_perp: float) -> np.ndarray:
    """R(theta) diag(s_par^2, s_perp^2) R(theta)^T for each heading, (N, 2, 2)."""
    c, s = np.cos(headings), np.sin(headings)
    p2, q2 = s_par * s_par, s_perp * s_perp
    out = np.empty(headings.shape + (2, 2))
    out[..., 0, 0] = c * c * p2 + s * s * q2
    out[..., 1, 1] = s * s * p2 + c * c * q2
    out[..., 0, 1] = out[..., 1, 0] = c * s * (p2 - q2)
    return out


def driving_noise_cov(velocity: np.ndarray, dt: float, params: MotionParams) -> np.ndarray:
    """Q of model (1) for each vehicle, (N, 4, 4), oriented by its (estimated) velocity.

    The paper orients the driving noise to the vehicle heading. An estimator
    only has its own velocity estimate; where that is slower than
    ``heading_min_speed`` the heading is unknown and the noise is isotropic.
    """
    v = np.asarray(velocity, dtype=float)
    speed = np.hypot(v[:, 0], v[:, 1])
    heading = np.arctan2(v[:, 1], v[:, 0])
    acc_cov = rotated_diag(heading, params.sigma_along, params.sigma_cross)
    slow = speed < params.heading_min_speed
    acc_cov[slow] = params.sigma_along**2 * np.eye(2)
    b = input_matrix(dt)
    return b @ acc_cov @ b.T


def feature_noise_cov(velocity: np.ndarray, dt: float, s_par: float, s_perp: float) -> np.ndarray:
    """Q_F of model (2), (K, 4, 4); a static feature (zero velocity) gets isotropic s_par."""
    v = np.asarray(velocity, dtype=float)
    heading = np.arctan2(v[:, 1], v[:, 0])
    cov = rotated_diag(heading, s_par, s_perp)
    still = np.hypot(v[:, 0], v[:, 1]) == 0.0
    cov[still] = s_par**2 * np.eye(2)
    g = np.vstack([dt * np.eye(2), np.eye(2)])
    return g @ cov @ g.T


def gnss_cov(sigma_p: np.ndarray, sigma_v: np.ndarray) -> np.ndarray:
    """R of model (3) for each vehicle, (N, 4, 4) = blockdiag(sp^2 I, sv^2 I)."""
    sp = np.asarray(sigma_p, dtype=float)
    sv = np.asarray(sigma_v, dtype=float)
    r = np.zeros(sp.shape + (4, 4))
    r[..., 0, 0] = r[..., 1, 1] = sp * sp
    r[..., 2, 2] = r[..., 3, 3] = sv * sv
    return r


def predict(mean: np.ndarray, cov: np.ndarray, accel: np.ndarray, dt: float, q: np.ndarray):
    """Prediction by model (1) for a batch: returns (mean (N,4), cov (N,4,4))."""
    a = transition_matrix(dt)
    b = input_matrix(dt)
    m = mean @ a.T + accel @ b.T
    p = a @ cov @ a.T + q
    return m, symmetrize(p)


def symmetrize(p: np.ndarray) -> np.ndarray:
    return 0.5 * (p + np.swapaxes(p, -1, -2))


def kalman_update(mean: np.ndarray, cov: np.ndarray, z: np.ndarray, r: np.ndarray):
    """Batched Kalman update with H = I (model (3)), Joseph form to keep P SPD."""
    s = cov + r
    # K = P S^-1; solve S^T K^T = P^T (S, P symmetric).
    gain = np.swapaxes(np.linalg.solve(s, cov), -1, -2)
    innov = z - mean
    m = mean + np.einsum("nij,nj->ni", gain, innov)
    i_k = np.eye(4) - gain
    p = i_k @ cov @ np.swapaxes(i_k, -1, -2) + gain @ r @ np.swapaxes(gain, -1, -2)
    return m, symmetrize(p)


# Constant-velocity model of Fröhle et al. (28)-(29) (their scenario and the rsu_bp estimator).


def cv_transition(dt: float) -> np.ndarray:
    """A of (28): [[1, dT], [0, 1]] ⊗ I_2, state [px, py, vx, vy]."""
    return np.kron(np.array([[1.0, dt], [0.0, 1.0]]), np.eye(2))


def cv_process_cov(dt: float, r: float) -> np.ndarray:
    """R of (29): r [[dT^3/3, dT^2/2], [dT^2/2, dT]] ⊗ I_2 (continuous white-noise acceleration)."""
    return r * np.kron(np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]]), np.eye(2))
