"""``icp_known_da``: ICP with the true feature-measurement association (the bound).

Brambilla et al.'s ICP-DA with perfect data association, i.e. Soatti et al.'s
implicit cooperative positioning [40]: Gaussian BPA-L (19)-(22) with the
feature beliefs (20) computed by average consensus over V2V links
(:mod:`coloc.inference` has the math and the equation mapping).

Because it is the bound, this method is told which feature produced each V2F
row. It never reads ``frame.truth``: the caller passes the association
explicitly through :meth:`IcpKnownDA.step_with_association` as an (O,) array
of **stable integer feature ids** (the same id for the same physical feature
at every step; the runner uses the row index into ``truth.features_true``,
which is stable for a scenario, i.e. ``truth.v2f_feature``). ``step(frame)``
refuses to guess and raises.

Per step:
1. vehicles: carried posterior predicted by model (1) with the inertial
   input and Q from :func:`coloc.core.models.driving_noise_cov`, then GNSS (3)
   update -> b^(0) of (11); vehicles fresh this step start from the frame's
   fast-start prior (updated by GNSS, not predicted; a prior that is the
   step's fix, ``Frame.prior_has_fix``, is not updated again), exactly as
   :class:`coloc.methods.gnss.GnssTracker`;
   the vehicle's own-sensor track (GNSS + inertial only) is advanced the
   same way; it is what the vehicle tells features in (19)
   (:func:`coloc.inference.bpa.bpa_localization` explains why);
2. features: tracks predicted by model (2) with Q_F -> b^(0) of (12),
   without the messages the observing vehicles are about to replace; a
   feature seen for the first time starts from the birth prior (uniform by
   default);
3. BPA-L iterations until the stopping rule of Sec. V-A;
4. each observing vehicle's message (its own-sensor one by default,
   ``IcpParams.feature_message``) replaces its previous one in the track
   (:class:`coloc.inference.feature_store.FeatureStore`); tracks nobody observed are predicted
   every step and dropped after ``feature_drop_after_s``. The step's feature
   estimates are the beliefs (20) with BPA-L's final messages
   (:func:`coloc.inference.bpa.step_feature_beliefs`).

With ``frame.v2x`` set, the consensus of (20) runs over the lossy V2X channel within the step's
round budget (:mod:`coloc.inference.bpa`). With ``frame.imu`` (``[inertial]``) the input of model (1), for
the belief and the own-sensor track alike, is the body-frame IMU rotated by the heading of the vehicle's
previous belief (22) (:func:`coloc.core.inertial.estimator_input`; the kept headings are
``IcpState.heading``). With ``frame.v2f_sensor`` (sensor-frame detections) the V2F rows of model (4) are
formed at step 1 from range, bearing and range rate by the heading of the own-sensor track at t (GNSS and
inertial only: its covariance is consistent, which b^(0)'s is not, and the rows it converts never fed it;
:func:`coloc.core.detections.with_net_detections`). ``last_comm`` is what the vehicles sent in the last step
(:mod:`coloc.inference.comm`: per BPA-L consensus round, one broadcast per vehicle with 16 words per
feature it shares with a neighbour).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from coloc.core.detections import HeadingMemory, with_net_detections
from coloc.core.frame import Frame, StepEstimate
from coloc.core.vehicle_rows import expand_rows, without_vehicle_rows
from coloc.core.inertial import estimator_input
from coloc.core.vehicles import carry_states, fresh_rows, keep_entry_fix, match_ids
from coloc.inference.bpa import BpaResult, bpa_localization, step_feature_beliefs, validate_association
from coloc.inference.comm import CommCount
from coloc.inference.feature_store import FeatureStore, vehicle_codes
from coloc.inference.params import IcpParams
from coloc.kernels import icp_fused
from coloc.kernels.icp_fused import carry_gnss_kernel, unique_inverse
from coloc.kernels.kalman import gnss_step_kernel
from coloc.methods.coop_fusion import CoopFusion, SplitPrior, SplitState, split_localization, split_prior
from coloc.methods.registry import ICP_KNOWN_DA

__all__ = ["IcpKnownDA", "IcpParams", "IcpState", "vehicle_prior_beliefs", "icp_known_da_step", "frame_vehicle_codes"]


def vehicle_prior_beliefs(
    prev_ids: np.ndarray, prev_mean: np.ndarray, prev_cov: np.ndarray, frame: Frame, params: IcpParams,
    match: np.ndarray | None = None, accel: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (11): b_i^(0) = GNSS likelihood x predicted belief (fresh vehicles: prior x GNSS).

    ``match``: ``match_ids(prev_ids, frame.vehicle_ids)`` when the caller has it (b^(0) and the
    own-sensor track share it); ``accel``: the input a_{t-1} of model (1) in frame order
    (:func:`coloc.core.inertial.estimator_input`; None: ``frame.accel``)."""
    mean, cov, fresh = carry_states(
        prev_ids, prev_mean, prev_cov, frame.vehicle_ids, frame.entered, frame.prior_z, frame.prior_R, match
    )
    # Predict (1) + GNSS update (3) in place, fresh vehicles update only: the numba kernel of
    # :class:`coloc.methods.gnss.GnssTracker` (numpy reference: gnss_predict_update / kalman_update).
    m = params.motion
    gnss_step_kernel(
        mean, cov, np.ascontiguousarray(frame.accel if accel is None else accel, dtype=float),
        np.ascontiguousarray(frame.gnss_z, dtype=float),
        np.ascontiguousarray(frame.gnss_R, dtype=float), ~fresh, float(frame.dt),
        m.sigma_along, m.sigma_cross, m.heading_min_speed,
    )
    keep_entry_fix(mean, cov, frame, fresh)  # a prior that is this step's fix is not updated by it again
    return mean, cov


def vehicle_prior_pair(
    state: "IcpState", frame: Frame, params: IcpParams, match: np.ndarray, accel: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`vehicle_prior_beliefs` of the belief and of the own-sensor track, (b0_mean, b0_cov, own_mean,
    own_cov): in one numba pass on the fused path (:func:`coloc.kernels.icp_fused.carry_gnss_kernel`,
    the same kernel and numbers), else two calls."""
    if not icp_fused.FUSED:
        b0 = vehicle_prior_beliefs(state.ids, state.mean, state.cov, frame, params, match, accel)
        return *b0, *vehicle_prior_beliefs(state.ids, state.own_mean, state.own_cov, frame, params, match, accel)
    fresh = fresh_rows(match, frame.entered, frame.prior_z)
    m = params.motion
    f64 = np.ascontiguousarray
    out = carry_gnss_kernel(
        f64(state.mean, dtype=float), f64(state.cov, dtype=float), f64(state.own_mean, dtype=float),
        f64(state.own_cov, dtype=float), match, fresh, f64(frame.prior_z, dtype=float), f64(frame.prior_R, dtype=float),
        f64(frame.accel if accel is None else accel, dtype=float), f64(frame.gnss_z, dtype=float),
        f64(frame.gnss_R, dtype=float), float(frame.dt), m.sigma_along, m.sigma_cross, m.heading_min_speed,
    )
    keep_entry_fix(out[0], out[1], frame, fresh)  # the entry protocol, as vehicle_prior_beliefs
    keep_entry_fix(out[2], out[3], frame, fresh)
    return out


def prior_pair(state: "IcpState", frame: Frame, params: IcpParams, match: np.ndarray, accel: np.ndarray | None,
               fusion: CoopFusion | None):
    """(b0_mean, b0_cov, own_mean, own_cov, split prior): :func:`vehicle_prior_pair` (split prior None), or
    with ``[fusion]`` the 6-D filters of :mod:`coloc.methods.coop_fusion` and their 4-D marginals."""
    if fusion is None:
        return (*vehicle_prior_pair(state, frame, params, match, accel), None)
    prior = split_prior(state.split, frame, match, frame.accel if accel is None else accel, params.motion,
                        fusion.model, fusion.params.common_mode_gnss, fusion.params.common_frame_messages,
                        belief_model=fusion.belief_model)
    return (*prior.marginal(), prior)


def localize(split: SplitPrior | None, b0_mean, b0_cov, own_mean, own_cov, owner, track, z, r, frame: Frame,
             f_lam0, f_eta0, params: IcpParams, feature_ci: bool = False) -> tuple[BpaResult, SplitState | None]:
    """The step's BPA-L (:func:`coloc.inference.bpa.bpa_localization`), or with ``[fusion]`` (``split``
    not None) the split-CI fusion (:func:`coloc.methods.coop_fusion.split_localization`)."""
    if split is None:
        return bpa_localization(b0_mean, b0_cov, own_mean, own_cov, owner, track, z, r, frame.neighbors, f_lam0,
                                f_eta0, params, v2x=frame.v2x), None
    return split_localization(split, owner, track, z, r, frame.neighbors, f_lam0, f_eta0, params, v2x=frame.v2x,
                              feature_ci=feature_ci)


def icp_known_da_step(state: "IcpState", frame: Frame, v2f_feature: np.ndarray, params: IcpParams,
                      fusion: CoopFusion | None = None) -> tuple[BpaResult, "IcpState"]:
    """One time step of ICP with known association (pure function of the previous state); ``fusion``:
    ``[fusion]`` (:mod:`coloc.methods.coop_fusion`), None: the paper's BPA-L."""
    assoc = validate_association(frame.v2f_owner, v2f_feature, frame.v2f_z.shape[0])
    match = match_ids(state.ids, frame.vehicle_ids)
    accel, heading = estimator_input(frame, match, state.mean[:, 2:], state.heading, params.motion.heading_min_speed,
                                     params.motion.holds_heading)
    b0_mean, b0_cov, own_mean, own_cov, split = prior_pair(state, frame, params, match, accel, fusion)
    # Sensor-frame detections (frame.v2f_sensor): model (4)'s rows by the heading of the own-sensor track at t
    # (coloc.core.detections).
    frame, sensor_heading = with_net_detections(frame, own_mean, own_cov, match, state.sensor_heading,
                                                params.motion.heading_min_speed)
    predicted = state.features.predict(frame.dt, params, 0.0 if fusion is None else fusion.map_drift(frame.dt))
    used = assoc >= 0
    owner_used = np.asarray(frame.v2f_owner, dtype=np.int64)[used]
    row_vehicle = np.asarray(frame.vehicle_ids, dtype=object)[owner_used]
    codes = frame_vehicle_codes(state, frame, match)
    row_codes = codes[owner_used]
    fids = unique_inverse(assoc[used])[0]
    row_class = frame.v2f_class[used] if frame.v2f_class is not None else None
    f_lam0, f_eta0 = predicted.prior_information(fids, assoc[used], row_vehicle, params, row_codes, row_class)
    res, split_after = localize(split, b0_mean, b0_cov, own_mean, own_cov, frame.v2f_owner, assoc, frame.v2f_z,
                                frame.v2f_R, frame, f_lam0, f_eta0, params,
                                fusion is not None and fusion.params.feature_ci)
    # Classes (frame.v2f_class, SUMO pedestrians): a track takes its first row's class, and its
    # model (2) noise follows it (coloc.inference.feature_store.feature_track_q).
    store = predicted.record(assoc[used], row_vehicle, res.msg_lam, res.msg_eta, frame.t, params, row_codes,
                             row_class)
    beliefs = step_feature_beliefs(store, params, assoc[used], res)
    return res, IcpState(frame.vehicle_ids, res.mean, res.cov, own_mean, own_cov, store, beliefs, heading, codes,
                         sensor_heading, split_after)


def frame_vehicle_codes(state: "IcpState", frame: Frame, match: np.ndarray) -> np.ndarray:
    """``vehicle_codes(frame.vehicle_ids)``: carried from the previous step's for the vehicles still
    present (``match = match_ids(state.ids, frame.vehicle_ids)``), looked up for the others."""
    if state.codes is None or not icp_fused.FUSED:
        return vehicle_codes(frame.vehicle_ids)
    codes = np.full(match.size, -1, dtype=np.int64)
    have = match >= 0
    codes[have] = state.codes[match[have]]
    if not have.all():
        codes[~have] = vehicle_codes(np.asarray(frame.vehicle_ids, dtype=object)[~have])
    return codes


@dataclass(frozen=True)
class IcpState:
    """What a Gaussian ICP carries between steps (vehicle rows in ``ids`` order)."""

    ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=object))
    mean: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))  # beliefs (22)
    cov: np.ndarray = field(default_factory=lambda: np.empty((0, 4, 4)))
    own_mean: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))  # own-sensor (GNSS-only) beliefs
    own_cov: np.ndarray = field(default_factory=lambda: np.empty((0, 4, 4)))
    features: FeatureStore = field(default_factory=FeatureStore)
    # (mean, cov) of (20) for ``features.ids`` after the step's BPA-L (coloc.inference.bpa.step_feature_beliefs);
    # None: the store's moments.
    feature_beliefs: tuple[np.ndarray, np.ndarray] | None = None
    # [inertial] only: the heading kept per vehicle row (coloc.core.inertial.net_frame_input); None otherwise.
    heading: np.ndarray | None = None
    # vehicle_codes(ids) (coloc.inference.feature_store), carried to the next step; None: not kept.
    codes: np.ndarray | None = None
    # Sensor-frame detections only: the heading each vehicle last had above the minimum speed
    # (coloc.core.detections.HeadingMemory); None otherwise.
    sensor_heading: HeadingMemory | None = None
    # [fusion] only: the 6-D cooperative and own-sensor filters (coloc.methods.coop_fusion); None otherwise.
    split: SplitState | None = None
    # ICP-DA-LC with [lc] anchor_margin only: each vehicle's map-anchored position (N, 2), which takes no fix
    # (coloc.methods.lc_reloc.anchored_mean); None otherwise.
    anchor: np.ndarray | None = None

    def estimate(self, v2f_assignment: np.ndarray, params: IcpParams) -> StepEstimate:
        f_mean, f_cov = self.features.moments(params) if self.feature_beliefs is None else self.feature_beliefs
        return StepEstimate(
            mean=self.mean.copy(),
            cov=self.cov.copy(),
            feature_mean=f_mean.copy(),  # moments are cached on the (immutable) store
            feature_cov=f_cov.copy(),
            feature_track_ids=self.features.ids.copy(),
            v2f_assignment=np.asarray(v2f_assignment, dtype=np.int64).copy(),
        )


@dataclass
class IcpKnownDA:
    """Stateful ICP with known DA: a :class:`coloc.core.protocol.KnownAssociationEstimator` (it has no
    ``step``; the true association of every V2F row comes with each frame)."""

    params: IcpParams = field(default_factory=IcpParams)
    name: str = ICP_KNOWN_DA.name
    last_iterations: int = 0
    last_converged: bool = True
    state: IcpState = field(default_factory=IcpState)
    last_comm: CommCount | None = None  # what the vehicles sent in the last step
    fusion: CoopFusion | None = None  # [fusion] (coloc.methods.coop_fusion); None: the paper's BPA-L

    def step_with_association(self, frame: Frame, v2f_feature: np.ndarray) -> StepEstimate:
        # Vehicle-class rows are not landmarks (coloc.core.vehicle_rows): dropped, as clutter rows are.
        n_rows = frame.v2f_z.shape[0]
        frame, kept = without_vehicle_rows(frame)
        assoc = np.asarray(v2f_feature)[kept] if kept is not None else v2f_feature
        res, self.state = icp_known_da_step(self.state, frame, assoc, self.params, self.fusion)
        self.last_iterations, self.last_converged, self.last_comm = res.iterations, res.converged, res.comm
        return self.state.estimate(expand_rows(np.asarray(assoc, dtype=np.int64), kept, n_rows)
                                   if kept is not None else v2f_feature, self.params)
