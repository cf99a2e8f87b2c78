"""Particle utilities shared by the particle estimators (:mod:`coloc.methods.icp_da_pf`,
:mod:`coloc.methods.rsu_bp`): log-domain weights, weighted moments, systematic resampling, kernel
density (Silverman's bandwidth, Liu-West shrinkage) and the particle prediction by models (1), (2).

ICP-DA-PF's pieces (Brambilla et al. Sec. IV-C): the synchronized generator of an entity (vehicle
or track) for one purpose and step, :func:`entity_rng`, and the GNSS weights of b_i^(0) in (23),
:func:`gnss_log_likelihood`.

Where the two estimators' contracts differ (resampling tie rule, moments of normalised or any
log-weights) both variants live here under their own names; each caller keeps its numbers.
"""

from __future__ import annotations

import math

import numpy as np

from coloc.core.models import input_matrix, transition_matrix
from coloc.inference.gaussian import log_gauss
from coloc.inference.params import IcpParams

LOG_FLOOR = -700.0  # log-weights are kept finite (consensus averages them)


def logsumexp(x: np.ndarray, axis: int | None = None, keepdims: bool = False) -> np.ndarray:
    """log sum exp over ``axis`` (plain numpy: scipy's is ~0.5 ms per call, and the particle
    estimators call it tens of times per step); all -inf gives -inf."""
    x = np.asarray(x, dtype=float)
    top = np.max(x, axis=axis, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    with np.errstate(divide="ignore"):
        out = np.log(np.sum(np.exp(x - top), axis=axis, keepdims=True)) + top
    return out if keepdims else (np.squeeze(out, axis=axis) if axis is not None else out.reshape(()))


def normalize_log(logw: np.ndarray) -> np.ndarray:
    """Log-weights normalised along the last axis (log-sum-exp = 0), floored at -700."""
    return np.maximum(logw - logsumexp(logw, axis=-1, keepdims=True), LOG_FLOOR)


def linear_weights(logw: np.ndarray) -> np.ndarray:
    """Weights summing to one along the last axis, from log-weights."""
    w = np.exp(normalize_log(logw))
    return w / w.sum(-1, keepdims=True)


def weighted_moments(particles: np.ndarray, logw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MMSE mean and weighted covariance of particle sets (..., J, 4) with log-weights (..., J), any
    normalisation (ICP-DA-PF; the covariance gets 1e-9 I). :func:`weighted_moments_normalized` is
    RSU-BP's exact variant for one set with normalised log-weights."""
    return _moments(particles, linear_weights(logw))


def _moments(particles: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = (w[..., None, :] @ particles)[..., 0, :]
    d = particles - mean[..., None, :]
    cov = np.swapaxes(d * w[..., None], -1, -2) @ d
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2)) + 1e-9 * np.eye(4)
    return mean, cov


def systematic_resample(logw: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of a systematic resampling of one set (J,) of log-weights (ICP-DA-PF): weights from
    :func:`normalize_log` (floored at -700), the cumulative sum rescaled to end at 1, each draw in the
    first cell whose edge is at or above it (``side="left"``). :func:`systematic_resample_right` is
    RSU-BP's variant."""
    j = logw.shape[0]
    w = np.exp(normalize_log(logw))
    c = np.cumsum(w)
    c /= c[-1]
    u = (rng.random() + np.arange(j)) / j
    return np.minimum(np.searchsorted(c, u), j - 1)


def silverman_factor(j, d: int = 4):
    """h^2 of Silverman's rule of thumb, h = (4 / ((d + 2) J))^(1 / (d + 4)) (J may be an array)."""
    return (4.0 / ((d + 2) * np.asarray(j, dtype=float))) ** (2.0 / (d + 4))


def kernel_density(particles: np.ndarray, logw: np.ndarray, bandwidth: str) -> tuple[np.ndarray, np.ndarray]:
    """Kernel centres and the kernel covariance added to R, for weighted particle sets (..., J, 4),
    by ``PfParams.message_bandwidth``: "none" the particles and 0 (the bare V2F kernel); "prior"
    the particles and h^2 Cov_w (Silverman's h, :func:`silverman_factor`, on the effective sample
    size 1 / sum w^2 for J);
    "shrunk" h^2 Cov_w with the particles pulled towards the weighted mean m by Liu and West's
    a = sqrt(1 - h^2), a x + (1 - a) m, so that the density keeps the set's mean and covariance
    (a^2 Cov + h^2 Cov = Cov) instead of inflating the covariance by 1 + h^2."""
    if bandwidth == "none":
        return particles, np.zeros(particles.shape[:-2] + (4, 4))
    w = linear_weights(logw)
    ess = 1.0 / np.einsum("...j,...j->...", w, w)
    mean, cov = _moments(particles, w)
    h2 = silverman_factor(ess)
    if bandwidth == "prior":
        return particles, h2[..., None, None] * cov
    a = np.sqrt(1.0 - h2)[..., None, None]
    return a * particles + (1.0 - a) * mean[..., None, :], h2[..., None, None] * cov


def regularized_resample(particles: np.ndarray, logw: np.ndarray, index: np.ndarray, rng: np.random.Generator,
                         regularize: bool) -> np.ndarray:
    """``particles[index]`` (a resampling of the set), then (if ``regularize``) Liu-West shrinkage jitter (PfParams)."""
    out = particles[index]
    if not regularize:
        return out
    j, d = particles.shape
    mean, cov = weighted_moments(particles, logw)
    h2 = silverman_factor(j, d)
    a = math.sqrt(1.0 - h2)
    vals, vecs = np.linalg.eigh(cov)
    root = vecs * np.sqrt(np.maximum(vals, 0.0))
    return a * out + (1.0 - a) * mean + math.sqrt(h2) * (rng.standard_normal((j, d)) @ root.T)


def sample_gaussian(mean: np.ndarray, cov: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    root = vecs * np.sqrt(np.maximum(vals, 0.0))
    return mean + rng.standard_normal((n, mean.size)) @ root.T


def gaussian_log_pdf(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    lp, _ = log_gauss(x - mean, np.broadcast_to(cov, x.shape + (x.shape[-1],)))
    return lp


def predict_vehicle_particles(particles: np.ndarray, accel: np.ndarray, dt: float, params: IcpParams,
                              noise: np.ndarray) -> np.ndarray:
    """Model (1) on (N, J, 4) particles; ``noise`` (N, J, 2) standard normal draws.

    The driving noise is rotated to the heading of each vehicle's mean
    velocity (isotropic below ``motion.heading_min_speed``), as the Gaussian
    trackers orient Q.
    """
    a, b = transition_matrix(dt), input_matrix(dt)
    mp = params.motion
    v = particles[..., 2:].mean(axis=1)
    heading = np.arctan2(v[:, 1], v[:, 0])
    c, s = np.cos(heading), np.sin(heading)
    slow = np.hypot(v[:, 0], v[:, 1]) < mp.heading_min_speed
    s_cross = np.where(slow, mp.sigma_along, mp.sigma_cross)
    along = noise[..., 0] * mp.sigma_along
    cross = noise[..., 1] * s_cross[:, None]
    acc = np.stack([c[:, None] * along - s[:, None] * cross, s[:, None] * along + c[:, None] * cross], axis=-1)
    return particles @ a.T + (accel[:, None, :] + acc) @ b.T


def predict_track_particles(particles: np.ndarray, logw: np.ndarray, dt: float, params: IcpParams,
                            noise: np.ndarray) -> np.ndarray:
    """Model (2) on (K, J, 4) track particles; ``noise`` (K, J, 2) standard normal draws."""
    a = transition_matrix(dt)
    g = np.vstack([dt * np.eye(2), np.eye(2)])
    mean, _ = weighted_moments(particles, logw)
    v = mean[:, 2:]
    heading = np.arctan2(v[:, 1], v[:, 0])
    slow = np.hypot(v[:, 0], v[:, 1]) < params.feature_heading_min_speed
    par, perp = params.feature_sigma_par, params.feature_sigma_perp_value
    c, s = np.cos(heading), np.sin(heading)
    s_perp = np.where(slow, par, perp)
    along = noise[..., 0] * par
    cross = noise[..., 1] * s_perp[:, None]
    dv = np.stack([c[:, None] * along - s[:, None] * cross, s[:, None] * along + c[:, None] * cross], axis=-1)
    return particles @ a.T + dv @ g.T


def systematic_resample_right(log_w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of a systematic resampling of one set (J,) of log-weights (one uniform draw), the
    variant of :mod:`coloc.methods.rsu_bp`: weights exp(log_w - logsumexp) without a floor, the last
    edge set to 1 and each draw in the first cell whose edge is *above* it (``side="right"``), so a
    particle of zero weight is never drawn. :func:`systematic_resample` (ICP-DA-PF) floors the
    log-weights, rescales the cumulative sum and searches ``side="left"``; the two are kept apart
    because each caller's draws must stay as they were."""
    w = np.exp(log_w - logsumexp(log_w))
    edges = np.cumsum(w)
    edges[-1] = 1.0
    n = w.size
    u = (rng.random() + np.arange(n)) / n
    return np.searchsorted(edges, u, side="right").clip(0, n - 1)


def weighted_moments_normalized(particles: np.ndarray, log_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (4,) and covariance (4, 4) of one particle set (J, 4) whose log weights are already
    normalised, exactly (no floor, no regularisation): the contract of :mod:`coloc.methods.rsu_bp`.
    :func:`weighted_moments` normalises any log-weights, batches over leading axes and adds 1e-9 I."""
    w = np.exp(log_w)
    mean = w @ particles
    d = particles - mean
    cov = (d * w[:, None]).T @ d
    return mean, 0.5 * (cov + cov.T)


# The synchronized generators of ICP-DA-PF: one purpose code per kind of draw (seeded with the
# purpose, the entity and the step, see :func:`entity_rng`).
_PURPOSE = {"vehicle_predict": 1, "vehicle_prior": 2, "track_predict": 3, "track_birth": 4,
            "vehicle_resample": 5, "track_resample": 6, "own_predict": 7, "own_prior": 8, "own_resample": 9,
            # [fusion]: the sets drawn from the split-CI filters' marginals (coloc.methods.pf_fusion)
            "split_belief": 10, "split_own": 11}


def entity_rng(seed: int, purpose: str, entity: int, step: int) -> np.random.Generator:
    """The synchronized generator of one entity (vehicle or track) for one purpose and step."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, _PURPOSE[purpose], int(entity) & 0xFFFFFFFF,
                                  int(step) & 0xFFFFFFFF])


def gnss_log_likelihood(particles: np.ndarray, z: np.ndarray, r: np.ndarray) -> np.ndarray:
    """log N(z_i; s_i^(v), R_i) of (23) for (N, J, 4) particles."""
    lp, _ = log_gauss(z[:, None, :] - particles, np.broadcast_to(r[:, None], particles.shape + (4,)))
    return lp
