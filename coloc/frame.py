"""The frame: the only thing that crosses from ``couplers`` to ``coloc``.

One frame per time step, arrays not objects (DESIGN "The frame"). Estimators
read only the measurement fields; ``truth`` is for scoring and tests, and an
estimator that reads it is a bug (``tests/coloc/test_truth_blind.py``).

State convention (Brambilla et al., model (1)): x = [px, py, vx, vy] in the
net's Cartesian frame (metres, metres per second).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class Truth:
    """Scoring-only ground truth of one frame."""

    x_true: np.ndarray  # (N, 4) true vehicle states
    v2f_feature: np.ndarray  # (O,) int, index into features_true of each V2F row
    features_true: np.ndarray  # (K, 4) true feature states
    zone: np.ndarray  # (N,) str, GNSS zone of each vehicle
    area: np.ndarray  # (N,) str, analysis area of each vehicle
    heading: np.ndarray | None = None  # (N,) true heading, rad from +x (defined when stopped too)
    feature_ids: np.ndarray | None = None  # (K,) str, stable feature names


@dataclass(frozen=True)
class Frame:
    """Measurements of all connected vehicles at time ``t``.

    ``entered[i]`` is True when vehicle i appears this step, or re-appears after
    a teleport: the estimator must (re)start it from the fast-start prior
    ``prior_z[i]``, ``prior_R[i]`` (a receiver fix in fast-start condition,
    Brambilla Sec. VI-A; rows of vehicles that did not enter are NaN).
    ``accel`` is the inertial input a_{t-1} of model (1) over (t - dt, t],
    in the net frame; ``dt`` is the sampling interval Ts.
    """

    t: float
    dt: float
    vehicle_ids: np.ndarray  # (N,) str
    entered: np.ndarray  # (N,) bool
    prior_z: np.ndarray  # (N, 4)
    prior_R: np.ndarray  # (N, 4, 4)
    accel: np.ndarray  # (N, 2)
    gnss_z: np.ndarray  # (N, 4)
    gnss_R: np.ndarray  # (N, 4, 4)
    v2f_z: np.ndarray  # (O, 4) relative feature state x_F - x_V + noise, model (4)
    v2f_owner: np.ndarray  # (O,) int row of the measuring vehicle; rows shuffled within a vehicle
    v2f_R: np.ndarray  # (O, 4, 4)
    neighbors: sp.csr_matrix  # (N, N) symmetric boolean V2V adjacency, empty diagonal
    truth: Truth | None = None

    @property
    def n_vehicles(self) -> int:
        return int(self.vehicle_ids.shape[0])

    def without_truth(self) -> "Frame":
        return replace(self, truth=None)


def empty_frame(t: float, dt: float) -> Frame:
    """A frame with no vehicles (e.g. the net is empty at the start)."""
    return Frame(
        t=t,
        dt=dt,
        vehicle_ids=np.empty(0, dtype=object),
        entered=np.empty(0, dtype=bool),
        prior_z=np.empty((0, 4)),
        prior_R=np.empty((0, 4, 4)),
        accel=np.empty((0, 2)),
        gnss_z=np.empty((0, 4)),
        gnss_R=np.empty((0, 4, 4)),
        v2f_z=np.empty((0, 4)),
        v2f_owner=np.empty(0, dtype=np.int64),
        v2f_R=np.empty((0, 4, 4)),
        neighbors=sp.csr_matrix((0, 0), dtype=bool),
    )


@dataclass(frozen=True)
class StepEstimate:
    """What an estimator returns for one frame, rows in ``frame.vehicle_ids`` order."""

    mean: np.ndarray  # (N, 4)
    cov: np.ndarray  # (N, 4, 4)
    feature_mean: np.ndarray | None = None  # (T, 4) feature-track estimates, if the method has them
    feature_cov: np.ndarray | None = None  # (T, 4, 4)
    feature_track_ids: np.ndarray | None = None  # (T,) int stable track ids
    # Per V2F row: the feature track the estimator paired it with (-1 = discarded).
    # Scored against truth outside the estimator.
    v2f_assignment: np.ndarray | None = None
