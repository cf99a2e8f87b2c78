"""``icp_da_lc``: ICP-DA low-complexity implementation (Brambilla et al. Sec. IV-D).

Per time step, with no knowledge of which feature produced a V2F row:

1. vehicle beliefs b_i^(0) (11) and own-sensor tracks, exactly as
   :mod:`coloc.methods.icp_known_da`; feature tracks predicted by model (2) (12);
2. candidate tracks F_i,t of vehicle i: tracks whose predicted position is
   within the sensing range Rs of the vehicle's predicted position plus a
   3-sigma margin of both uncertainties (the vehicle knows its own sensor's
   range, not the features);
3. eta of (13) for every (candidate track k, row l) of a vehicle: the
   Gaussian integral of the V2F likelihood (4) against b_i^(0) and b_k^(0)
   (b_i^(0) with the own-sensor covariance, see :func:`icp_da_lc_step`),
       eta(alpha_ik = l) = P_D N(z_l; m_k - m_i, P_k + P_i + R_l) / (mu_new f_new(z_l)),
   gated at ``gate_probability`` (chi-square, 4 dof), and eta(alpha_ik = 0)
   = 1 - P_D. The paper leaves eta(0) and the clutter/new-feature weight
   implicit (its features are always in range and known in number). Here a
   measurement that no track explains has weight 1 in the BP of
   :mod:`coloc.inference.association`, so eta is divided by the density of a
   measurement from an untracked feature: position uniform in the sensing
   disc (1 / (pi Rs^2)) and velocity z_v = v_F - v_V with v_F ~ N(0,
   s_new^2 I), times the expected number mu_new of untracked features in
   view (``new_feature_rate``). With P_D = 0.95 and Rs = 75 m (crossroad)
   this density is about 8.5e-6 per m^2 (m/s)^2, so eta(l) is of order
   1e4-1e5 for a consistent pairing and b(alpha = 0) of order 1e-5: eta_TH
   = 0.5 then discards only rows that two tracks explain about equally.
   ``new_feature_density`` > 0 replaces the whole density by that constant
   (1 = eta of (13) as written, unnormalised);
4. BPA-DA (14)-(17) per vehicle, all vehicles in one numba call;
5. MAP pairing (30), by ``pairing``:

   * ``"gated"`` (default, ours): track k is detected iff b(alpha = 0) <
     eta_TH (at eta_TH = 1: iff it has a gated row) and is paired with
     argmax_l b(alpha = l); two tracks claiming the same row: the larger
     belief wins, the other is not detected;
   * ``"paper"`` (the literal (30)-(31)): no chi-square gate in step 3 (eta of
     every candidate pair, however far), track k detected iff b(alpha = 0) <
     eta_TH at every eta_TH, and nothing stops two tracks from taking the
     same row: each pairing enters the likelihood (31), so a shared row is
     used once per track that took it. The row's reported assignment is the
     track of largest belief (scoring sees one track per row);
5a. the fix arbitrated by the map (``fix_map_margin`` and ``anchor_margin``, off by default;
   :mod:`coloc.methods.lc_reloc`): a vehicle whose motion prediction puts more of its rows on confirmed
   tracks than b^(0)'s mean (this step's fix included) is associated at the prediction; with
   ``anchor_margin``, one whose map-anchored position (which no fix moves, refreshed to the posterior
   whenever the map supports it) puts more rows on the map is associated there;
5b. relocalization (``relocalize_radius_m``, off by default; :mod:`coloc.methods.lc_reloc`): a vehicle
   none of whose rows found a confirmed track is moved, for steps 3-6 and 9 of this step only, by the
   translation that puts its rows on confirmed tracks, and steps 3-5 run again (with
   ``relocalize_min_gain`` also a vehicle partly on the map whose translation gains that many rows);
6. feature tracks without a map (docs/architecture.md "Features without a map"): a row no
   track took whose "new" belief is >= ``birth_probability`` starts a track;
   rows of different vehicles whose implied feature positions (m_i + z_l)
   agree within the 99 % chi-square gate (2 dof) start *one* track
   (vehicles share new tracks over V2V; the lowest new id wins); other unpaired rows
   are discarded (counted as such by the scoring);
7. Gaussian BPA-L (19)-(22) with consensus on the paired rows, i.e. the
   likelihood (31), and the latest-message track store of :mod:`coloc.inference`;
8. merging: two tracks whose means are within ``merge_gate_m`` and within the
   99 % chi-square gate (2 dof) of their summed position covariances, and
   that no vehicle observed both at this step, are merged into the older id;
   tracks nobody observed for ``feature_drop_after_s`` are dropped;
9. track existence (realistic sensing; ``track_existence``, off by default): every
   track carries the probability r that it is a real object, as in
   belief-propagation multitarget tracking (Meyer et al., "Message passing
   algorithms for scalable multitarget tracking", Proc. IEEE 106(2), 2018):
   predicted r <- p_s r (``survival_probability``); eta of (13) becomes
   eta(alpha = 0) = 1 - r P_D and eta(alpha = l) = r x (the weight of step
   3); after BPA-DA each vehicle's problem gives P(exists | z_i) = 1 -
   b(alpha = 0) (1 - q), q = r (1 - P_D) / (1 - r P_D), and the vehicles'
   evidence adds in log-odds (:func:`existence_update`); a candidate in a
   vehicle's range with no gated row counts as missed (odds x (1 - P_D)). A
   row that starts a track gives it r = mu_new f_new / (mu_new f_new +
   lambda_c f_c) (several rows: their log-odds add). A track localizes
   vehicles only while r >= ``confirm_existence``; below that it is
   tentative: it takes part in the association (so clutter keeps hitting it
   rather than starting more tracks) and is updated with the observing
   vehicles' own-sensor messages, but BPA-L leaves its rows out and they are
   reported as discarded. Tracks with r < ``drop_existence`` are dropped. A
   landmark re-detected in a tight gate gains odds of order P_D N / lambda_c
   per detection; clutter, drawn anew every scan, loses (1 - P_D) per miss.
   Without clutter in the model every birth has r = 1 (up to 1e-12) and
   nothing changes but the missed-detection decay;
10. own-sensor consistency (realistic sensing; ``own_consistency_gate``, off by
   default): a vehicle whose cooperative position leaves the chi-square gate
   of its own-sensor track is reset to that track (:func:`own_consistency_reset`),
   an innovation-based fault check in the spirit of receiver autonomous
   integrity monitoring. It bounds what a wrong pairing can do to a vehicle.
   With ``reset_map_margin`` m > 0 the map arbitrates: a vehicle whose static rows land on at least m more
   distinct confirmed tracks from its cooperative position than from its own track's is not reset (the own
   receiver is in an excursion the landmarks do not share; :func:`coloc.methods.lc_reloc.map_support`).

11. classes (frames with ``v2f_class``, ``[features] pedestrians``): the
   classifier's label of a row is known, so in step 3 a row is a candidate of tracks of its own
   class only (eta(alpha = l) = 0 otherwise), step 6 clusters births per class and a new track
   takes its rows' class, step 8 merges only tracks of one class; model (2) of a track uses its
   class's noise (:func:`coloc.inference.feature_store.feature_track_q`). Without ``v2f_class``
   nothing of this runs (the estimates are byte for byte those without classes).

The parameters (:class:`LcParams`, the pairing rules of step 5) live in
:mod:`coloc.inference.params`, next to :class:`coloc.inference.params.IcpParams`.

``StepEstimate.v2f_assignment`` is the track id of each V2F row (-1 =
discarded); scoring maps tracks to true features outside the estimator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from coloc.core.detection import DetectionModel, expected_detection_probability
from coloc.core.frame import Frame, StepEstimate
from coloc.core.vehicle_rows import expand_rows, without_vehicle_rows
from coloc.core.detections import with_net_detections
from coloc.core.inertial import estimator_input
from coloc.core.vehicles import match_ids
from coloc.inference.association import association_marginals_batch, layout_and_marginals_kernel
from coloc.inference.bpa import step_feature_beliefs
from coloc.inference.comm import LC_BIRTH_WORDS, CommCount, announcements
from coloc.inference.existence import TrackExistence, birth_existence, existence_update
from coloc.inference.gaussian import chi2_ppf, log_gauss, relative_message, to_information
from coloc.inference.params import PAIRING_RULES, IcpParams, LcParams
from coloc.kernels import icp_fused
from coloc.kernels.detection import detection_probability_pairs
from coloc.kernels.track_index import candidate_pairs_kernel
from coloc.kernels.icp_fused import (
    association_log_weights_kernel,
    association_terms_kernel,
    map_pairing_kernel,
    unique_inverse,
)
from coloc.methods.coop_fusion import CoopFusion
from coloc.methods.icp_known_da import IcpState, frame_vehicle_codes, localize, prior_pair
from coloc.methods.lc_reloc import (anchored_mean, fix_arbitrated_mean, map_rows, predicted_anchor, refreshed_anchor,
                                    relocalization_offsets)
from coloc.methods.lc_births import PRUNE_MARGIN, birth_clusters, birth_pairs, merge_candidates  # noqa: F401
from coloc.methods.registry import ICP_DA_LC

__all__ = [
    "LcParams", "IcpDaLc", "LcStepInfo", "AssociationBeliefs", "association_beliefs", "association_weights",
    "map_pairing", "map_pairs", "icp_da_lc_step", "candidate_rows", "new_feature_log_density", "PAIRING_RULES",
]


def _f64(*arrays):
    return tuple(np.ascontiguousarray(a, dtype=np.float64) for a in arrays)


def _i64(*arrays):
    return tuple(np.ascontiguousarray(a, dtype=np.int64) for a in arrays)


DENSE_PAIRS_MAX = 200_000  # vehicles x tracks above which candidate_pairs indexes the tracks (a city)


def candidate_pairs(
    v_mean: np.ndarray, v_cov: np.ndarray, t_mean: np.ndarray, t_cov: np.ndarray, lc: LcParams
) -> tuple[np.ndarray, np.ndarray]:
    """(vehicle, track) index pairs with the track predicted in the vehicle's sensing range (+3 sigma)."""
    if v_mean.shape[0] == 0 or t_mean.shape[0] == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    if icp_fused.FUSED:  # the tracks indexed by spread and x, the same pairs (coloc.kernels.track_index)
        return candidate_pairs_kernel(*_f64(v_mean, v_cov, t_mean, t_cov), float(lc.sensing_range_m))
    tr_v = np.trace(v_cov[:, :2, :2], axis1=1, axis2=2)
    tr_t = np.trace(t_cov[:, :2, :2], axis1=1, axis2=2)
    if v_mean.shape[0] * t_mean.shape[0] > DENSE_PAIRS_MAX:
        # a city: the tracks near each vehicle from a k-d tree (radius: the test below with the largest
        # spreads, widened past hypot's rounding), then the same test on those; same pairs, same order
        reach = (lc.sensing_range_m + 3.0 * math.sqrt(tr_v.max() + tr_t.max())) * (1.0 + 1e-9)
        near = cKDTree(v_mean[:, :2]).sparse_distance_matrix(cKDTree(t_mean[:, :2]), reach, output_type="ndarray")
        order = np.lexsort((near["j"], near["i"]))  # np.nonzero's row-major order
        vi, ti = near["i"][order].astype(np.int64), near["j"][order].astype(np.int64)
        d = np.hypot(v_mean[vi, 0] - t_mean[ti, 0], v_mean[vi, 1] - t_mean[ti, 1])
        keep = d <= lc.sensing_range_m + 3.0 * np.sqrt(tr_v[vi] + tr_t[ti])
        return vi[keep], ti[keep]
    d = np.hypot(v_mean[:, None, 0] - t_mean[None, :, 0], v_mean[:, None, 1] - t_mean[None, :, 1])
    spread = tr_v[:, None] + tr_t[None]
    vi, ti = np.nonzero(d <= lc.sensing_range_m + 3.0 * np.sqrt(spread))
    return vi.astype(np.int64), ti.astype(np.int64)


def candidate_rows(
    v_mean: np.ndarray, v_cov: np.ndarray, t_mean: np.ndarray, t_cov: np.ndarray, owner: np.ndarray, lc: LcParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vehicle, track, row) for every row of a vehicle and every candidate track of that vehicle."""
    owner = np.asarray(owner, dtype=np.int64)
    n = v_mean.shape[0]
    vi, ti = candidate_pairs(v_mean, v_cov, t_mean, t_cov, lc)
    rows_by_vehicle = np.argsort(owner, kind="stable")
    n_rows = np.bincount(owner, minlength=n)
    start = np.concatenate([[0], np.cumsum(n_rows)[:-1]])
    reps = n_rows[vi]
    pv, pt = np.repeat(vi, reps), np.repeat(ti, reps)
    within = np.arange(reps.sum()) - np.repeat(np.cumsum(reps) - reps, reps)
    pr = rows_by_vehicle[np.repeat(start[vi], reps) + within]
    return pv, pt, pr


def new_feature_log_density(v_mean: np.ndarray, v_cov: np.ndarray, z: np.ndarray, r: np.ndarray, lc: LcParams) -> np.ndarray:
    """log of mu_new f_new(z) [+ lambda_c f_c(z)]: a row from an untracked feature (module
    docstring, step 3), plus clutter when ``lc.clutter_intensity`` > 0, per row.

    Position uniform in the sensing disc, v_F ~ N(0, s^2 I), so z_v = v_F - v_V
    is Gaussian around -v_V; ``v_mean``/``v_cov`` are the measuring vehicle's.
    """
    log_new = _untracked_feature_log_density(v_mean, v_cov, z, r, lc)
    if lc.clutter_intensity > 0:
        log_new = np.logaddexp(log_new, clutter_log_density(v_mean, v_cov, z, r, lc))
    return log_new


def _untracked_feature_log_density(v_mean, v_cov, z, r, lc: LcParams) -> np.ndarray:
    """log mu_new f_new(z) alone (module docstring, step 3)."""
    if lc.new_feature_density > 0:
        return np.full(z.shape[0], math.log(lc.new_feature_density))
    s_v = v_cov[:, 2:, 2:] + r[:, 2:, 2:] + lc.new_feature_velocity_sigma**2 * np.eye(2)
    log_new_v, _ = log_gauss(z[:, 2:] + v_mean[:, 2:], s_v)
    return math.log(lc.new_feature_rate) - math.log(math.pi * lc.sensing_range_m**2) + log_new_v


def clutter_log_density(v_mean, v_cov, z, r, lc: LcParams) -> np.ndarray:
    """log lambda_c f_c(z) per row: clutter uniform in position with intensity lambda_c per m^2,
    reported like a static object, z_v = -v_V + noise (as the perception model draws it)."""
    log_v, _ = log_gauss(z[:, 2:] + v_mean[:, 2:], v_cov[:, 2:, 2:] + r[:, 2:, 2:])
    return math.log(lc.clutter_intensity) + log_v


def new_feature_share(v_mean, v_cov, z, r, lc: LcParams) -> np.ndarray:
    """P(new feature | the row comes from no track) = mu_new f_new / (mu_new f_new + lambda_c f_c), per
    row (1 without clutter): the existence of a track the row starts (step 9)."""
    if lc.clutter_intensity <= 0:
        return np.ones(z.shape[0])
    log_f = _untracked_feature_log_density(v_mean, v_cov, z, r, lc)
    return np.exp(log_f - np.logaddexp(log_f, clutter_log_density(v_mean, v_cov, z, r, lc)))


def association_weights(
    v_mean, v_cov, t_mean, t_cov, owner, z, r, lc: LcParams, detection: DetectionModel | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """eta of (13) for every vehicle's (candidate track, row) pair, as BP problems.

    Returns ``(pair_vehicle, pair_track, pair_row, weight)`` with one entry per
    (vehicle i, candidate track k, row l of i): weight = eta(alpha_ik = l)
    normalised by the new-feature density (module docstring, step 3); 0
    outside the gate (no gate with ``lc.pairing = "paper"``). With a
    ``detection`` model P_D is the pair's expected detection probability
    (:func:`coloc.core.detection.expected_detection_probability`), not
    ``lc.detection_probability``.
    """
    if icp_fused.FUSED:  # one numba pass, same operations (coloc.kernels.icp_fused)
        owner = np.asarray(owner, dtype=np.int64)
        # pairs outside the gate get weight 0 below: their log-likelihoods are not computed
        gate = chi2_ppf(lc.gate_probability, 4) if lc.pairing == "gated" else math.inf
        args = (*_f64(v_mean, v_cov, t_mean, t_cov), owner, *_f64(z, r), float(lc.sensing_range_m), gate)
        if detection is None and lc.new_feature_density == 0 and lc.clutter_intensity <= 0:
            # log_w below in the same call (the density of _untracked_feature_log_density per row)
            log_new_const = math.log(lc.new_feature_rate) - math.log(math.pi * lc.sensing_range_m**2)
            pv, pt, pr, log_w, d2 = association_log_weights_kernel(
                *args, float(lc.new_feature_velocity_sigma**2), log_new_const, math.log(lc.detection_probability))
            if pr.size == 0:
                return pv, pt, pr, np.empty(0)
            return pv, pt, pr, _gated_weights(log_w, d2, lc)
        pv, pt, pr, log_lik, d2 = association_terms_kernel(*args)
        if pr.size == 0:
            return pv, pt, pr, np.empty(0)
        # a row's new-feature density depends on the row alone: once per row, then per pair
        log_new = new_feature_log_density(v_mean[owner], v_cov[owner], z, r, lc)[pr]
    else:
        pv, pt, pr = candidate_rows(v_mean, v_cov, t_mean, t_cov, owner, lc)
        if pr.size == 0:
            return pv, pt, pr, np.empty(0)
        nu = z[pr] - (t_mean[pt] - v_mean[pv])
        log_lik, d2 = log_gauss(nu, t_cov[pt] + v_cov[pv] + r[pr])
        log_new = new_feature_log_density(v_mean[pv], v_cov[pv], z[pr], r[pr], lc)
    if detection is None:
        log_w = math.log(lc.detection_probability) + log_lik - log_new
    else:
        # P_D only of the pairs that can get a weight: _gated_weights gives 0 to those beyond the gate
        pd = np.zeros(pr.size)
        need = ~(d2 > chi2_ppf(lc.gate_probability, 4)) if lc.pairing == "gated" else np.ones(pr.size, dtype=bool)
        pd[need] = pair_detection_probability(v_mean, t_mean, pv[need], pt[need], detection)
        with np.errstate(divide="ignore", invalid="ignore"):
            log_w = np.log(pd) + log_lik - log_new
    return pv, pt, pr, _gated_weights(log_w, d2, lc)


def pair_detection_probability(v_mean, t_mean, vi, ti, detection: DetectionModel) -> np.ndarray:
    """P_D of the (vehicle ``vi``, track ``ti``) pairs: ``expected_detection_probability(v_mean[vi],
    t_mean[ti, :2], detection)``, by one numba pass when fused (the same numbers)."""
    if icp_fused.FUSED:
        return detection_probability_pairs(v_mean, t_mean, vi, ti, detection)
    return expected_detection_probability(v_mean[vi], t_mean[ti, :2], detection)


def _gated_weights(log_w: np.ndarray, d2: np.ndarray, lc: LcParams) -> np.ndarray:
    """exp(log eta), capped, and 0 outside the chi-square gate (``pairing = "gated"``)."""
    w = np.exp(np.minimum(log_w, 600.0))
    if lc.pairing == "gated":
        w[d2 > chi2_ppf(lc.gate_probability, 4)] = 0.0
    return w


@dataclass(frozen=True)
class AssociationBeliefs:
    """BPA-DA (14)-(17) marginals of all vehicles' problems, indexed by (vehicle, track) combo.

    ``combo_vehicle``/``combo_track`` (C,): the combos with at least one gated
    row; ``combo_start`` (C,): flat index of (combo, option 0) in ``belief``;
    ``combo_rows`` (C,): rows of the combo's vehicle; option l >= 1 of a combo
    is row ``rows[row_first[c] + l - 1]`` (rows sorted by (vehicle, row)).
    ``row_new`` (O,): each row's belief of coming from no track.
    """

    belief: np.ndarray
    combo_vehicle: np.ndarray
    combo_track: np.ndarray
    combo_start: np.ndarray
    combo_rows: np.ndarray
    row_first: np.ndarray
    rows: np.ndarray
    row_new: np.ndarray

    def row_of_option(self, combo: np.ndarray, option: np.ndarray) -> np.ndarray:
        """Row index of option ``option`` (>= 1) of ``combo``."""
        return self.rows[self.row_first[combo] + option - 1]


def association_beliefs(
    pair_vehicle, pair_track, pair_row, weight, n_vehicles: int, n_rows: int, lc: LcParams,
    missed_weight: np.ndarray | None = None,
) -> AssociationBeliefs | None:
    """BPA-DA per vehicle (14)-(17): one BP problem per vehicle, K_i tracks x
    (M_i + 1) options, assembled with array operations and solved in one
    numba call. None when no pair is gated. ``missed_weight`` (per pair,
    equal over the rows of one (vehicle, track) combo): eta(alpha = 0) of the
    combo (1 - r P_D, step 9, with a per-pair P_D); None: 1 - P_D."""
    row_new = np.ones(n_rows)
    if icp_fused.FUSED:  # the layout below in one numba pass (coloc.kernels.icp_fused)
        missed = np.full(weight.size, 1.0 - lc.detection_probability) if missed_weight is None else missed_weight
        # the layout and the BP of every problem in one call (association.layout_and_marginals_kernel)
        out = layout_and_marginals_kernel(*_i64(pair_vehicle, pair_track, pair_row), *_f64(weight, missed),
                                          int(n_vehicles), int(lc.bp_iterations), float(lc.bp_tol))
        eta, k_sizes, m_sizes, c_vehicle, c_track, c_start, c_rows, c_row_first, rows_sorted, pf, pn, ok = out
        if c_vehicle.size == 0:
            return None
        if not ok:  # not finite or negative: association_marginals_batch raises
            pf, pn = association_marginals_batch(eta, k_sizes, m_sizes, lc.bp_iterations, lc.bp_tol)
        row_new[rows_sorted] = pn
        return AssociationBeliefs(pf, c_vehicle, c_track, c_start, c_rows, c_row_first, rows_sorted, row_new)
    keep = weight > 0
    pv, pt, pr, w = pair_vehicle[keep], pair_track[keep], pair_row[keep], weight[keep]
    if pv.size == 0:
        return None
    n_t = int(pt.max()) + 1
    # Problem-local indices: (vehicle, track) combos and rows, both sorted by vehicle.
    combo, c_inv = np.unique(pv * n_t + pt, return_inverse=True)
    c_vehicle, c_track = combo // n_t, combo % n_t
    rows_u, r_inv = np.unique(pr, return_inverse=True)  # a row belongs to one vehicle
    r_vehicle = np.zeros(rows_u.size, dtype=np.int64)
    r_vehicle[r_inv] = pv
    order_r = np.lexsort((rows_u, r_vehicle))  # rows sorted by (vehicle, row)
    rank_r = np.empty_like(order_r)
    rank_r[order_r] = np.arange(order_r.size)
    k_sizes = np.bincount(c_vehicle, minlength=n_vehicles)
    m_sizes = np.bincount(r_vehicle, minlength=n_vehicles)
    probs = np.flatnonzero(k_sizes > 0)  # every vehicle with a gated pair has >= 1 track and row
    k_sizes, m_sizes = k_sizes[probs], m_sizes[probs]
    prob_of_vehicle = np.full(n_vehicles, -1, dtype=np.int64)
    prob_of_vehicle[probs] = np.arange(probs.size)
    block = k_sizes * (m_sizes + 1)
    block_off = np.concatenate([[0], np.cumsum(block)[:-1]])
    c_first = np.concatenate([[0], np.cumsum(k_sizes)[:-1]])
    r_first = np.concatenate([[0], np.cumsum(m_sizes)[:-1]])
    c_prob = prob_of_vehicle[c_vehicle]
    c_local = np.arange(combo.size) - c_first[c_prob]
    c_start = block_off[c_prob] + c_local * (m_sizes[c_prob] + 1)  # flat index of (track, option 0)
    eta = np.zeros(int(block.sum()))
    if missed_weight is None:
        eta[c_start] = 1.0 - lc.detection_probability
    else:
        eta[c_start[c_inv]] = missed_weight[keep]
    r_local = rank_r[r_inv] - r_first[prob_of_vehicle[pv]]
    eta[c_start[c_inv] + 1 + r_local] = w
    pf, pn = association_marginals_batch(eta, k_sizes, m_sizes, lc.bp_iterations, lc.bp_tol)
    rows_sorted = rows_u[order_r]
    row_new[rows_sorted] = pn
    return AssociationBeliefs(pf, c_vehicle, c_track, c_start, m_sizes[c_prob], r_first[c_prob], rows_sorted, row_new)


def _map_decisions(ab: AssociationBeliefs, lc: LcParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(30) per (vehicle, track) combo: the detected combos, their MAP rows and beliefs.

    A combo is detected iff its best row has a positive belief and b(alpha = 0) < eta_TH;
    with ``pairing = "gated"`` the threshold test is skipped at eta_TH = 1 (every combo
    with a gated row is detected). Ties between rows go to the lowest option.
    """
    pf, c_start, combo_n = ab.belief, ab.combo_start, ab.combo_vehicle.size
    m_c = ab.combo_rows
    seg = np.repeat(np.arange(combo_n), m_c)
    opt = np.arange(seg.size) - np.repeat(np.cumsum(m_c) - m_c, m_c)
    vals = pf[np.repeat(c_start, m_c) + 1 + opt]
    best_val = np.zeros(combo_n)
    np.maximum.at(best_val, seg, vals)
    is_best = vals == best_val[seg]
    best_opt = np.full(combo_n, np.iinfo(np.int64).max)
    np.minimum.at(best_opt, seg[is_best], opt[is_best])
    detected = best_val > 0
    if lc.pairing == "paper" or lc.eta_threshold < 1.0:
        detected &= pf[c_start] < lc.eta_threshold
    cand = np.flatnonzero(detected)
    return cand, ab.row_of_option(cand, best_opt[cand] + 1), best_val[cand]


def map_pairing(
    pair_vehicle, pair_track, pair_row, weight, n_vehicles: int, n_rows: int, lc: LcParams
) -> tuple[np.ndarray, np.ndarray]:
    """BPA-DA per vehicle (14)-(17) (:func:`association_beliefs`) and the MAP decision (30).

    Returns ``(row_track, row_new)``: the track index paired with each row (-1
    = none) and each row's belief of coming from no track (1 for rows of
    vehicles without gated pairs). A row claimed by several tracks goes to the
    largest belief (ties: the lowest combo); with ``lc.pairing = "paper"`` the
    other claims are the extra pairs of :func:`map_pairs`.
    """
    row_track, row_new, _, _ = map_pairs(pair_vehicle, pair_track, pair_row, weight, n_vehicles, n_rows, lc)
    return row_track, row_new


def map_pairs(
    pair_vehicle, pair_track, pair_row, weight, n_vehicles: int, n_rows: int, lc: LcParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`map_pairing` plus every pairing the rule (30) makes beyond one per row.

    Returns ``(row_track, row_new, extra_row, extra_track)``. ``row_track`` is
    each row's track index of largest belief; with ``lc.pairing = "paper"``
    the other tracks that took the same row are ``(extra_row, extra_track)``
    (sorted by row, then belief), to be used in (31) as well; with "gated"
    they are empty (a contested row goes to the larger belief alone).
    """
    ab = association_beliefs(pair_vehicle, pair_track, pair_row, weight, n_vehicles, n_rows, lc)
    return pairs_from_beliefs(ab, n_rows, lc)


def pairs_from_beliefs(
    ab: AssociationBeliefs | None, n_rows: int, lc: LcParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The MAP decision (30) on BPA-DA beliefs; returns what :func:`map_pairs` returns."""
    row_track = np.full(n_rows, -1, dtype=np.int64)
    none = np.empty(0, np.int64)
    if ab is None:
        return row_track, np.ones(n_rows), none, none
    if icp_fused.FUSED and lc.pairing != "paper":  # (30) in one numba pass (coloc.kernels.icp_fused)
        row_track = map_pairing_kernel(ab.belief, ab.combo_start, ab.combo_rows, ab.row_first, ab.rows, ab.combo_track,
                                       int(n_rows), float(lc.eta_threshold), lc.eta_threshold < 1.0)
        return row_track, ab.row_new, none, none
    cand, cand_row, cand_val = _map_decisions(ab, lc)
    order = np.lexsort((cand, -cand_val, cand_row))  # by row, then larger belief, then combo
    first = np.ones(order.size, dtype=bool)
    first[1:] = cand_row[order][1:] != cand_row[order][:-1]
    win = order[first]
    row_track[cand_row[win]] = ab.combo_track[cand[win]]
    if lc.pairing != "paper":
        return row_track, ab.row_new, none, none
    extra = order[~first]
    return row_track, ab.row_new, cand_row[extra], ab.combo_track[cand[extra]]


@dataclass(frozen=True)
class LcStepInfo:
    """Association bookkeeping of one step (not scoring: no truth here)."""

    row_track: np.ndarray  # (O,) track id per row, -1 = discarded
    paired: int  # (track, row) pairings of (30); with pairing = "paper" a row may count more than once
    born: int
    discarded: int
    merged: int
    iterations: int
    shared: int = 0  # pairings beyond the first on a row (pairing = "paper": a row taken by several tracks)
    tentative: int = 0  # rows paired with (or starting) a track not yet confirmed: not used for the vehicles
    existence: TrackExistence | None = None  # existence of the tracks after the step (lc.track_existence)
    resets: int = 0  # vehicles reset to their own-sensor track (step 10)
    comm: CommCount | None = None  # what the vehicles sent: BPA-L consensus and new tracks (coloc.inference.comm)


def icp_da_lc_step(
    state: IcpState, next_id: int, frame: Frame, params: IcpParams, lc: LcParams,
    existence: TrackExistence | None = None, detection: DetectionModel | None = None,
    fusion: CoopFusion | None = None,
) -> tuple[IcpState, int, LcStepInfo]:
    """One ICP-DA-LC step (pure). Returns the new state, the next free track id and the step's
    bookkeeping; ``existence``: the tracks' existence after the previous step (``lc.track_existence``;
    the new one is ``info.existence``); ``detection``: the vehicles' sensors, for a P_D per
    (vehicle, track) (:mod:`coloc.core.detection`; None: ``lc.detection_probability``); ``fusion``: ``[fusion]``
    (:mod:`coloc.methods.coop_fusion`: split-CI fusion and the receiver model; the association then gates on
    b^(0)'s own, consistent covariance), None: the paper's BPA-L."""
    match = match_ids(state.ids, frame.vehicle_ids)
    # [inertial]: the body-frame IMU rotated by the heading of the previous belief (22) (None: frame.accel).
    accel, heading = estimator_input(frame, match, state.mean[:, 2:], state.heading, params.motion.heading_min_speed,
                                     params.motion.holds_heading)
    b0_mean, b0_cov, own_mean, own_cov, split = prior_pair(state, frame, params, match, accel, fusion)
    # The covariance the association, the births and the existence see with b^(0)'s mean (below).
    gate_cov = own_cov if split is None else b0_cov
    # Sensor-frame detections (frame.v2f_sensor): model (4)'s rows by the heading of the own-sensor track at t
    # (coloc.core.detections; as coloc.methods.icp_known_da).
    frame, sensor_heading = with_net_detections(frame, own_mean, own_cov, match, state.sensor_heading,
                                                params.motion.heading_min_speed)
    predicted = state.features.predict(frame.dt, params, 0.0 if fusion is None else fusion.map_drift(frame.dt))
    owner = np.asarray(frame.v2f_owner, dtype=np.int64)
    o = owner.size
    t_mean, t_cov = predicted.moments(params)
    r_pred = (existence or TrackExistence()).of(predicted.ids) * lc.survival_probability if lc.track_existence \
        else None
    a_mean = b0_mean  # the mean the association, births and existence see (steps 5a and 5b may move it)
    row_cls = frame.v2f_class
    # The step's rows and confirmed tracks for the map's support of a position (steps 5a, 5b, 10).
    uses_map = lc.relocalize_radius_m > 0 or lc.fix_map_margin > 0 or lc.anchor_margin > 0 or lc.reset_map_margin > 0
    rows = map_rows(predicted, r_pred, t_mean, frame, owner, lc) if uses_map else None
    if lc.fix_map_margin > 0 and predicted.size:  # step 5a: the map arbitrates this step's fix for the association
        a_mean = fix_arbitrated_mean(b0_mean, state, frame, match, accel, rows, lc.fix_map_margin)
    anchor_xy = None
    if lc.anchor_margin > 0:  # step 5a: or the vehicle's map-anchored position, which takes no fix
        anchor_xy = predicted_anchor(state.anchor, match, frame, b0_mean)
        if predicted.size:
            a_mean = anchored_mean(a_mean, anchor_xy, rows, lc.anchor_margin)

    def pd_of(vi: np.ndarray, ti: np.ndarray) -> np.ndarray:
        """P_D of (vehicle, predicted track) pairs."""
        if detection is None:
            return np.full(vi.size, lc.detection_probability)
        return pair_detection_probability(a_mean, t_mean, vi, ti, detection)

    ab, row_idx, row_new, extra_row, extra_idx = _associate(a_mean, gate_cov, t_mean, t_cov, predicted, owner, frame,
                                                            lc, detection, r_pred, pd_of)
    if lc.relocalize_radius_m > 0 and predicted.size:  # step 5b: lost vehicles relocalized against the confirmed tracks
        on_map = np.bincount(owner[(row_idx >= 0) & rows.confirmed[np.maximum(row_idx, 0)]],
                             minlength=frame.n_vehicles)
        enough = np.bincount(rows.owner, minlength=frame.n_vehicles) >= lc.relocalize_min_support
        lost = enough & (on_map == 0)
        shift = relocalization_offsets(a_mean, rows.owner, rows.z, lost, rows.track_xy,
                                       lc.relocalize_radius_m, lc.relocalize_tolerance_m, lc.relocalize_min_support,
                                       enough & (on_map > 0), lc.relocalize_min_gain)
        if shift.any():
            a_mean = a_mean.copy()
            a_mean[:, :2] += shift
            ab, row_idx, row_new, extra_row, extra_idx = _associate(a_mean, gate_cov, t_mean, t_cov, predicted, owner,
                                                                    frame, lc, detection, r_pred, pd_of)
    if lc.track_existence:  # r updated by the step
        existence = existence_after_association(r_pred, ab, a_mean, gate_cov, t_mean, t_cov, predicted.ids, pd_of,
                                                lc, detection is None)
    row_track = np.where(row_idx >= 0, predicted.ids[np.maximum(row_idx, 0)] if predicted.size else -1, -1)
    # Births (step 6). A row no track explains may be a new feature or clutter: it starts a track
    # either way, and with clutter in the model the confirmation of step 9 tells them apart (a
    # static landmark and a false detection look alike in one scan).
    birth = np.flatnonzero((row_idx < 0) & (row_new >= lc.birth_probability))
    implied = a_mean[owner[birth], :2] + frame.v2f_z[birth, :2]
    implied_cov = gate_cov[owner[birth], :2, :2] + frame.v2f_R[birth, :2, :2]
    if row_cls is None:
        labels = birth_clusters(owner[birth], implied, implied_cov, chi2_ppf(0.99, 2))
    else:  # rows of one class only start one track together
        labels = np.empty(birth.size, dtype=np.int64)
        off = 0
        for c in np.unique(row_cls[birth]):
            sub = np.flatnonzero(row_cls[birth] == c)
            lab = birth_clusters(owner[birth][sub], implied[sub], implied_cov[sub], chi2_ppf(0.99, 2))
            labels[sub] = lab + off
            off += int(lab.max()) + 1
    row_track[birth] = next_id + labels
    born = int(labels.max()) + 1 if labels.size else 0
    next_id += born
    # The rows of (31): every row once, plus a copy of a row for every further track that took it
    # (pairing = "paper" only; with "gated" the arrays are the frame's own).
    l_owner, l_z, l_r, l_track = owner, frame.v2f_z, frame.v2f_R, row_track
    l_cls = row_cls
    if extra_row.size:
        l_cls = np.concatenate([row_cls, row_cls[extra_row]]) if row_cls is not None else None
        l_owner = np.concatenate([owner, owner[extra_row]])
        l_z = np.concatenate([frame.v2f_z, frame.v2f_z[extra_row]])
        l_r = np.concatenate([frame.v2f_R, frame.v2f_R[extra_row]])
        l_track = np.concatenate([row_track, predicted.ids[extra_idx]])
    # Confirmation (step 9): rows of tentative tracks update their track but not the vehicles.
    bpa_track = l_track
    if lc.track_existence:
        share = new_feature_share(a_mean[owner[birth]], gate_cov[owner[birth]], frame.v2f_z[birth],
                                  frame.v2f_R[birth], lc)
        existence = existence.with_tracks(next_id - born + np.arange(born), birth_existence(share, labels, born))
        bpa_track = np.where(existence.confirmed(l_track, lc.confirm_existence), l_track, -1)
    # BPA-L on the paired rows of confirmed tracks (31).
    used = bpa_track >= 0
    row_vehicle = np.asarray(frame.vehicle_ids, dtype=object)[l_owner[used]]
    codes = frame_vehicle_codes(state, frame, match)
    row_codes = codes[l_owner[used]]
    fids = unique_inverse(bpa_track[used])[0]
    f_lam0, f_eta0 = predicted.prior_information(fids, bpa_track[used], row_vehicle, params, row_codes,
                                                 l_cls[used] if l_cls is not None else None)
    res, split_after = localize(split, b0_mean, b0_cov, own_mean, own_cov, l_owner, bpa_track, l_z, l_r, frame,
                                f_lam0, f_eta0, params, fusion is not None and fusion.params.feature_ci)
    rec_track, rec_owner, rec_lam, rec_eta = bpa_track[used], l_owner[used], res.msg_lam, res.msg_eta
    rec_cls = l_cls[used] if l_cls is not None else None
    tentative = (l_track >= 0) & ~used
    if tentative.any():
        # A tentative track gets each observing vehicle's own-sensor message (19) (no other feature
        # in the cavity: the message IcpParams.feature_message = "own" keeps).
        own_lam, own_eta = to_information(own_mean, own_cov)
        t_own = l_owner[tentative]
        t_lam, t_eta = relative_message(own_lam[t_own], own_eta[t_own], l_z[tentative], l_r[tentative])
        rec_track = np.concatenate([rec_track, l_track[tentative]])
        rec_owner = np.concatenate([rec_owner, t_own])
        rec_lam, rec_eta = np.concatenate([rec_lam, t_lam]), np.concatenate([rec_eta, t_eta])
        if rec_cls is not None:
            rec_cls = np.concatenate([rec_cls, l_cls[tentative]])
        row_vehicle = np.asarray(frame.vehicle_ids, dtype=object)[rec_owner]
        row_codes = codes[rec_owner]
    store = predicted.record(rec_track, row_vehicle, rec_lam, rec_eta, frame.t, params, row_codes, rec_cls)
    # Merging (step 8).
    absorbed, into = merge_candidates(store, params, lc, rec_owner, rec_track)
    store = store.merge(absorbed, into)
    if absorbed.size:
        order = np.argsort(absorbed)
        pos = np.minimum(np.searchsorted(absorbed[order], row_track), absorbed.size - 1)
        hit = absorbed[order][pos] == row_track
        row_track = np.where(hit, into[order][pos], row_track)
        pos = np.minimum(np.searchsorted(absorbed[order], bpa_track), absorbed.size - 1)
        hit = absorbed[order][pos] == bpa_track
        bpa_track = np.where(hit, into[order][pos], bpa_track)
    n_tentative = 0
    if lc.track_existence:
        existence = existence.merged(absorbed, into)
        store = store.drop(existence.ids[existence.r < lc.drop_existence])
        existence = existence.restricted(store.ids)
        n_tentative = int(tentative[:o].sum())
        # Rows not used for the vehicles are reported as discarded.
        row_track = np.where(existence.confirmed(row_track, lc.confirm_existence), row_track, -1)
    v_mean, v_cov, resets = res.mean, res.cov, 0
    if lc.own_consistency_gate > 0:
        kept = None
        if lc.reset_map_margin > 0 and predicted.size:  # the map arbitrates between the two positions
            kept = rows.support(res.mean) >= rows.support(own_mean) + lc.reset_map_margin
        v_mean, v_cov, reset = own_consistency_reset(res.mean, res.cov, own_mean, own_cov, lc.own_consistency_gate,
                                                     kept)
        resets = int(reset.sum())
        if split_after is not None and resets:  # the 6-D filters too: the own track, all of it independent
            split_after = split_after.reset_to_own(reset)
    info = LcStepInfo(row_track, int((row_idx >= 0).sum()) + int(extra_row.size), born, int((row_track < 0).sum()),
                      int(absorbed.size), res.iterations, int(extra_row.size), n_tentative,
                      existence if lc.track_existence else None, resets,
                      res.comm + announcements(owner[birth], frame.n_vehicles, LC_BIRTH_WORDS))
    beliefs = step_feature_beliefs(store, params, bpa_track[used], res)
    anchor_next = None
    if anchor_xy is not None:
        anchor_next = anchor_xy if not predicted.size else refreshed_anchor(anchor_xy, v_mean, rows)
    return (IcpState(frame.vehicle_ids, v_mean, v_cov, own_mean, own_cov, store, beliefs, heading, codes,
                     sensor_heading, split_after, anchor_next), next_id, info)


def _associate(a_mean, gate_cov, t_mean, t_cov, predicted, owner, frame: Frame, lc: LcParams,
               detection: DetectionModel | None, r_pred: np.ndarray | None, pd_of):
    """Steps 3-5 of one ICP-DA-LC step with the vehicles' means ``a_mean``: eta of (13) (class-gated), BPA-DA
    (14)-(17) and the MAP pairing (30). Returns ``(beliefs, row_idx, row_new, extra_row, extra_idx)``."""
    # (13) with the mean of b_i^(0) and the covariance of the own-sensor track: Gaussian loopy BP
    # and its time recursion leave b_i^(0) overconfident (position NEES ~100 measured on the
    # arterial), which gates out correct pairings (arterial TLR, 300 s: 1494 births and 1208
    # merges with the b^(0) covariance, 171 births and no merge with the own-sensor one).
    pv, pt, pr, w = association_weights(a_mean, gate_cov, t_mean, t_cov, owner, frame.v2f_z, frame.v2f_R, lc, detection)
    row_cls = frame.v2f_class
    if row_cls is not None:
        # Class gating (SUMO pedestrians): the classifier's label is known, so a row of class c is
        # only a candidate of tracks of class c (eta(alpha = l) = 0 otherwise).
        t_cls = predicted.klass if predicted.klass is not None else np.zeros(predicted.size, np.int8)
        w = np.where(t_cls[pt] == row_cls[pr], w, 0.0)
    # BPA-DA (association_beliefs) keeps the pairs of positive weight only: the others (outside the
    # gate, e.g. the clutter rows near a city's many tracks) are dropped before their P_D is computed.
    gated = w > 0
    if not gated.all():
        pv, pt, pr, w = pv[gated], pt[gated], pr[gated], w[gated]
    # (13)-(17); step 9: eta with the tracks' predicted existence r and the pairs' P_D.
    missed = None
    if r_pred is not None:
        w = w * r_pred[pt]
        missed = 1.0 - r_pred[pt] * pd_of(pv, pt)
    elif detection is not None:
        missed = 1.0 - pd_of(pv, pt)
    ab = association_beliefs(pv, pt, pr, w, frame.n_vehicles, owner.size, lc, missed)
    return (ab, *pairs_from_beliefs(ab, owner.size, lc))


def existence_after_association(
    r_pred: np.ndarray, ab: AssociationBeliefs | None, v_mean: np.ndarray, v_cov: np.ndarray, t_mean: np.ndarray,
    t_cov: np.ndarray, track_ids: np.ndarray, pd_of, lc: LcParams, in_range_only: bool,
) -> TrackExistence:
    """Step 9's update of the tracks' existence (:func:`existence_update`): the detections of the
    step's association beliefs ``ab`` and the expected detections that did not come, i.e. the
    candidate (vehicle, track) pairs with no gated row, with P_D ``pd_of(vehicles, tracks)``
    (``in_range_only``: without a sensor model, expected only within Rs of the vehicle's estimate).
    ``r_pred``: the predicted r of ``track_ids`` (the rows of ``t_mean``). Shared by ICP-DA-LC and
    ICP-DA-PF (which passes its particle moments)."""
    cv, ct = candidate_pairs(v_mean, v_cov, t_mean, t_cov, lc)
    pd_c = pd_of(cv, ct)
    if in_range_only:
        pd_c = np.where(np.hypot(*(v_mean[cv, :2] - t_mean[ct, :2]).T) <= lc.sensing_range_m, pd_c, 0.0)
    n_t = max(track_ids.size, 1)
    missed = pd_c > 0
    if ab is not None:  # candidates with a gated row are in ab already
        missed &= ~np.isin(cv * n_t + ct, ab.combo_vehicle * n_t + ab.combo_track)
    pd_combo = pd_of(ab.combo_vehicle, ab.combo_track) if ab is not None else np.empty(0)
    return TrackExistence(track_ids.copy(), existence_update(r_pred, ab, pd_combo, ct[missed], pd_c[missed]))


def own_consistency_reset(
    mean: np.ndarray, cov: np.ndarray, own_mean: np.ndarray, own_cov: np.ndarray, gate_probability: float,
    kept: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 10: vehicles whose cooperative position is outside the ``gate_probability`` chi-square
    gate (2 dof) of their own-sensor track, d^T P_own^-1 d with d = m - m_own (positions), take the
    own-sensor belief. The own-sensor track (GNSS + inertial) carries no feature evidence, so a
    vehicle pulled away by a wrong pairing (a false detection next to a landmark) and made
    overconfident by it returns to what its own sensors support. ``kept`` (N,) bool or None: vehicles whose
    cooperative position the map supports better than the own track's (``reset_map_margin``) are not reset.
    Returns (mean, cov, reset mask)."""
    d = mean[:, :2] - own_mean[:, :2]
    d2 = np.einsum("ni,ni->n", d, np.linalg.solve(own_cov[:, :2, :2], d[..., None])[..., 0])
    reset = d2 > chi2_ppf(gate_probability, 2)
    if kept is not None:
        reset &= ~kept
    if not reset.any():
        return mean, cov, reset
    mean, cov = mean.copy(), cov.copy()
    mean[reset], cov[reset] = own_mean[reset], own_cov[reset]
    return mean, cov, reset


@dataclass
class IcpDaLc:
    """Stateful ICP-DA-LC: ``step(frame)`` reads only the measurements."""

    params: IcpParams = field(default_factory=IcpParams)
    lc: LcParams = field(default_factory=LcParams)
    name: str = ICP_DA_LC.name
    state: IcpState = field(default_factory=IcpState)
    next_id: int = 0
    last: LcStepInfo | None = None
    # The vehicles' sensors (field of view, range, detection profile), for a P_D per (vehicle,
    # track); None: lc.detection_probability everywhere in range.
    detection: DetectionModel | None = None
    fusion: CoopFusion | None = None  # [fusion] (coloc.methods.coop_fusion); None: the paper's BPA-L

    def step(self, frame: Frame) -> StepEstimate:
        existence = self.last.existence if self.last is not None else None
        n_rows = frame.v2f_z.shape[0]
        frame, kept = without_vehicle_rows(frame)  # vehicle-class rows are not landmarks (coloc.core.vehicle_rows)
        self.state, self.next_id, self.last = icp_da_lc_step(
            self.state, self.next_id, frame, self.params, self.lc, existence, self.detection, self.fusion
        )
        est = self.state.estimate(expand_rows(self.last.row_track, kept, n_rows), self.params)
        if self.last.existence is None:
            return est
        # Only confirmed tracks are features of the estimate (step 9).
        keep = self.last.existence.confirmed(est.feature_track_ids, self.lc.confirm_existence)
        return replace(est, feature_mean=est.feature_mean[keep], feature_cov=est.feature_cov[keep],
                       feature_track_ids=est.feature_track_ids[keep])
