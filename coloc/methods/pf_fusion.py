"""Consistent fusion in ``icp_da_pf`` (config ``[fusion] rule = "split_ci"``, with ``[gnss_model]``'s receiver
model): the PF's vehicle localization by the split covariance intersection of :mod:`coloc.methods.coop_fusion`.

The rule. The particle BPA-L of :mod:`coloc.inference.particle_bp` multiplies a vehicle's particle weights by
the feature messages of every step; like the Gaussian BPA-L it counts the same vehicles' histories again at
every step (the feature messages carry the other vehicles' GNSS errors, which are the same over consecutive
steps), so its weights are overconfident in the same way (:mod:`coloc.inference.split_ci`, module docstring).
A weighting that stays consistent under unknown correlation is covariance intersection; for densities it is
the weighted geometric mean p1^w p2^(1-w) (Hurley, "An information theoretic justification for covariance
intersection and its generalization", FUSION 2002), which on particles needs the density of the predicted
belief at its own particles (a kernel estimate) and has no split (independent / dependent) form. Here the
vehicle belief is instead moment-matched to a Gaussian, which is what split CI needs:

* each vehicle carries the two 6-D filters [p, v, b] of :mod:`coloc.methods.coop_fusion` (own-sensor track
  with the receiver's Gauss-Markov bias and fault exclusion, and the cooperative belief with its independent
  part), predicted and updated by the fix with :func:`coloc.methods.coop_fusion.split_prior`;
* the PF's particle machinery stays for the features and the association: each step the vehicle sets are
  drawn from the two filters' kinematic marginals (the own-sensor set from the own track, the belief set from
  the cooperative prior b^(0)), equally weighted; eta (25), BPA-DA, births, existence and the particle BPA-L
  that updates the tracks run on them unchanged (the association gates on b^(0)'s consistent covariance, as
  ICP-DA-LC under ``[fusion]``);
* the vehicle's belief is b^(0) fused by split CI (:func:`coloc.methods.coop_fusion.split_localization`) with
  the step's feature evidence of the rows the association paired with confirmed tracks (the row's track of
  largest belief; rows of no track or of a tentative track do not localize). The evidence is this step's other
  observers' own-sensor messages (with ``feature_ci`` their equal-weight intersection,
  :func:`coloc.inference.split_ci.feature_evidence`); a track's b_k^(0) enters only as the birth information
  (uniform position, the velocity prior), i.e. the stored messages of earlier observers are left out, which
  keeps the bound (leaving information out never makes the fused covariance smaller than the error's). Taking
  b_k^(0) as the moments of the track's particle set without this step's observers' messages was tried: after
  regularized resampling and the division by the stored messages moved by the prediction, those moments claim
  more than the stored information, and the fused covariance fell below the centralized joint KF's on small
  scenes (smallest eigenvalue of the difference -0.24 m^2; tests/coloc/test_pf_split_ci.py checks the order).

With ``[lc] own_consistency_gate`` the fused belief then takes ICP-DA-LC's step 10
(:func:`coloc.methods.icp_da_lc.own_consistency_reset`): a vehicle whose position leaves that chi-square gate of
its own-sensor track takes the track (mean, covariance and the carried filters); not the known-DA variant.

The PF's particle weights of the vehicles (27) are then not used for the estimate. No parameter is tuned.
Nothing here reads the world: the receiver's reported covariance, the V2F rows and the config values.
"""

from __future__ import annotations

import math

import numpy as np

from coloc.core.frame import Frame
from coloc.inference.feature_store import birth_information
from coloc.inference.params import IcpParams
from coloc.inference.particles import entity_rng, sample_gaussian
from coloc.methods.coop_fusion import SplitPrior, SplitState, split_localization

__all__ = ["gaussian_sets", "track_prior_information", "pf_split_localization"]


def gaussian_sets(mean: np.ndarray, cov: np.ndarray, ents: np.ndarray, step: int, seed: int, purpose: str,
                  jv: int) -> tuple[np.ndarray, np.ndarray]:
    """Equally weighted sets of ``jv`` particles drawn from N(mean_i, cov_i) (4-D) per vehicle, each from
    its synchronized generator (``purpose``, the vehicle's entity, the step). Returns (particles (n, jv, 4),
    log-weights (n, jv))."""
    n = mean.shape[0]
    out = np.empty((n, jv, 4))
    for i in range(n):
        out[i] = sample_gaussian(mean[i], cov[i], jv, entity_rng(seed, purpose, ents[i], step))
    return out, np.full((n, jv), -math.log(jv))


def track_prior_information(feature_ids: np.ndarray, params: IcpParams) -> tuple[np.ndarray, np.ndarray]:
    """b_k^(0) of the ``feature_ids`` as split CI takes it here (module docstring): the birth information
    (uniform position; the velocity prior of ``IcpParams`` if set), in information form."""
    k = feature_ids.size
    return np.broadcast_to(birth_information(params), (k, 4, 4)).copy(), np.zeros((k, 4))


def pf_split_localization(prior: SplitPrior, frame: Frame, owner: np.ndarray, row_track: np.ndarray, z: np.ndarray,
                          r: np.ndarray, params: IcpParams, feature_ci: bool) -> tuple[np.ndarray, np.ndarray, SplitState]:
    """The vehicles' beliefs of the step: b^(0) fused by split CI with the evidence of the rows paired with
    a track (``row_track`` stable ids, -1: not used). Returns the kinematic (mean (n, 4), cov (n, 4, 4)) and
    the 6-D filters to carry."""
    row_track = np.asarray(row_track, dtype=np.int64)
    fids = np.unique(row_track[row_track >= 0])
    lam0, eta0 = track_prior_information(fids, params)
    res, split = split_localization(prior, owner, row_track, z, r, frame.neighbors, lam0, eta0, params,
                                    v2x=frame.v2x, feature_ci=feature_ci)
    return res.mean, res.cov, split
