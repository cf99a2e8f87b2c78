"""Feature tracks shared over V2V, kept as latest messages per vehicle (:class:`FeatureStore`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from coloc.core.models import feature_noise_cov, symmetrize
from coloc.inference.gaussian import from_information, to_information
from coloc.inference.params import CLASS_PEDESTRIAN, IcpParams
from coloc.kernels import icp_fused
from coloc.kernels.icp import predict_no_input_kernel, scatter_add
from coloc.kernels.icp_fused import (
    lookup_kernel,
    message_round_trip,
    pair_member_table,
    predict_store_kernel,
    record_kernel,
    track_information_kernel,
    track_moments_kernel,
)

# ----------------------------------------------------------------------------- feature tracks


def feature_track_q(mean: np.ndarray, dt: float, params: IcpParams, klass: np.ndarray | None = None) -> np.ndarray:
    """Q_F of model (2) for tracks with these means, isotropic below the heading speed.

    ``klass`` (T,): the tracks' classes (None: every track static). Static landmarks use
    ``feature_sigma_par`` / ``feature_sigma_perp``; pedestrians ``pedestrian_sigma_par`` with
    sv_perp = sv_par / 2 (Brambilla et al. Sec. V-B's moving-feature noise)."""
    v = np.array(mean[:, 2:], dtype=float)
    slow = np.hypot(v[:, 0], v[:, 1]) < params.feature_heading_min_speed
    v[slow] = 0.0
    q = _feature_noise_cov_rows(v, slow, dt, params.feature_sigma_par, params.feature_sigma_perp_value)
    if klass is not None:
        ped = np.asarray(klass) == CLASS_PEDESTRIAN
        if ped.any():
            s = params.pedestrian_sigma_par
            q[ped] = feature_noise_cov(v[ped], dt, s, s / 2)
    return q


_STILL_Q: dict[tuple[float, float, float], np.ndarray] = {}


def _feature_noise_cov_rows(v: np.ndarray, slow: np.ndarray, dt: float, s_par: float, s_perp: float) -> np.ndarray:
    """``feature_noise_cov(v, dt, s_par, s_perp)``. It is computed row by row (elementwise operations
    and one matrix product per row), and a row with zero velocity (``slow``: set to 0 by the caller)
    gets the isotropic Q_F whatever its heading: on the fused path those rows take that row as
    feature_noise_cov computes it for one still row (kept per (dt, s_par, s_perp)), the others are
    computed as they are."""
    if not icp_fused.FUSED or not slow.any():
        return feature_noise_cov(v, dt, s_par, s_perp)
    key = (float(dt), float(s_par), float(s_perp))
    still_q = _STILL_Q.get(key)
    if still_q is None:
        if len(_STILL_Q) > 64:
            _STILL_Q.clear()
        still_q = _STILL_Q[key] = feature_noise_cov(np.zeros((1, 2)), dt, s_par, s_perp)[0]
    q = np.empty((v.shape[0], 4, 4))
    q[slow] = still_q
    if not slow.all():
        q[~slow] = feature_noise_cov(v[~slow], dt, s_par, s_perp)
    return q


def birth_information(params: IcpParams) -> np.ndarray:
    """Information (4, 4) of a newborn track: uniform position; velocity N(0, s^2 I) if s is set."""
    lam = np.zeros((4, 4))
    s = params.feature_velocity_prior_sigma
    if s:  # None or 0: uniform
        lam[2, 2] = lam[3, 3] = 1.0 / (s * s)
    return lam


def class_birth_information(params: IcpParams, klass: np.ndarray | None, k: int) -> np.ndarray:
    """(k, 4, 4) birth information of tracks of classes ``klass`` (None: all static).

    A pedestrian track is born with the paper's uniform belief (no velocity prior: it walks at
    ~1.3 m/s in an unknown direction); a static one with :func:`birth_information`."""
    lam = np.broadcast_to(birth_information(params), (k, 4, 4)).copy()
    if klass is not None:
        lam[np.asarray(klass) == CLASS_PEDESTRIAN] = 0.0
    return lam


#: Process-wide integer code of every vehicle id seen (by its string form, as before): pair keys
#: become integer arithmetic instead of a sort of Python strings at every call.
_VEHICLE_CODES: dict[str, int] = {}


def vehicle_codes(vehicles) -> np.ndarray:
    """Process-wide integer code of each vehicle id (equal iff the id strings are equal)."""
    reg = _VEHICLE_CODES
    return np.fromiter(
        (reg.setdefault(v if type(v) is str else str(v), len(reg)) for v in vehicles), dtype=np.int64,
        count=len(vehicles),
    )


def _pair_keys(tracks_a, vehicles_a, tracks_b, vehicles_b, codes_a=None) -> tuple[np.ndarray, np.ndarray]:
    """Integer keys of (track, vehicle) pairs of two lists, comparable with each other
    (equal iff same track id and same vehicle id string)."""
    ca = vehicle_codes(vehicles_a) if codes_a is None else codes_a
    cb = vehicle_codes(vehicles_b)
    ka = np.asarray(tracks_a, dtype=np.int64) * (1 << 32) + ca
    kb = np.asarray(tracks_b, dtype=np.int64) * (1 << 32) + cb
    return ka, kb


@dataclass(frozen=True)
class FeatureStore:
    """Feature tracks shared over V2V, kept as *latest messages per vehicle*.

    The belief of track k is the product of
      * the birth prior (:func:`birth_information`),
      * a folded part: messages of vehicles that stopped observing k more than
        ``message_memory_s`` ago, multiplied into one Gaussian (info form),
      * the latest vehicle -> feature message of every vehicle that observed k
        recently (moment form, one per (track, vehicle)): by default (19)
        built on the vehicle's own-sensor belief alone, see
        ``IcpParams.feature_message``.
    A vehicle observing k again *replaces* its previous message instead of
    multiplying a new one in. Its own-sensor belief, from which the message is
    built, already contains all its earlier evidence (see
    :func:`bpa_localization`), so replacing avoids counting one vehicle's GNSS
    history once per step (the time-correlated double counting that otherwise
    makes tracks arbitrarily overconfident). Evidence of *different* vehicles
    (independent GNSS errors) accumulates. The paper's (20) treats every step
    anew; this is our documented choice for carrying tracks between steps.

    Messages and the folded part are predicted by model (2) separately, each
    with the track's Q_F (conservative for moving features: the noise enters
    every factor, not once; exact for static ones in the limit Q_F -> 0).
    """

    ids: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    last_seen: np.ndarray = field(default_factory=lambda: np.empty(0))
    folded_lam: np.ndarray = field(default_factory=lambda: np.empty((0, 4, 4)))
    folded_eta: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))
    msg_track: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    msg_vehicle: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=object))
    msg_mean: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))
    msg_cov: np.ndarray = field(default_factory=lambda: np.empty((0, 4, 4)))
    msg_time: np.ndarray = field(default_factory=lambda: np.empty(0))
    # (T,) int8 class of each track (CLASS_STATIC / CLASS_PEDESTRIAN), from the V2F row that started
    # it; None while no frame carried classes (every track static: today's model (2) path).
    klass: np.ndarray | None = None

    @property
    def size(self) -> int:
        return int(self.ids.size)

    def lookup(self, feature_ids: np.ndarray) -> np.ndarray:
        """Row of each id in the store (ids are sorted), -1 where absent."""
        feature_ids = np.asarray(feature_ids, dtype=np.int64)
        if icp_fused.FUSED:
            return lookup_kernel(self.ids, np.ascontiguousarray(feature_ids))
        if self.ids.size == 0:
            return np.full(feature_ids.size, -1, dtype=np.int64)
        pos = np.minimum(np.searchsorted(self.ids, feature_ids), self.ids.size - 1)
        return np.where(self.ids[pos] == feature_ids, pos, -1)

    @cached_property
    def _message_information(self) -> tuple[np.ndarray, np.ndarray]:
        """(Lambda, eta) of every stored message, computed once per store (the store is immutable)."""
        return to_information(self.msg_mean, self.msg_cov)

    def information(self, params: IcpParams, exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(Lambda, eta) of every track: birth x folded x messages (those not excluded)."""
        if icp_fused.FUSED:  # one numba pass, same operations; the full product is kept per store and params
            cache = self.__dict__.setdefault("_information_cache", {})
            if exclude is None and params in cache:
                return tuple(a.copy() for a in cache[params])
            out = track_information_kernel(*self._information_args(params, exclude))
            if exclude is None:
                cache[params] = tuple(a.copy() for a in out)
            return out
        if self.klass is None:
            lam = self.folded_lam + birth_information(params)
        else:
            lam = self.folded_lam + class_birth_information(params, self.klass, self.ids.size)
        eta = self.folded_eta.copy()
        use = np.ones(self.msg_track.size, bool) if exclude is None else ~exclude
        if use.any():
            ml, me = self._message_information
            rows = self.lookup(self.msg_track[use])
            scatter_add(lam, rows, ml[use])
            scatter_add(eta, rows, me[use])
        return symmetrize(lam), eta

    def _information_args(self, params: IcpParams, exclude: np.ndarray | None):
        """The arguments of :func:`coloc.kernels.icp_fused.track_information_kernel`."""
        birth = (birth_information(params)[None] if self.klass is None
                 else class_birth_information(params, self.klass, self.ids.size))
        use = np.ones(self.msg_track.size, bool) if exclude is None else ~exclude
        ml, me = self._message_information
        return self.folded_lam, self.folded_eta, birth, self.ids, self.msg_track, ml, me, use

    def moments(self, params: IcpParams) -> tuple[np.ndarray, np.ndarray]:
        """Track means and covariances (every stored track has had at least one message).

        Cached per store and params (the store is immutable); treat the arrays as read-only."""
        last = self.__dict__.get("_moments_last")
        if last is not None and last[0] is params:  # the same params object: no hashing of the dataclass
            return last[1]
        cache = self.__dict__.setdefault("_moments_cache", {})
        if params not in cache:
            info = self.__dict__.get("_information_cache", {})
            if self.ids.size == 0:
                cache[params] = (np.empty((0, 4)), np.empty((0, 4, 4)))
            elif icp_fused.FUSED and params not in info:
                # the information and its moments in one call (track_moments_kernel: the same kernels)
                lam, eta, mean, cov = track_moments_kernel(*self._information_args(params, None))
                self.__dict__.setdefault("_information_cache", {})[params] = (lam, eta)
                cache[params] = (mean, cov)
            else:
                cache[params] = from_information(*self.information(params))
        self.__dict__["_moments_last"] = (params, cache[params])
        return cache[params]

    def predict(self, dt: float, params: IcpParams, folded_drift: float = 0.0) -> "FeatureStore":
        """Eq. (12): every factor of every track predicted by model (2) (no input).

        ``folded_drift`` (m^2 per axis, this step): position noise added to Q_F of the folded part of every
        track only (the messages of vehicles that stopped observing it): the map's frame drifting by that
        much a step (:meth:`coloc.methods.coop_fusion.CoopFusion.map_drift`). 0: model (2) alone."""
        if self.ids.size == 0:
            return self
        mean, _ = self.moments(params)
        q = feature_track_q(mean, dt, params, self.klass)
        q_folded = q
        if folded_drift > 0.0:
            q_folded = q.copy()
            q_folded[:, 0, 0] += folded_drift
            q_folded[:, 1, 1] += folded_drift
        if icp_fused.FUSED:  # one numba pass, same operations (coloc.kernels.icp_fused.predict_store_kernel)
            folded_lam, folded_eta, msg_mean, msg_cov, msg_lam, msg_eta = predict_store_kernel(
                self.folded_lam, self.folded_eta, np.ascontiguousarray(q), np.ascontiguousarray(q_folded),
                self.lookup(self.msg_track),
                np.ascontiguousarray(self.msg_mean), np.ascontiguousarray(self.msg_cov), float(dt))
            out = dataclasses.replace(
                self, folded_lam=folded_lam, folded_eta=folded_eta, msg_mean=msg_mean, msg_cov=msg_cov
            )
            return out._with_codes(self._msg_codes)._with_message_information((msg_lam, msg_eta))
        folded_lam, folded_eta = self.folded_lam.copy(), self.folded_eta.copy()
        has = np.abs(folded_lam).sum(axis=(1, 2)) > 0
        if has.any():
            fm, fp = from_information(folded_lam[has], folded_eta[has])
            fm, fp = predict_no_input_kernel(fm, fp, np.ascontiguousarray(q_folded[has]), float(dt))
            folded_lam[has], folded_eta[has] = to_information(fm, fp)
        msg_mean, msg_cov = self.msg_mean, self.msg_cov
        if self.msg_track.size:
            rows = self.lookup(self.msg_track)
            msg_mean, msg_cov = predict_no_input_kernel(
                np.ascontiguousarray(msg_mean), np.ascontiguousarray(msg_cov), np.ascontiguousarray(q[rows]), float(dt)
            )
        out = dataclasses.replace(
            self, folded_lam=folded_lam, folded_eta=folded_eta, msg_mean=msg_mean, msg_cov=msg_cov
        )
        return out._with_codes(self._msg_codes)

    def _with_codes(self, codes: np.ndarray) -> "FeatureStore":
        """Seed the cached vehicle codes of the messages (same vehicles as ``codes`` describe)."""
        self.__dict__["_msg_codes"] = codes
        return self

    @cached_property
    def _msg_codes(self) -> np.ndarray:
        return vehicle_codes(self.msg_vehicle)

    def _replaced(self, row_feature: np.ndarray, row_vehicle: np.ndarray, row_codes=None) -> np.ndarray:
        """Mask over stored messages whose (track, vehicle) pair appears in the rows."""
        if row_codes is None:
            row_codes = vehicle_codes(row_vehicle)
        row_feature = np.asarray(row_feature, dtype=np.int64)
        # prior_information and record ask the same (predicted) store about the same rows: keep the last answer.
        last = self.__dict__.get("_replaced_last")
        if last is not None and np.array_equal(last[0], row_feature) and np.array_equal(last[1], row_codes):
            return last[2]
        if icp_fused.FUSED:  # the pairs marked in a table (coloc.kernels.icp_fused.pair_member_table), same mask
            mask = pair_member_table(np.ascontiguousarray(self.msg_track, dtype=np.int64),
                                     np.ascontiguousarray(self._msg_codes, dtype=np.int64), row_feature,
                                     np.ascontiguousarray(row_codes, dtype=np.int64))
        else:
            km = np.asarray(self.msg_track, dtype=np.int64) * (1 << 32) + self._msg_codes
            kr = row_feature * (1 << 32) + row_codes
            mask = np.isin(km, kr)
        self.__dict__["_replaced_last"] = (row_feature.copy(), np.array(row_codes, copy=True), mask)
        return mask

    def prior_information(
        self, feature_ids: np.ndarray, row_feature: np.ndarray, row_vehicle: np.ndarray, params: IcpParams,
        row_codes: np.ndarray | None = None,
        row_class: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """b_k^(0) of (12) for ``feature_ids``, without the messages the rows' vehicles will replace.

        ``row_feature``/``row_vehicle``: the (track id, vehicle id) of every used
        V2F row of this step. New ids get the birth prior only (of their first row's class,
        ``row_class``, when given: :func:`class_birth_information`). ``row_codes``:
        ``vehicle_codes(row_vehicle)`` if the caller has them.
        """
        k = len(feature_ids)
        if row_class is None:
            lam = np.broadcast_to(birth_information(params), (k, 4, 4)).copy()
        else:
            uniq, first = np.unique(np.asarray(row_feature, dtype=np.int64), return_index=True)
            pos = np.minimum(np.searchsorted(uniq, feature_ids), max(uniq.size - 1, 0))
            cls = np.asarray(row_class, dtype=np.int8)[first[pos]] if uniq.size else np.zeros(k, np.int8)
            lam = class_birth_information(params, cls, k)
        eta = np.zeros((k, 4))
        idx = self.lookup(feature_ids)
        have = idx >= 0
        if have.any():
            tl, te = self.information(params, exclude=self._replaced(row_feature, row_vehicle, row_codes))
            lam[have], eta[have] = tl[idx[have]], te[idx[have]]
        return lam, eta

    def record(
        self,
        row_feature: np.ndarray,
        row_vehicle: np.ndarray,
        msg_lam: np.ndarray,
        msg_eta: np.ndarray,
        t: float,
        params: IcpParams,
        row_codes: np.ndarray | None = None,
        row_class: np.ndarray | None = None,
    ) -> "FeatureStore":
        """Store this step's final messages (19), fold old ones, drop stale tracks.

        Each row's message replaces the previous message of its (track, vehicle)
        pair; new track ids are created; tracks observed now get last_seen = t.
        ``row_class`` (rows,): the class of each row; a new track takes the class of its first row
        (None, and a store without classes: no classes are kept).
        """
        row_feature = np.asarray(row_feature, dtype=np.int64)
        if row_codes is None:
            row_codes = vehicle_codes(row_vehicle)
        keep = ~self._replaced(row_feature, row_vehicle, row_codes)
        if icp_fused.FUSED:  # one numba pass, same operations (coloc.kernels.icp_fused.record_kernel)
            # the messages to moments and back (the kept information) in one call
            mm, mc, nl, ne = message_round_trip(np.ascontiguousarray(msg_lam, dtype=np.float64),
                                                np.ascontiguousarray(msg_eta, dtype=np.float64))
            return self._record_fused(row_feature, row_vehicle, row_codes, row_class, keep, mm, mc, nl, ne, float(t),
                                      params)
        mm, mc = from_information(msg_lam, msg_eta) if row_feature.size else (np.empty((0, 4)), np.empty((0, 4, 4)))
        new_ids = np.setdiff1d(np.unique(row_feature), self.ids)
        ids = np.concatenate([self.ids, new_ids])
        order = np.argsort(ids, kind="stable")
        ids = ids[order]
        last_seen = np.concatenate([self.last_seen, np.full(new_ids.size, float(t))])[order]
        last_seen[np.searchsorted(ids, np.unique(row_feature))] = float(t)
        folded_lam = np.concatenate([self.folded_lam, np.zeros((new_ids.size, 4, 4))])[order]
        folded_eta = np.concatenate([self.folded_eta, np.zeros((new_ids.size, 4))])[order]
        klass = None
        if row_class is not None or self.klass is not None:
            old_k = self.klass if self.klass is not None else np.zeros(self.ids.size, np.int8)
            new_k = np.zeros(new_ids.size, np.int8)
            if row_class is not None and new_ids.size:
                uniq, first = np.unique(row_feature, return_index=True)
                new_k = np.asarray(row_class, dtype=np.int8)[first[np.searchsorted(uniq, new_ids)]]
            klass = np.concatenate([old_k, new_k])[order]
        msg_track = np.concatenate([self.msg_track[keep], row_feature])
        msg_vehicle = np.concatenate([self.msg_vehicle[keep], np.asarray(row_vehicle, dtype=object)])
        msg_codes = np.concatenate([self._msg_codes[keep], row_codes])
        msg_mean = np.concatenate([self.msg_mean[keep], mm])
        msg_cov = np.concatenate([self.msg_cov[keep], mc])
        msg_time = np.concatenate([self.msg_time[keep], np.full(row_feature.size, float(t))])
        # Messages of vehicles that stopped observing a track are folded into it.
        old = msg_time < t - params.message_memory_s
        if old.any():
            ol, oe = to_information(msg_mean[old], msg_cov[old])
            rows = np.searchsorted(ids, msg_track[old])
            scatter_add(folded_lam, rows, ol)
            scatter_add(folded_eta, rows, oe)
            msg_track, msg_vehicle, msg_codes, msg_mean, msg_cov, msg_time = (
                a[~old] for a in (msg_track, msg_vehicle, msg_codes, msg_mean, msg_cov, msg_time)
            )
        # Tracks nobody observed for longer than feature_drop_after_s are dropped
        # (the paper's reset of an unobserved feature to a uniform belief).
        live = (t - last_seen) <= params.feature_drop_after_s
        keep_msg = np.isin(msg_track, ids[live])
        return FeatureStore(
            ids=ids[live],
            last_seen=last_seen[live],
            folded_lam=symmetrize(folded_lam[live]),
            folded_eta=folded_eta[live],
            msg_track=msg_track[keep_msg],
            msg_vehicle=msg_vehicle[keep_msg],
            msg_mean=msg_mean[keep_msg],
            msg_cov=msg_cov[keep_msg],
            msg_time=msg_time[keep_msg],
            klass=klass[live] if klass is not None else None,
        )._with_codes(msg_codes[keep_msg])

    def _record_fused(self, row_feature, row_vehicle, row_codes, row_class, keep, mm, mc, nl, ne, t: float,
                      params: IcpParams) -> "FeatureStore":
        """:meth:`record` by :func:`coloc.kernels.icp_fused.record_kernel` (the numpy code of
        :meth:`record` is the reference)."""
        # The information of the kept messages is what this store computed for them (row by row, the
        # same kernel), and the step's (nl, ne) = to_information(mm, mc): the kernel gathers both.
        ml, me = self._message_information
        (ids, last_seen, folded_lam, folded_eta, src, m_src, m_track, m_mean, m_cov, m_time, k_lam,
         k_eta) = record_kernel(
            self.ids, self.last_seen, self.folded_lam, self.folded_eta, self.msg_track, self.msg_mean, self.msg_cov,
            self.msg_time, keep, row_feature, np.ascontiguousarray(mm), np.ascontiguousarray(mc), t,
            t - params.message_memory_s, float(params.feature_drop_after_s), np.ascontiguousarray(ml),
            np.ascontiguousarray(me), np.ascontiguousarray(nl), np.ascontiguousarray(ne),
        )
        klass = None
        if row_class is not None or self.klass is not None:
            old_k = self.klass if self.klass is not None else np.zeros(self.ids.size, np.int8)
            new_row = np.maximum(-1 - src, 0)
            new_k = (np.asarray(row_class, dtype=np.int8)[new_row] if row_class is not None and row_feature.size
                     else np.zeros(src.size, np.int8))
            klass = np.where(src >= 0, old_k[np.maximum(src, 0)] if old_k.size else 0, new_k).astype(np.int8)
        msg_vehicle = np.concatenate([self.msg_vehicle, np.asarray(row_vehicle, dtype=object)])[m_src]
        codes = np.concatenate([self._msg_codes, np.asarray(row_codes, dtype=np.int64)])[m_src]
        info = (k_lam, k_eta)
        return FeatureStore(
            ids=ids, last_seen=last_seen, folded_lam=folded_lam, folded_eta=folded_eta, msg_track=m_track,
            msg_vehicle=msg_vehicle, msg_mean=m_mean, msg_cov=m_cov, msg_time=m_time, klass=klass,
        )._with_codes(codes)._with_message_information(info)

    def _with_message_information(self, info) -> "FeatureStore":
        """Seed :attr:`_message_information` (the messages' (Lambda, eta), as to_information gives them)."""
        self.__dict__["_message_information"] = info
        return self

    def _subset_information(self, keep: np.ndarray):
        """The messages' information restricted to ``keep`` when already computed (fused path), else None."""
        info = self.__dict__.get("_message_information")
        if not icp_fused.FUSED or info is None:
            return None
        return info[0][keep], info[1][keep]

    def _seeded(self, info) -> "FeatureStore":
        return self if info is None else self._with_message_information(info)

    def merge(self, absorbed: np.ndarray, into: np.ndarray) -> "FeatureStore":
        """Merge track ``absorbed[j]`` into track ``into[j]`` (ids; every absorbed id distinct, not a target).

        The merged track keeps the target id; folded parts multiply; of two
        messages of the same vehicle the more recent one is kept (the older
        is subsumed by it, as in :meth:`record`); last_seen is the later one.
        """
        absorbed = np.asarray(absorbed, dtype=np.int64)
        into = np.asarray(into, dtype=np.int64)
        if absorbed.size == 0:
            return self
        ra, ri = self.lookup(absorbed), self.lookup(into)
        if (ra < 0).any() or (ri < 0).any() or np.isin(into, absorbed).any():
            raise ValueError("merge: unknown track id, or a track both absorbed and absorbing")
        folded_lam, folded_eta, last_seen = self.folded_lam.copy(), self.folded_eta.copy(), self.last_seen.copy()
        scatter_add(folded_lam, ri, folded_lam[ra])
        scatter_add(folded_eta, ri, folded_eta[ra])
        np.maximum.at(last_seen, ri, last_seen[ra])
        msg_track = self.msg_track.copy()
        hit = self.lookup(msg_track)
        remap = np.arange(self.ids.size)
        remap[ra] = ri
        msg_track = self.ids[remap[hit]]
        # One message per (track, vehicle): keep the latest (stable order breaks ties).
        key, _ = _pair_keys(msg_track, self.msg_vehicle, np.empty(0, np.int64), np.empty(0, dtype=object), self._msg_codes)
        order = np.lexsort((-self.msg_time, key))
        first = np.ones(order.size, bool)
        first[1:] = key[order][1:] != key[order][:-1]
        keep = np.sort(order[first])
        live = np.ones(self.ids.size, bool)
        live[ra] = False
        return FeatureStore(
            ids=self.ids[live],
            last_seen=last_seen[live],
            folded_lam=symmetrize(folded_lam[live]),
            folded_eta=folded_eta[live],
            msg_track=msg_track[keep],
            msg_vehicle=self.msg_vehicle[keep],
            msg_mean=self.msg_mean[keep],
            msg_cov=self.msg_cov[keep],
            msg_time=self.msg_time[keep],
            klass=self.klass[live] if self.klass is not None else None,
        )._with_codes(self._msg_codes[keep])._seeded(self._subset_information(keep))

    def drop(self, track_ids: np.ndarray) -> "FeatureStore":
        """The store without the tracks ``track_ids`` (ids not in the store are ignored)."""
        gone = np.isin(self.ids, np.asarray(track_ids, dtype=np.int64))
        if not gone.any():
            return self
        keep_msg = ~np.isin(self.msg_track, self.ids[gone])
        return FeatureStore(
            ids=self.ids[~gone],
            last_seen=self.last_seen[~gone],
            folded_lam=self.folded_lam[~gone],
            folded_eta=self.folded_eta[~gone],
            msg_track=self.msg_track[keep_msg],
            msg_vehicle=self.msg_vehicle[keep_msg],
            msg_mean=self.msg_mean[keep_msg],
            msg_cov=self.msg_cov[keep_msg],
            msg_time=self.msg_time[keep_msg],
            klass=self.klass[~gone] if self.klass is not None else None,
        )._with_codes(self._msg_codes[keep_msg])._seeded(self._subset_information(keep_msg))

    def drop_stale(self, t: float, params: IcpParams) -> "FeatureStore":
        """Drop tracks nobody observed for longer than ``feature_drop_after_s`` (no new messages)."""
        empty = np.empty(0, dtype=np.int64)
        return self.record(empty, np.empty(0, dtype=object), np.empty((0, 4, 4)), np.empty((0, 4)), t, params)


