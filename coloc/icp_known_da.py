"""``icp_known_da``: ICP with the true feature-measurement association (the bound).

Brambilla et al.'s ICP-DA with perfect data association, i.e. Soatti et al.'s
implicit cooperative positioning [40]: Gaussian BPA-L (19)-(22) with the
feature beliefs (20) computed by average consensus over V2V links
(:mod:`coloc.icp` has the math and the equation mapping).

Because it is the bound, this method is told which feature produced each V2F
row. It never reads ``frame.truth``: the caller passes the association
explicitly through :meth:`IcpKnownDA.step_with_association` as an (O,) array
of **stable integer feature ids** (the same id for the same physical feature
at every step; the runner uses the row index into ``truth.features_true``,
which is stable for a scenario, i.e. ``truth.v2f_feature``). ``step(frame)``
refuses to guess and raises.

Per step:
1. vehicles: carried posterior predicted by model (1) with the inertial
   input and Q from :func:`coloc.models.driving_noise_cov`, then GNSS (3)
   update -> b^(0) of (11); vehicles fresh this step start from the frame's
   fast-start prior (updated by GNSS, not predicted), exactly as
   :class:`coloc.gnss.GnssTracker`;
2. features: tracks predicted by model (2) with Q_F -> b^(0) of (12); a
   feature seen for the first time starts from a uniform belief;
3. BPA-L iterations until the stopping rule of Sec. V-A;
4. tracks of the features observed are replaced by the fused belief; tracks
   nobody observed keep their last belief (predicted every step) and are
   dropped after ``feature_drop_after_s``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from coloc.frame import Frame, StepEstimate
from coloc.gnss import gnss_predict_update
from coloc.icp import BpaResult, FeatureStore, IcpParams, bpa_localization, validate_association
from coloc.models import kalman_update
from coloc.vehicles import carry_states

__all__ = ["IcpKnownDA", "IcpParams", "vehicle_prior_beliefs", "icp_known_da_step"]


def vehicle_prior_beliefs(
    prev_ids: np.ndarray, prev_mean: np.ndarray, prev_cov: np.ndarray, frame: Frame, params: IcpParams
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (11): b_i^(0) = GNSS likelihood x predicted belief (fresh vehicles: prior x GNSS)."""
    mean, cov, fresh = carry_states(
        prev_ids, prev_mean, prev_cov, frame.vehicle_ids, frame.entered, frame.prior_z, frame.prior_R
    )
    old = ~fresh
    if old.any():
        mean[old], cov[old] = gnss_predict_update(
            mean[old], cov[old], frame.accel[old], frame.gnss_z[old], frame.gnss_R[old], frame.dt, params.motion
        )
    if fresh.any():
        mean[fresh], cov[fresh] = kalman_update(mean[fresh], cov[fresh], frame.gnss_z[fresh], frame.gnss_R[fresh])
    return mean, cov


def icp_known_da_step(
    prev_ids: np.ndarray,
    prev_mean: np.ndarray,
    prev_cov: np.ndarray,
    features: FeatureStore,
    frame: Frame,
    v2f_feature: np.ndarray,
    params: IcpParams,
) -> tuple[BpaResult, FeatureStore]:
    """One time step of ICP with known association (pure function).

    ``features`` is the track store after the previous step (not yet
    predicted). Returns the BPA-L result and the updated store.
    """
    assoc = validate_association(frame.v2f_owner, v2f_feature, frame.v2f_z.shape[0])
    b0_mean, b0_cov = vehicle_prior_beliefs(prev_ids, prev_mean, prev_cov, frame, params)
    predicted = features.predict(frame.dt, params)
    res = bpa_localization(
        b0_mean, b0_cov, frame.v2f_owner, assoc, frame.v2f_z, frame.v2f_R, frame.neighbors, predicted, params
    )
    store = predicted.upsert(res.feature_ids, res.feature_mean, res.feature_cov, frame.t).drop_stale(frame.t, params)
    return res, store


@dataclass
class IcpKnownDA:
    """Stateful ICP with known DA. Use :meth:`step_with_association`."""

    params: IcpParams = field(default_factory=IcpParams)
    name: str = "icp_known_da"
    last_iterations: int = 0
    last_converged: bool = True
    _ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=object))
    _mean: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))
    _cov: np.ndarray = field(default_factory=lambda: np.empty((0, 4, 4)))
    _features: FeatureStore = field(default_factory=FeatureStore)

    def step(self, frame: Frame) -> StepEstimate:
        raise TypeError(
            "icp_known_da is the known-association bound and needs the true feature of every V2F row; "
            "call step_with_association(frame, v2f_feature) with stable integer feature ids "
            "(e.g. frame.truth.v2f_feature, taken by the runner, never by the estimator)"
        )

    def step_with_association(self, frame: Frame, v2f_feature: np.ndarray) -> StepEstimate:
        res, store = icp_known_da_step(
            self._ids, self._mean, self._cov, self._features, frame, v2f_feature, self.params
        )
        self._ids, self._mean, self._cov, self._features = frame.vehicle_ids, res.mean, res.cov, store
        self.last_iterations, self.last_converged = res.iterations, res.converged
        assoc = np.asarray(v2f_feature, dtype=np.int64).copy()
        return StepEstimate(
            mean=res.mean.copy(),
            cov=res.cov.copy(),
            feature_mean=store.mean.copy(),
            feature_cov=store.cov.copy(),
            feature_track_ids=store.ids.copy(),
            v2f_assignment=assoc,
        )
