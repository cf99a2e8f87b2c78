"""Relocalization of a lost vehicle against ICP-DA-LC's confirmed tracks (``[lc] relocalize_radius_m``, off by default;
:mod:`coloc.methods.icp_da_lc`, step 5b), and the map's support of a vehicle's position that steps 5a
(``fix_map_margin``, ``anchor_margin``: the map-anchored position at the end) and 10 (``reset_map_margin``) decide on.

A vehicle is *lost* at a step when it has at least ``relocalize_min_support`` rows and none of them was paired with a
confirmed track: its belief b_i^(0) (mean and covariance) no longer overlaps the map, so every row falls outside its
gate, the rows start tentative tracks and the vehicle gets no feature evidence (the failure the tuning-seed diagnosis
of docs/validation/realistic_sensing.md, 2026-11-28, traces most of ICP-DA-LC's excess error over known association
to). Its rows still carry the map's geometry: the translation that puts the most of their implied feature positions
m_i + z_l onto confirmed tracks is found by consensus voting over the candidate translations each (row, track) pair
proposes (hypothesise-and-verify as RANSAC, Fischler and Bolles, Commun. ACM 24(6), 1981; the translation-only
point-set registration of map-based relocalization). A translation is taken only if at least
``relocalize_min_support`` rows of the vehicle land within ``relocalize_tolerance_m`` of distinct confirmed tracks,
and it is unique: no other translation at least 2 tolerances away has the same support (a near-periodic landmark
layout, as the arterial's, proposes aliases that tie). Among those of maximal support the one nearest the prior
wins. The translation only moves the mean the association, births and existence see at this step; the vehicle's
belief is then updated by the feature evidence of the rows so paired (31), as any other vehicle's.

A vehicle can also be *partly* off the map (``relocalize_min_gain`` g > 0): some of its rows were paired with
confirmed tracks, but its mean, carried by a run of its receiver's fixes, puts most of its rows beside them, so
they start tentative tracks or are taken as clutter, and what is paired may be the wrong neighbour. The same vote is
asked of it, and its translation taken only when it puts at least g more rows on distinct confirmed tracks than the
zero translation does (the support of the vehicle's own mean, counted the same way), besides the conditions above.

Nothing here reads the truth: the vehicles' beliefs, their rows and the confirmed tracks' means.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

if TYPE_CHECKING:
    from coloc.core.frame import Frame
    from coloc.inference.params import LcParams

__all__ = ["MapRows", "anchored_mean", "fix_arbitrated_mean", "map_rows", "map_support", "predicted_anchor",
           "refreshed_anchor", "relocalization_offsets"]


def map_support(xy: np.ndarray, owner: np.ndarray, z: np.ndarray, track_xy: np.ndarray, tolerance_m: float,
                n_vehicles: int) -> np.ndarray:
    """(N,) the number of distinct confirmed tracks each vehicle's rows land within ``tolerance_m`` of when the
    vehicle is at ``xy`` (N, 2): the support of the zero translation in the vote above, for all vehicles at once.
    ``owner`` (O,), ``z`` (O, >= 2) the rows, ``track_xy`` (T, 2) the confirmed tracks' predicted positions."""
    owner = np.asarray(owner, dtype=np.int64)
    if track_xy.shape[0] == 0 or owner.size == 0:
        return np.zeros(n_vehicles, dtype=np.int64)
    dist, idx = cKDTree(track_xy).query(xy[owner, :2] + z[:, :2], distance_upper_bound=tolerance_m)
    hit = np.isfinite(dist)
    pairs = np.unique(np.stack([owner[hit], idx[hit]], 1), axis=0)  # (vehicle, track), each track once
    return np.bincount(pairs[:, 0], minlength=n_vehicles) if pairs.size else np.zeros(n_vehicles, dtype=np.int64)


def relocalization_offsets(
    v_mean: np.ndarray, owner: np.ndarray, z: np.ndarray, lost: np.ndarray, track_xy: np.ndarray,
    radius_m: float, tolerance_m: float, min_support: int, partial: np.ndarray | None = None, min_gain: int = 0,
) -> np.ndarray:
    """(N, 2) translation of each vehicle's position for the association; 0 for vehicles neither ``lost`` nor
    ``partial``, or for which no unique translation within ``radius_m`` reaches ``min_support`` rows (and, for a
    ``partial`` one, the zero translation's support + ``min_gain``) (module docstring).

    ``v_mean`` (N, >= 2) the vehicles' means, ``owner`` (O,) and ``z`` (O, >= 2) the rows (relative position
    in the net frame), ``lost`` (N,) bool, ``track_xy`` (T, 2) the confirmed tracks' predicted positions,
    ``partial`` (N,) bool or None: vehicles with rows on the map asked the vote too (``min_gain`` > 0).
    """
    offsets = np.zeros((v_mean.shape[0], 2))
    voting_partial = partial is not None and min_gain > 0
    ask = lost | partial if voting_partial else lost
    if track_xy.shape[0] == 0 or not ask.any():
        return offsets
    owner = np.asarray(owner, dtype=np.int64)
    # rows a translation needs: min_support; a vehicle partly on the map must also beat its own mean by min_gain
    need = np.full(v_mean.shape[0], min_support)
    if voting_partial:
        own = map_support(v_mean, owner, z, track_xy, tolerance_m, v_mean.shape[0])
        need = np.where(lost, min_support, np.maximum(min_support, own + min_gain))
    tree = cKDTree(track_xy)
    # A few lost vehicles per step (about 3 % of vehicle-steps): one small voting problem each.
    for i in np.flatnonzero(ask):
        rows = np.flatnonzero(owner == i)
        if rows.size < need[i]:
            continue
        implied = v_mean[i, :2] + z[rows, :2]
        near = tree.query_ball_point(implied, radius_m)
        cand = [track_xy[k] - implied[l] for l, ks in enumerate(near) for k in ks]
        if not cand:
            continue
        cand = np.asarray(cand)
        cand = cand[np.hypot(cand[:, 0], cand[:, 1]) <= radius_m]
        if cand.shape[0] == 0:
            continue
        # support of every candidate translation: the rows that land within the tolerance of a track, each
        # track counted once (one vehicle's rows are distinct features)
        moved = implied[None, :, :] + cand[:, None, :]  # (C, L, 2)
        dist, idx = tree.query(moved.reshape(-1, 2), distance_upper_bound=tolerance_m)
        hit = np.isfinite(dist).reshape(cand.shape[0], rows.size)
        idx = idx.reshape(cand.shape[0], rows.size)
        support = np.array([np.unique(idx[c][hit[c]]).size for c in range(cand.shape[0])])
        best = int(support.max())
        if best < need[i]:
            continue
        top = np.flatnonzero(support == best)
        norm = np.hypot(cand[top, 0], cand[top, 1])
        pick = top[int(np.argmin(norm))]
        rivals = cand[top] - cand[pick]
        if (np.hypot(rivals[:, 0], rivals[:, 1]) >= 2.0 * tolerance_m).any():
            continue  # an alias with the same support: ambiguous, leave the vehicle alone
        # refine: the mean residual of the supporting rows
        m = hit[pick]
        offsets[i] = cand[pick] + np.mean(track_xy[idx[pick][m]] - moved[pick][m], axis=0)
    return offsets


@dataclass(frozen=True)
class MapRows:
    """One step's static rows and the confirmed tracks that can anchor a vehicle, for :func:`map_support` (steps
    5a, 5b and 10). ``confirmed`` (T,) the predicted tracks confirmed at this step (all without
    ``lc.track_existence``); ``track_xy`` (A, 2) those of them that can anchor a position (with classes, static
    landmarks only); ``owner`` and ``z`` the rows of the static class (all rows without classes)."""

    confirmed: np.ndarray
    track_xy: np.ndarray
    owner: np.ndarray
    z: np.ndarray
    tolerance_m: float
    n_vehicles: int

    def support(self, xy: np.ndarray) -> np.ndarray:
        """(N,) :func:`map_support` of the vehicles at ``xy``."""
        return map_support(xy, self.owner, self.z, self.track_xy, self.tolerance_m, self.n_vehicles)


def map_rows(predicted, r_pred, t_mean: np.ndarray, frame: "Frame", owner: np.ndarray, lc: "LcParams") -> MapRows:
    """The step's :class:`MapRows` from the predicted tracks (``t_mean``, existence ``r_pred``, classes) and the
    frame's rows."""
    confirmed = np.ones(predicted.size, dtype=bool) if r_pred is None else r_pred >= lc.confirm_existence
    row_cls = frame.v2f_class
    static = np.ones(owner.size, dtype=bool) if row_cls is None else row_cls == 0
    anchor = confirmed & (predicted.klass == 0) if row_cls is not None and predicted.klass is not None else confirmed
    return MapRows(confirmed, t_mean[anchor, :2], owner[static], frame.v2f_z[static], lc.relocalize_tolerance_m,
                   frame.n_vehicles)


def fix_arbitrated_mean(b0_mean, state, frame: "Frame", match, accel, rows: MapRows, margin: int) -> np.ndarray:
    """Step 5a (``fix_map_margin`` m > 0): b^(0)'s mean, except for vehicles whose motion prediction (the previous
    belief's position advanced by its velocity and this step's input, before this step's fix) puts at least m
    more static rows on distinct confirmed tracks than b^(0)'s mean: they are associated at the prediction.
    A reflected fix that moves b^(0) metres off would otherwise take the vehicle's rows out of their gates
    before its landmarks could outweigh it. Only the association, births and existence see the moved mean."""
    carried = (match >= 0) & ~np.asarray(frame.entered, dtype=bool)
    if not carried.any():
        return b0_mean
    prev = state.mean[match[carried]]
    u = np.asarray(frame.accel if accel is None else accel, dtype=float)[carried]
    u = np.where(np.isfinite(u), u, 0.0)
    pred_xy = b0_mean[:, :2].copy()
    pred_xy[carried] = prev[:, :2] + frame.dt * prev[:, 2:4] + 0.5 * frame.dt ** 2 * u  # model (1)'s mean
    use = carried & (rows.support(pred_xy) >= rows.support(b0_mean) + margin)
    if not use.any():
        return b0_mean
    a_mean = b0_mean.copy()
    a_mean[use, :2] = pred_xy[use]
    return a_mean


# The map-anchored position (``[lc] anchor_margin``): a second candidate mean for the association that no fix moves.
# A receiver whose fix ramps metres off over seconds, under a report that does not know it, pulls b^(0) and with it
# the gates off the vehicle's landmarks, one step at a time (docs/validation/consistency.md, "ICP-DA-LC's association
# when the vehicle is off its landmarks"); the anchor stays where the map last placed the vehicle, carried by its
# velocity.
ANCHOR_REFRESH_SUPPORT = 2  # rows on distinct confirmed tracks that make a posterior the new anchor (our choice)


def predicted_anchor(anchor: np.ndarray | None, match: np.ndarray, frame: "Frame", b0_mean: np.ndarray) -> np.ndarray:
    """(N, 2) the anchors at this step: the previous step's, moved by b^(0)'s velocity over ``frame.dt``; b^(0)'s
    position for a vehicle without one (entering, or the first step)."""
    out = b0_mean[:, :2].copy()
    if anchor is None:
        return out
    carried = (match >= 0) & ~np.asarray(frame.entered, dtype=bool)
    out[carried] = anchor[match[carried]] + frame.dt * b0_mean[carried, 2:4]
    return out


def anchored_mean(a_mean: np.ndarray, anchor_xy: np.ndarray, rows: MapRows, margin: int) -> np.ndarray:
    """``a_mean`` with the position of every vehicle whose anchor puts at least max(2, its support at ``a_mean`` +
    ``margin``) static rows on distinct confirmed tracks replaced by the anchor."""
    use = rows.support(anchor_xy) >= np.maximum(ANCHOR_REFRESH_SUPPORT, rows.support(a_mean) + margin)
    if not use.any():
        return a_mean
    out = a_mean.copy()
    out[use, :2] = anchor_xy[use]
    return out


def refreshed_anchor(anchor_xy: np.ndarray, v_mean: np.ndarray, rows: MapRows) -> np.ndarray:
    """(N, 2) the anchors carried to the next step: the posterior's position where its static rows land on at least
    ``ANCHOR_REFRESH_SUPPORT`` distinct confirmed tracks, the anchor otherwise."""
    return np.where((rows.support(v_mean) >= ANCHOR_REFRESH_SUPPORT)[:, None], v_mean[:, :2], anchor_xy)
