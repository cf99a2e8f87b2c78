"""``rsu_bp``: centralized nonparametric belief propagation at a road-side unit with data
association (Fröhle, Lindberg, Wymeersch, "Cooperative Localization of Vehicles without
Inter-vehicle Measurements", WCNC 2018; seed paper 001/000).

All vehicles in range send their GNSS fix and their unlabelled V2F (vehicle-to-feature)
measurements to the RSU, which runs loopy BP on the factor graph (9) of one time step:

* Step 1, prediction (10)-(11): every feature and vehicle particle is moved by the motion model.
* Step 2, measurement evaluation (12)-(14): beta_{k,s}(m) = int int v_k phi_s chi_s alpha_k,
  the likelihood that feature k produced measurement m of vehicle s.
* Steps 3-4, data association (15)-(20): P iterations of BP on the one-to-one association
  factors Psi(a_k, b_m) (6), per vehicle, giving eta_{k,s}(m).
* Step 5, measurement correction (21)-(24): I iterations exchanging gamma_{k,s} (vehicle s's
  V2F information about feature k) and mu_{k,s} (feature k's information about vehicle s).
* Step 6, beliefs (25)-(26): b_k ∝ alpha_k prod_s gamma_{k,s}; b_s ∝ phi_s chi_s prod_k mu_{k,s}.

Particle representation (Sec. IV-B, (27)): each feature and vehicle belief is a set of Np
particles; every message on f_k is a weight vector on feature k's predicted particles and every
message on x_s a weight vector on vehicle s's predicted particles ("products of messages
represented by a common list of particles are done by pointwise multiplication of the
weights"). All weights are kept as logarithms. The only O(Np^2) work is the V2F kernel
p(z_m | f_k, x_s) summed over one particle set for every particle of the other
(:func:`pair_log_messages`, numba); everything else is O(K^2 + Np) per (k, s).

Decisions where the paper is silent (stated again in the docstrings below):

* The DA messages are kept in the two-valued form of Williams & Lau (the paper's ref. [7]):
  with delta_{m,k}(a_k != m) = 1 and epsilon_{k,m}(b_m != k) = 1 the BP messages (15)-(20) reduce
  to mu_{k->m} = beta_k(m) / sum_{m' != m} beta_k(m') nu_{m'->k} and
  nu_{m->k} = 1 / sum_{k' != k} mu_{k'->m}, eta_k(m) ∝ nu_{m->k}; ``tests/coloc/test_rsu_bp.py``
  checks this against the literal sums over a_k and b_m.
* As in the paper's model (Sec. II) every vehicle observes every feature once per step
  (M_s = K); there are no missed detections or clutter.
* After Step 6 both beliefs are resampled (systematic resampling) to Np equally weighted
  particles, which are the priors of the next step.
* The MMSE estimate (Sec. III-A) is the weighted particle mean of the belief before resampling.

``coloc`` stays free of simulators: :func:`rsu_bp_step` is a plain function of (vehicle and
feature particles of the previous step, GNSS fixes, V2F measurements with owners, parameters,
random generator), so it can run per RSU on the vehicles in its range.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numba import njit

from coloc.core.models import cv_process_cov, cv_transition
from coloc.inference.particles import logsumexp, systematic_resample_right, weighted_moments_normalized


@dataclass(frozen=True)
class RsuBpParams:
    """Parameters of the RSU particle BP (defaults: Fröhle et al. Sec. V-A)."""

    n_particles: int = 600  # Np
    da_iterations: int = 5  # P, Step 4
    correction_iterations: int = 1  # I, Step 5
    dt: float = 0.5  # Delta T of (28)-(29), s
    process_intensity: float = 0.1  # r of (29), m^2/s^3 (the paper writes "m^2")
    # Prior spread of the velocity of a vehicle / a feature initialised from a position only
    # (footnote 1: "a large enough support"), m/s. Sec. V-A draws vehicle velocities from
    # N(0, 0.25 I) and features reach ~3.6 m/s at the ends of the run. A vehicle prior much wider
    # than needed degenerates the particles of the well-localized vehicle (GNSS std 0.1 m) at
    # the first prediction (ESS ~ Np (0.1 / (dT sigma_v))^2).
    vehicle_init_velocity_std: float = 1.0
    feature_init_velocity_std: float = 5.0

    def __post_init__(self):
        if self.n_particles < 2:
            raise ValueError("n_particles must be >= 2")
        if self.da_iterations < 1:
            raise ValueError("da_iterations (P) must be >= 1")
        if self.correction_iterations < 1:
            raise ValueError("correction_iterations (I) must be >= 1")
        for name in ("dt", "process_intensity", "vehicle_init_velocity_std", "feature_init_velocity_std"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")


# --------------------------------------------------------------------------- pairwise V2F kernel

# Reassociation lets LLVM vectorize the sums and maxima; no "nnan"/"ninf": -inf weights are meaningful.
_FAST = {"reassoc", "contract", "arcp", "nsz"}


@njit(cache=True, fastmath=_FAST, inline="always")
def _exp_nonpositive(x):
    """exp(x) for x <= 0 to ~1e-12 relative, 0 below -40 (a term < 4e-18 of the largest one of a
    log-sum-exp). exp(x / 128)^128 with the Taylor polynomial of degree 11 (remainder < 2e-15 on
    [-40/128, 0]) and 7 squarings: plain arithmetic, so the summing loop vectorizes (no SIMD exp
    in numba without SVML). Checked against numpy.exp in the tests."""
    y = max(x, -40.0) * (1.0 / 128.0)
    p = 1.0 + y * (1.0 + y * (1.0 / 2 + y * (1.0 / 6 + y * (1.0 / 24 + y * (1.0 / 120 + y * (
        1.0 / 720 + y * (1.0 / 5040 + y * (1.0 / 40320 + y * (1.0 / 362880 + y * (
            1.0 / 3628800 + y * (1.0 / 39916800)))))))))))
    for _ in range(7):
        p = p * p
    return p if x > -40.0 else 0.0


@njit(cache=True, fastmath=_FAST)
def pair_log_messages(outer, summed, log_w, z, prec, log_norm, sign, out):
    """The O(Np^2) particle kernel of (14), (21) and (23).

    out[m, i] = log sum_l exp(log_w[l] + log N(z_m; sign * (outer_i - summed_l), R_m))

    with the V2F model z = p_F - p_V + w (Sec. V-A, H^(V2F) = [H, -H]): for messages on a
    feature (14), (21) ``outer`` are the feature positions, ``summed`` the vehicle positions and
    sign = +1; for messages on a vehicle (23) ``outer`` are the vehicle positions, ``summed``
    the feature positions and sign = -1. ``prec[m] = (P00, P01, P11)`` is R_m^-1 and
    ``log_norm[m] = -log(2 pi) - 0.5 log det R_m``. Log-sum-exp with the maximum taken per
    output, so nothing under- or overflows; an output whose weights are all -inf is -inf.
    """
    n_out = outer.shape[0]
    n_sum = summed.shape[0]
    buf = np.empty(n_sum)
    for m in range(z.shape[0]):
        zx, zy = z[m, 0], z[m, 1]
        a, b, c = prec[m, 0], prec[m, 1], prec[m, 2]
        for i in range(n_out):
            ux = zx - sign * outer[i, 0]
            uy = zy - sign * outer[i, 1]
            best = -np.inf
            for l in range(n_sum):
                dx = ux + sign * summed[l, 0]
                dy = uy + sign * summed[l, 1]
                e = log_w[l] - 0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy)
                buf[l] = e
                best = max(best, e)
            if not best > -np.inf:
                out[m, i] = -np.inf
                continue
            acc = 0.0
            for l in range(n_sum):
                acc += _exp_nonpositive(buf[l] - best)
            out[m, i] = best + np.log(acc) + log_norm[m]


def _precisions(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P00, P01, P11) of each 2x2 covariance and the Gaussian log normaliser."""
    cov = np.asarray(cov, dtype=float).reshape(-1, 2, 2)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0]
    if np.any(det <= 0) or np.any(cov[:, 0, 0] <= 0):
        raise ValueError("V2F covariances must be positive definite")
    prec = np.stack([cov[:, 1, 1] / det, -cov[:, 0, 1] / det, cov[:, 0, 0] / det], axis=1)
    return np.ascontiguousarray(prec), -np.log(2.0 * np.pi) - 0.5 * np.log(det)


def _normalize(logw: np.ndarray, axis: int = -1) -> np.ndarray:
    return logw - logsumexp(logw, axis=axis, keepdims=True)


# --------------------------------------------------------------------------- data association


def association_messages(log_beta: np.ndarray, iterations: int) -> np.ndarray:
    """Steps 3-4, (15)-(20), for one vehicle: log eta_k(m), (K, M) with M = K, each row normalised.

    Two-valued messages (Williams & Lau): nu_{m->k} = delta_{m,k}(a_k = m) / delta_{m,k}(a_k != m),
    mu_{k->m} = epsilon_{k,m}(b_m = k) / epsilon_{k,m}(b_m != k). With the delta initialised to 1
    (16), (15)/(17) give mu^(0)_{k->m} = beta_k(m) / sum_{m' != m} beta_k(m'); for p = 1..P,
    (18) nu^(p)_{m->k} = 1 / sum_{k' != k} mu^(p-1)_{k'->m} and (19)
    mu^(p)_{k->m} = beta_k(m) / sum_{m' != m} beta_k(m') nu^(p)_{m'->k}; (20)
    eta_k(m) = prod_{m'} delta^(P)_{m',k}(a_k = m) ∝ nu^(P)_{m->k}.
    Each row of beta may be scaled freely (the ratios do not change), so it is shifted by its
    maximum before leaving the log domain.
    """
    log_beta = np.asarray(log_beta, dtype=float)
    k, m = log_beta.shape
    if k != m:
        raise ValueError(f"association needs as many measurements as features (got {m} for {k})")
    if k == 1:
        return np.zeros((1, 1))
    tiny = np.finfo(float).tiny
    beta = np.exp(log_beta - log_beta.max(axis=1, keepdims=True))  # (K, M), row max 1
    nu = np.ones((m, k))  # nu[m, k] = nu_{m->k}
    for p in range(iterations + 1):
        # (19) (p = 0: (17)): mu[k, m] = beta_k(m) / sum_{m' != m} beta_k(m') nu_{m'->k}
        weighted = beta * nu.T  # [k, m'] = beta_k(m') nu_{m'->k}
        mu = beta / np.maximum(weighted.sum(axis=1, keepdims=True) - weighted, tiny)
        if p == iterations:
            break
        # (18): nu[m, k] = 1 / sum_{k' != k} mu_{k'->m}
        col = mu.sum(axis=0)  # [m] = sum_k mu_{k->m}
        nu = 1.0 / np.maximum(col[:, None] - mu.T, tiny)
    # (20) uses delta^(P), i.e. nu^(P): the last (18) update of the loop above.
    log_eta = np.log(np.maximum(nu.T, tiny))  # [k, m]
    return _normalize(log_eta, axis=1)


def association_probabilities(log_beta: np.ndarray, log_eta: np.ndarray) -> np.ndarray:
    """Approximate marginals p(a_k = m) ∝ beta_k(m) eta_k(m), (K, M), rows sum to one."""
    return np.exp(_normalize(np.asarray(log_beta) + np.asarray(log_eta), axis=1))


# --------------------------------------------------------------------------- particles


def init_particles(
    position: np.ndarray, position_cov: np.ndarray, params: RsuBpParams, rng: np.random.Generator,
    velocity: np.ndarray | None = None, velocity_cov: np.ndarray | None = None,
) -> np.ndarray:
    """Np particles (n, Np, 4) around positions (n, 2) with covariances (n, 2, 2) and a velocity
    prior (zero mean, ``vehicle_init_velocity_std`` unless given): the paper's footnote 1 (initialise
    from the GNSS fix, or GNSS plus V2F for a feature, "with a large enough support")."""
    position = np.atleast_2d(np.asarray(position, dtype=float))
    n = position.shape[0]
    pos_cov = np.broadcast_to(np.asarray(position_cov, dtype=float), (n, 2, 2))
    vel = np.zeros((n, 2)) if velocity is None else np.atleast_2d(np.asarray(velocity, dtype=float))
    vel_cov = (np.broadcast_to(params.vehicle_init_velocity_std**2 * np.eye(2), (n, 2, 2)) if velocity_cov is None
               else np.broadcast_to(np.asarray(velocity_cov, dtype=float), (n, 2, 2)))
    np_ = params.n_particles
    out = np.empty((n, np_, 4))
    std = rng.standard_normal((n, np_, 4))
    out[:, :, :2] = position[:, None, :] + np.einsum("nij,npj->npi", np.linalg.cholesky(pos_cov), std[:, :, :2])
    out[:, :, 2:] = vel[:, None, :] + np.einsum("nij,npj->npi", np.linalg.cholesky(vel_cov), std[:, :, 2:])
    return out


def predict_particles(particles: np.ndarray, params: RsuBpParams, rng: np.random.Generator) -> np.ndarray:
    """Step 1, (10)-(11): draw x_t ~ p(x_t | x_{t-1}) for every particle, CV model (28)-(29)."""
    a = cv_transition(params.dt)
    chol = np.linalg.cholesky(cv_process_cov(params.dt, params.process_intensity))
    noise = rng.standard_normal(particles.shape) @ chol.T
    return particles @ a.T + noise


def gnss_log_likelihood(particles: np.ndarray, z: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """chi_s = log p(z^(G)_s | x_s) for each particle, (S, Np). z (S, D), cov (S, D, D): D = 2 is
    the paper's H = [1 0] ⊗ I_2 (30) (position fix), D = 4 a position-velocity fix."""
    d = z.shape[1]
    if d not in (2, 4):
        raise ValueError(f"GNSS fixes must have 2 or 4 components, got {d}")
    chol = np.linalg.cholesky(cov)  # (S, D, D)
    diff = z[:, None, :] - particles[:, :, :d]  # (S, Np, D)
    sol = np.linalg.solve(chol[:, None, :, :], diff[..., None])[..., 0]
    logdet = 2.0 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(axis=1)
    return -0.5 * (sol * sol).sum(axis=2) - 0.5 * (d * np.log(2.0 * np.pi) + logdet)[:, None]


# --------------------------------------------------------------------------- one BP step


@dataclass(frozen=True)
class RsuBpStep:
    """Result of one RSU BP step (Step 6): estimates and the resampled particles for the next step."""

    vehicle_mean: np.ndarray  # (S, 4) MMSE estimates (weighted mean of b_s before resampling)
    vehicle_cov: np.ndarray  # (S, 4, 4)
    feature_mean: np.ndarray  # (K, 4)
    feature_cov: np.ndarray  # (K, 4, 4)
    vehicle_particles: np.ndarray  # (S, Np, 4), equally weighted: the prior of the next step
    feature_particles: np.ndarray  # (K, Np, 4)
    # (O, K): approximate p(b_m = k) of each V2F row from beta_k(m) eta_k(m), rows sum to one
    v2f_association: np.ndarray
    vehicle_ess: np.ndarray  # (S,) effective sample size of b_s before resampling
    feature_ess: np.ndarray  # (K,)


def _ess(log_w: np.ndarray) -> np.ndarray:
    return 1.0 / np.exp(logsumexp(2.0 * log_w, axis=-1))


def rsu_bp_step(
    vehicle_particles: np.ndarray,
    feature_particles: np.ndarray,
    gnss_z: np.ndarray,
    gnss_cov: np.ndarray,
    v2f_z: np.ndarray,
    v2f_cov: np.ndarray,
    v2f_owner: np.ndarray,
    params: RsuBpParams,
    rng: np.random.Generator,
    predict: bool = True,
) -> RsuBpStep:
    """One time step of the RSU BP, Steps 1-6 of Sec. IV-A.

    vehicle_particles (S, Np, 4), feature_particles (K, Np, 4): equally weighted beliefs of the
    previous step (or the priors b_0). gnss_z (S, D), gnss_cov (S, D, D): the fixes (D = 2 or 4).
    v2f_z (O, 2), v2f_cov (O, 2, 2), v2f_owner (O,) row of the measuring vehicle: relative
    positions p_F - p_V of unknown feature, in any order; every vehicle has exactly K rows.
    ``predict=False`` skips Step 1 (particles already at time t, e.g. fresh priors).
    """
    xs = np.asarray(vehicle_particles, dtype=float)
    fs = np.asarray(feature_particles, dtype=float)
    n_veh, np_ = xs.shape[0], xs.shape[1]
    n_feat = fs.shape[0]
    gnss_z = np.asarray(gnss_z, dtype=float).reshape(n_veh, -1)
    gnss_cov = np.asarray(gnss_cov, dtype=float).reshape(n_veh, gnss_z.shape[1], gnss_z.shape[1])
    v2f_z = np.asarray(v2f_z, dtype=float).reshape(-1, 2)
    v2f_owner = np.asarray(v2f_owner, dtype=np.int64).reshape(-1)
    prec, log_norm = _precisions(np.asarray(v2f_cov, dtype=float).reshape(-1, 2, 2)) if v2f_z.shape[0] else (
        np.empty((0, 3)), np.empty(0))
    if v2f_owner.shape[0] != v2f_z.shape[0]:
        raise ValueError("v2f_owner must have one entry per V2F row")
    if v2f_owner.size and (v2f_owner.min() < 0 or v2f_owner.max() >= n_veh):
        raise ValueError("v2f_owner refers to a vehicle that is not in the step")
    rows_of = [np.flatnonzero(v2f_owner == s) for s in range(n_veh)]
    for s, rows in enumerate(rows_of):
        if rows.size not in (0, n_feat):
            raise ValueError(f"vehicle {s} has {rows.size} V2F measurements, expected 0 or K = {n_feat}")

    # Step 1 (10)-(11): alpha_k, phi_s as equally weighted predicted particles.
    if predict:
        xs = predict_particles(xs, params, rng)
        fs = predict_particles(fs, params, rng) if n_feat else fs
    uniform = np.full(np_, -np.log(np_))
    log_alpha = np.broadcast_to(uniform, (n_feat, np_))
    log_phi_chi = _normalize(uniform + gnss_log_likelihood(xs, gnss_z, gnss_cov))  # phi_s chi_s, (S, Np)

    xpos = np.ascontiguousarray(xs[:, :, :2])
    fpos = np.ascontiguousarray(fs[:, :, :2])
    observing = [s for s in range(n_veh) if rows_of[s].size]

    # Step 2 (12)-(14): alpha~^(0) = alpha, rho^(0) = phi chi. cf[s][k][m, j] = log sum_l rho_l v(z_m; f_j, x_l),
    # the kernel of (14) and (21) on feature k's particles.
    def feature_side(s, k, log_rho):
        rows = rows_of[s]
        out = np.empty((rows.size, np_))
        pair_log_messages(fpos[k], xpos[s], np.ascontiguousarray(log_rho), v2f_z[rows], prec[rows],
                          log_norm[rows], 1.0, out)
        return out

    cf = {s: [feature_side(s, k, log_phi_chi[s]) for k in range(n_feat)] for s in observing}
    log_eta = {}
    association = np.zeros((v2f_z.shape[0], n_feat))
    for s in observing:
        log_beta = np.stack([logsumexp(log_alpha[k][None, :] + cf[s][k], axis=1) for k in range(n_feat)])  # (14)
        # Steps 3-4 (15)-(20)
        log_eta[s] = association_messages(log_beta, params.da_iterations)
        # p(b_m = k) for scoring: beta eta normalised over the features of each measurement
        association[rows_of[s]] = np.exp(_normalize((log_beta + log_eta[s]).T, axis=1))

    # Step 5 (21)-(24)
    log_rho = {s: np.broadcast_to(log_phi_chi[s], (n_feat, np_)) for s in observing}  # rho^(0)_{k,s}
    log_gamma = np.zeros((n_veh, n_feat, np_))  # vehicles without measurements send gamma = 1
    log_mu = np.zeros((n_veh, n_feat, np_))
    for i in range(1, params.correction_iterations + 1):
        for s in observing:
            for k in range(n_feat):
                kern = cf[s][k] if i == 1 else feature_side(s, k, log_rho[s][k])
                # (21): gamma_{k,s}(f) = sum_m eta_k(m) int v_k(m) rho^(i-1)_{k,s} dx_s
                log_gamma[s, k] = _normalize(logsumexp(log_eta[s][k][:, None] + kern, axis=0))
        total_gamma = log_gamma.sum(axis=0)  # (K, Np)
        for s in observing:
            rows = rows_of[s]
            for k in range(n_feat):
                # (22): alpha~_{k,s} = alpha_k prod_{s' != s} gamma_{k,s'}
                log_alpha_t = _normalize(log_alpha[k] + total_gamma[k] - log_gamma[s, k])
                out = np.empty((rows.size, np_))
                pair_log_messages(xpos[s], fpos[k], np.ascontiguousarray(log_alpha_t), v2f_z[rows], prec[rows],
                                  log_norm[rows], -1.0, out)
                # (23): mu_{k,s}(x) = sum_m eta_k(m) int v_k(m) alpha~_{k,s} df_k
                log_mu[s, k] = _normalize(logsumexp(log_eta[s][k][:, None] + out, axis=0))
            # (24): rho_{k,s} = phi_s chi_s prod_{k' != k} mu_{k',s}
            total_mu = log_mu[s].sum(axis=0)
            log_rho[s] = _normalize(log_phi_chi[s][None, :] + total_mu[None, :] - log_mu[s])

    # Step 6 (25)-(26)
    log_bf = _normalize(log_alpha + log_gamma.sum(axis=0)) if n_feat else np.empty((0, np_))
    log_bx = _normalize(log_phi_chi + log_mu.sum(axis=1))
    vmean, vcov = zip(*(weighted_moments_normalized(xs[s], log_bx[s]) for s in range(n_veh))) if n_veh else ((), ())
    fmean, fcov = zip(*(weighted_moments_normalized(fs[k], log_bf[k]) for k in range(n_feat))) if n_feat else ((), ())
    new_x = np.stack([xs[s][systematic_resample_right(log_bx[s], rng)] for s in range(n_veh)]) if n_veh else xs
    new_f = np.stack([fs[k][systematic_resample_right(log_bf[k], rng)] for k in range(n_feat)]) if n_feat else fs
    return RsuBpStep(
        vehicle_mean=np.array(vmean).reshape(n_veh, 4),
        vehicle_cov=np.array(vcov).reshape(n_veh, 4, 4),
        feature_mean=np.array(fmean).reshape(n_feat, 4),
        feature_cov=np.array(fcov).reshape(n_feat, 4, 4),
        vehicle_particles=new_x,
        feature_particles=new_f,
        v2f_association=association,
        vehicle_ess=_ess(log_bx),
        feature_ess=_ess(log_bf) if n_feat else np.empty(0),
    )


# --------------------------------------------------------------------------- the GNSS-only baseline


def cv_kalman_filter(
    gnss_z: np.ndarray, gnss_cov: np.ndarray, mean0: np.ndarray, cov0: np.ndarray, dt: float, r: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's GNSS-only non-cooperative Kalman filter (Sec. V-B), batched over vehicles.

    gnss_z (T, S, 2) position fixes, gnss_cov (S, 2, 2); prior N(mean0 (S, 4), cov0 (S, 4, 4)) at
    step 0, which is updated (not predicted) with the first fix, as the particle BP is. Model
    (28)-(30); Joseph-form update. Returns means (T, S, 4) and covariances (T, S, 4, 4).
    """
    a = cv_transition(dt)
    q = cv_process_cov(dt, r)
    h = np.kron(np.array([[1.0, 0.0]]), np.eye(2))  # (30)
    n_t, n_s = gnss_z.shape[0], gnss_z.shape[1]
    means = np.empty((n_t, n_s, 4))
    covs = np.empty((n_t, n_s, 4, 4))
    m, p = np.array(mean0, dtype=float), np.array(cov0, dtype=float)
    eye = np.eye(4)
    for t in range(n_t):
        if t > 0:
            m = m @ a.T
            p = a @ p @ a.T + q
        s_cov = h @ p @ h.T + gnss_cov  # (S, 2, 2)
        gain = np.swapaxes(np.linalg.solve(s_cov, h @ p), -1, -2)  # P H^T S^-1, (S, 4, 2)
        m = m + np.einsum("sij,sj->si", gain, gnss_z[t] - m[:, :2])
        ikh = eye - gain @ h
        p = ikh @ p @ np.swapaxes(ikh, -1, -2) + gain @ gnss_cov @ np.swapaxes(gain, -1, -2)
        p = 0.5 * (p + np.swapaxes(p, -1, -2))
        means[t], covs[t] = m, p
    return means, covs


# --------------------------------------------------------------------------- a whole run


def initial_beliefs(
    gnss_z: np.ndarray, gnss_cov: np.ndarray, v2f_z: np.ndarray, v2f_cov: np.ndarray, v2f_owner: np.ndarray,
    n_features: int, params: RsuBpParams, rng: np.random.Generator, spread: float = 4.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Priors b_0 of footnote 1, as particles: each vehicle around its first GNSS position fix,
    each feature k around GNSS + V2F row k of the vehicle with the most precise fix (the RSU knows
    the GNSS covariances), position covariances inflated by ``spread`` ("a large enough support"),
    velocities zero-mean with ``params.vehicle_init_velocity_std`` / ``feature_init_velocity_std``. The feature index is only a track label:
    which true feature a track follows is scored outside the estimator."""
    gnss_z = np.asarray(gnss_z, dtype=float)
    gnss_cov = np.asarray(gnss_cov, dtype=float)
    pos_cov = spread * gnss_cov[:, :2, :2]
    vehicles = init_particles(gnss_z[:, :2], pos_cov, params, rng)
    if n_features == 0:
        return vehicles, np.empty((0, params.n_particles, 4))
    v2f_owner = np.asarray(v2f_owner)
    candidates = [s for s in range(gnss_z.shape[0]) if np.count_nonzero(v2f_owner == s) == n_features]
    if not candidates:
        raise ValueError("no vehicle observes all features: cannot initialise the feature priors")
    ref = min(candidates, key=lambda s: np.linalg.det(gnss_cov[s, :2, :2]))
    rows = np.flatnonzero(v2f_owner == ref)
    f_pos = gnss_z[ref, :2] + np.asarray(v2f_z, dtype=float)[rows]
    f_cov = spread * (gnss_cov[ref, :2, :2] + np.asarray(v2f_cov, dtype=float).reshape(-1, 2, 2)[rows])
    f_vel_cov = params.feature_init_velocity_std**2 * np.eye(2)
    return vehicles, init_particles(f_pos, f_cov, params, rng, velocity_cov=f_vel_cov)


@dataclass(frozen=True)
class RsuBpRun:
    vehicle_mean: np.ndarray  # (T, S, 4)
    vehicle_cov: np.ndarray  # (T, S, 4, 4)
    feature_mean: np.ndarray  # (T, K, 4), track k = prior k of initial_beliefs
    v2f_association: np.ndarray  # (T, O, K)
    seconds: np.ndarray  # (T,) wall time of each step


def rsu_bp_filter(
    gnss_z: np.ndarray, gnss_cov: np.ndarray, v2f_z: np.ndarray, v2f_cov: np.ndarray, v2f_owner: np.ndarray,
    n_features: int, params: RsuBpParams, rng: np.random.Generator, init_spread: float = 4.0,
) -> RsuBpRun:
    """The RSU BP over a whole run with a fixed set of S vehicles and K features.

    gnss_z (T, S, D), gnss_cov (S, D, D); v2f_z (T, O, 2), v2f_cov (O, 2, 2), v2f_owner (O,)
    (rows in any order at each step; O = S K or 0). Step 0 starts from :func:`initial_beliefs`."""
    n_t, n_s = gnss_z.shape[0], gnss_z.shape[1]
    n_o = v2f_z.shape[1] if n_features else 0
    vmean = np.empty((n_t, n_s, 4))
    vcov = np.empty((n_t, n_s, 4, 4))
    fmean = np.empty((n_t, n_features, 4))
    assoc = np.empty((n_t, n_o, n_features))
    seconds = np.empty(n_t)
    z0 = v2f_z[0] if n_features else np.empty((0, 2))
    xs, fs = initial_beliefs(gnss_z[0], gnss_cov, z0, v2f_cov, v2f_owner, n_features, params, rng, init_spread)
    empty_z, empty_cov, empty_owner = np.empty((0, 2)), np.empty((0, 2, 2)), np.empty(0, dtype=np.int64)
    for t in range(n_t):
        t0 = time.perf_counter()
        if n_features:
            res = rsu_bp_step(xs, fs, gnss_z[t], gnss_cov, v2f_z[t], v2f_cov, v2f_owner, params, rng, predict=t > 0)
        else:
            res = rsu_bp_step(xs, fs, gnss_z[t], gnss_cov, empty_z, empty_cov, empty_owner, params, rng,
                              predict=t > 0)
        seconds[t] = time.perf_counter() - t0
        xs, fs = res.vehicle_particles, res.feature_particles
        vmean[t], vcov[t], fmean[t], assoc[t] = res.vehicle_mean, res.vehicle_cov, res.feature_mean, res.v2f_association
    return RsuBpRun(vehicle_mean=vmean, vehicle_cov=vcov, feature_mean=fmean, v2f_association=assoc, seconds=seconds)


# --------------------------------------------------------------------------- open association (infrastructure mode)
#
# Fröhle's model has every vehicle measure every feature once per step (M_s = K). At an RSU of
# the arterial, vehicles see different subsets of the landmarks and a landmark seen for the first
# time has no track yet. The step below extends (15)-(24) with the standard dummy hypotheses of
# Williams & Lau (the paper's ref. [7]) / Meyer et al.'s BP-MTT:
#
# * a_k = 0: feature k is missed by vehicle s (probability 1 - P_D), for every feature k that the
#   vehicle could see (``visible[s, k]``, a gate on the predicted estimates); features outside the
#   gate take no part in vehicle s's association (probability of detection 0);
# * b_m = 0: measurement m comes from no tracked feature ("new feature or clutter"), with density
#   lambda (uniform over the V2F sensing disc: lambda = 1 / (pi Rs^2) by default).
#
# With beta_k(m) = P_D p(z_m | f_k, x_s) / lambda and beta_k(0) = 1 - P_D the two-valued messages
# become mu_{k->m} = beta_k(m) / (beta_k(0) + sum_{m' != m} beta_k(m') nu_{m'->k}) and
# nu_{m->k} = 1 / (1 + sum_{k' != k} mu_{k'->m}); eta_k(0) = 1, eta_k(m) = nu_{m->k}; and the
# messages (21), (23) gain the missed-detection term: gamma_{k,s}(f) ∝ eta_k(0) (1 - P_D) +
# sum_m eta_k(m) P_D int v_k(m) rho dx / lambda (likewise mu_{k,s}(x)). With P_D -> 1 and every
# feature visible to every vehicle with K rows this reduces to the closed form above up to the
# new-feature hypothesis (lambda -> 0 removes it).


def association_messages_open(
    log_beta: np.ndarray, log_beta_miss: float, iterations: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Association BP with missed detections and new/clutter measurements, one vehicle.

    log_beta (K, M): log beta_k(m) = log(P_D p(z_m | k) / lambda); log_beta_miss = log(1 - P_D).
    Returns (log eta (K, M + 1) with column 0 the missed hypothesis, rows normalised;
    p(b_m = k) (M, K); p(b_m = new) (M,)).
    """
    log_beta = np.asarray(log_beta, dtype=float)
    k, m = log_beta.shape
    tiny = np.finfo(float).tiny
    # Scale each row by a common factor (ratios unchanged): the miss term scales with it.
    top = np.maximum(log_beta.max(axis=1, keepdims=True), log_beta_miss)
    top = np.where(np.isfinite(top), top, 0.0)
    beta = np.exp(log_beta - top)  # (K, M)
    beta0 = np.exp(log_beta_miss - top[:, 0])  # (K,)
    nu = np.ones((m, k))
    for p in range(iterations + 1):
        weighted = beta * nu.T
        mu = beta / np.maximum(beta0[:, None] + weighted.sum(axis=1, keepdims=True) - weighted, tiny)
        if p == iterations:
            break
        col = mu.sum(axis=0)
        nu = 1.0 / (1.0 + np.maximum(col[:, None] - mu.T, 0.0))
    log_eta = np.concatenate([np.zeros((k, 1)), np.log(np.maximum(nu.T, tiny))], axis=1)
    log_eta = _normalize(log_eta, axis=1)
    denom = 1.0 + mu.sum(axis=0)  # (M,)
    return log_eta, (mu / denom[None, :]).T, 1.0 / denom


def _safe_normalize(logw: np.ndarray) -> np.ndarray:
    """Normalise log weights along the last axis; an all -inf row becomes uniform (no information)."""
    out = _normalize(logw)
    bad = ~np.isfinite(out).any(axis=-1)
    if np.any(bad):
        out[bad] = -np.log(logw.shape[-1])
    return np.where(np.isnan(out), -np.inf, out)


@dataclass(frozen=True)
class RsuBpOpenStep:
    vehicle_mean: np.ndarray  # (S, 4)
    vehicle_cov: np.ndarray  # (S, 4, 4)
    feature_mean: np.ndarray  # (K, 4)
    feature_cov: np.ndarray  # (K, 4, 4)
    vehicle_particles: np.ndarray  # (S, Np, 4) resampled
    feature_particles: np.ndarray  # (K, Np, 4) resampled
    v2f_association: np.ndarray  # (O, K + 1): p(b_m = k), last column p(b_m = new/clutter)


def rsu_bp_step_open(
    vehicle_particles: np.ndarray,
    feature_particles: np.ndarray,
    gnss_z: np.ndarray,
    gnss_cov: np.ndarray,
    v2f_z: np.ndarray,
    v2f_cov: np.ndarray,
    v2f_owner: np.ndarray,
    visible: np.ndarray,
    detection_prob: float,
    clutter_density: float,
    params: RsuBpParams,
    rng: np.random.Generator,
    bandwidth: bool = True,
) -> RsuBpOpenStep:
    """Steps 2-6 of Sec. IV-A with the open association above, particles already predicted to t.

    ``visible`` (S, K) bool: the features each vehicle may have detected (its gate); every vehicle
    may have any number of V2F rows. ``gnss_z = None``: the vehicle particles are equally weighted
    draws from phi_s chi_s already (the caller did the GNSS update), so chi_s is not applied again. Step 1 (prediction) is left to the caller, which uses the
    motion model of its data (model (1) with the inertial input on SUMO frames).
    """
    xs = np.asarray(vehicle_particles, dtype=float)
    fs = np.asarray(feature_particles, dtype=float)
    n_veh, np_ = xs.shape[0], xs.shape[1]
    n_feat = fs.shape[0]
    v2f_z = np.asarray(v2f_z, dtype=float).reshape(-1, 2)
    v2f_owner = np.asarray(v2f_owner, dtype=np.int64).reshape(-1)
    n_obs = v2f_z.shape[0]
    prec, log_norm = _precisions(np.asarray(v2f_cov, dtype=float).reshape(-1, 2, 2)) if n_obs else (
        np.empty((0, 3)), np.empty(0))
    visible = np.asarray(visible, dtype=bool).reshape(n_veh, n_feat)
    rows_of = [np.flatnonzero(v2f_owner == s) for s in range(n_veh)]
    log_miss = float(np.log1p(-detection_prob)) if detection_prob < 1.0 else -np.inf
    log_det = float(np.log(detection_prob) - np.log(clutter_density))

    uniform = np.full(np_, -np.log(np_))
    log_alpha = np.broadcast_to(uniform, (n_feat, np_))
    if gnss_z is None:  # the particles already represent phi_s chi_s (drawn from the GNSS-updated prediction)
        log_phi_chi = np.broadcast_to(uniform, (n_veh, np_)).copy()
    else:
        log_phi_chi = _safe_normalize(uniform + gnss_log_likelihood(xs, np.asarray(gnss_z, float),
                                                                    np.asarray(gnss_cov, float)))
    xpos = np.ascontiguousarray(xs[:, :, :2])
    fpos = np.ascontiguousarray(fs[:, :, :2])

    # Kernel regularisation (nonparametric BP, Sudderth et al.): the V2F kernel between two clouds of
    # Np particles uses R + h^2 I with Silverman's bandwidth h^2 = Np^(-1/3) var (d = 2) of each cloud's
    # positions. With the 0.1 m V2F noise against metre-wide clouds the unregularised kernel gave
    # spiky messages and collapsed the effective sample size (worse than GNSS alone on a test road).
    v2f_cov2 = np.asarray(v2f_cov, dtype=float).reshape(-1, 2, 2)
    bw_x = (np_ ** (-1.0 / 3.0)) * xs[:, :, :2].var(axis=1).mean(axis=1) if bandwidth else np.zeros(n_veh)
    bw_f = (np_ ** (-1.0 / 3.0)) * fs[:, :, :2].var(axis=1).mean(axis=1) if bandwidth else np.zeros(n_feat)
    kernel_cache = {}

    def kernel(s, k):
        if (s, k) not in kernel_cache:
            rows = rows_of[s]
            kernel_cache[s, k] = _precisions(v2f_cov2[rows] + (bw_x[s] + bw_f[k]) * np.eye(2))
        return kernel_cache[s, k]

    def feature_side(s, k, log_rho):
        rows = rows_of[s]
        out = np.empty((rows.size, np_))
        pk, nk = kernel(s, k)
        pair_log_messages(fpos[k], xpos[s], np.ascontiguousarray(log_rho), v2f_z[rows], pk, nk, 1.0, out)
        return out

    pairs = {s: np.flatnonzero(visible[s]) for s in range(n_veh) if rows_of[s].size and visible[s].any()}
    association = np.zeros((n_obs, n_feat + 1))
    association[:, -1] = 1.0  # rows of vehicles without a visible feature: new/clutter
    cf, log_eta = {}, {}
    for s, ks in pairs.items():
        cf[s] = {k: feature_side(s, k, log_phi_chi[s]) for k in ks}
        log_beta = np.stack([logsumexp(log_alpha[k][None, :] + cf[s][k], axis=1) for k in ks]) + log_det  # (14)
        log_eta[s], p_feat, p_new = association_messages_open(log_beta, log_miss, params.da_iterations)
        rows = rows_of[s]
        association[rows, -1] = p_new
        association[np.ix_(rows, ks)] = p_feat

    def combine(eta_row, kern):
        """log( eta(0) (1 - P_D) + sum_m eta(m) P_D exp(kern_m) / lambda ), per particle."""
        meas = logsumexp(eta_row[1:, None] + log_det + kern, axis=0)
        return np.logaddexp(eta_row[0] + log_miss, meas) if np.isfinite(log_miss) else meas

    log_gamma = np.zeros((n_veh, n_feat, np_))
    log_mu = np.zeros((n_veh, n_feat, np_))
    log_rho = {s: {k: log_phi_chi[s] for k in ks} for s, ks in pairs.items()}
    for i in range(1, params.correction_iterations + 1):
        for s, ks in pairs.items():
            for j, k in enumerate(ks):
                kern = cf[s][k] if i == 1 else feature_side(s, k, log_rho[s][k])
                log_gamma[s, k] = _safe_normalize(combine(log_eta[s][j], kern))  # (21)
        total_gamma = log_gamma.sum(axis=0)
        for s, ks in pairs.items():
            rows = rows_of[s]
            for j, k in enumerate(ks):
                log_alpha_t = _safe_normalize(log_alpha[k] + total_gamma[k] - log_gamma[s, k])  # (22)
                out = np.empty((rows.size, np_))
                pk, nk = kernel(s, k)
                pair_log_messages(xpos[s], fpos[k], np.ascontiguousarray(log_alpha_t), v2f_z[rows], pk, nk, -1.0, out)
                log_mu[s, k] = _safe_normalize(combine(log_eta[s][j], out))  # (23)
            total_mu = log_mu[s].sum(axis=0)
            log_rho[s] = {k: _safe_normalize(log_phi_chi[s] + total_mu - log_mu[s, k]) for k in ks}  # (24)

    log_bf = _safe_normalize(log_alpha + log_gamma.sum(axis=0)) if n_feat else np.empty((0, np_))  # (25)
    log_bx = _safe_normalize(log_phi_chi + log_mu.sum(axis=1)) if n_veh else np.empty((0, np_))  # (26)
    vm = [weighted_moments_normalized(xs[s], log_bx[s]) for s in range(n_veh)]
    fm = [weighted_moments_normalized(fs[k], log_bf[k]) for k in range(n_feat)]
    new_x = np.stack([xs[s][systematic_resample_right(log_bx[s], rng)] for s in range(n_veh)]) if n_veh else xs
    new_f = np.stack([fs[k][systematic_resample_right(log_bf[k], rng)] for k in range(n_feat)]) if n_feat else fs
    return RsuBpOpenStep(
        vehicle_mean=np.array([m for m, _ in vm]).reshape(n_veh, 4),
        vehicle_cov=np.array([c for _, c in vm]).reshape(n_veh, 4, 4),
        feature_mean=np.array([m for m, _ in fm]).reshape(n_feat, 4),
        feature_cov=np.array([c for _, c in fm]).reshape(n_feat, 4, 4),
        vehicle_particles=new_x,
        feature_particles=new_f,
        v2f_association=association,
    )
