"""``gnss``: the non-cooperative benchmark of Brambilla et al.

A Kalman tracker per vehicle with model (1) driven by the inertial input and
updated by the GNSS fix of model (3) with the zone-dependent covariance the
frame carries. All vehicles of a frame are processed as one batch.

With ``frame.imu`` (``[inertial]``) the input of model (1) is the body-frame IMU rotated by the
tracker's own heading estimate (:func:`coloc.core.inertial.estimator_input`); the tracker keeps one
heading per vehicle for when it is too slow for its velocity to give one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from coloc.core.frame import Frame, StepEstimate
from coloc.core.inertial import estimator_input
from coloc.core.models import MotionParams, driving_noise_cov, kalman_update, predict
from coloc.core.vehicles import carry_states, keep_entry_fix, match_ids
from coloc.inference.comm import CommCount
from coloc.kernels.kalman import gnss_step_kernel
from coloc.methods.registry import GNSS


def gnss_predict_update(
    mean: np.ndarray,
    cov: np.ndarray,
    accel: np.ndarray,
    gnss_z: np.ndarray,
    gnss_R: np.ndarray,
    dt: float,
    motion: MotionParams,
) -> tuple[np.ndarray, np.ndarray]:
    """One tracker step for a batch: predict by model (1), update by GNSS (3)."""
    q = driving_noise_cov(mean[:, 2:], dt, motion)
    m, p = predict(mean, cov, accel, dt, q)
    return kalman_update(m, p, gnss_z, gnss_R)


@dataclass
class GnssTracker:
    """Stateful wrapper: keeps each vehicle's posterior between frames."""

    motion: MotionParams = field(default_factory=MotionParams)
    name: str = GNSS.name
    _ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=object))
    _mean: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))
    _cov: np.ndarray = field(default_factory=lambda: np.empty((0, 4, 4)))
    last_comm: CommCount | None = None  # non-cooperative: sends nothing (coloc.inference.comm)
    _heading: np.ndarray | None = None  # kept heading per vehicle row ([inertial] only)

    def step(self, frame: Frame) -> StepEstimate:
        idx = match_ids(self._ids, frame.vehicle_ids)
        accel, self._heading = estimator_input(frame, idx, self._mean[:, 2:], self._heading,
                                               self.motion.heading_min_speed,
                                               self.motion.holds_heading)
        mean, cov, fresh = carry_states(
            self._ids, self._mean, self._cov, frame.vehicle_ids, frame.entered, frame.prior_z, frame.prior_R, idx
        )
        # A fresh vehicle's prior is already at time t: it is only updated.
        m = self.motion
        gnss_step_kernel(
            mean, cov, np.ascontiguousarray(accel, dtype=float), np.ascontiguousarray(frame.gnss_z, dtype=float),
            np.ascontiguousarray(frame.gnss_R, dtype=float), ~fresh, float(frame.dt),
            m.sigma_along, m.sigma_cross, m.heading_min_speed,
        )
        keep_entry_fix(mean, cov, frame, fresh)  # a prior that is this step's fix is not updated by it again
        self._ids, self._mean, self._cov = frame.vehicle_ids, mean, cov
        self.last_comm = CommCount.zeros(frame.n_vehicles)
        return StepEstimate(mean=mean.copy(), cov=cov.copy())
