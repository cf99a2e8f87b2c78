"""Gaussian information algebra: (mean, cov) <-> (Lambda, eta), the PSD projection and the
relative message of model (4) (eqs. (19), (21))."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy.special import gammaincinv

from coloc.core.models import symmetrize
from coloc.kernels import icp_fused, numpy_blas
from coloc.kernels.bpa_rows import information_rows, inverse_rows
from coloc.kernels.icp import information_kernel, inverse_spd_kernel, log_gauss_kernel
from coloc.kernels.icp import surely_above_floor as _surely_above_floor  # noqa: F401 (its home before)

# ----------------------------------------------------------------------------- Gaussian algebra


@lru_cache(maxsize=64)
def chi2_ppf(p: float, dof: int) -> float:
    """Quantile ``p`` of the chi-square distribution with ``dof`` degrees of freedom (a Mahalanobis
    gate), computed once per (p, dof). It is what ``scipy.stats.chi2.ppf`` returns, bit for bit
    (scipy's ``chi2._ppf`` is ``2 * gammaincinv(dof / 2, p)``; tested), without importing
    ``scipy.stats`` (0.35 s at every process start, measured by ``bench/startup.py``)."""
    return float(2 * gammaincinv(dof / 2, p))


def _inv_spd_numpy(m: np.ndarray) -> np.ndarray:
    return symmetrize(np.linalg.inv(m))


def _inv_spd(m: np.ndarray) -> np.ndarray:
    """Inverse of symmetric positive definite 4x4 matrices (numba Cholesky; numpy reference above)."""
    m = np.asarray(m, dtype=np.float64)
    if m.ndim < 2 or m.shape[-2:] != (4, 4):
        return _inv_spd_numpy(m)
    kernel = inverse_rows if icp_fused.FUSED else inverse_spd_kernel  # same numbers (tests)
    return kernel(np.ascontiguousarray(m.reshape(-1, 4, 4))).reshape(m.shape)


def to_information(mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean (..,4), cov (..,4,4)) -> (Lambda, eta) = (P^-1, P^-1 m)."""
    mean = np.asarray(mean, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    if cov.shape[-2:] != (4, 4) or mean.shape != cov.shape[:-1]:
        lam = _inv_spd_numpy(cov)
        return lam, np.einsum("...ij,...j->...i", lam, mean)
    kernel = information_rows if icp_fused.FUSED else information_kernel  # same numbers (tests)
    lam, eta = kernel(np.ascontiguousarray(mean.reshape(-1, 4)), np.ascontiguousarray(cov.reshape(-1, 4, 4)))
    return lam.reshape(cov.shape), eta.reshape(mean.shape)


def from_information(lam: np.ndarray, eta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Lambda, eta) -> (mean, cov); Lambda must be positive definite (same kernel as :func:`to_information`)."""
    cov, mean = to_information(eta, lam)
    return mean, cov


def psd_clip(lam: np.ndarray, eta: np.ndarray, floor: float = 0.0, sure: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Project information matrices on the PSD cone (eigenvalues < floor -> floor).

    Only needed for extrinsic information after *finite* consensus: count *
    average - own message can be slightly indefinite. The eta component along
    a clipped direction is removed too (no information -> no mean there).
    """
    if lam.shape[0] == 0:
        return lam, eta
    # Most calls clip nothing. Rows that a shifted Cholesky proves safely positive definite
    # (smallest eigenvalue far above the floor and the eigensolver's rounding) cannot be
    # clipped; only the others need the eigendecomposition. If none of them is clipped the
    # inputs are returned as they are, exactly as below.
    if sure is None:  # (``sure``: the caller's _surely_above_floor(lam, floor), e.g. from a fused kernel)
        sure = _surely_above_floor(np.ascontiguousarray(lam, dtype=np.float64), float(floor))
    unsure = np.flatnonzero(~sure)
    if unsure.size == 0 or not (np.linalg.eigh(symmetrize(lam[unsure]))[0] < floor).any():
        return lam, eta
    w, v = np.linalg.eigh(symmetrize(lam))
    bad = w < floor
    if not bad.any():
        return lam, eta
    keep = ~bad
    w = np.where(keep, w, floor)
    lam_c = np.einsum("...ik,...k,...jk->...ij", v, w, v)
    # Remove the part of eta in the clipped eigen-directions.
    coef = np.einsum("...ki,...k->...i", v, eta) * keep
    eta_c = np.einsum("...ik,...k->...i", v, coef)
    return symmetrize(lam_c), eta_c


def relative_message(
    lam: np.ndarray, eta: np.ndarray, offset: np.ndarray, r: np.ndarray, r_inv: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Information form of y = x + offset + n, x ~ (Lambda, eta), n ~ N(0, R), batched.

    This is the integral in (19) (offset +z: x_F = x_V + z) and (21)
    (offset -z: x_V = x_F - z) of a Gaussian belief against the V2F likelihood
    of model (4). Moments: N(m + offset, P + R). Computed without inverting
    Lambda so that a singular Lambda (uniform belief, e.g. a feature seen for
    the first time) gives the zero message:
        S = Lambda + R^-1,  Lambda_y = (P + R)^-1 = Lambda S^-1 R^-1,
        eta_y = R^-1 S^-1 eta + Lambda_y offset.
    """
    if r_inv is None:
        r_inv = _inv_spd_numpy(r)
    if icp_fused.FUSED and _blas_shapes(lam, eta, offset, r_inv) and numpy_blas.available():
        # the same LAPACK / BLAS calls and sums row by row in one numba call (coloc.kernels.numpy_blas)
        lam_y, eta_y, ok = numpy_blas.relative_message_numpy_blas(lam, eta, offset, r_inv)
        if ok:
            return lam_y, eta_y
    return relative_message_numpy(lam, eta, offset, r_inv)


def _blas_shapes(lam, eta, offset, r_inv) -> bool:
    """Rows of :func:`coloc.kernels.numpy_blas.relative_message_numpy_blas`: C-contiguous float64 (O, 4, 4) / (O, 4)."""
    o = lam.shape[0] if lam.ndim == 3 else -1
    return all(a.dtype == np.float64 and a.flags.c_contiguous and a.shape == sh
               for a, sh in ((lam, (o, 4, 4)), (eta, (o, 4)), (offset, (o, 4)), (r_inv, (o, 4, 4))))


def relative_message_numpy(lam: np.ndarray, eta: np.ndarray, offset: np.ndarray, r_inv: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`relative_message` with numpy (the reference of its kernel)."""
    s = lam + r_inv
    s_inv = _inv_spd_numpy(s)
    lam_y = symmetrize(lam @ s_inv @ r_inv)
    eta_y = np.einsum("nij,nj->ni", r_inv @ s_inv, eta) + np.einsum("nij,nj->ni", lam_y, offset)
    return lam_y, eta_y


_LOG_2PI = math.log(2.0 * math.pi)


def log_gauss(nu: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """log N(nu; 0, S) and the squared Mahalanobis distance, batched over rows (numba kernel)."""
    nu = np.asarray(nu, dtype=np.float64)
    d = nu.shape[-1]
    lp, d2 = log_gauss_kernel(
        np.ascontiguousarray(nu.reshape(-1, d)), np.ascontiguousarray(np.asarray(s, dtype=np.float64).reshape(-1, d, d))
    )
    return lp.reshape(nu.shape[:-1]), d2.reshape(nu.shape[:-1])


def log_gauss_numpy(nu: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference of :func:`log_gauss`: log N(nu; 0, S) and the squared Mahalanobis distance."""
    chol = np.linalg.cholesky(s)
    w = np.linalg.solve(chol, nu[..., None])[..., 0]
    d2 = np.einsum("...i,...i->...", w, w)
    logdet = 2.0 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1)
    return -0.5 * (d2 + logdet + nu.shape[-1] * _LOG_2PI), d2
