"""``icp_da_pf``: particle-based ICP-DA (Brambilla et al. Sec. IV-C, eqs. (23)-(29)).

Vehicle beliefs are sets of Jv particles, feature-track beliefs sets of Jf
particles. Per time step:

1. prediction by model (1) (vehicles: inertial input, driving noise rotated to
   the heading of the vehicle's MMSE velocity) and model (2) (tracks); a
   vehicle that enters samples its particles from the fast-start prior. b_i^(0)
   of (23): equal weights times the GNSS likelihood N(z; s, R) of (3);
   b_k^(0) of (24): the track's carried weights (equal after resampling);
2. eta of (25) for every (vehicle i, candidate track k, row l of i): the
   double sum over vehicle and feature particles,
       eta(alpha = l) = P_D sum_v w_i^(v) (1/Jf) sum_f N(z_l; s_k^(f) - s_i^(v), R_l) / (mu_new f_new(z_l)),
   normalised by the density of a measurement from an untracked feature exactly
   as ICP-DA-LC (:mod:`coloc.methods.icp_da_lc`, step 3) so that the two
   implementations take the same decisions on the same beliefs;
   eta(alpha = 0) = 1 - P_D. Candidate triples are pre-gated with the
   particle clouds' moments (chi-square, ``lc.gate_probability``): outside the
   gate the double sum is not evaluated and eta = 0 (``lc.pairing = "paper"``:
   no pre-gate, the double sum for every candidate triple; the rest of LC's
   pairing rule does not apply, the PF keeps every association in (18));
3. BPA-DA (14)-(17), the same numba BP as LC (:func:`coloc.methods.icp_da_lc.association_beliefs`);
4. the V2F likelihood (18) for localization, a mixture over the association
   beliefs, with p(z | x, alpha = 0) = 1 - P_D and
   p(z | x, alpha = l) = P_D N(z_l; x_F - x_V, R_l) / (mu_new f_new(z_l)),
   the same scale as eta; options with belief below
   ``pf.min_association_belief`` are left out of the mixture;
5. BPA-L (19)-(22) on particles: message i -> k, weights on the feature
   particles (the expression after (25)); feature belief (26) through (28)-(29):
   every vehicle of V_k holds log w_{i->k}, an *average consensus* over the
   V2V links among V_k gives the mean log-weight, times |V_k| (the component's
   participant count), followed by a *max consensus* so that every vehicle of
   the component holds identical weights; message k -> i (weights on the
   vehicle particles, after (26)) with the feature cavity b_k / m_{i->k};
   vehicle belief (27). Iterations stop by the rule of Sec. V-A on the MMSE
   estimates of vehicles and features (10 cm, 0.1 m/s);
6. MMSE estimates and weighted covariances, then systematic resampling of
   vehicles and observed tracks (equal weights for (23)-(24) next step);
7. feature tracks without a map as in LC: a row whose "new" belief is at
   least ``lc.birth_probability`` starts a track (rows of several vehicles
   implying the same position start one, :func:`coloc.methods.icp_da_lc.birth_clusters`).
   A newborn track's particles are drawn from the Gaussian the row implies
   (vehicle moments + z, with the velocity prior of ``IcpParams`` if set) and
   carry importance weights prior / proposal, i.e. the paper's uniform belief
   (times the velocity prior) represented on those particles; the row's own
   message then multiplies in during BPA-L. While a track's b_k^(0) is that
   prior alone and one vehicle observes it, its message to the vehicle is
   taken in closed form (``track_flat`` of :func:`coloc.inference.particle_bp.pf_bpa_localization`).
   Merging: LC's rule on the particle moments, the older track kept; dropping
   after ``feature_drop_after_s``.
8. under clutter and missed detections (realistic sensing), LC's steps 3 and 9 on the particle moments:
   with ``detection`` (``lc.sensor_fov``, the ``[perception]`` sensors) P_D is per (vehicle, track)
   pair at the moments, 0 outside every field of view, in eta (25) and in the terms of (18); with
   ``lc.track_existence`` every track carries an existence probability r
   (:mod:`coloc.inference.existence`, Meyer et al. 2018): eta(alpha = l) scaled by r, eta(alpha = 0)
   = 1 - r P_D, r updated from the association beliefs and the expected detections that did not
   come, a newborn track's r from the rows that started it. Rows of tracks below
   ``lc.confirm_existence`` do not enter (18) or BPA-L: they move no vehicle, the track keeps its
   birth particles (predicted by model (2)) until confirmed, and the rows are reported as discarded;
   tracks below ``lc.drop_existence`` are dropped. Without either option the step is the paper's.

Identical particle sets at all vehicles (the paper's synchronized local
generators): every random draw of a vehicle's or a track's particles comes from
a generator seeded by (``pf.seed``, purpose, entity, step), entity being a
CRC32 of the vehicle id or the track id, so any vehicle holding a copy of
track k draws the same particles without communicating. The pairwise sums are
the kernels of :mod:`coloc.kernels.pf` (a k-d tree kernel exact to
``kernel_rel_tol`` per entry, or the brute force) or of :mod:`coloc.kernels.pf_fast`
(``kernel = "fast"``: float32 and 16-bit kept matrices, every entry within 1e-3,
checked on the estimates by ``tools/pf_equivalence.py``); BPA-L's two message sums keep
their kernel matrices through the iterations of a step (``pf.kernel_cache_mb``),
since only the cavity weights change between iterations.

Step 5 (BPA-L on particles, (19)-(22) and (26)-(29)) and the settings :class:`PfParams` live in
:mod:`coloc.inference.particle_bp`; the particle utilities (prediction by models (1)-(2),
resampling, moments, kernel density, the synchronized generators) in :mod:`coloc.inference.particles`.

The time recursion (``PfParams.recursion``): "paper" is (23)-(24) as written
(vehicle sets carry the cooperative belief, tracks their posterior); the
default "latest_message" is the particle counterpart of the own-sensor cavity
and latest-message store that :mod:`coloc.inference` adds to the Gaussian ICP
against the feedback of a feature's information through the vehicle belief.

Two departures keep the particle messages from being Monte Carlo noise
(``PfParams.message_bandwidth``, and the closed-form prior message of
:func:`coloc.inference.particle_bp.pf_bpa_localization`'s ``track_flat``). The V2F noise (0.1 m, 0.1 m/s)
is far narrower than the particle clouds: summed with the bare kernel N(z;
x_F - x_V, R), a message is a comb of J spikes (a vehicle particle meets on
average well under one feature particle inside the 4-D kernel at J = 1000),
and a product of several such messages keeps one particle. "prior" (default)
treats each particle set as a kernel density estimate, as nonparametric BP
does (Sudderth et al.; the RSU BP of :mod:`coloc.methods.rsu_bp` likewise): the
kernel of every double sum becomes R + h^2 Cov of the source set, Silverman's
h for the effective sample size of b^(0) (:func:`kernel_density`). The
smoothing is a bias that vanishes as J grows. Measured in the tests'
5-vehicle scenario with known association (J = 300 / 1000): 0.63 / 0.74 m
with it, 2.50 / 1.89 m without; Gaussian bound 0.55 m, GNSS 1.58 m. A
bandwidth from each iteration's cavity instead of b^(0) was tried and drifts
on the crossroad (Nf = 20, seeds 1-3: 2.63 / 2.86 / 3.27 m against 1.91 /
1.68 / 2.36 m).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import logsumexp

from coloc.core.detection import DetectionModel, expected_detection_probability
from coloc.core.frame import Frame, StepEstimate
from coloc.core.vehicle_rows import expand_rows, without_vehicle_rows
from coloc.core.detections import HeadingMemory, with_net_detections
from coloc.core.inertial import estimator_input
from coloc.core.vehicles import entry_fix_rows, fresh_rows, match_ids
from coloc.inference.comm import CommCount
from coloc.inference.existence import TrackExistence, birth_existence
from coloc.inference.gaussian import chi2_ppf, log_gauss
from coloc.inference.params import IcpParams
from coloc.inference.particle_bp import PfParams, bpa_components, gauss_transforms, pf_bpa_localization, pf_step_comm
from coloc.inference.particles import (
    entity_rng,
    gaussian_log_pdf,
    gnss_log_likelihood,
    kernel_density,
    normalize_log,
    predict_track_particles,
    predict_vehicle_particles,
    regularized_resample,
    sample_gaussian,
    systematic_resample,
    weighted_moments,
)
from coloc.kernels.icp import scatter_add
from coloc.kernels.pf import KernelWorkspace
from coloc.methods.icp_da_lc import (
    LcParams,
    association_beliefs,
    birth_clusters,
    candidate_rows,
    existence_after_association,
    merge_candidates,
    new_feature_log_density,
    new_feature_share,
    own_consistency_reset,
)
from coloc.methods.coop_fusion import CoopFusion, SplitState, split_prior
from coloc.methods.pf_fusion import gaussian_sets, pf_split_localization
from coloc.methods.registry import ICP_DA_PF

__all__ = [
    "PfParams", "PfState", "PfStepInfo", "IcpDaPf", "icp_da_pf_step", "pf_bpa_localization", "entity_rng",
    "systematic_resample", "weighted_moments", "bpa_components", "pf_step_comm",
]

# ----------------------------------------------------------------------------- synchronized generators


def _vehicle_entity(vehicle_id) -> int:
    return zlib.crc32(str(vehicle_id).encode())


# ----------------------------------------------------------------------------- state and step


@dataclass(frozen=True)
class PfState:
    """What ICP-DA-PF carries between steps (resampled, equal-weight vehicle sets)."""

    ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=object))
    particles: np.ndarray = field(default_factory=lambda: np.empty((0, 0, 4)))  # beliefs (27), resampled
    own_particles: np.ndarray = field(default_factory=lambda: np.empty((0, 0, 4)))  # own-sensor sets (latest_message)
    track_ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    track_particles: np.ndarray = field(default_factory=lambda: np.empty((0, 0, 4)))
    track_logw: np.ndarray = field(default_factory=lambda: np.empty((0, 0)))
    track_last_seen: np.ndarray = field(default_factory=lambda: np.empty(0))
    # Latest message per (track, vehicle) at the track's particles ("latest_message" recursion).
    msg_track: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    msg_vehicle: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=object))
    msg_logv: np.ndarray = field(default_factory=lambda: np.empty((0, 0)))
    msg_time: np.ndarray = field(default_factory=lambda: np.empty(0))
    # Per track: evidence is folded into its weights beyond the stored messages (an expired message).
    track_folded: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=bool))
    # [inertial] only: the heading kept per vehicle row (coloc.core.inertial.net_frame_input); None otherwise.
    heading: np.ndarray | None = None
    # Sensor-frame detections only: the heading each vehicle last had above the minimum speed
    # (coloc.core.detections.HeadingMemory); None otherwise.
    sensor_heading: HeadingMemory | None = None
    # [fusion] only: the 6-D cooperative and own-sensor filters (coloc.methods.pf_fusion); None otherwise.
    split: SplitState | None = None


@dataclass(frozen=True)
class PfStepInfo:
    row_track: np.ndarray
    born: int
    discarded: int
    merged: int
    iterations: int
    pair_evaluations: int
    comm: CommCount | None = None  # what the vehicles sent (pf_step_comm)
    existence: TrackExistence | None = None  # the tracks' existence after the step (lc.track_existence)
    tentative: int = 0  # rows paired with (or starting) a track not yet confirmed: not used for the vehicles


@dataclass(frozen=True)
class _TrackMoments:
    """The piece of the track-store interface :func:`coloc.methods.icp_da_lc.merge_candidates` reads."""

    ids: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    klass: np.ndarray | None = None  # the PF's tracks have no class ([features] pedestrians is refused with it)

    @property
    def size(self) -> int:
        return int(self.ids.size)

    def moments(self, params):
        return self.mean, self.cov

    def lookup(self, feature_ids: np.ndarray) -> np.ndarray:
        pos = np.searchsorted(self.ids, feature_ids)
        return np.minimum(pos, max(self.ids.size - 1, 0))


def _birth_particles(v_mean, v_cov, z_rows, r_rows, entities, step, params: IcpParams, pf: PfParams):
    """Particles and log-weights (prior / proposal) of newborn tracks, one per cluster seed row."""
    jf = pf.feature_particles
    out = np.empty((len(entities), jf, 4))
    logw = np.empty((len(entities), jf))
    s = params.feature_velocity_prior_sigma
    for c, ent in enumerate(entities):
        mean = v_mean[c] + z_rows[c]
        cov = v_cov[c] + r_rows[c]
        if s:  # velocity prior N(0, s^2 I) times the implied velocity: proposal closer to the posterior
            pv = np.linalg.inv(cov[2:, 2:])
            post = np.linalg.inv(pv + np.eye(2) / (s * s))
            mean = mean.copy()
            mean[2:] = post @ (pv @ mean[2:])
            cov = cov.copy()
            cov[2:, 2:] = post
            cov[:2, 2:] = cov[2:, :2] = 0.0
        x = sample_gaussian(mean, cov, jf, entity_rng(pf.seed, "track_birth", ent, step))
        log_q = gaussian_log_pdf(x, mean, cov)
        log_prior = gaussian_log_pdf(x[:, 2:], np.zeros(2), s * s * np.eye(2)) if s else 0.0
        out[c] = x
        logw[c] = normalize_log(log_prior - log_q)
    return out, logw


def icp_da_pf_step(
    state: PfState, next_id: int, frame: Frame, params: IcpParams, lc: LcParams, pf: PfParams,
    known_association: np.ndarray | None = None, workspace: KernelWorkspace | None = None,
    existence: TrackExistence | None = None, detection: DetectionModel | None = None,
    fusion: CoopFusion | None = None,
) -> tuple[PfState, int, PfStepInfo, StepEstimate]:
    """One ICP-DA-PF step (pure). ``known_association`` (O,) stable feature ids: the known-DA
    variant used by tests (association BP skipped, tracks keyed by the given ids). ``existence``: the
    tracks' existence after the previous step (``lc.track_existence``; the new one is
    ``info.existence``); ``detection``: the vehicles' sensors, for a P_D per (vehicle, track) (None:
    ``lc.detection_probability``). Both as ICP-DA-LC's steps 3 and 9 (:mod:`coloc.methods.icp_da_lc`).
    ``fusion``: ``[fusion]``, the vehicles localized by split CI with the receiver model
    (:mod:`coloc.methods.pf_fusion`); None: the paper's particle BPA-L."""
    jv, jf = pf.vehicle_particles, pf.feature_particles
    step = int(round(frame.t / frame.dt)) if frame.dt > 0 else 0
    n = frame.n_vehicles
    owner = np.asarray(frame.v2f_owner, dtype=np.int64)
    o = owner.size
    z, r = np.asarray(frame.v2f_z, float), np.asarray(frame.v2f_R, float)
    ents = np.array([_vehicle_entity(v) for v in frame.vehicle_ids], dtype=np.int64)

    # 1. Vehicles: model (1) or the fast-start prior, then (23).
    latest = pf.recursion == "latest_message"
    idx = match_ids(state.ids, frame.vehicle_ids)
    fresh = fresh_rows(idx, frame.entered, frame.prior_z)
    # Input of model (1): frame.accel, or with [inertial] the body-frame IMU rotated by the heading of the
    # previous belief's mean velocity (coloc.core.inertial.estimator_input), for both particle sets.
    prev_velocity = (state.particles[:, :, 2:].mean(axis=1) if frame.imu is not None and state.particles.shape[0]
                     else np.empty((0, 2)))
    if fusion is not None and state.split is not None and frame.imu is not None:
        prev_velocity = state.split.mean[:, 2:4]  # the previous belief's mean velocity, as ICP-DA-LC
    accel, heading = estimator_input(frame, idx, prev_velocity, state.heading, params.motion.heading_min_speed,
                                     params.motion.holds_heading)

    # Model (1)'s driving noise for the vehicle particles: [motion]'s, or the PF's own (PfParams).
    v_params = params
    if pf.sigma_along is not None or pf.sigma_cross is not None:
        m = params.motion
        v_params = replace(params, motion=replace(m, sigma_along=pf.sigma_along or m.sigma_along,
                                                  sigma_cross=pf.sigma_cross or m.sigma_cross))

    def vehicle_sets(carried: np.ndarray, predict_purpose: str, prior_purpose: str) -> np.ndarray:
        out = np.empty((n, jv, 4))
        old = np.flatnonzero(~fresh)
        if old.size:
            noise = np.stack([entity_rng(pf.seed, predict_purpose, ents[i], step).standard_normal((jv, 2)) for i in old])
            out[old] = predict_vehicle_particles(carried[idx[old]], accel[old], frame.dt, v_params, noise)
        for i in np.flatnonzero(fresh):
            out[i] = sample_gaussian(frame.prior_z[i], frame.prior_R[i], jv, entity_rng(pf.seed, prior_purpose, ents[i], step))
        return out

    # The entry protocol (coloc.core.vehicles.entry_fix_rows): a set drawn from a prior that is this step's fix
    # is not weighted by it again (equal weights).
    once = entry_fix_rows(frame, fresh)

    def gnss_weights(sets: np.ndarray) -> np.ndarray:
        ll = gnss_log_likelihood(sets, frame.gnss_z, frame.gnss_R)
        if once.any():
            ll[once] = 0.0
        return normalize_log(ll)

    split = None
    if fusion is not None:
        # [fusion] (coloc.methods.pf_fusion): the 6-D filters carried and updated by the fix; the particle
        # sets drawn from their kinematic marginals, equally weighted; the association gates on b^(0)'s
        # consistent covariance, as ICP-DA-LC.
        split = split_prior(state.split, frame, idx, frame.accel if accel is None else accel, params.motion,
                            fusion.model, fusion.params.common_mode_gnss, fusion.params.common_frame_messages,
                            belief_model=fusion.belief_model)
        v_mean, v_cov, own_mean, own_cov = split.marginal()
        particles, log_gnss = gaussian_sets(v_mean, v_cov, ents, step, pf.seed, "split_belief", jv)
        own, log_own = (gaussian_sets(own_mean, own_cov, ents, step, pf.seed, "split_own", jv) if latest
                        else (particles, log_gnss))
        assoc_particles, assoc_logw, assoc_cov = particles, log_gnss, v_cov
    else:
        particles = vehicle_sets(state.particles, "vehicle_predict", "vehicle_prior")
        log_gnss = gnss_weights(particles) if n else np.empty((0, jv))
        v_mean, v_cov = weighted_moments(particles, log_gnss) if n else (np.empty((0, 4)), np.empty((0, 4, 4)))
        if latest:  # the own-sensor sets carry no feature evidence; they run BPA-L, the belief sets get its messages
            own = vehicle_sets(state.own_particles, "own_predict", "own_prior")
            log_own = gnss_weights(own) if n else np.empty((0, jv))
            own_mean, own_cov = weighted_moments(own, log_own) if n else (np.empty((0, 4)), np.empty((0, 4, 4)))
            # eta and births as LC: the mean of b_i^(0), the spread of the own-sensor belief.
            assoc_particles = own + (v_mean - own_mean)[:, None, :]
            assoc_logw, assoc_cov = log_own, own_cov
        else:
            own, log_own = particles, log_gnss
            assoc_particles, assoc_logw, assoc_cov = particles, log_gnss, v_cov
    # Sensor-frame detections (frame.v2f_sensor): model (4)'s rows by the heading of the own-sensor sets' moments
    # at t (the belief's with the "belief" recursion; coloc.core.detections, as coloc.methods.icp_known_da).
    if frame.v2f_sensor is not None:
        h_mean, h_cov = (own_mean, own_cov) if (latest or fusion is not None) else (v_mean, v_cov)
        frame, sensor_heading = with_net_detections(frame, h_mean, h_cov, idx, state.sensor_heading,
                                                    params.motion.heading_min_speed)
        z, r = np.asarray(frame.v2f_z, float), np.asarray(frame.v2f_R, float)
    else:
        sensor_heading = None

    # 2. Tracks: model (2), (24).
    k_old = state.track_ids.size
    if k_old:
        noise = np.stack([entity_rng(pf.seed, "track_predict", t, step).standard_normal((jf, 2)) for t in state.track_ids])
        t_particles = predict_track_particles(state.track_particles, state.track_logw, frame.dt, params, noise)
        t_logw = state.track_logw
    else:
        t_particles, t_logw = np.empty((0, jf, 4)), np.empty((0, jf))
    t_ids = state.track_ids.copy()
    t_mean, t_cov = weighted_moments(t_particles, t_logw) if k_old else (np.empty((0, 4)), np.empty((0, 4, 4)))

    row_track = np.full(o, -1, dtype=np.int64)  # track id per row
    log_pd, log_1mpd = math.log(lc.detection_probability), math.log(1.0 - lc.detection_probability)
    # LC's steps 3 and 9 (per-pair P_D from the sensors, track existence); the known-DA variant is told
    # the association and keeps every track.
    with_existence = known_association is None and lc.track_existence
    per_pair_pd = known_association is None and (lc.track_existence or detection is not None)
    ex = None

    def pd_of(vi: np.ndarray, ti: np.ndarray) -> np.ndarray:
        """P_D of (vehicle, predicted track) pairs, at the moments (as LC)."""
        if detection is None:
            return np.full(vi.size, lc.detection_probability)
        return expected_detection_probability(v_mean[vi], t_mean[ti, :2], detection)
    if known_association is not None:
        assoc = np.asarray(known_association, dtype=np.int64)
        new_ids = np.setdiff1d(np.unique(assoc[assoc >= 0]), t_ids)
        birth_rows = np.array([np.flatnonzero(assoc == f)[0] for f in new_ids], dtype=np.int64)
        birth_ids = new_ids
        announced = birth_rows
        term_rows = np.flatnonzero(assoc >= 0)
        term_track_id = assoc[term_rows]
        term_log_c = np.zeros(term_rows.size)
        row_track[term_rows] = term_track_id
        combo_c0 = None
    else:
        # 2-3. eta (25) on the pre-gated candidates, BPA-DA (14)-(17).
        pv, pt, pr = candidate_rows(v_mean, assoc_cov, t_mean, t_cov, owner, lc)
        if pr.size:
            _, d2 = log_gauss(z[pr] - (t_mean[pt] - v_mean[pv]), t_cov[pt] + assoc_cov[pv] + r[pr])
            if lc.pairing == "gated":  # "paper": (25) for every candidate triple, ungated
                keep = d2 <= chi2_ppf(lc.gate_probability, 4)
                pv, pt, pr = pv[keep], pt[keep], pr[keep]
        w = np.zeros(pr.size)
        log_new = np.zeros(0)
        if pr.size:
            # Both clouds as kernel density estimates (PfParams.message_bandwidth).
            t_centres, t_bw = kernel_density(t_particles, t_logw, pf.message_bandwidth)
            v_centres, v_bw = kernel_density(assoc_particles, assoc_logw, pf.message_bandwidth)
            r_eta = r[pr] + t_bw[pt] + v_bw[pv]
            g, _ = gauss_transforms(pf, t_centres, normalize_log(t_logw)[pt], pt, np.zeros((pr.size, 4)), v_centres,
                                    pv, z[pr], r_eta)
            log_eta = logsumexp(assoc_logw[pv] + g, axis=1)
            log_new = new_feature_log_density(v_mean[pv], assoc_cov[pv], z[pr], r[pr], lc)
            if per_pair_pd:
                w = pd_of(pv, pt) * np.exp(np.minimum(log_eta - log_new, 600.0))
            else:
                w = np.exp(np.minimum(log_pd + log_eta - log_new, 600.0))
        # Step 9 of LC: eta with the tracks' predicted existence r and the pairs' P_D.
        missed = None
        if with_existence:
            r_pred = (existence or TrackExistence()).of(t_ids) * lc.survival_probability
            w = w * r_pred[pt]
            missed = 1.0 - r_pred[pt] * pd_of(pv, pt)
        elif per_pair_pd:
            missed = 1.0 - pd_of(pv, pt)
        ab = association_beliefs(pv, pt, pr, w, n, o, lc, missed)
        row_new = np.ones(o) if ab is None else ab.row_new
        if with_existence:  # r updated by the step: detections and expected detections that did not come
            ex = existence_after_association(r_pred, ab, v_mean, assoc_cov, t_mean, t_cov, t_ids, pd_of, lc,
                                             detection is None)
        # Terms of (18) for every combo option with a belief worth keeping.
        term_rows = np.empty(0, np.int64)
        term_track_id = np.empty(0, np.int64)
        term_log_c = np.empty(0)
        combo_c0 = None
        if ab is not None:
            c_n = ab.combo_vehicle.size
            m_c = ab.combo_rows
            seg = np.repeat(np.arange(c_n), m_c)
            opt = np.arange(seg.size) - np.repeat(np.cumsum(m_c) - m_c, m_c) + 1
            bel = ab.belief[ab.combo_start[seg] + opt]
            rows = ab.row_of_option(seg, opt)
            keep = bel >= max(pf.min_association_belief, 1e-300)
            # log_new per (vehicle, row): recompute for the kept options.
            lnew = new_feature_log_density(v_mean[ab.combo_vehicle[seg[keep]]], assoc_cov[ab.combo_vehicle[seg[keep]]],
                                           z[rows[keep]], r[rows[keep]], lc)
            term_rows = rows[keep]
            term_track_id = t_ids[ab.combo_track[seg[keep]]]
            b0 = ab.belief[ab.combo_start]
            if per_pair_pd:  # P_D of each option's (vehicle, track) combo
                pd_cmb = pd_of(ab.combo_vehicle, ab.combo_track)
                term_log_c = np.log(bel[keep]) + np.log(pd_cmb[seg[keep]]) - lnew
                c0 = np.log(np.maximum(b0, 1e-300)) + np.log(np.maximum(1.0 - pd_cmb, 1e-300))
            else:
                term_log_c = np.log(bel[keep]) + log_pd - lnew
                c0 = np.log(np.maximum(b0, 1e-300)) + log_1mpd
            combo_c0 = (ab.combo_vehicle, t_ids[ab.combo_track], c0)
            # Row -> track: the option of largest belief, if it beats "new".
            best = np.full(o, -1.0)
            best_track = np.full(o, -1, np.int64)
            order = np.lexsort((-bel, rows))
            firsts = np.ones(order.size, bool)
            firsts[1:] = rows[order][1:] != rows[order][:-1]
            best[rows[order][firsts]] = bel[order][firsts]
            best_track[rows[order][firsts]] = t_ids[ab.combo_track[seg[order][firsts]]]
            take = best > row_new
            row_track[take] = best_track[take]
        # Births (LC step 6).
        birth_rows_all = np.flatnonzero((row_track < 0) & (row_new >= lc.birth_probability))
        labels = birth_clusters(owner[birth_rows_all], v_mean[owner[birth_rows_all], :2] + z[birth_rows_all, :2],
                                assoc_cov[owner[birth_rows_all], :2, :2] + r[birth_rows_all, :2, :2], chi2_ppf(0.99, 2))
        n_born = int(labels.max()) + 1 if labels.size else 0
        birth_ids = next_id + np.arange(n_born, dtype=np.int64)
        birth_rows = np.array([birth_rows_all[np.flatnonzero(labels == c)[0]] for c in range(n_born)], dtype=np.int64)
        announced = birth_rows_all
        row_track[birth_rows_all] = next_id + labels
        next_id += n_born
        term_rows = np.concatenate([term_rows, birth_rows_all])
        term_track_id = np.concatenate([term_track_id, next_id - n_born + labels])
        term_log_c = np.concatenate([term_log_c, np.zeros(birth_rows_all.size)])
        if with_existence:
            # Births' existence (LC step 9), then confirmation: rows of tracks not yet confirmed do not
            # enter (18) and BPA-L, so they move no vehicle (and the tentative track is only predicted
            # until it is confirmed: it keeps the particles it was born with).
            share = new_feature_share(v_mean[owner[birth_rows_all]], assoc_cov[owner[birth_rows_all]],
                                      z[birth_rows_all], r[birth_rows_all], lc)
            ex = ex.with_tracks(birth_ids, birth_existence(share, labels, n_born))
            use = ex.confirmed(term_track_id, lc.confirm_existence)
            term_rows, term_track_id, term_log_c = term_rows[use], term_track_id[use], term_log_c[use]
            if combo_c0 is not None:
                use = ex.confirmed(combo_c0[1], lc.confirm_existence)
                combo_c0 = (combo_c0[0][use], combo_c0[1][use], combo_c0[2][use])

    # Newborn tracks (prior / proposal weights).
    if birth_rows.size:
        b_part, b_logw = _birth_particles(v_mean[owner[birth_rows]], assoc_cov[owner[birth_rows]], z[birth_rows],
                                          r[birth_rows], birth_ids, step, params, pf)
        t_particles = np.concatenate([t_particles, b_part])
        t_logw = np.concatenate([t_logw, b_logw])
        t_ids = np.concatenate([t_ids, birth_ids])
        srt = np.argsort(t_ids, kind="stable")
        t_particles, t_logw, t_ids = t_particles[srt], t_logw[srt], t_ids[srt]
    t_last = np.concatenate([state.track_last_seen, np.full(birth_rows.size, frame.t)])
    t_folded = np.concatenate([state.track_folded, np.zeros(birth_rows.size, bool)])
    t_newborn = np.concatenate([np.zeros(k_old, bool), np.ones(birth_rows.size, bool)])
    if birth_rows.size:
        t_last, t_folded, t_newborn = t_last[srt], t_folded[srt], t_newborn[srt]

    # Entries (vehicle, track) and their terms.
    term_vehicle = owner[term_rows]
    term_track = np.searchsorted(t_ids, term_track_id)
    if combo_c0 is not None:
        c_vehicle, c_trackid, c_logc0 = combo_c0
        keys = np.concatenate([term_vehicle * (t_ids.size + 1) + term_track])
        entry_keys, term_entry = np.unique(keys, return_inverse=True)
        entry_vehicle, entry_track = entry_keys // (t_ids.size + 1), entry_keys % (t_ids.size + 1)
        entry_log_c0 = np.full(entry_keys.size, -np.inf)
        ck = c_vehicle * (t_ids.size + 1) + np.searchsorted(t_ids, c_trackid)
        pos = np.searchsorted(entry_keys, ck)
        ok = (pos < entry_keys.size) & (entry_keys[np.minimum(pos, entry_keys.size - 1)] == ck)
        entry_log_c0[pos[ok]] = c_logc0[ok]
    else:
        keys = term_vehicle * (t_ids.size + 1) + term_track
        entry_keys, term_entry = np.unique(keys, return_inverse=True)
        entry_vehicle, entry_track = entry_keys // (t_ids.size + 1), entry_keys % (t_ids.size + 1)
        entry_log_c0 = np.full(entry_keys.size, -np.inf)
    term_entry = np.asarray(term_entry, dtype=np.int64).ravel()

    entry_vehicle, entry_track = entry_vehicle.astype(np.int64), entry_track.astype(np.int64)
    vids = np.asarray(frame.vehicle_ids, dtype=object)
    msg_track, msg_vehicle, msg_logv, msg_time = state.msg_track, state.msg_vehicle, state.msg_logv, state.msg_time
    t_log_b0 = t_logw
    replaced = np.zeros(msg_track.size, bool)
    if latest and msg_track.size and entry_vehicle.size:
        # b_k^(0) without the previous messages of this step's observers (they are about to be replaced).
        e_keys = {(int(t_ids[entry_track[e]]), vids[entry_vehicle[e]]) for e in range(entry_vehicle.size)}
        replaced = np.array([(int(a), b) in e_keys for a, b in zip(msg_track, msg_vehicle)], dtype=bool)
        if replaced.any():
            t_log_b0 = t_logw.copy()
            scatter_add(t_log_b0, np.searchsorted(t_ids, msg_track[replaced]), -msg_logv[replaced])
            t_log_b0 = normalize_log(t_log_b0)
    # b_k^(0) is the newborn prior alone: born this step, or (latest_message) every stored message is
    # this step's observers' and none was folded in.
    t_flat = t_newborn.copy()
    if latest:
        informed = np.isin(t_ids, msg_track[~replaced])
        t_flat |= ~t_folded & ~informed
    res = pf_bpa_localization(own, log_own, t_particles, t_log_b0, entry_vehicle,
                              entry_track, entry_log_c0, term_entry, term_rows, term_log_c, z, r,
                              frame.neighbors, params, pf, particles if latest else None, log_gnss if latest else None,
                              t_flat, workspace, frame.v2x)
    # Posterior weights of observed tracks; estimates.
    t_post = t_logw.copy()
    seen = res.track_entry >= 0
    if seen.any():
        t_post[seen] = res.entry_feature_logw[res.track_entry[seen]]
    # What the tracks carry to the next step (PfParams.recursion, IcpParams.feature_message).
    carry_own = latest and params.feature_message == "own" and res.first_feature_logw is not None
    t_carry, kept_messages = t_post, res.entry_message_logw
    if carry_own:
        t_carry = t_post.copy()
        t_carry[seen] = res.first_feature_logw[res.track_entry[seen]]
        kept_messages = res.first_message_logw
    mean, cov = weighted_moments(particles, res.vehicle_logw) if n else (np.empty((0, 4)), np.empty((0, 4, 4)))
    split_after = None
    if split is not None:  # the vehicles by split CI on the rows paired with a confirmed track
        loc_track = np.where(ex.confirmed(row_track, lc.confirm_existence), row_track, -1) if with_existence \
            else row_track
        mean, cov, split_after = pf_split_localization(split, frame, owner, loc_track, z, r, params,
                                                       fusion.params.feature_ci)
        if lc.own_consistency_gate > 0 and known_association is None:
            # ICP-DA-LC's step 10 ([lc] own_consistency_gate, coloc.methods.icp_da_lc): a vehicle whose fused
            # position leaves the gate of its own-sensor track takes that track, in its filters too.
            mean, cov, reset = own_consistency_reset(mean, cov, own_mean, own_cov, lc.own_consistency_gate)
            if reset.any():
                split_after = split_after.reset_to_own(reset)
    f_mean, f_cov = weighted_moments(t_particles, t_post) if t_ids.size else (np.empty((0, 4)), np.empty((0, 4, 4)))
    # Tracks observed this step: a detected option (belief >= 0.5) or a birth.
    observed_ids = np.unique(row_track[row_track >= 0])
    t_last = np.where(np.isin(t_ids, observed_ids), frame.t, t_last)

    # Latest messages: this step's replace the observers' previous ones; old ones stay folded.
    if latest:
        keep_m = ~replaced & (frame.t - msg_time <= params.message_memory_s)
        t_folded = t_folded | np.isin(t_ids, msg_track[~replaced & ~keep_m])
        msg_track = np.concatenate([msg_track[keep_m], t_ids[entry_track]])
        msg_vehicle = np.concatenate([msg_vehicle[keep_m], vids[entry_vehicle]])
        msg_logv = np.concatenate([msg_logv[keep_m].reshape(-1, jf), kept_messages])
        msg_time = np.concatenate([msg_time[keep_m], np.full(entry_vehicle.size, frame.t)])
    # Resampling (so that (23)-(24) start from equal weights); own-sensor sets by their GNSS weights.
    new_particles = np.empty_like(particles)
    new_own = np.empty_like(own) if latest else np.empty((n, 0, 4))
    for i in range(n):
        if split is not None:  # the sets are drawn afresh from the filters next step
            new_particles[i] = particles[i]
            if latest:
                new_own[i] = own[i]
            continue
        g = entity_rng(pf.seed, "vehicle_resample", ents[i], step)
        new_particles[i] = regularized_resample(particles[i], res.vehicle_logw[i],
                                                systematic_resample(res.vehicle_logw[i], g), g, pf.regularize)
        if latest:
            g = entity_rng(pf.seed, "own_resample", ents[i], step)
            new_own[i] = regularized_resample(own[i], log_own[i], systematic_resample(log_own[i], g), g, pf.regularize)
    new_t_particles, new_t_logw = t_particles.copy(), t_carry.copy()
    for kk in np.flatnonzero(seen):
        g = entity_rng(pf.seed, "track_resample", t_ids[kk], step)
        sel = systematic_resample(t_carry[kk], g)
        new_t_particles[kk] = regularized_resample(t_particles[kk], t_carry[kk], sel, g, pf.regularize)
        new_t_logw[kk] = -math.log(jf)
        if latest:
            mine = msg_track == t_ids[kk]
            msg_logv[mine] = msg_logv[mine][:, sel]

    # Merging and dropping (LC steps 8).
    merged = 0
    keep_t = np.ones(t_ids.size, bool)
    if known_association is None and t_ids.size > 1:
        absorbed, into = merge_candidates(_TrackMoments(t_ids, f_mean, f_cov), params, lc, owner[row_track >= 0],
                                          row_track[row_track >= 0])
        if absorbed.size:
            merged = int(absorbed.size)
            keep_t &= ~np.isin(t_ids, absorbed)
            pos = np.searchsorted(t_ids, into)
            t_last[pos] = np.maximum(t_last[pos], t_last[np.searchsorted(t_ids, absorbed)])
            for a_id, i_id in zip(absorbed, into):
                row_track[row_track == a_id] = i_id
    keep_t &= (frame.t - t_last) <= params.feature_drop_after_s
    keep_f = keep_t
    n_tentative = 0
    if with_existence:
        if merged:
            ex = ex.merged(absorbed, into)
        keep_t &= ex.of(t_ids) >= lc.drop_existence
        ex = ex.restricted(t_ids[keep_t])
        n_tentative = int(((row_track >= 0) & ~ex.confirmed(row_track, lc.confirm_existence)).sum())
        # Rows not used for the vehicles are reported as discarded; only confirmed tracks are features.
        row_track = np.where(ex.confirmed(row_track, lc.confirm_existence), row_track, -1)
        keep_f = keep_t & ex.confirmed(t_ids, lc.confirm_existence)
    estimate = StepEstimate(
        mean=mean, cov=cov, feature_mean=f_mean[keep_f], feature_cov=f_cov[keep_f],
        feature_track_ids=t_ids[keep_f].copy(), v2f_assignment=row_track.copy(),
    )
    if latest:
        keep_m = np.isin(msg_track, t_ids[keep_t])
        msg_track, msg_vehicle, msg_logv, msg_time = msg_track[keep_m], msg_vehicle[keep_m], msg_logv[keep_m], msg_time[keep_m]
    new_state = PfState(vids.copy(), new_particles, new_own, t_ids[keep_t], new_t_particles[keep_t], new_t_logw[keep_t],
                        t_last[keep_t], msg_track, msg_vehicle, msg_logv, msg_time, t_folded[keep_t], heading,
                        sensor_heading, split_after)
    info = PfStepInfo(row_track, int(birth_rows.size), int((row_track < 0).sum()), merged, res.iterations,
                      res.pair_evaluations,
                      pf_step_comm(entry_vehicle, entry_track, frame.neighbors, owner[announced],
                                   res.iterations if res.entry_iterations is None else res.entry_iterations, n,
                                   params, pf, res.rounds), ex, n_tentative)
    return new_state, next_id, info, estimate


@dataclass
class IcpDaPf:
    """Stateful ICP-DA-PF: ``step(frame)`` reads only the measurements."""

    params: IcpParams = field(default_factory=IcpParams)
    lc: LcParams = field(default_factory=LcParams)
    pf: PfParams = field(default_factory=PfParams)
    name: str = ICP_DA_PF.name  # or icp_known_da_pf: the registry's builder sets it
    state: PfState = field(default_factory=PfState)
    next_id: int = 0
    last: PfStepInfo | None = None
    workspace: KernelWorkspace = field(default_factory=KernelWorkspace, repr=False)  # scratch, never read across steps
    # The vehicles' sensors (field of view, range, detection profile), for a P_D per (vehicle,
    # track); None: lc.detection_probability everywhere in range.
    detection: DetectionModel | None = None
    fusion: CoopFusion | None = None  # [fusion] (coloc.methods.pf_fusion); None: the paper's particle BPA-L

    def step(self, frame: Frame) -> StepEstimate:
        existence = self.last.existence if self.last is not None else None
        n_rows = frame.v2f_z.shape[0]
        frame, kept = without_vehicle_rows(frame)  # vehicle-class rows are not landmarks (coloc.core.vehicle_rows)
        self.state, self.next_id, self.last, est = icp_da_pf_step(self.state, self.next_id, frame, self.params,
                                                                   self.lc, self.pf, workspace=self.workspace,
                                                                   existence=existence, detection=self.detection,
                                                                   fusion=self.fusion)
        if kept is None:
            return est
        return replace(est, v2f_assignment=expand_rows(est.v2f_assignment, kept, n_rows))

    def step_with_association(self, frame: Frame, v2f_feature: np.ndarray) -> StepEstimate:
        """Known-DA variant (``icp_known_da_pf``; tests: PF against the Kalman bound)."""
        self.state, self.next_id, self.last, est = icp_da_pf_step(self.state, self.next_id, frame, self.params,
                                                                   self.lc, self.pf, known_association=v2f_feature,
                                                                   workspace=self.workspace, fusion=self.fusion)
        return est
