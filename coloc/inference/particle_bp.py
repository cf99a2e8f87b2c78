"""Particle BPA-L of ICP-DA-PF (Brambilla et al. Sec. IV-C: (19)-(22) on particles, (25)-(29)) and
the PF's settings.

Mapping of the equations to code (the method around it -- prediction, eta of (25), BPA-DA,
births, resampling -- is :mod:`coloc.methods.icp_da_pf`):

* the pair sums over vehicle and feature particles with the V2F kernel N(z; x_F - x_V, R) (plus
  ``PfParams.message_bandwidth``'s kernel density bandwidth): :func:`gauss_transforms` (one batch
  by :mod:`coloc.kernels.pf` or :mod:`coloc.kernels.pf_fast`), kept through a step's iterations in
  :func:`pf_bpa_localization`;
* (19) message i -> k on the feature particles, (21) message k -> i on the vehicle particles with
  the feature cavity b_k / m_{i->k}, each a mixture over the options of the likelihood (18):
  :func:`pf_bpa_localization` (sums per entry by :func:`_segment_logsumexp`);
* (26) feature belief through (28) average consensus of the log-weights times |V_k| and (29) max
  consensus: :func:`pf_bpa_localization`;
* (27) vehicle belief b_i = b_i^(0) prod_k m_{k->i}: :func:`pf_bpa_localization`;
* m_{k->i} in closed form for a track whose cavity is the newborn prior alone:
  :func:`_flat_prior_messages`;
* the stopping rule of Sec. V-A, over the net or per connected component: :func:`pf_bpa_localization`,
  :func:`bpa_components`;
* what the vehicles send in a step, rounds of (28)-(29) and birth announcements: :func:`pf_step_comm`;
* the settings: :class:`PfParams`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from coloc.core.v2x import V2xFrame
from coloc.inference.comm import PF_BIRTH_WORDS, CommCount, announcements, broadcast_rounds, pf_words
from coloc.inference.consensus import average_consensus_with_weights, max_consensus, metropolis_weights
from coloc.inference.gaussian import log_gauss
from coloc.inference.params import IcpParams
from coloc.inference.particles import kernel_density, normalize_log, weighted_moments
from coloc.inference.row_consensus import ChannelRowConsensus, consensus_graph, row_components
from coloc.kernels.icp import scatter_add, scatter_max
from coloc.kernels.pf import KERNELS, KernelWorkspace, RepeatedTransforms, kept_problem_count, transform_batch
from coloc.kernels.pf_fast import FAST, FastRepeatedTransforms, fast_kept_problem_count, fast_transform_batch

__all__ = ["PfParams", "PfBpaResult", "pf_bpa_localization", "bpa_components", "gauss_transforms", "pf_step_comm"]

RECURSIONS = ("latest_message", "paper")
PF_KERNELS = KERNELS + (FAST,)  # the exact tree (reference), brute force, the 1e-3 approximation
BANDWIDTHS = ("prior", "shrunk", "none")
BPA_STOPS = ("net", "component")  # PfParams.bpa_stop


@dataclass(frozen=True)
class PfParams:
    """ICP-DA-PF settings (the paper: Jv = Jf = 5000 on the single road).

    ``recursion``: "paper" is the time recursion as written: vehicle particle
    sets carry the cooperative posterior (b_i^(0) of (23) from the propagated
    belief (27)), and a track's b_k^(0) of (24) is its propagated posterior,
    so each step multiplies in again, through the vehicle and through the
    track, the evidence of earlier steps. "latest_message" (default) is the
    particle counterpart of what :mod:`coloc.inference` does for the Gaussian ICP:
    a vehicle's particle set is its own-sensor belief (GNSS + inertial,
    resampled by its GNSS weights; the cooperative belief (27) is its output),
    and a track keeps, per observing vehicle, the log-value of that vehicle's
    latest message at each of its particles (carried through resampling by
    index and through prediction as the ancestor's value): when the vehicle
    observes the track again its old message is divided out of b_k^(0) and the
    new one replaces it; messages older than ``message_memory_s`` are left
    folded into the track. With ``IcpParams.feature_message = "own"`` (default)
    what a track carries to the next step is b_k^(0) times this step's
    own-sensor messages, i.e. the feature belief (26) of the *first* BPA-L
    iteration (every m_{k->i} still 1, so each vehicle's cavity is its
    own-sensor set), and the kept messages are that iteration's; the step's
    estimate is the final (26). As for the Gaussian ICP (:class:`coloc.inference.params.IcpParams`),
    the final messages carry the other features' messages, i.e. other
    vehicles' evidence, and carrying them counts that evidence again in every
    track. Measured on the crossroad (Nf = 20, J = 1000, seeds 1-6): PF
    1.99 -> 1.68 m, feature RMSE 1.84 -> 1.47 m. "bpa" carries the final (26)
    and messages; the "paper" recursion always does.
    ``regularize``: after resampling, move the particles by the Liu-West
    kernel shrinkage x' = a x + (1 - a) m + h L e, a = sqrt(1 - h^2),
    h = (4 / ((d + 2) J))^(1 / (d + 4)) (Silverman's bandwidth, d = 4), L L^T
    the weighted covariance: mean and covariance are kept, duplicates are
    spread. Static features (model (2) noise 0.01 m/s) otherwise never
    rejuvenate: after a few resamplings a track is a handful of distinct
    particles and its messages become spiky. The paper does not say how it
    fights this degeneracy; False = plain resampling.
    ``message_bandwidth``: "prior" (default) smooths every particle double
    sum as kernel density estimates of the two sets, kernel R + h^2 Cov with
    Silverman's h on the effective sample size of b^(0) (vehicle and track
    sets of the step; see :mod:`coloc.methods.icp_da_pf`); "shrunk" is the same kernel
    with the source particles pulled towards their mean by Liu and West's
    a = sqrt(1 - h^2) (:func:`kernel_density`), so the kernel density keeps the
    set's covariance instead of inflating it by 1 + h^2. Measured against
    "prior": one-step tree test 0.26 / 0.08 m from the exact joint at
    J = 500 / 4000 (prior 0.26 / 0.10 m); crossroad (J = 1000, seeds 1-10)
    vehicles 1.95 / 1.67 m at Nf = 3 / 20 (prior 1.90 / 1.67 m), features
    1.58 / 1.35 m (1.68 / 1.41 m); single road df = 3 m (J = 5000, seeds
    1-20) 1.69 / 1.73 m (1.69 / 1.68 m): no gain for the vehicles, so not the
    default. "none" is the bare V2F kernel of (25)-(27), exact for the
    particle sets as they are.
    ``kernel``: "tree" (k-d tree pruned, exact to ``kernel_rel_tol`` per
    entry; the reference), "brute" (every particle pair) or "fast" (every pair, float32
    distances and exponential, kept matrices in 16 bits a pair: every entry within 1e-3
    relative, :mod:`coloc.kernels.pf_fast`; ``kernel_rel_tol`` does not apply; arterial,
    first 60 s of TLR at J = 1000: 2.5x faster per step). ``kernel_cache_mb``: with "tree"
    or "fast", the
    two message sums of BPA-L (19)/(21) keep their kernel matrices (float32, 4 bytes
    a pair) through the iterations of a step, as far as they fit in this many MB:
    the particles and kernels do not change between iterations, only the cavity
    weights, so each later iteration is a matrix-vector product, exact to
    ``kernel_rel_tol`` as the tree (:func:`coloc.kernels.pf.fixed_transforms`; "fast":
    2 bytes a pair, within its 1e-3).
    The single road at J = 5000 needs 1.6 GB (8 terms, two directions; "fast" 0.8 GB); 0 keeps
    none. ``min_association_belief``: options of (18) with a smaller BPA-DA belief
    are left out of the mixture.
    ``sigma_along``, ``sigma_cross``: the driving noise of model (1) for the vehicle particles, in
    place of ``[motion]``'s (None: ``[motion]``'s). A Kalman filter absorbs an input error larger
    than its driving noise analytically (it lags); a bootstrap particle filter whose proposal is
    model (1) cannot, because no particle reaches the GNSS likelihood. With ``[inertial]`` the IMU's
    turn-on accelerometer bias (0.196 m/s^2, RotorS) is twice the presets' sigma_cross = 0.1 m/s^2,
    and the PF diverges (realistic TLR preset, first 60 s, J = 200: PF 12.96 m against GNSS 4.93 m;
    with sigma_cross = 0.3 m/s^2: 3.51 m against 5.00 m, docs/validation/realistic_sensing.md).
    ``bpa_stop``: where BPA-L's stopping rule (Sec. V-A) applies. "net" (default, the paper): every
    vehicle and track iterates until the whole net has converged. "component": per connected
    component of BPA-L's graph (entries (vehicle, track) linked through their vehicle and through
    V2V links among a track's observers, :func:`bpa_components`): a component whose vehicles and
    tracks have settled stops iterating (its messages and beliefs stay those of its last iteration),
    the others continue. Components share no message, so each ends exactly as if it ran alone
    with the net rule (tested bit for bit); what changes is only that a settled component no longer
    waits for the slowest one (whose further iterations would move it by less than the stopping
    tolerance). The iteration count of the step is then its slowest component's.
    """

    vehicle_particles: int = 1000
    feature_particles: int = 1000
    seed: int = 0
    kernel: str = "tree"
    kernel_rel_tol: float = 1e-6
    kernel_cache_mb: float = 2048.0
    min_association_belief: float = 1e-6
    recursion: str = "latest_message"
    regularize: bool = True
    message_bandwidth: str = "prior"
    sigma_along: float | None = None
    sigma_cross: float | None = None
    bpa_stop: str = "net"

    def __post_init__(self):
        if self.vehicle_particles < 1 or self.feature_particles < 1:
            raise ValueError("vehicle_particles and feature_particles must be >= 1")
        if any(s is not None and not s > 0 for s in (self.sigma_along, self.sigma_cross)):
            raise ValueError("sigma_along and sigma_cross must be positive (leave them out for [motion]'s)")
        if self.kernel not in PF_KERNELS:
            raise ValueError(f"kernel must be one of {', '.join(PF_KERNELS)}")
        if not self.kernel_rel_tol > 0:
            raise ValueError("kernel_rel_tol must be positive")
        if not self.kernel_cache_mb >= 0:
            raise ValueError("kernel_cache_mb must be >= 0")
        if self.message_bandwidth not in BANDWIDTHS:
            raise ValueError(f"message_bandwidth must be one of {', '.join(BANDWIDTHS)}")
        if self.recursion not in RECURSIONS:
            raise ValueError(f"recursion must be one of {', '.join(RECURSIONS)}")
        if self.bpa_stop not in BPA_STOPS:
            raise ValueError(f"bpa_stop must be one of {', '.join(BPA_STOPS)}")
        if not 0.0 <= self.min_association_belief < 1.0:
            raise ValueError("min_association_belief must be in [0, 1)")


# ----------------------------------------------------------------------------- BPA-L on particles


@dataclass(frozen=True)
class PfBpaResult:
    vehicle_logw: np.ndarray  # (N, Jv) final beliefs (27), normalised
    entry_feature_logw: np.ndarray  # (E, Jf) each participant's copy of (26) after max consensus
    entry_message_logw: np.ndarray  # (E, Jf) the final messages m_{i->k} (19), normalised
    track_entry: np.ndarray  # (K,) entry whose copy is the track's posterior (-1: track not observed)
    iterations: int
    converged: bool
    pair_evaluations: int
    # (E, Jf) the first iteration's (26) and messages (19): own-sensor cavities (IcpParams.feature_message)
    first_feature_logw: np.ndarray | None = None
    first_message_logw: np.ndarray | None = None
    # consensus rounds of the step: average (28) and max (29); None = iterations x the params' rounds
    rounds: tuple[int, int] | None = None
    # (E,) iterations each entry's component ran (PfParams.bpa_stop = "component"); None = all ``iterations``
    entry_iterations: np.ndarray | None = None


def gauss_transforms(pf: PfParams, src_sets, src_logw, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r):
    """One batch of the pair sums (25)-(27) by ``pf.kernel``: :func:`coloc.kernels.pf.transform_batch`
    (exact tree, brute force) or :func:`coloc.kernels.pf_fast.fast_transform_batch` (within 1e-3)."""
    if pf.kernel == FAST:
        return fast_transform_batch(src_sets, src_logw, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r)
    return transform_batch(src_sets, src_logw, src_index, src_shift, tgt_sets, tgt_index, tgt_shift, r, pf.kernel,
                           pf.kernel_rel_tol)


def _segment_logsumexp(values: np.ndarray, seg: np.ndarray, n_seg: int, init: np.ndarray) -> np.ndarray:
    """log(exp(init[e]) + sum_{t: seg[t] = e} exp(values[t])) per segment, (n_seg, J)."""
    j = values.shape[1] if values.ndim == 2 else 1
    top = np.broadcast_to(init[:, None], (n_seg, j)).copy()
    if values.shape[0]:
        scatter_max(top, seg, values)
    top = np.where(np.isfinite(top), top, 0.0)
    acc = np.exp(init[:, None] - top)
    if values.shape[0]:
        scatter_add(acc, seg, np.exp(values - top[seg]))
    with np.errstate(divide="ignore"):
        return top + np.log(acc)


def _flat_prior_messages(vehicle_particles, flat_e, entry_vehicle, term_entry, t_z, t_r, term_log_c,
                         velocity_prior_sigma) -> np.ndarray:
    """m_{k->i} at the vehicle particles for entries whose cavity is the newborn prior alone
    (see ``track_flat`` of :func:`pf_bpa_localization`), normalised log-values (F, Jv)."""
    ents = np.flatnonzero(flat_e)
    jv = vehicle_particles.shape[1]
    if not velocity_prior_sigma:
        return np.zeros((ents.size, jv))
    sel = np.flatnonzero(flat_e[term_entry])
    v = vehicle_particles[entry_vehicle[term_entry[sel]]][..., 2:]  # (T, Jv, 2)
    cov = velocity_prior_sigma**2 * np.eye(2) + t_r[sel, 2:, 2:]
    lp, _ = log_gauss(t_z[sel, None, 2:] + v, np.broadcast_to(cov[:, None], v.shape + (2,)))
    seg = np.searchsorted(ents, term_entry[sel])
    return normalize_log(_segment_logsumexp(term_log_c[sel, None] + lp, seg, ents.size, np.full(ents.size, -np.inf)))


def pf_bpa_localization(
    vehicle_particles: np.ndarray,
    vehicle_log_b0: np.ndarray,
    track_particles: np.ndarray,
    track_log_b0: np.ndarray,
    entry_vehicle: np.ndarray,
    entry_track: np.ndarray,
    entry_log_c0: np.ndarray,
    term_entry: np.ndarray,
    term_row: np.ndarray,
    term_log_c: np.ndarray,
    z: np.ndarray,
    r: np.ndarray,
    adjacency: sp.spmatrix,
    params: IcpParams,
    pf: PfParams,
    output_particles: np.ndarray | None = None,
    output_log_b0: np.ndarray | None = None,
    track_flat: np.ndarray | None = None,
    workspace: KernelWorkspace | None = None,
    v2x: V2xFrame | None = None,
) -> PfBpaResult:
    """Particle BPA-L (19)-(22) with the feature product (26) by consensus (28)-(29).

    Entries e = (vehicle, track) pairs of the likelihood (18); each has the
    constant term ``entry_log_c0`` (log of b(alpha = 0) p(z | alpha = 0),
    -inf if none) and terms t (row, log coefficient) for the options alpha = l.
    Vehicle and track beliefs b^(0) are given as normalised log-weights.
    ``output_particles``/``output_log_b0``: another particle set per vehicle
    (the carried cooperative belief of the "latest_message" recursion) onto
    which the converged messages m_{k->i} are also evaluated, giving the
    returned ``vehicle_logw`` (27) on that set; None = the same set.
    ``track_flat`` (K,) bool: b_k^(0) carries no evidence, only the uniform
    position prior of a newborn track (times the velocity prior of
    ``IcpParams`` if set), represented on the particles by importance weights
    prior / proposal. An entry whose cavity b_k / m_{i->k} is then that prior
    alone (the track's only observer this step) gets the message m_{k->i} in
    closed form: the V2F likelihood integrated over the prior, i.e. 1 without
    a velocity prior and N(z_v + v_i; 0, s^2 I + R_v) with one (option
    alpha = 0 of (18) left out). On the particles the same cavity is the
    weights 1 / proposal, whose variance is unbounded: the few particles in
    the proposal's tails dominate and the "flat" message becomes a random
    spike that pulls the vehicle.

    ``v2x``: the frame's V2X channel (aligned with ``adjacency`` = ``frame.neighbors``): the average
    consensus of (28) is running-sum ratio consensus and the max consensus of (29) a lossy max
    consensus, both over the rounds the channel delivers (:class:`ChannelRowConsensus`: a vehicle's
    broadcast of a round carries its log-weights of every track it observes), within the step's round
    budget as in the Gaussian BPA-L (:mod:`coloc.inference.bpa`): each exchange gets min(wanted, rounds
    left), average first, and BPA-L stops after the iteration that used the last round. The
    participant count |V_k ∩ C| stays that of the intended graph. None: lossless, as before.
    """
    n, jv = vehicle_log_b0.shape
    k, jf = track_log_b0.shape[0], track_particles.shape[1]
    e = entry_vehicle.size
    logb_v = normalize_log(vehicle_log_b0)
    if e == 0:
        if output_particles is not None:
            logb_v = normalize_log(output_log_b0)
        return PfBpaResult(logb_v, np.empty((0, jf)), np.empty((0, jf)), np.full(k, -1, np.int64), 0, True, 0)
    t_vehicle, t_track = entry_vehicle[term_entry], entry_track[term_entry]
    t_z, t_r = z[term_row], r[term_row]
    zero_shift = np.zeros((term_row.size, 4))
    # Kernel centres of the sources and the V2F kernel of the messages from the vehicle / feature particles.
    v_centres, v_bw = kernel_density(vehicle_particles, vehicle_log_b0, pf.message_bandwidth)
    f_centres, f_bw = kernel_density(track_particles, track_log_b0, pf.message_bandwidth)
    r_from_v, r_from_f = t_r + v_bw[t_vehicle], t_r + f_bw[t_track]
    graph = consensus_graph(entry_vehicle, entry_track, adjacency)
    _, count = row_components(graph)
    channel = None if v2x is None else ChannelRowConsensus(entry_vehicle, entry_track, k, adjacency, v2x)
    weights = metropolis_weights(graph) if channel is None else None
    c_avg, c_max = int(params.consensus_iterations), max(int(params.consensus_iterations), 1)
    rounds_avg = rounds_max = 0
    log_b0_e = normalize_log(track_log_b0[entry_track])
    log_m_fv = np.zeros((e, jv))  # m_{k->i}^(0) = 1
    n_obs = np.bincount(entry_track, minlength=k)
    flat_e = np.zeros(e, bool)  # entries whose cavity is the newborn prior alone
    if track_flat is not None:
        flat_e = np.asarray(track_flat, bool)[entry_track] & (n_obs[entry_track] == 1)
    flat_m = None  # their messages m_{k->i}: fixed, whatever the iteration
    if flat_e.any():
        flat_m = _flat_prior_messages(vehicle_particles, flat_e, entry_vehicle, term_entry, t_z, t_r, term_log_c,
                                      params.feature_velocity_prior_sigma)
    log_m_vf = np.zeros((e, jf))
    v_mean, _ = weighted_moments(vehicle_particles, logb_v)
    f_mean, _ = weighted_moments(track_particles[entry_track], log_b0_e)
    converged, pairs, it = False, 0, 0
    logb_f = log_b0_e
    # The particles and kernels of the two message sums stay fixed through the iterations, only the
    # cavity weights change: within pf.kernel_cache_mb their kernel matrices are kept (FixedTransforms),
    # each built in the first iteration together with that iteration's sum.
    keep_bytes = 0.5e6 * pf.kernel_cache_mb
    storage = [None, None]
    if pf.kernel == FAST:  # 16-bit kept values (coloc.kernels.pf_fast), two to a float32 of the workspace
        if workspace is not None:
            n_keep = fast_kept_problem_count(term_row.size, jv, jf, keep_bytes)
            storage = [a.view(np.uint16) for a in workspace.arrays(*((n_keep * jv * jf + 1) // 2 for _ in range(2)))]
        to_features = FastRepeatedTransforms(v_centres, t_vehicle, t_z, track_particles, t_track, zero_shift, r_from_v,
                                             keep_bytes, storage[0])
        to_vehicles = FastRepeatedTransforms(f_centres, t_track, zero_shift, vehicle_particles, t_vehicle, t_z,
                                             r_from_f, keep_bytes, storage[1])
    else:
        if workspace is not None:
            storage = workspace.arrays(*(kept_problem_count(term_row.size, jv, jf, pf.kernel, pf.kernel_rel_tol,
                                                            keep_bytes) * jv * jf for _ in range(2)))
        to_features = RepeatedTransforms(v_centres, t_vehicle, t_z, track_particles, t_track, zero_shift, r_from_v,
                                         pf.kernel, pf.kernel_rel_tol, keep_bytes, storage[0])
        to_vehicles = RepeatedTransforms(f_centres, t_track, zero_shift, vehicle_particles, t_vehicle, t_z, r_from_f,
                                         pf.kernel, pf.kernel_rel_tol, keep_bytes, storage[1])
    # PfParams.bpa_stop = "component": only the entries (act_e) and terms (act_t) of components still
    # iterating are summed; the others keep their last messages. None: every one (the net rule).
    per_component = pf.bpa_stop == "component"
    act_e = act_t = act_seg = None
    if per_component:
        comp_e, comp_v, n_comp = bpa_components(graph, entry_vehicle, n)
        live = np.ones(n_comp, bool)
        comp_iterations = np.zeros(n_comp, np.int64)

    def messages(transforms, cavity: np.ndarray, previous: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(19) or (21): the terms' sums of the cavity, mixed per entry with its constant; the live
        entries' only (``act_e``), the others keep ``previous``."""
        if act_t is None:
            out, p = transforms.sum(cavity[term_entry])
            return normalize_log(_segment_logsumexp(term_log_c[:, None] + out, term_entry, e, entry_log_c0)), p
        out, p = transforms.sum(cavity[term_entry[act_t]], act_t)
        new = previous.copy()
        new[act_e] = normalize_log(_segment_logsumexp(term_log_c[act_t, None] + out, act_seg, act_e.size,
                                                      entry_log_c0[act_e]))
        return new, p

    for it in range(1, params.bpa_max_iterations + 1):
        # (19): vehicle cavity b_i / m_{k->i}, summed over the vehicle particles for every feature particle.
        log_m_vf, p1 = messages(to_features, normalize_log(logb_v[entry_vehicle] - log_m_fv), log_m_vf)
        # (28)-(29): sum of log-messages over V_k = |V_k ∩ C| x average consensus; then max consensus.
        # (A settled component's rows are recomputed from its unchanged messages: the same values.)
        if channel is None:
            avg = average_consensus_with_weights(log_m_vf, weights, c_avg)
        else:
            granted = channel.grant(c_avg, params.exchanges_left(it, per_iteration=2))
            avg = channel.average(log_m_vf, granted)
            rounds_avg += granted
        loc = log_b0_e + count[:, None] * avg
        loc = loc - loc.max(axis=1, keepdims=True)
        if channel is None:
            new_f = normalize_log(max_consensus(loc, graph, c_max))
        else:
            granted = channel.grant(c_max, params.exchanges_left(it, per_iteration=2, done=1))
            new_f = normalize_log(channel.maximum(loc, granted))
            rounds_max += granted
        if act_e is None:
            logb_f = new_f
        else:  # (over a lossy channel a settled component's rows would differ: keep them)
            logb_f = logb_f.copy()
            logb_f[act_e] = new_f[act_e]
        if it == 1:
            first_f, first_m = logb_f, log_m_vf
        # (21): feature cavity b_k / m_{i->k}, summed over the feature particles for every vehicle particle.
        cav_f = normalize_log(logb_f - log_m_vf)
        log_m_fv, p2 = messages(to_vehicles, cav_f, log_m_fv)
        if flat_m is not None:
            log_m_fv[flat_e] = flat_m
        pairs += int(p1.sum() + p2.sum())
        # (27): b_i = b_i^(0) prod_k m_{k->i}.
        acc = vehicle_log_b0.copy()
        scatter_add(acc, entry_vehicle, log_m_fv)
        logb_v = normalize_log(acc)
        new_v, _ = weighted_moments(vehicle_particles, logb_v)
        new_f, _ = weighted_moments(track_particles[entry_track], logb_f)
        dv_v, dv_f = np.hypot(*(new_v[:, :2] - v_mean[:, :2]).T), np.hypot(*(new_f[:, :2] - f_mean[:, :2]).T)
        dw_v, dw_f = np.hypot(*(new_v[:, 2:] - v_mean[:, 2:]).T), np.hypot(*(new_f[:, 2:] - f_mean[:, 2:]).T)
        v_mean, f_mean = new_v, new_f
        if per_component:  # Sec. V-A within each component
            moved = np.zeros(n_comp, bool)
            moved[comp_v[~((dv_v < params.stop_pos_m) & (dw_v < params.stop_vel_mps))]] = True  # (nan: moved,
            moved[comp_e[~((dv_f < params.stop_pos_m) & (dw_f < params.stop_vel_mps))]] = True  # as the net rule)
            comp_iterations[live] = it
            live &= moved
            if not live.any():
                converged = True
                break
            act_e = np.flatnonzero(live[comp_e])
            act_t = np.flatnonzero(live[comp_e[term_entry]])
            act_seg = np.searchsorted(act_e, term_entry[act_t])
        elif np.concatenate([dv_v, dv_f]).max() < params.stop_pos_m and \
                np.concatenate([dw_v, dw_f]).max() < params.stop_vel_mps:  # Sec. V-A
            converged = True
            break
        if channel is not None and channel.exhausted:
            break  # the step's round budget is used up
    if output_particles is not None:
        t_out, p3 = gauss_transforms(pf, f_centres, cav_f[term_entry], t_track, zero_shift, output_particles,
                                     t_vehicle, t_z, r_from_f)
        pairs += int(p3.sum())
        out_m = normalize_log(_segment_logsumexp(term_log_c[:, None] + t_out, term_entry, e, entry_log_c0))
        if flat_e.any():
            out_m[flat_e] = _flat_prior_messages(output_particles, flat_e, entry_vehicle, term_entry, t_z, t_r,
                                                 term_log_c, params.feature_velocity_prior_sigma)
        acc = output_log_b0.copy()
        scatter_add(acc, entry_vehicle, out_m)
        logb_v = normalize_log(acc)
    # A track's posterior: the copy of its largest consensus component (lowest entry on ties).
    comp_size = count
    order = np.lexsort((np.arange(e), -comp_size, entry_track))
    first = np.ones(e, bool)
    first[1:] = entry_track[order][1:] != entry_track[order][:-1]
    track_entry = np.full(k, -1, np.int64)
    track_entry[entry_track[order][first]] = order[first]
    rounds = None if channel is None else (rounds_avg, rounds_max)
    entry_its = None
    if per_component:
        comp_iterations[live] = it
        entry_its = comp_iterations[comp_e]
    return PfBpaResult(logb_v, logb_f, log_m_vf, track_entry, it, converged, pairs, first_f, first_m, rounds,
                       entry_its)


def bpa_components(graph: sp.csr_matrix, entry_vehicle: np.ndarray, n_vehicles: int
                   ) -> tuple[np.ndarray, np.ndarray, int]:
    """Connected components of BPA-L's graph: entries (vehicle, track) linked to their vehicle and,
    by the consensus ``graph`` (:func:`coloc.inference.row_consensus.consensus_graph`), to the other
    observers of their track among their V2V neighbours. No message of (19)-(29) crosses from one
    component to another. Returns (component of each entry (E,), of each vehicle (N,), count); a
    vehicle without entries is a component of its own."""
    e = entry_vehicle.size
    g = sp.csr_matrix(graph, dtype=bool)
    links = sp.bmat([[g, sp.csr_matrix((np.ones(e, bool), (np.arange(e), entry_vehicle)), shape=(e, n_vehicles))],
                     [None, sp.csr_matrix((n_vehicles, n_vehicles), dtype=bool)]], format="csr")
    count, labels = connected_components(links, directed=False)
    return labels[:e].astype(np.int64), labels[e:].astype(np.int64), int(count)


# ----------------------------------------------------------------------------- communication


def pf_step_comm(entry_vehicle: np.ndarray, entry_track: np.ndarray, adjacency: sp.spmatrix, birth_owner: np.ndarray,
                 iterations: int | np.ndarray, n_vehicles: int, params: IcpParams, pf: PfParams,
                 rounds: tuple[int, int] | None = None) -> CommCount:
    """What the vehicles sent in one step (:mod:`coloc.inference.comm`): every BPA-L iteration,
    ``consensus_iterations`` rounds of average consensus of the Jf log-weights (28) and
    max(``consensus_iterations``, 1) rounds of max consensus (29), one broadcast per round from every
    vehicle with an entry (vehicle, track) that has a consensus partner (another observer of the
    track among its V2V neighbours); plus one announcement of the rows that start tracks.
    ``rounds``: the (average, max) rounds the step used over a V2X channel (:class:`PfBpaResult`), in
    place of iterations x the params' rounds. ``iterations``: the step's, or (E,) per entry (its
    component's, ``PfParams.bpa_stop = "component"``)."""
    graph = consensus_graph(entry_vehicle, entry_track, adjacency)
    active = np.diff(graph.indptr) > 0 if entry_vehicle.size else np.zeros(0, bool)
    avg_words, max_words = pf_words(pf.feature_particles)
    c = int(params.consensus_iterations)
    birth = announcements(birth_owner, n_vehicles, PF_BIRTH_WORDS)
    if np.ndim(iterations) and rounds is None:  # per entry (bpa_stop = "component"): each component its own
        its = np.asarray(iterations, dtype=np.int64)
        total = CommCount.zeros(n_vehicles)
        for g in np.unique(its):
            sel = active & (its == g)
            total = (total + broadcast_rounds(entry_vehicle, sel, n_vehicles, int(g) * c, avg_words)
                     + broadcast_rounds(entry_vehicle, sel, n_vehicles, int(g) * max(c, 1), max_words))
        most = int(its.max(initial=0))
        return CommCount(total.messages, total.bytes, most * c + most * max(c, 1)) + birth
    it = int(np.max(iterations, initial=0))
    r_avg, r_max = (it * c, it * max(c, 1)) if rounds is None else rounds
    return (broadcast_rounds(entry_vehicle, active, n_vehicles, r_avg, avg_words)
            + broadcast_rounds(entry_vehicle, active, n_vehicles, r_max, max_words)
            + birth)
