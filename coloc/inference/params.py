"""Parameters of the ICP estimators: the Gaussian ICP (BPA-L with consensus) shared by all of them,
:class:`IcpParams`, and what ICP-DA-LC adds (also read by ICP-DA-PF): the association (13)-(17),
the MAP pairing (30), track births, merging and existence, :class:`LcParams`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from coloc.core.models import MotionParams

#: What a vehicle's stored message to a feature track is built on (see :class:`IcpParams`).
FEATURE_MESSAGES = ("bpa", "own")
#: Default sv_par (m/s per step) of model (2) for pedestrian tracks (measured; see :class:`IcpParams`).
PEDESTRIAN_SIGMA_PAR = 0.05
#: Class codes of feature tracks (the frame's ``v2f_class``; couplers.sensing.perception CLASS_*).
CLASS_STATIC, CLASS_PEDESTRIAN = 0, 1
#: What the BPA-L stopping rule tests (see :class:`IcpParams`).
STOP_RULES = ("vehicles", "vehicles_and_features")
BUDGET_SPLITS = ("greedy", "even")


@dataclass(frozen=True)
class IcpParams:
    """Parameters of the Gaussian ICP (BPA-L with consensus).

    ``feature_sigma_par`` / ``feature_sigma_perp``: velocity random walk of
    model (2), m/s per step (Q_F = G diag(sv_par^2, sv_perp^2) G^T). Static
    features get a small default, sv_par = 0.01 m/s (the crossroad rule
    sv_par = vf/100 at vf = 1 m/s) so that tracks stay slightly open and their
    information does not grow without bound; sv_perp defaults to sv_par/2.
    A feature whose estimated speed is below ``feature_heading_min_speed``
    has no trusted heading and gets the isotropic Q_F (sv_par on both axes).

    ``pedestrian_sigma_par``: sv_par of model (2) for tracks of class pedestrian (frames with
    ``v2f_class``, ``[features] pedestrians``); sv_perp = sv_par / 2 as in Sec. V-B. Default 0.05
    m/s per step, not the Sec. V-B rule sv_par = vf / 100 (0.013 at a walking speed vf = 1.3 m/s):
    SUMO's walkers stop and start within a step at red crossings and turn 90 degrees at corners.
    Measured on arterial_ped TLR, first 600 s, seed 1 (docs/validation/realistic_sensing.md "SUMO
    pedestrians"), sv_par 0.013 / 0.03 / 0.05 / 0.1: ICP known DA pedestrian-track 4-D NEES mean
    158 / 107 / 96 / 89 (landmark tracks' 2-D position NEES is ~70 too: the rest is the vehicles'
    overconfidence, not model (2)), velocity RMSE 0.19 / 0.15 / 0.14 / 0.13 m/s; ICP-DA-LC
    pedestrian rows correctly associated 88.2 / 87.4 / 90.4 / 83.3 % (71.2 % at 0.3, where the
    vehicle RMSE also grows from 0.58 to 0.70 m).

    A feature track no vehicle observed for more than
    ``feature_drop_after_s`` seconds is dropped (the paper resets an unobserved
    feature to a uniform belief; keeping it a while lets vehicles arriving
    later reuse what earlier vehicles learned).

    ``feature_velocity_prior_sigma``: a newborn track has a uniform position
    and, if set, a N(0, s^2 I) velocity (features known to be landmarks or
    slow objects); None or 0 is the paper's uniform belief.
    ``message_memory_s``: how long the latest message of a vehicle that
    stopped observing a track is kept apart (to be replaced if the vehicle
    observes the track again) before it is folded into the track
    (:class:`FeatureStore`).

    ``feature_message``: what each vehicle's message to a track is built on
    when it is *stored* in the track for later steps (within a step BPA-L
    always iterates the full messages (19)):

    * ``"own"`` (default): the vehicle's own-sensor belief (GNSS + inertial)
      integrated against this row's V2F likelihood, i.e. (19) with the
      other features' messages left out of the cavity. Own-sensor errors of
      different vehicles are independent, and each vehicle's message is kept
      once per track (latest message), so a track accumulates every vehicle's
      evidence exactly once and keeps converging as vehicles pass.
    * ``"bpa"``: the final message (19) of the step's BPA-L. Its cavity holds
      the other features' messages, which carry the other vehicles' evidence;
      storing and folding it counts that evidence again in every track the
      vehicle observes, step after step. Tracks become overconfident and stop
      absorbing new vehicles. Measured on the arterial TLR, first 600 s, LC:
      with Q_F sv_par = 0.001 m/s a block of 22 features locked onto a common
      ~2 m offset (vehicle RMSE 1.13 m, against 0.63 m with "own"); at
      0.0001 "own" gives 0.60 m, while "bpa" needs Q_F = 0.01 to forget fast
      enough (0.69 m). Kept to reproduce earlier results.

    ``budget_split``: how the consensus exchanges of a step share a V2X round budget
    (``frame.v2x.rounds_per_step``; no effect without one). "greedy" (default): each exchange takes
    min(``consensus_iterations``, rounds left), so a budget below ``consensus_iterations`` allows a
    single BPA-L iteration. "even": each takes min(``consensus_iterations``, max(1, rounds left //
    exchanges still to come up to ``bpa_max_iterations``)), so every iteration gets rounds.
    ``stop_on``: the BPA-L stopping rule (Sec. V-A: stop when no MMSE
    estimate moved by more than ``stop_pos_m`` / ``stop_vel_mps`` since the
    previous iteration). "vehicles" (default) tests the vehicle estimates
    only; "vehicles_and_features", the paper's reading, also every vehicle's
    estimate of each feature it observes (b_k of (20) at that vehicle; a
    track still at its uniform prior has no estimate before the first
    iteration, so it never lets the first iteration stop).
    """

    motion: MotionParams = field(default_factory=MotionParams)
    consensus_iterations: int = 20
    bpa_max_iterations: int = 10
    stop_pos_m: float = 0.1
    stop_vel_mps: float = 0.1
    feature_sigma_par: float = 0.01
    feature_sigma_perp: float | None = None
    pedestrian_sigma_par: float = PEDESTRIAN_SIGMA_PAR
    feature_heading_min_speed: float = 0.5
    feature_drop_after_s: float = 10.0
    feature_velocity_prior_sigma: float | None = None
    message_memory_s: float = 10.0
    feature_message: str = "own"
    stop_on: str = "vehicles"
    budget_split: str = "greedy"

    def __post_init__(self):
        if self.consensus_iterations < 0:
            raise ValueError("consensus_iterations must be >= 0")
        if self.bpa_max_iterations < 1:
            raise ValueError("bpa_max_iterations must be >= 1")
        if self.stop_pos_m < 0 or self.stop_vel_mps < 0:
            raise ValueError("stopping thresholds must be >= 0")
        if self.feature_sigma_par < 0 or (self.feature_sigma_perp is not None and self.feature_sigma_perp < 0):
            raise ValueError("feature driving noise must be >= 0")
        if self.pedestrian_sigma_par < 0:
            raise ValueError("pedestrian_sigma_par must be >= 0")
        if self.feature_drop_after_s < 0:
            raise ValueError("feature_drop_after_s must be >= 0")
        if self.feature_velocity_prior_sigma is not None and self.feature_velocity_prior_sigma < 0:
            raise ValueError("feature_velocity_prior_sigma must be >= 0 (0 or None: uniform)")
        if self.message_memory_s < 0:
            raise ValueError("message_memory_s must be >= 0")
        if self.feature_message not in FEATURE_MESSAGES:
            raise ValueError(f"feature_message must be one of {FEATURE_MESSAGES}")
        if self.stop_on not in STOP_RULES:
            raise ValueError(f"stop_on must be one of {STOP_RULES}")
        if self.budget_split not in BUDGET_SPLITS:
            raise ValueError(f"budget_split must be one of {BUDGET_SPLITS}")

    def exchanges_left(self, iteration: int, per_iteration: int = 1, done: int = 0) -> int:
        """How many consensus exchanges of the step share the rounds left, counting the next one: 1
        under "greedy" (it takes what it wants), every exchange still to come in the BPA-L iterations
        ``iteration`` .. ``bpa_max_iterations`` under "even" (``per_iteration`` exchanges an iteration,
        ``done`` of them made in this one); coloc.inference.row_consensus.ChannelRowConsensus.grant."""
        if self.budget_split == "greedy":
            return 1
        return max(1, (self.bpa_max_iterations - int(iteration) + 1) * int(per_iteration) - int(done))

    @property
    def feature_sigma_perp_value(self) -> float:
        return self.feature_sigma_par / 2 if self.feature_sigma_perp is None else self.feature_sigma_perp


#: MAP pairing rules of (30) (:class:`LcParams`): ours and the paper's literal one.
PAIRING_RULES = ("gated", "paper")


@dataclass(frozen=True)
class LcParams:
    """Parameters of ICP-DA-LC that the paper leaves open (plus eta_TH of (30)); the steps named
    below are those of :mod:`coloc.methods.icp_da_lc`.

    * ``eta_threshold``: eta_TH of (30); a track k is detected by vehicle i iff
      b_ik(alpha = 0) < eta_TH (1 = pair every gated measurement, 0.5 = drop
      ambiguous ones; the paper's two settings).
    * ``detection_probability``: P_D of a track inside the sensing range, which
      sets the missed-detection weight eta(alpha = 0) = 1 - P_D of (13).
    * ``gate_probability``: chi-square gate on the 4-D V2F innovation; outside
      it eta(alpha = l) = 0.
    * ``new_feature_velocity_sigma``: velocity spread (m/s) of an untracked
      feature, in the density of a measurement from a new feature.
    * ``birth_probability``: a measurement that no track took starts a track
      when its probability of coming from no track is at least this.
    * ``merge_gate_m``: two tracks closer than this (and within the 99 %
      position gate of each other) are merged.
    * ``sensing_range_m``: the vehicle's own V2F range Rs (candidate tracks are
      those predicted within Rs plus a 3-sigma margin).
    * ``new_feature_rate``: mu_new, expected number of untracked features in
      a vehicle's view (weight of the "new feature" hypothesis).
    * ``new_feature_density``: mu_new f_new(z) as one constant (per m^2 per
      (m/s)^2) in place of the derived density (:mod:`coloc.methods.icp_da_lc`, step 3);
      0 (default) = derived from ``new_feature_rate``, ``sensing_range_m``
      and ``new_feature_velocity_sigma``; 1 = no normalisation, eta as (13)
      reads.
    * ``pairing``: the MAP rule (30) (:mod:`coloc.methods.icp_da_lc`, step 5): "gated"
      (ours) or "paper" (literal: ungated, threshold at every eta_TH, a row
      may be taken by several tracks).
    * ``clutter_intensity``: lambda_c, false detections per m^2 per scan that
      the estimator expects (a sensor's false alarms, looking like static
      objects); 0 (default) = no clutter, the paper's model. It joins the
      new-feature density in the normaliser of eta (step 3); telling a
      clutter-born track from a feature is left to the confirmation (step 9).
    * ``sensor_fov``: P_D per (vehicle, track) from the vehicles' sensors
      (field of view around the estimated heading, range, detection profile:
      :mod:`coloc.core.detection`), given to :class:`IcpDaLc` as
      ``detection`` by whoever builds it (``coloc run``: from
      ``[perception]``); a track outside every field of view is not expected
      to be detected. Off: ``detection_probability`` within the range.
      ``visibility``: the share of in-view tracks the estimator expects not
      to be occluded (it cannot predict every occluder); it scales the
      sensors' P_D (1, default: no occlusion expected).
    * ``track_existence``: carry an existence probability r with every track
      (step 9); off (default): every track exists (r = 1, the paper's tracks).
      ``survival_probability``: r is multiplied by it every step;
      ``confirm_existence``: a track localizes vehicles only while r is at
      least this; ``drop_existence``: a track is dropped when r falls below.
    * ``own_consistency_gate``: step 10, a chi-square probability (2 dof):
      a vehicle whose cooperative position estimate lies outside this gate
      of its own-sensor (GNSS + inertial) track is reset to that track; 0
      (default) = never (the paper).
    * ``relocalize_radius_m``: step 5b (:mod:`coloc.methods.lc_reloc`): a vehicle with at least
      ``relocalize_min_support`` rows and none paired with a confirmed track is relocalized for the
      association by the unique translation, within this radius, that puts the most of its rows
      within ``relocalize_tolerance_m`` of distinct confirmed tracks (at least ``relocalize_min_support``);
      0 (default) = never.
    * ``relocalize_min_gain``: step 5b for vehicles that are not lost: with g > 0 a vehicle with some rows on
      confirmed tracks takes the vote's translation too when it puts at least g more of its rows on distinct
      confirmed tracks than its own mean does (the same tolerance); 0 (default) = lost vehicles only.
    * ``reset_map_margin``: step 10 with m > 0: a vehicle whose rows land on at least m more distinct confirmed
      tracks (within ``relocalize_tolerance_m``) from its cooperative position than from its own track's is not
      reset; 0 (default) = the gate alone decides.
    * ``fix_map_margin``: step 5a with m > 0: a vehicle whose motion prediction (before this step's fix) puts at
      least m more rows on distinct confirmed tracks than b^(0)'s mean is associated at the prediction; 0
      (default) = at b^(0)'s mean.
    * ``anchor_margin``: step 5a with m > 0: each vehicle keeps a map-anchored position that no fix moves
      (carried by its velocity, refreshed to the posterior whenever that has rows on >= 2 confirmed tracks); a
      vehicle whose anchor puts at least max(2, the association mean's support + m) rows on the map is associated
      at its anchor; 0 (default) = no anchor.
    * ``bp_iterations`` / ``bp_tol``: BPA-DA iterations (14)-(17).
    """

    eta_threshold: float = 0.5
    detection_probability: float = 0.95
    gate_probability: float = 0.9999
    new_feature_velocity_sigma: float = 1.0
    birth_probability: float = 0.5
    merge_gate_m: float = 2.0
    sensing_range_m: float = 50.0
    new_feature_rate: float = 1.0
    new_feature_density: float = 0.0
    pairing: str = "gated"
    clutter_intensity: float = 0.0
    sensor_fov: bool = False
    visibility: float = 1.0
    track_existence: bool = False
    survival_probability: float = 0.999
    confirm_existence: float = 0.9
    drop_existence: float = 0.01
    own_consistency_gate: float = 0.0
    relocalize_radius_m: float = 0.0
    relocalize_tolerance_m: float = 1.5
    relocalize_min_support: int = 3
    relocalize_min_gain: int = 0
    reset_map_margin: int = 0
    fix_map_margin: int = 0
    anchor_margin: int = 0
    bp_iterations: int = 50
    bp_tol: float = 1e-6

    def __post_init__(self):
        if not 0.0 <= self.eta_threshold <= 1.0:
            raise ValueError("eta_threshold must be in [0, 1]")
        if not 0.0 < self.detection_probability < 1.0:
            raise ValueError("detection_probability must be in (0, 1)")
        if not 0.0 < self.gate_probability < 1.0:
            raise ValueError("gate_probability must be in (0, 1)")
        if not 0.0 < self.birth_probability <= 1.0:
            raise ValueError("birth_probability must be in (0, 1]")
        if self.new_feature_velocity_sigma <= 0 or self.merge_gate_m < 0 or self.sensing_range_m <= 0:
            raise ValueError("new_feature_velocity_sigma and sensing_range_m must be positive, merge_gate_m >= 0")
        if not self.new_feature_rate > 0:
            raise ValueError("new_feature_rate must be positive")
        if not (self.new_feature_density >= 0 and math.isfinite(self.new_feature_density)):
            raise ValueError("new_feature_density must be >= 0 (0: derived from new_feature_rate)")
        if self.pairing not in PAIRING_RULES:
            raise ValueError(f"pairing must be one of {PAIRING_RULES}")
        if not (self.clutter_intensity >= 0 and math.isfinite(self.clutter_intensity)):
            raise ValueError("clutter_intensity must be >= 0 (false detections per m^2 per scan)")
        if not 0.0 < self.survival_probability <= 1.0:
            raise ValueError("survival_probability must be in (0, 1]")
        if not 0.0 < self.visibility <= 1.0:
            raise ValueError("visibility must be in (0, 1] (1: no occlusion expected)")
        if not 0.0 <= self.own_consistency_gate < 1.0:
            raise ValueError("own_consistency_gate must be in [0, 1) (0: off)")
        if self.relocalize_radius_m < 0 or self.relocalize_tolerance_m <= 0 or self.relocalize_min_support < 1:
            raise ValueError("relocalize_radius_m must be >= 0, relocalize_tolerance_m > 0, relocalize_min_support >= 1")
        if self.relocalize_min_gain < 0:
            raise ValueError("relocalize_min_gain must be >= 0 (0: lost vehicles only)")
        if self.anchor_margin < 0:
            raise ValueError("anchor_margin must be >= 0 (0: no map-anchored position)")
        if self.fix_map_margin < 0:
            raise ValueError("fix_map_margin must be >= 0 (0: the association at b^(0)'s mean)")
        if self.reset_map_margin < 0:
            raise ValueError("reset_map_margin must be >= 0 (0: the gate alone decides)")
        if not 0.0 < self.drop_existence < self.confirm_existence < 1.0:
            raise ValueError("existence thresholds must satisfy 0 < drop_existence < confirm_existence < 1")
        if self.bp_iterations < 1 or self.bp_tol <= 0:
            raise ValueError("bp_iterations must be >= 1 and bp_tol > 0")
