"""Relocalization of a lost vehicle against ICP-DA-LC's confirmed tracks (``[lc] relocalize_radius_m``, off by default;
:mod:`coloc.methods.icp_da_lc`, step 5b).

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

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["map_support", "relocalization_offsets"]


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
    ask = lost if partial is None or min_gain <= 0 else lost | partial
    if track_xy.shape[0] == 0 or not ask.any():
        return offsets
    tree = cKDTree(track_xy)
    owner = np.asarray(owner, dtype=np.int64)
    # A few lost vehicles per step (about 3 % of vehicle-steps): one small voting problem each.
    for i in np.flatnonzero(ask):
        rows = np.flatnonzero(owner == i)
        if rows.size < min_support:
            continue
        implied = v_mean[i, :2] + z[rows, :2]
        need = min_support
        if not lost[i]:  # partly on the map: the vote must beat the vehicle's own mean by min_gain rows
            d0, i0 = tree.query(implied, distance_upper_bound=tolerance_m)
            need = max(min_support, np.unique(i0[np.isfinite(d0)]).size + min_gain)
            if rows.size < need:
                continue
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
        if best < need:
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
