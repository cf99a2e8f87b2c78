"""The frame: the only thing that crosses from ``couplers`` to ``coloc``.

One frame per time step, arrays not objects (docs/architecture.md "The frame contract"). Estimators
read only the measurement fields; ``truth`` is for scoring and tests, and an
estimator that reads it is a bug (``tests/coloc/test_contract.py``).

State convention (Brambilla et al., model (1)): x = [px, py, vx, vy] in the
net's Cartesian frame (metres, metres per second).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from coloc.core.detections import SensorDetections
from coloc.core.inertial import ImuFrame
from coloc.core.v2x import V2xFrame


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
    # Class of each feature (0 static landmark, 1 pedestrian; couplers.sensing.pedestrians); None: all static.
    # With SUMO pedestrians, rows K0.. are persons by first appearance (NaN state once they have left).
    feature_class: np.ndarray | None = None  # (K,) int8
    # What each V2F row truly is, with [perception] road_users / persistent clutter / class_error
    # (couplers.sensing.road_users KIND_*: 0 landmark, 1 clutter, 2 persistent clutter, 3 vehicle,
    # 4 pedestrian); None: a row with v2f_feature >= 0 is a feature, -1 clutter.
    v2f_kind: np.ndarray | None = None  # (O,) int8
    # Infrastructure mode only: row (into the frame's vehicles) of each radar detection.
    radar_vehicle: np.ndarray | None = None  # (P,) int


@dataclass(frozen=True)
class InfraFrame:
    """Road-side units of one step (infrastructure mode; ``Frame.infra``).

    * ``rsu_xy`` (R, 2): the RSU positions, known to the estimators (surveyed).
    * ``v2i`` (R, N) boolean CSR: vehicle i is within ``rsu_range_m`` of RSU r. V2I is a
      physical link, decided from the true positions exactly as the V2V ``neighbors`` are;
      vehicle i sends its GNSS and V2F measurements to every RSU it is linked to.
    * ``radar_z`` (P, 2): detections of an infrastructure radar at each RSU, in the radar's
      own frame q = R(theta_r)^T (p - s_r) + n, n ~ N(0, radar_var I2). The radar pose
      (s_r = RSU position + offset, theta_r) is drawn once per run from the seed and is
      unknown to the estimators. Simplification: radar range = V2I range (one disc per RSU)
      and detection probability 1, so the detections of RSU r are exactly the vehicles of
      ``v2i`` row r, without identities (rows shuffled within each RSU).
    * ``radar_owner`` (P,): RSU index of each detection, rows grouped by RSU.
    * ``odom`` (N, 2): each vehicle's odometry displacement over the last step in the net
      frame (Gulati (4)-(5)): true displacement + N(0, odom_var I2); NaN for vehicles that
      entered (or re-entered) this step.
    """

    rsu_ids: np.ndarray  # (R,) str
    rsu_xy: np.ndarray  # (R, 2) surveyed RSU positions (known; the radar pose is not)
    v2i: sp.csr_matrix  # (R, N) bool
    radar_z: np.ndarray  # (P, 2)
    radar_owner: np.ndarray  # (P,) int
    radar_var: float
    odom: np.ndarray  # (N, 2)
    odom_var: float

    @property
    def n_rsu(self) -> int:
        return int(self.rsu_ids.shape[0])


@dataclass(frozen=True)
class OracleGnss:
    """What ``joint_oracle`` is told of the satellite receivers of one step (``[gnss_error] model = "satellites"``,
    only in a run whose methods include ``joint_oracle``; every other estimator ignores it, the contract test
    ``tests/coloc/test_contract.py`` checks it). S is every satellite of the constellation, at a fixed index.

    * ``gain`` (N, 2, S): each receiver's weighted least-squares position gain, the east/north rows of
      (H^T W H)^-1 H^T W over the satellites of its fix (zero columns elsewhere), so that its fix error is
      ``gain[i] @ eps_i`` for its pseudorange errors eps_i (the clock column absorbs what all its ranges share);
    * ``used`` (N, S): the satellites of the fix; ``reflected`` (N, S): received by reflection (NLOS);
    * ``elevation`` (S,): rad; ``fix`` (N,): the receiver has a fix of its own this step (else it holds the last);
    * ``velocity_gain`` (N, 2, S), ``velocity_used`` (N, S), ``velocity_solved`` (N,): the same for the Doppler
      velocity (``velocity = "doppler"``; None otherwise).

    The structure of the error, never its realisation (couplers/sensing/gnss_satellites.py, ``oracle_frame``)."""

    gain: np.ndarray
    used: np.ndarray
    reflected: np.ndarray
    elevation: np.ndarray
    fix: np.ndarray
    velocity_gain: np.ndarray | None = None
    velocity_used: np.ndarray | None = None
    velocity_solved: np.ndarray | None = None


@dataclass(frozen=True)
class Frame:
    """Measurements of all connected vehicles at time ``t``.

    ``entered[i]`` is True when vehicle i appears this step, or re-appears after
    a teleport: the estimator must (re)start it from the fast-start prior
    ``prior_z[i]``, ``prior_R[i]`` (a receiver fix in fast-start condition,
    Brambilla Sec. VI-A; rows of vehicles that did not enter are NaN).
    ``prior_has_fix[i]`` (SUMO runs with ``[scenario] start = "gnss_fix"``) says that this prior *is*
    this step's fix ``gnss_z[i]``, ``gnss_R[i]``: the vehicle's belief at entry is that prior and the
    fix must not update it a second time (:func:`coloc.core.vehicles.entry_fix_rows`). None: no prior
    holds a fix of the step (the paper's fast start, and the Sec. V scenarios' independent first fix).
    ``accel`` is the inertial input a_{t-1} of model (1) over (t - dt, t],
    in the net frame; ``dt`` is the sampling interval Ts.

    ``imu`` (the ``[inertial]`` table, :mod:`coloc.core.inertial`) is the vehicles' body-frame IMU:
    ``imu.accel_body`` (N, 2) longitudinal / lateral acceleration and ``imu.yaw_rate`` (N,), each with
    white noise and a drifting bias. When it is set, ``accel`` is NaN (it would carry the true
    heading): an estimator forms a_{t-1} itself by rotating ``imu.accel_body`` with its *estimated*
    heading (:func:`coloc.core.inertial.estimator_input`). None (the default): ``accel`` is the
    paper's net-frame input, exactly as before.

    ``v2f_sensor`` (``[perception] detections = "range_bearing"``, :mod:`coloc.core.detections`): the V2F
    rows as the sensors report them, range, bearing and range rate in each sensor's frame with the
    sensor's mounting and noise std per row. When it is set, ``v2f_z`` and ``v2f_R`` are NaN (they would
    carry the true heading; ``v2f_owner`` and the truth's ``v2f_feature`` keep their meaning): an
    estimator forms model (4)'s rows itself with its own heading estimate
    (:func:`coloc.core.detections.with_net_detections`). None (the default): ``v2f_z`` / ``v2f_R`` are
    the net-frame rows, exactly as before.
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
    infra: InfraFrame | None = None  # road-side units and radars (infrastructure mode only)
    # Realistic V2X ([v2x] table): per-link delivery probabilities aligned with ``neighbors``, the
    # round budget and the step's channel seed (coloc.core.v2x). None: every link delivers every round.
    v2x: V2xFrame | None = None
    # Body-frame IMU ([inertial] table): accel_body (N, 2) and yaw_rate (N,) (coloc.core.inertial). None:
    # ``accel`` is the net-frame input of model (1).
    imu: ImuFrame | None = None
    # Class label of each V2F row as the sensor's classifier reports it (``[features] pedestrians``):
    # 0 = static landmark, 1 = pedestrian, 2 = vehicle (couplers.sensing.perception CLASS_*; vehicles:
    # [perception] road_users, couplers.sensing.road_users); a false detection is reported
    # as static (it is drawn as a static object). None (pedestrians off): every row is a static landmark,
    # and estimators run exactly as without classes.
    v2f_class: np.ndarray | None = None  # (O,) int8
    # Sensor-frame detections ([perception] detections = "range_bearing"): range, bearing, range rate per V2F
    # row (coloc.core.detections). None: v2f_z / v2f_R are the net-frame rows.
    v2f_sensor: SensorDetections | None = None
    # (N,) bool: the entering vehicle's prior is this step's receiver fix (start = "gnss_fix"); None: none is.
    prior_has_fix: np.ndarray | None = None
    # The satellite receivers' structure for joint_oracle alone (OracleGnss); None for every run without it.
    oracle_gnss: OracleGnss | None = None

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
    # Infrastructure methods: True where the row was estimated by an RSU (vehicle within
    # V2I range of one); other rows carry the method's fallback GNSS tracker estimate.
    covered: np.ndarray | None = None  # (N,) bool
