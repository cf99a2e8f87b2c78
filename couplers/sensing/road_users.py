"""Other road users and persistent false alarms in the simulated perception (opt-in, ``[perception]``
keys ``road_users``, ``persistent_clutter_per_km``, ``persistent_clutter_pd``, ``class_error``).

A real radar reports every object in view, not only the landmarks of the feature set:

* Other road users (``road_users = true``): every SUMO vehicle on the road (equipped or not) and, when
  the scenario has persons and ``[features] pedestrians`` is off (then they are features already),
  every SUMO person. A target inside a sensor's field of view whose sight line no other vehicle
  footprint (nor a building) crosses is detected with that sensor's P_D(d) and range noise
  (:mod:`couplers.sensing.perception`); a vehicle target never occludes its own sight line and an
  observer never sees itself. The reported point of a vehicle is the centre of its footprint
  (length x width behind the front bumper); its relative velocity is the true relative velocity +
  noise. Class: ``CLASS_VEHICLE`` (2) or ``CLASS_PEDESTRIAN`` (1).
* Persistent clutter (``persistent_clutter_per_km`` > 0): false-alarm sources tied to places (guard
  rails, poles, parked cars and multipath ghosts that are not in the feature set). Drawn once per run
  (:func:`persistent_clutter_sites`): a Poisson number of sites per km of road (each directed edge's
  rightmost vehicle lane), uniform along the lane, beside it (half the lane width plus U(0.5, 3) m to
  the right of the direction of travel). A site in view and not occluded is detected with the
  constant probability ``persistent_clutter_pd`` (one draw per (vehicle, site, scan), whichever sensors
  see it; the row's noise is that of the sensor of smallest sigma). Reported as static objects
  (``CLASS_STATIC``): to the classifier they look exactly like landmarks.
* Classifier error (``class_error``): each row's class (landmarks, clutter and the rows above) is
  replaced with that probability by one of the other two classes, uniformly. Default 0: an
  idealisation (a perfect object classifier; no per-class confusion matrix of a production radar
  was found to cite).

Truth (scoring only): ``Truth.v2f_kind`` per row, :data:`KIND_LANDMARK` .. :data:`KIND_PEDESTRIAN`;
``Truth.v2f_feature`` is -1 for every row that is not a feature (the known-association reference
drops those rows as it drops clutter).

Random streams, each its own (``effect_rng`` with tag :data:`ROAD_USER_STREAM_TAG`): "sites" (the
persistent sites), "detect", "noise", "class" and "shuffle" (the rows of the step, perception's and
these, shuffled again within each vehicle). The perception's own streams are drawn as before, so
switching these keys on keeps every landmark and clutter draw.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numba import njit

from couplers.sensing import streams
from couplers.sensing.occlusion import (OccluderIndex, _building_hits, _segments_occluded_by_buildings,
                                        _segments_occluded_by_buildings_shapely, _segments_occluded_by_vehicles,
                                        building_edges)
from couplers.sensing.perception import (_NO_BUILDINGS, _NO_CORNERS, Detections, _fov_params, effect_rng,
                                         sensor_boresights)
from couplers.sensing.perception_kernels import (CLASS_PEDESTRIAN, CLASS_STATIC, _distinct_lines, _fov_stage,
                                                _range_fraction_and_sigma, _sharper, _sight_lines, clear_of_vehicles,
                                                line_segments)
from couplers.sensing.rows import shuffle_within_owner
from couplers.sensing.streams import StreamHandles, stream

#: Class the classifier reports for a vehicle (``Frame.v2f_class``; 0 static, 1 pedestrian).
CLASS_VEHICLE = 2
N_CLASSES = 3

#: What a V2F row truly is (``Truth.v2f_kind``).
KIND_LANDMARK = 0
KIND_CLUTTER = 1
KIND_PERSISTENT_CLUTTER = 2
KIND_VEHICLE = 3
KIND_PEDESTRIAN = 4
KIND_NAMES = ("landmark", "clutter", "persistent_clutter", "vehicle", "pedestrian")

ROAD_USER_STREAM_TAG = 0x9E6


class RoadUserNoise:
    """The streams of this module (see the module docstring)."""

    STREAMS = ("sites", "detect", "noise", "class", "shuffle")

    def __init__(self, seed: int):
        for name in self.STREAMS:
            setattr(self, name, effect_rng(seed, ROAD_USER_STREAM_TAG, name))
        self.handles = StreamHandles(self, self.STREAMS)  # the same streams drawn in _targets_stage


def persistent_clutter_sites(lanes: list[tuple[np.ndarray, float]], per_km: float,
                             rng: np.random.Generator) -> np.ndarray:
    """(P, 2) places of the persistent false alarms: ``lanes`` (shape (n, 2), width) in a fixed order,
    Poisson(per_km * total km) sites, each on a lane chosen by length, uniform along it, offset to the
    right of its direction by width / 2 + U(0.5, 3) m."""
    shapes = [np.asarray(s, dtype=float).reshape(-1, 2) for s, _ in lanes]
    seg_len = [np.hypot(*np.diff(s, axis=0).T) if len(s) > 1 else np.zeros(0) for s in shapes]
    lengths = np.array([x.sum() for x in seg_len])
    total = float(lengths.sum())
    count = int(rng.poisson(per_km * total / 1000.0)) if total > 0 else 0
    if count == 0:
        return np.empty((0, 2))
    u_lane, u_along, u_off = rng.random(count), rng.random(count), rng.random(count)
    lane = np.minimum(np.searchsorted(np.cumsum(lengths) / total, u_lane, side="right"), len(lanes) - 1)
    out = np.empty((count, 2))
    for k in range(count):
        s, seg = shapes[lane[k]], seg_len[lane[k]]
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        a = u_along[k] * cum[-1]
        j = min(int(np.searchsorted(cum, a, side="right")) - 1, seg.size - 1)
        j = max(j, 0)
        d = (s[j + 1] - s[j]) / max(seg[j], 1e-12)
        p = s[j] + d * (a - cum[j])
        off = lanes[lane[k]][1] / 2.0 + 0.5 + 2.5 * u_off[k]
        out[k] = p + off * np.array([d[1], -d[0]])  # right of the direction of travel
    return out


def perceive_targets(*, x_true: np.ndarray, direction: np.ndarray, heading: np.ndarray, targets: np.ndarray,
                     target_pd: np.ndarray, target_occluder: np.ndarray, pair_owner: np.ndarray,
                     pair_target: np.ndarray, params, noise: RoadUserNoise,
                     occluder_corners: np.ndarray | None, observer_occluder: np.ndarray, buildings=None,
                     reference: bool = False, boresight: np.ndarray | None = None):
    """Detections of the targets (M, 4) (true states) by the vehicles ``x_true``: candidates of every
    sensor (the perception's field of view), sight lines cleared of every vehicle footprint but the
    observer's and the target's own (``target_occluder``, -1: none) and of buildings, detection with
    the sensor's P_D(d) or, where ``target_pd`` >= 0, once per (vehicle, target) with that probability;
    one row per detected pair (the detecting sensor of smallest sigma_p, ties: the first listed).
    Returns (owner, target, sensor, z (D, 4), sigma_p, sigma_v): rows in the order of the pairs. The field of
    view, the draws, the sight lines and their occlusion run in one kernel (:func:`_targets_stage`, the draws
    inside it through :mod:`couplers.sensing.streams`), the detection and the rows in :func:`_target_rows`;
    ``reference`` (or numba's draws not numpy's on this installation): :func:`_perceive_targets_stages`, the
    same steps as separate kernels with numpy's draws and :func:`_target_rows_reference` (tested equal).
    ``boresight``: :func:`couplers.sensing.perception.sensor_boresights` of ``heading`` when the caller has it."""
    if reference or not streams.available():
        return _perceive_targets_stages(x_true, direction, heading, targets, target_pd, target_occluder, pair_owner,
                                        pair_target, params, noise, occluder_corners, observer_occluder, buildings,
                                        reference)
    a, k = params.arrays, params.kernel_consts
    heading = np.asarray(heading, dtype=np.float64)
    n = x_true.shape[0]
    if boresight is None:  # the sensors along the heading take ``direction`` instead
        boresight = sensor_boresights(params, heading, n)
    pair_owner = np.asarray(pair_owner, dtype=np.int64)
    pair_target = np.asarray(pair_target, dtype=np.int64)
    targets = np.ascontiguousarray(targets, dtype=np.float64)
    use_vehicles = bool(params.occlusion_vehicles and occluder_corners is not None and len(occluder_corners))
    corners = (np.ascontiguousarray(occluder_corners, dtype=np.float64).reshape(-1, 4, 2) if use_vehicles
               else _NO_CORNERS)
    use_buildings = bool(params.occlusion_buildings and buildings is not None and len(buildings))
    if use_buildings:
        g, bb = buildings.cells, buildings.boxes
        grid = (g.x0, g.y0, g.cell, g.values, bb.start, bb.ids, bb.boxes, bb.margin) + building_edges(buildings)
    else:
        grid = _NO_BUILDINGS + (np.zeros(1, dtype=np.int64), np.empty((0, 4)))
    h = noise.handles
    pair, dist, sensor, u, w, line_of, clear, seg, rows, hits = _targets_stage(
        h["detect"], h["noise"], np.ascontiguousarray(x_true[:, :2], dtype=np.float64),
        np.ascontiguousarray(direction, dtype=np.float64), a["mount_x_m"], boresight, k["along_heading_array"],
        targets, pair_owner, pair_target, a["range_m"], k["cos_half"], k["full"], heading, a["yaw_deg"],
        a["fov_deg"], k["groups"], np.asarray(observer_occluder, dtype=np.int64),
        np.asarray(target_occluder, dtype=np.int64), use_vehicles, corners, use_buildings, *grid)
    odd = rows[hits == 2]  # a sight line that is not finite: shapely's test, as _segments_occluded_by_buildings
    if odd.size:
        clear[odd] = ~_segments_occluded_by_buildings_shapely(seg[odd], buildings)
    return _target_rows(pair, dist, sensor, clear, line_of, u, w, pair_owner, pair_target,
                        np.ascontiguousarray(target_pd, dtype=np.float64), targets,
                        np.ascontiguousarray(x_true, dtype=np.float64), a["range_m"], a["pd_near"], a["pd_far"],
                        a["sigma_p_m"], a["sigma_growth"], a["sigma_v_mps"])


def _perceive_targets_stages(x_true, direction, heading, targets, target_pd, target_occluder, pair_owner, pair_target,
                             params, noise, occluder_corners, observer_occluder, buildings, reference):
    """:func:`perceive_targets` as separate kernels with numpy between them and numpy's draws (its reference, and
    its path where numba's draws are not numpy's); ``reference``: the detection and rows in numpy too."""
    a, k = params.arrays, params.kernel_consts
    xy = np.ascontiguousarray(x_true[:, :2], dtype=np.float64)
    origins = xy[None, :, :] + a["mount_x_m"][:, None, None] * direction[None, :, :]
    pair_owner = np.asarray(pair_owner, dtype=np.int64)
    pair_target = np.asarray(pair_target, dtype=np.int64)
    target_xy = np.ascontiguousarray(targets[pair_target, :2], dtype=np.float64)
    pair, dist, sensor = _fov_params(origins, heading, direction, pair_owner, target_xy, params)
    u = noise.detect.random(pair.size)
    w = noise.noise.standard_normal((pair.size, 4))
    owner_c = pair_owner[pair]
    line, line_of = _distinct_lines(pair, sensor, k["groups"], pair_owner.size)
    seg = _sight_lines(origins, sensor[line], owner_c[line], target_xy[pair[line]])
    clear = np.ones(line.size, dtype=bool)
    if params.occlusion_vehicles and occluder_corners is not None and len(occluder_corners) and line.size:
        clear &= ~_segments_occluded_by_vehicles(seg, OccluderIndex.build(occluder_corners),
                                                 observer_occluder[owner_c[line]],
                                                 target_occluder[pair_target[pair[line]]])
    if params.occlusion_buildings and buildings is not None and len(buildings) and clear.any():
        clear[clear] &= ~_segments_occluded_by_buildings(seg[clear], buildings)
    tail = _target_rows_reference if reference else _target_rows
    return tail(pair, dist, sensor, clear, line_of, u, w, pair_owner, pair_target,
                np.ascontiguousarray(target_pd, dtype=np.float64), np.ascontiguousarray(targets, dtype=np.float64),
                np.ascontiguousarray(x_true, dtype=np.float64), a["range_m"], a["pd_near"], a["pd_far"],
                a["sigma_p_m"], a["sigma_growth"], a["sigma_v_mps"])


@njit(cache=True)
def _targets_stage(h_detect, h_noise, xy, direction, mount_x, boresight, along, targets, pair_owner, pair_target,
                   range_m, cos_half, full, heading, yaw_deg, fov_deg, groups, observer_occluder, target_occluder,
                   use_vehicles, corners, use_buildings, x0, y0, cell, near, b_start, b_ids, b_boxes, b_margin,
                   edge_start, edges):
    """The candidates of every sensor (:func:`couplers.sensing.perception_kernels._fov_stage` with the targets as
    its features and no clutter), their detection uniforms and (C, 4) noise normals from the streams of the
    handles ``h_*``, the distinct sight lines (:func:`_distinct_lines`), cleared of those a footprint other than
    the observer's and the target's own hides (``use_vehicles``), and of those a building hides
    (``use_buildings``: :func:`couplers.sensing.occlusion._building_hits` of the clear lines: 1 hidden, 2 to be
    decided by shapely). Returns (pair, dist, sensor, u, w, line of each candidate, clear (L,), segments (L, 4),
    the clear lines tested against the buildings, their hits)."""
    n_s = mount_x.size
    no_clutter = np.zeros(xy.shape[0] * n_s, dtype=np.int64)
    origins, target, pair, dist, sensor, _, _, _, _ = _fov_stage(
        xy, direction, mount_x, boresight, along, targets, pair_owner, pair_target, range_m, cos_half, full,
        no_clutter, n_s, np.empty(0), np.empty(0), heading, yaw_deg, fov_deg)
    u = stream(h_detect).random(pair.size)
    w = stream(h_noise).standard_normal((pair.size, 4))
    line, line_of = _distinct_lines(pair, sensor, groups, pair_owner.size)
    m = line.size
    seg, skip_a = line_segments(line, pair, sensor, pair_owner, origins, target, observer_occluder)
    skip_b = np.empty(m, dtype=np.int64)  # a target's own footprint does not hide it either
    for r in range(m):
        skip_b[r] = target_occluder[pair_target[pair[line[r]]]]
    clear, rows = clear_of_vehicles(seg, skip_a, skip_b, use_vehicles, corners)
    if not use_buildings or rows.size == 0:
        return pair, dist, sensor, u, w, line_of, clear, seg, np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int8)
    hits = _building_hits(seg[rows], x0, y0, cell, near, b_start, b_ids, b_boxes, b_margin, edge_start, edges)
    for q in range(rows.size):
        if hits[q] == 1:
            clear[rows[q]] = False
    return pair, dist, sensor, u, w, line_of, clear, seg, rows, hits


def _target_rows_reference(pair, dist, sensor, clear, line_of, u, w, pair_owner, pair_target, target_pd, targets,
                           x_true, range_m, pd_near, pd_far, sigma_p_m, sigma_growth, sigma_v):
    """Detection, the best sensor per detected pair and the rows (:func:`perceive_targets`), in numpy: the
    reference of :func:`_target_rows`."""
    visible = clear[line_of]
    frac = np.clip(dist / range_m[sensor], 0.0, 1.0)
    sig = sigma_p_m[sensor] * (1.0 + sigma_growth[sensor] * frac)
    pd = pd_near[sensor] + (pd_far[sensor] - pd_near[sensor]) * frac
    fixed = target_pd[pair_target[pair]]
    detected = visible & (u < pd)
    if (fixed >= 0).any():  # one draw per (vehicle, target): the first candidate's, any sensor seeing it
        first_of = np.full(pair_owner.size, -1, dtype=np.int64)
        first_of[pair[::-1]] = np.arange(pair.size)[::-1]
        u_pair = u[first_of[pair]]
        detected = np.where(fixed >= 0, visible & (u_pair < fixed), detected)
    cand = np.flatnonzero(detected)
    order = cand[np.lexsort((sensor[cand], sig[cand], pair[cand]))]
    _, first = np.unique(pair[order], return_index=True)
    best = order[first]
    owner = pair_owner[pair[best]]
    tgt = pair_target[pair[best]]
    sp, sv = sig[best], sigma_v[sensor[best]]
    z = targets[tgt] - x_true[owner]
    z[:, :2] += w[best, :2] * sp[:, None]
    z[:, 2:] += w[best, 2:] * sv[:, None]
    return owner, tgt, sensor[best], z, sp, sv


@njit(cache=True)
def _target_rows(pair, dist, sensor, clear, line_of, u, w, pair_owner, pair_target, target_pd, targets, x_true,
                 range_m, pd_near, pd_far, sigma_p_m, sigma_growth, sigma_v):
    """:func:`_target_rows_reference` in one pass over the candidates (same arithmetic, same order of the
    operations): a candidate is detected if its sight line is clear and its uniform is below the sensor's
    P_D(d), or, for a target with a fixed probability, below that with the uniform of the pair's first
    candidate; per detected pair the detecting candidate of smallest sigma_p, then smallest sensor index, then
    first listed (the reference's stable lexsort); rows in pair order."""
    c_total, n_pairs = pair.size, pair_owner.size
    first_of = np.full(n_pairs, -1, dtype=np.int64)
    for c in range(c_total):
        if first_of[pair[c]] < 0:
            first_of[pair[c]] = c
    sig = np.empty(c_total)
    best = np.full(n_pairs, -1, dtype=np.int64)
    for c in range(c_total):
        s = sensor[c]
        frac, sig[c] = _range_fraction_and_sigma(dist[c], s, range_m, sigma_p_m, sigma_growth)
        fixed = target_pd[pair_target[pair[c]]]
        if fixed >= 0:
            det = clear[line_of[c]] and u[first_of[pair[c]]] < fixed
        else:
            det = clear[line_of[c]] and u[c] < pd_near[s] + (pd_far[s] - pd_near[s]) * frac
        if det and _sharper(c, best[pair[c]], sig, sensor):
            best[pair[c]] = c
    d = 0
    for p in range(n_pairs):
        if best[p] >= 0:
            d += 1
    owner = np.empty(d, dtype=np.int64)
    tgt = np.empty(d, dtype=np.int64)
    sens = np.empty(d, dtype=np.int64)
    sp = np.empty(d)
    sv = np.empty(d)
    z = np.empty((d, targets.shape[1]))
    r = 0
    for p in range(n_pairs):
        c = best[p]
        if c < 0:
            continue
        i, t = pair_owner[p], pair_target[p]
        owner[r], tgt[r], sens[r] = i, t, sensor[c]
        sp[r] = sig[c]
        sv[r] = sigma_v[sensor[c]]
        for j in range(targets.shape[1]):
            z[r, j] = targets[t, j] - x_true[i, j]
        z[r, 0] += w[c, 0] * sp[r]
        z[r, 1] += w[c, 1] * sp[r]
        z[r, 2] += w[c, 2] * sv[r]
        z[r, 3] += w[c, 3] * sv[r]
        r += 1
    return owner, tgt, sens, z, sp, sv


def confuse_classes(klass: np.ndarray, class_error: float, rng: np.random.Generator) -> np.ndarray:
    """The classifier's report: each class replaced with probability ``class_error`` by one of the other
    classes, uniformly (two uniforms per row, drawn only when ``class_error`` > 0)."""
    if class_error <= 0 or klass.size == 0:
        return klass
    flip = rng.random(klass.size) < class_error
    other = (klass.astype(np.int64) + 1 + (rng.random(klass.size) * (N_CLASSES - 1)).astype(np.int64)) % N_CLASSES
    return np.where(flip, other, klass).astype(np.int8)


def row_kinds(feature: np.ndarray, feature_class: np.ndarray | None) -> np.ndarray:
    """``Truth.v2f_kind`` of the perception's own rows: landmark (or pedestrian feature) or clutter (one numba
    pass, :func:`_row_kinds`; :func:`row_kinds_reference` is the numpy reference)."""
    classed = feature_class is not None
    return _row_kinds(np.ascontiguousarray(feature, dtype=np.int64).reshape(-1),
                      np.ascontiguousarray(feature_class, dtype=np.int8) if classed else _NO_CLASS, classed
                      ).reshape(np.shape(feature))


_NO_CLASS = np.zeros(0, dtype=np.int8)


@njit(cache=True)
def _row_kinds(feature, feature_class, classed):
    """:func:`row_kinds_reference` row by row."""
    kind = np.empty(feature.size, dtype=np.int8)
    for r in range(feature.size):
        f = feature[r]
        if f < 0:
            kind[r] = KIND_CLUTTER
        elif classed and feature_class[f] == CLASS_PEDESTRIAN:
            kind[r] = KIND_PEDESTRIAN
        else:
            kind[r] = KIND_LANDMARK
    return kind


def row_kinds_reference(feature: np.ndarray, feature_class: np.ndarray | None) -> np.ndarray:
    """:func:`row_kinds` in numpy (its reference in the tests)."""
    kind = np.full(feature.shape, KIND_CLUTTER, dtype=np.int8)
    real = feature >= 0
    kind[real] = KIND_LANDMARK
    if feature_class is not None and real.any():
        kind[real] = np.where(np.asarray(feature_class)[feature[real]] == CLASS_PEDESTRIAN, KIND_PEDESTRIAN,
                              KIND_LANDMARK)
    return kind


@njit(cache=True)
def body_centre_states(front, dims, direction, velocity):
    """(N, 4) targets of the vehicle part: the body's middle front - (0.5 length) direction (``dims`` (N, 2) length
    and width) and the velocity, numpy's ``np.hstack([front - 0.5 * dims[:, :1] * direction, velocity])`` (the same
    products in the same order)."""
    n = front.shape[0]
    out = np.empty((n, 4))
    for i in range(n):
        half = 0.5 * dims[i, 0]
        out[i, 0] = front[i, 0] - half * direction[i, 0]
        out[i, 1] = front[i, 1] - half * direction[i, 1]
        out[i, 2], out[i, 3] = velocity[i, 0], velocity[i, 1]
    return out


@njit(cache=True)
def other_pairs(owner, tgt):
    """The (owner, target) pairs with target != owner (a vehicle never sees itself), in order."""
    m = 0
    for k in range(owner.size):
        if tgt[k] != owner[k]:
            m += 1
    o = np.empty(m, dtype=owner.dtype)
    t = np.empty(m, dtype=tgt.dtype)
    m = 0
    for k in range(owner.size):
        if tgt[k] != owner[k]:
            o[m], t[m] = owner[k], tgt[k]
            m += 1
    return o, t


TARGET_PARTS = ("vehicle", "person", "persistent")


def target_columns(key: tuple, persistent_pd: float) -> tuple:
    """(P_D (-1: the sensor's), footprint row (-1: none), class, kind) of the targets of parts ``key`` ((size,
    what) each, in order, what one of :data:`TARGET_PARTS`): vehicles are footprint rows 0.. and detected with the
    sensor's P_D, persons with it too, persistent sites with ``persistent_pd``. One numba pass
    (:func:`_target_columns`); :func:`target_columns_reference` is the numpy reference."""
    sizes = np.array([size for size, _ in key], dtype=np.int64)
    whats = np.array([TARGET_PARTS.index(what) for _, what in key], dtype=np.int64)
    return _target_columns(sizes, whats, float(persistent_pd))


@njit(cache=True)
def _target_columns(sizes, whats, persistent_pd):
    """:func:`target_columns_reference`'s columns, part after part (``whats``: 0 vehicle, 1 person, 2 persistent)."""
    total = 0
    for p in range(sizes.size):
        total += sizes[p]
    pd = np.empty(total)
    occ = np.empty(total, dtype=np.int64)
    klass = np.empty(total, dtype=np.int64)
    kind = np.empty(total, dtype=np.int64)
    r = 0
    for p in range(sizes.size):
        for i in range(sizes[p]):
            if whats[p] == 0:
                pd[r], occ[r], klass[r], kind[r] = -1.0, i, CLASS_VEHICLE, KIND_VEHICLE
            elif whats[p] == 1:
                pd[r], occ[r], klass[r], kind[r] = -1.0, -1, CLASS_PEDESTRIAN, KIND_PEDESTRIAN
            else:
                pd[r], occ[r], klass[r], kind[r] = persistent_pd, -1, CLASS_STATIC, KIND_PERSISTENT_CLUTTER
            r += 1
    return pd, occ, klass, kind


def target_columns_reference(key: tuple, persistent_pd: float) -> tuple:
    """:func:`target_columns` in numpy (its reference in the tests)."""
    cols = []
    for size, what in key:
        if what == "vehicle":
            cols.append((np.full(size, -1.0), np.arange(size), np.full(size, CLASS_VEHICLE),
                         np.full(size, KIND_VEHICLE)))
        elif what == "person":
            cols.append((np.full(size, -1.0), np.full(size, -1), np.full(size, CLASS_PEDESTRIAN),
                         np.full(size, KIND_PEDESTRIAN)))
        else:
            cols.append((np.full(size, persistent_pd), np.full(size, -1), np.full(size, CLASS_STATIC),
                         np.full(size, KIND_PERSISTENT_CLUTTER)))
    pd, occ, klass, kind = (np.concatenate(c) for c in zip(*cols))
    return pd, occ.astype(np.int64), klass, kind


def merged_rows(det, extra: list, noise: RoadUserNoise, class_error: float, kind: np.ndarray | None = None):
    """The perception's rows ``det`` (:class:`couplers.sensing.perception.Detections`) and the ``extra`` rows
    ((owner, z, sigma_p, sigma_v, sensor, class, kind) tuples of per-row arrays), shuffled within each
    vehicle, classes as the classifier reports them; returns a Detections with ``kind`` (truth) set. ``kind``:
    the kinds of ``det``'s rows when ``det`` does not carry them (None: ``det.kind``). The
    gathers and the extra rows' covariances run in one numba pass (:func:`_merge_gather`);
    :func:`merged_rows_reference` is the numpy reference."""
    owner = np.concatenate([det.owner] + [e[0] for e in extra]).astype(np.int64, copy=False)
    perm = shuffle_within_owner(owner, noise.shuffle)
    if len(extra) == 1:  # one part: its columns as they are (a concatenation would copy them)
        ex = list(extra[0])
    else:
        ex = [np.concatenate(c) for c in zip(*extra)] if extra else [np.empty(0)] * 7
    m = ex[0].size
    z, R, feature, sensor, klass, kind = _merge_gather(
        perm, np.ascontiguousarray(det.z, dtype=np.float64).reshape(-1, 4),
        np.ascontiguousarray(det.R, dtype=np.float64).reshape(-1, 4, 4),
        np.ascontiguousarray(det.feature, dtype=np.int64), np.ascontiguousarray(det.sensor, dtype=np.int64),
        np.ascontiguousarray(det.klass, dtype=np.int8),
        np.ascontiguousarray(det.kind if kind is None else kind, dtype=np.int8),
        np.ascontiguousarray(ex[1], dtype=np.float64).reshape(m, 4), np.ascontiguousarray(ex[2], dtype=np.float64),
        np.ascontiguousarray(ex[3], dtype=np.float64), np.ascontiguousarray(ex[4], dtype=np.int64),
        np.ascontiguousarray(ex[5], dtype=np.int8), np.ascontiguousarray(ex[6], dtype=np.int8))
    klass = confuse_classes(klass, class_error, getattr(noise, "class"))
    return Detections(z=z, owner=owner[perm], R=R, feature=feature, sensor=sensor, klass=klass, stats=det.stats,
                      kind=kind)


@njit(cache=True)
def _merge_gather(perm, z0, R0, feature0, sensor0, klass0, kind0, z1, sp1, sv1, sensor1, klass1, kind1):
    """Row r of the merged rows is row perm[r] of the perception's rows followed by the extra rows (feature -1,
    covariance diag(sp^2, sp^2, sv^2, sv^2)): :func:`merged_rows_reference`'s concatenations and gathers."""
    n0, o = z0.shape[0], perm.size
    z = np.empty((o, 4))
    R = np.empty((o, 4, 4))
    feature = np.empty(o, dtype=np.int64)
    sensor = np.empty(o, dtype=np.int64)
    klass = np.empty(o, dtype=np.int8)
    kind = np.empty(o, dtype=np.int8)
    for r in range(o):
        q = perm[r]
        if q < n0:
            for j in range(4):
                z[r, j] = z0[q, j]
                for c in range(4):
                    R[r, j, c] = R0[q, j, c]
            feature[r], sensor[r], klass[r], kind[r] = feature0[q], sensor0[q], klass0[q], kind0[q]
            continue
        e = q - n0
        for j in range(4):
            z[r, j] = z1[e, j]
            for c in range(4):
                R[r, j, c] = 0.0
        R[r, 0, 0] = R[r, 1, 1] = sp1[e] ** 2
        R[r, 2, 2] = R[r, 3, 3] = sv1[e] ** 2
        feature[r], sensor[r], klass[r], kind[r] = -1, sensor1[e], klass1[e], kind1[e]
    return z, R, feature, sensor, klass, kind


def merged_rows_reference(det, extra: list, noise: RoadUserNoise, class_error: float):
    """:func:`merged_rows` in numpy (its reference in the tests)."""
    owner = np.concatenate([det.owner] + [e[0] for e in extra]).astype(np.int64)
    z = np.concatenate([det.z] + [e[1] for e in extra])
    R_extra = []
    for e in extra:
        r = np.zeros((e[0].size, 4, 4))
        r[:, 0, 0] = r[:, 1, 1] = e[2] ** 2
        r[:, 2, 2] = r[:, 3, 3] = e[3] ** 2
        R_extra.append(r)
    R = np.concatenate([det.R] + R_extra)
    feature = np.concatenate([det.feature] + [np.full(e[0].size, -1, dtype=np.int64) for e in extra])
    sensor = np.concatenate([det.sensor] + [np.asarray(e[4], dtype=np.int64) for e in extra])
    klass = np.concatenate([det.klass] + [np.asarray(e[5], dtype=np.int8) for e in extra]).astype(np.int8)
    kind = np.concatenate([det.kind] + [np.asarray(e[6], dtype=np.int8) for e in extra])
    perm = shuffle_within_owner(owner, noise.shuffle)
    klass = confuse_classes(klass[perm], class_error, getattr(noise, "class"))
    return replace(det, z=z[perm], owner=owner[perm], R=R[perm], feature=feature[perm], sensor=sensor[perm],
                   klass=klass, kind=kind[perm])


__all__ = ["CLASS_VEHICLE", "CLASS_STATIC", "CLASS_PEDESTRIAN", "KIND_NAMES", "RoadUserNoise",
           "persistent_clutter_sites", "perceive_targets", "confuse_classes", "row_kinds", "row_kinds_reference",
           "body_centre_states", "other_pairs", "target_columns", "target_columns_reference", "merged_rows",
           "merged_rows_reference"]
