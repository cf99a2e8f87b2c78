"""The synthetic scenario of Fröhle et al. Sec. V-A (seed paper 001): S vehicles and K mobile
features on the constant-velocity model (28)-(29), GNSS position fixes (30) and unlabelled V2F
relative positions z = p_F - p_V + w.

* Features: f_k ~ N(0, 0.25 I_4) at the middle step (step 250 of 0..500: the paper's
  "t = 251" in 1-based steps), then the CV model run forward and backward in time (backward:
  f_{t-1} = A^-1 (f_t - r_t), r_t ~ N(0, R)), so that the feature trajectories cross near the
  origin in the middle of the run (the paper's "challenging scenario for DA").
* Vehicles: the paper gives only their motion model. Here x_s,0 ~ N(0, 0.25 I_4) at step 0 and
  the CV model forward (a stated choice: with unlimited V2F range and a relative measurement the
  vehicle geometry does not enter the estimation problem).
* Every vehicle measures every feature at every step (Sec. II); the rows of each vehicle are
  shuffled independently at each step (the association is unknown to the estimator).

Randomness: one ``numpy.random.Generator`` per purpose, spawned from ``SeedSequence(seed)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from coloc.core.models import cv_process_cov, cv_transition


@dataclass(frozen=True)
class FrohleScenarioParams:
    n_steps: int = 501
    dt: float = 0.5
    process_intensity: float = 0.1  # r of (29)
    gnss_var: tuple[float, ...] = (0.01, 15.0)  # sigma_s^(G),2 per vehicle, m^2
    v2f_var: float = 1.0  # sigma^(V2F),2, m^2
    n_features: int = 3
    init_var: float = 0.25  # N(0, init_var I_4) of the feature (middle) and vehicle (start) states

    def __post_init__(self):
        if self.n_steps < 1:
            raise ValueError("n_steps must be >= 1")
        if self.n_features < 0:
            raise ValueError("n_features must be >= 0")
        if not self.gnss_var or any(not v > 0 for v in self.gnss_var):
            raise ValueError("gnss_var must list one positive variance per vehicle")
        for name in ("dt", "process_intensity", "v2f_var", "init_var"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")


@dataclass(frozen=True)
class FrohleScenario:
    t: np.ndarray  # (T,) s
    x_true: np.ndarray  # (T, S, 4) vehicle states (scoring only)
    f_true: np.ndarray  # (T, K, 4) feature states (scoring only)
    gnss_z: np.ndarray  # (T, S, 2)
    gnss_cov: np.ndarray  # (S, 2, 2)
    v2f_z: np.ndarray  # (T, S*K, 2) rows grouped by owner, shuffled within each owner at every step
    v2f_cov: np.ndarray  # (S*K, 2, 2)
    v2f_owner: np.ndarray  # (S*K,)
    v2f_feature: np.ndarray  # (T, S*K) true feature of each row (scoring only)


def simulate(params: FrohleScenarioParams, seed: int | list[int]) -> FrohleScenario:
    """One Monte Carlo realisation; same params and seed (an int or a list of ints, the entropy of a
    SeedSequence) give identical arrays."""
    motion_rng, feature_rng, gnss_rng, v2f_rng, order_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(5)
    )
    n_t, n_s, n_k = params.n_steps, len(params.gnss_var), params.n_features
    a = cv_transition(params.dt)
    chol_q = np.linalg.cholesky(cv_process_cov(params.dt, params.process_intensity))
    init_std = np.sqrt(params.init_var)

    x = np.empty((n_t, n_s, 4))
    x[0] = init_std * motion_rng.standard_normal((n_s, 4))
    noise = motion_rng.standard_normal((n_t, n_s, 4)) @ chol_q.T
    for t in range(1, n_t):
        x[t] = x[t - 1] @ a.T + noise[t]

    f = np.empty((n_t, n_k, 4))
    mid = (n_t - 1) // 2
    f[mid] = init_std * feature_rng.standard_normal((n_k, 4))
    noise = feature_rng.standard_normal((n_t, n_k, 4)) @ chol_q.T
    a_inv = np.linalg.inv(a)
    for t in range(mid + 1, n_t):
        f[t] = f[t - 1] @ a.T + noise[t]
    for t in range(mid - 1, -1, -1):
        f[t] = (f[t + 1] - noise[t]) @ a_inv.T

    gnss_std = np.sqrt(np.asarray(params.gnss_var, dtype=float))
    gnss_z = x[:, :, :2] + gnss_std[None, :, None] * gnss_rng.standard_normal((n_t, n_s, 2))
    gnss_cov = np.asarray(params.gnss_var, dtype=float)[:, None, None] * np.eye(2)

    owner = np.repeat(np.arange(n_s), n_k)
    feature = np.empty((n_t, n_s * n_k), dtype=np.int64)
    for t in range(n_t):
        for s in range(n_s):
            feature[t, s * n_k:(s + 1) * n_k] = order_rng.permutation(n_k)
    rel = np.take_along_axis(f[:, :, :2], feature[:, :, None], axis=1) - x[:, owner, :2]
    v2f_z = rel + np.sqrt(params.v2f_var) * v2f_rng.standard_normal(rel.shape)
    return FrohleScenario(
        t=params.dt * np.arange(n_t), x_true=x, f_true=f, gnss_z=gnss_z, gnss_cov=gnss_cov, v2f_z=v2f_z,
        v2f_cov=np.broadcast_to(params.v2f_var * np.eye(2), (n_s * n_k, 2, 2)).copy(), v2f_owner=owner,
        v2f_feature=feature,
    )
