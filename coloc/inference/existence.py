"""Track existence for data association under clutter (used by ICP-DA-LC, step 9 of
:mod:`coloc.methods.icp_da_lc`), as in belief-propagation multitarget tracking (F. Meyer, T.
Kropfreiter, J. L. Williams, R. Lau, F. Hlawatsch, P. Braca, M. Z. Win, "Message passing algorithms
for scalable multitarget tracking", Proc. IEEE 106(2), 2018): every feature track carries the
probability r that it is a real object.

- :class:`TrackExistence`: r per track id, with the bookkeeping of merges and drops.
- :func:`existence_update`: r after one step's BPA-DA, from each vehicle's association beliefs
  (``ab`` is a :class:`coloc.methods.icp_da_lc.AssociationBeliefs`: ``combo_track``,
  ``combo_start``, ``belief``), the vehicles' evidence adding in log-odds.
- :func:`birth_existence`: r of a new track from the rows that started it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import expit, logit

__all__ = ["TrackExistence", "existence_update", "birth_existence"]


_R_CLIP = 1e-12  # existence probabilities are kept in [1e-12, 1 - 1e-12] (finite log-odds)


def _logit(r: np.ndarray) -> np.ndarray:
    return logit(np.clip(r, _R_CLIP, 1.0 - _R_CLIP))


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return np.clip(expit(x), _R_CLIP, 1.0 - _R_CLIP)


@dataclass(frozen=True)
class TrackExistence:
    """Existence probability r of every feature track (ICP-DA-LC step 9), over ``ids`` (sorted)."""

    ids: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    r: np.ndarray = field(default_factory=lambda: np.empty(0))

    def of(self, track_ids: np.ndarray) -> np.ndarray:
        """r of each id (0 for ids without a record)."""
        track_ids = np.asarray(track_ids, dtype=np.int64)
        if self.ids.size == 0:
            return np.zeros(track_ids.shape)
        pos = np.minimum(np.searchsorted(self.ids, track_ids), self.ids.size - 1)
        return np.where(self.ids[pos] == track_ids, self.r[pos], 0.0)

    def confirmed(self, track_ids: np.ndarray, threshold: float) -> np.ndarray:
        """Tracks that localize vehicles: r >= ``threshold`` (False for -1 and unknown ids)."""
        return self.of(track_ids) >= threshold

    def with_tracks(self, ids: np.ndarray, r: np.ndarray) -> "TrackExistence":
        """These tracks set to r (added or replaced); the result sorted by id."""
        ids = np.asarray(ids, dtype=np.int64)
        keep = ~np.isin(self.ids, ids)
        all_ids = np.concatenate([self.ids[keep], ids])
        order = np.argsort(all_ids, kind="stable")
        return TrackExistence(all_ids[order], np.concatenate([self.r[keep], np.asarray(r, float)])[order])

    def merged(self, absorbed: np.ndarray, into: np.ndarray) -> "TrackExistence":
        """After :meth:`FeatureStore.merge`: the target keeps the larger r."""
        absorbed = np.asarray(absorbed, dtype=np.int64)
        if absorbed.size == 0:
            return self
        r_into = np.maximum(self.of(into), self.of(absorbed))
        keep = ~np.isin(self.ids, absorbed)
        return TrackExistence(self.ids[keep], self.r[keep]).with_tracks(into, r_into)

    def restricted(self, ids: np.ndarray) -> "TrackExistence":
        """Only the tracks ``ids`` (those the store holds)."""
        keep = np.isin(self.ids, ids)
        return TrackExistence(self.ids[keep], self.r[keep])


def existence_update(
    r_prior: np.ndarray, ab, pd_combo: np.ndarray, missed_track: np.ndarray, pd_missed: np.ndarray,
) -> np.ndarray:
    """Existence after this step's association (ICP-DA-LC step 9), per predicted track.

    ``r_prior`` (K,): predicted r of the tracks. ``ab``: BPA-DA beliefs of the combos (vehicle,
    track) with gated rows, solved with eta(alpha = 0) = 1 - r P_D and eta(alpha = l) scaled by r;
    ``pd_combo`` (C,): each combo's P_D. Vehicle i's problem gives P(k exists | z_i) = 1 - b_ik(0)
    (1 - q), with q = r (1 - P_D) / (1 - r P_D) the existence of a track that was not detected; a
    candidate track expected in i's view (``missed_track``, P_D ``pd_missed``) with no gated row
    at all has b_ik(0) = 1. The vehicles' problems are independent given existence, so their
    evidence adds in log-odds: logit r_post = logit r + sum_i [logit P(k exists | z_i) - logit r].
    """
    logit_r = _logit(r_prior)
    gain = np.zeros(r_prior.size)
    if ab is not None and ab.combo_track.size:
        k = ab.combo_track
        q = r_prior[k] * (1.0 - pd_combo) / (1.0 - r_prior[k] * pd_combo)
        b0 = ab.belief[ab.combo_start]
        np.add.at(gain, k, _logit(1.0 - b0 * (1.0 - q)) - logit_r[k])
    if missed_track.size:
        rk = r_prior[missed_track]
        q = rk * (1.0 - pd_missed) / (1.0 - rk * pd_missed)
        np.add.at(gain, missed_track, _logit(q) - logit_r[missed_track])
    return _sigmoid(logit_r + gain)


def birth_existence(share: np.ndarray, labels: np.ndarray, n_born: int) -> np.ndarray:
    """r of each new track: each of its rows is independent evidence that it is a feature, with
    probability ``share`` = mu_new f_new / (mu_new f_new + lambda_c f_c) (Meyer et al.'s birth), so
    the log-odds of the rows that started it add."""
    log_odds = np.zeros(n_born)
    np.add.at(log_odds, labels, _logit(share))
    return _sigmoid(log_odds)
