"""The numba kernels of the realistic perception (:mod:`couplers.sensing.perception`, whose docstring
describes the model and its random streams): field-of-view selection, occlusion, detection, clutter and the
shuffled rows, as the stages :func:`couplers.sensing.perception.perceive` runs and the pieces of its numpy
reference path :func:`couplers.sensing.perception.perceive_reference`."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from couplers.sensing.occlusion import (
    OCCLUDER_BUCKET_M,
    _needs_building_test,
    _occluded_by_quads_bucketed,
    _occluder_buckets,
    _rectangles,
)
from couplers.sensing.rows import _order_by_owner_then_key
from couplers.sensing.streams import stream

#: Class of a detection (``Frame.v2f_class``): static landmark, or a SUMO pedestrian
#: (couplers.sensing.pedestrians). A false detection carries the class the sensor reports for it, a static
#: object (it is drawn as one: relative velocity -v_vehicle).
CLASS_STATIC = 0
CLASS_PEDESTRIAN = 1


@njit(cache=True)
def _fov_select(origin, boresight, owner, target, range_m, cos_half, full):
    """Candidates of every sensor s, sensor after sensor: rows k with target[k] inside the sector of
    sensor s on vehicle owner[k] (origin (S, N, 2), boresight (S, N, 2)). Returns (rows, distances,
    sensors)."""
    n_sensors = origin.shape[0]
    m = owner.size
    rows = np.empty(n_sensors * m, dtype=np.int64)
    dist = np.empty(n_sensors * m)
    sensor = np.empty(n_sensors * m, dtype=np.int64)
    count = 0
    for s in range(n_sensors):
        # d^2 beyond range^2 (1 + 1e-12) puts d = sqrt(d^2) (correctly rounded, monotone) beyond the range for
        # certain: those pairs skip the square root
        far2 = range_m[s] * range_m[s] * (1.0 + 1e-12)
        for k in range(m):
            i = owner[k]
            dx = target[k, 0] - origin[s, i, 0]
            dy = target[k, 1] - origin[s, i, 1]
            d2 = dx * dx + dy * dy
            if d2 > far2:
                continue
            d = math.sqrt(d2)
            if d > range_m[s]:
                continue
            # angle to the boresight <= half the opening  <=>  d . b >= |d| cos(half)
            if not full[s] and dx * boresight[s, i, 0] + dy * boresight[s, i, 1] < d * cos_half[s]:
                continue
            rows[count] = k
            dist[count] = d
            sensor[count] = s
            count += 1
    return rows[:count], dist[:count], sensor[:count]


@njit(cache=True)
def _clutter_geometry(counts, n_sensors, u_r, u_a, heading, range_m, yaw_deg, fov_deg):
    """(vehicle, sensor) of each false detection (:func:`_repeat_rows`), r = range sqrt(u_r) and bearing
    heading + radians(yaw + fov (u_a - 0.5)) (``np.radians``: x * (pi / 180), tested equal)."""
    owner, sensor = _repeat_rows(counts, n_sensors)
    c = owner.size
    r = np.empty(c)
    ang = np.empty(c)
    for k in range(c):
        s = sensor[k]
        r[k] = range_m[s] * math.sqrt(u_r[k])
        ang[k] = heading[owner[k]] + (yaw_deg[s] + fov_deg[s] * (u_a[k] - 0.5)) * (math.pi / 180.0)
    return owner, sensor, r, ang


@njit(cache=True)
def _repeat_rows(counts, n_sensors):
    """(vehicle, sensor) of each of counts[i * S + s] rows, in that order."""
    total = 0
    for k in range(counts.size):
        total += counts[k]
    owner = np.empty(total, dtype=np.int64)
    sensor = np.empty(total, dtype=np.int64)
    c = 0
    for k in range(counts.size):
        for _ in range(counts[k]):
            owner[c] = k // n_sensors
            sensor[c] = k % n_sensors
            c += 1
    return owner, sensor


@njit(cache=True)
def _clutter_xy(origins, owner, sensor, r, direction):
    """origins[sensor, owner] + r * direction."""
    pts = np.empty((owner.size, 2))
    for c in range(owner.size):
        pts[c, 0] = origins[sensor[c], owner[c], 0] + r[c] * direction[c, 0]
        pts[c, 1] = origins[sensor[c], owner[c], 1] + r[c] * direction[c, 1]
    return pts


@njit(cache=True)
def _clutter_rows(origins, owner, sensor, r, cos_a, sin_a, x_true, cw, range_m, sigma_p_m, sigma_growth, sigma_v):
    """Rows of the false detections at origins + r (cos_a, sin_a): z (static objects: relative velocity
    -v_vehicle), sigma_p, sigma_v."""
    c_total = owner.size
    z = np.empty((c_total, 4))
    sp = np.empty(c_total)
    sv = np.empty(c_total)
    for c in range(c_total):
        s, i = sensor[c], owner[c]
        frac = min(max(r[c] / range_m[s], 0.0), 1.0)
        sp[c] = sigma_p_m[s] * (1.0 + sigma_growth[s] * frac)
        sv[c] = sigma_v[s]
        z[c, 0] = (origins[s, i, 0] + r[c] * cos_a[c]) - x_true[i, 0] + cw[c, 0] * sp[c]
        z[c, 1] = (origins[s, i, 1] + r[c] * sin_a[c]) - x_true[i, 1] + cw[c, 1] * sp[c]
        for j in range(2):
            z[c, 2 + j] = -x_true[i, 2 + j] + cw[c, 2 + j] * sv[c]
    return z, sp, sv


@njit(cache=True)
def _range_fraction_and_sigma(d, s, range_m, sigma_p_m, sigma_growth):
    """A detection at distance ``d`` by sensor ``s``: its share of the sensor's range (clipped to [0, 1]) and
    its position sigma, sigma_p (1 + growth x share)."""
    frac = min(max(d / range_m[s], 0.0), 1.0)
    return frac, sigma_p_m[s] * (1.0 + sigma_growth[s] * frac)


@njit(cache=True)
def _sharper(c, b, sig, sensor):
    """Candidate ``c`` replaces the pair's best so far ``b`` (-1: none): smaller sigma, ties to the sensor
    listed first."""
    return b < 0 or sig[c] < sig[b] or (sig[c] == sig[b] and sensor[c] < sensor[b])


@njit(cache=True)
def _merge_detections(pair, dist, sensor, detected, n_pairs, range_m, pd_near, pd_far, sigma_p_m, sigma_growth,
                      u, visible):
    """P_D and sigma_p of every candidate (per its sensor), the detections (visible and u < P_D), and
    per detected pair the detecting candidate of smallest sigma_p (ties: the sensor listed first).
    Writes ``detected`` (C,) and returns (sigma_p (C,), first (D,) candidate rows in pair order)."""
    c_total = pair.size
    sig = np.empty(c_total)
    best = np.full(n_pairs, -1, dtype=np.int64)
    for c in range(c_total):
        s = sensor[c]
        frac, sig[c] = _range_fraction_and_sigma(dist[c], s, range_m, sigma_p_m, sigma_growth)
        detected[c] = visible[c] and u[c] < pd_near[s] + (pd_far[s] - pd_near[s]) * frac
        if detected[c] and _sharper(c, best[pair[c]], sig, sensor):
            best[pair[c]] = c
    count = 0
    for p in range(n_pairs):
        if best[p] >= 0:
            count += 1
    first = np.empty(count, dtype=np.int64)
    count = 0
    for p in range(n_pairs):
        if best[p] >= 0:
            first[count] = best[p]
            count += 1
    return sig, first


@njit(cache=True)
def _distinct_lines(pair, sensor, group, n_pairs):
    """Candidates with distinct sight lines (pair, mount point of the sensor): (the first candidate of
    each line (L,), the line of every candidate (C,))."""
    n_groups = group.size
    seen = np.full(n_pairs * n_groups, -1, dtype=np.int64)
    line_of = np.empty(pair.size, dtype=np.int64)
    first = np.empty(pair.size, dtype=np.int64)
    count = 0
    for c in range(pair.size):
        key = pair[c] * n_groups + group[sensor[c]]
        if seen[key] < 0:
            seen[key] = count
            first[count] = c
            count += 1
        line_of[c] = seen[key]
    return first[:count], line_of


@njit(cache=True)
def _sight_lines(origins, sensor, owner, target):
    """(C, 4) segments from the mount point of sensor[c] on vehicle owner[c] to target[c]."""
    c_total = sensor.size
    seg = np.empty((c_total, 4))
    for c in range(c_total):
        seg[c, 0] = origins[sensor[c], owner[c], 0]
        seg[c, 1] = origins[sensor[c], owner[c], 1]
        seg[c, 2] = target[c, 0]
        seg[c, 3] = target[c, 1]
    return seg


@njit(cache=True)
def _detected_rows(first, pair, sensor, pair_owner, pair_feature, features_true, x_true, w, sig, sigma_v):
    """Rows of the detections ``first``: owner, feature, sensor, sigma_p, sigma_v and z = x_F - x_V + n."""
    d = first.size
    owner = np.empty(d, dtype=np.int64)
    feat = np.empty(d, dtype=np.int64)
    sens = np.empty(d, dtype=np.int64)
    sp = np.empty(d)
    sv = np.empty(d)
    z = np.empty((d, 4))
    for r in range(d):
        c = first[r]
        i = pair_owner[pair[c]]
        f = pair_feature[pair[c]]
        owner[r], feat[r], sens[r] = i, f, sensor[c]
        sp[r] = sig[c]
        sv[r] = sigma_v[sensor[c]]
        for j in range(4):
            z[r, j] = features_true[f, j] - x_true[i, j]
        z[r, 0] += w[c, 0] * sp[r]
        z[r, 1] += w[c, 1] * sp[r]
        z[r, 2] += w[c, 2] * sv[r]
        z[r, 3] += w[c, 3] * sv[r]
    return owner, feat, sens, sp, sv, z


@njit(cache=True)
def _sense_stage(h_clutter, h_detect, h_noise, clutter_rate, xy, direction, mount_x, boresight, along, features,
                 pair_owner, pair_feature, range_m, cos_half, full, heading, yaw_deg, fov_deg, groups,
                 observer_occluder, use_vehicles, corners, use_buildings, x0, y0, cell, near, b_start, b_ids, b_boxes,
                 b_margin):
    """The clutter draws (Poisson counts per (vehicle, sensor) in that order, then the distance and bearing
    uniforms and the (C, 4) noise normals, as :func:`_clutter_polar` and :func:`perceive_reference` draw them),
    :func:`_fov_stage`, the candidates' detection uniforms and (C, 4) noise normals, and
    :func:`_occlusion_stage`; the draws from the streams of the handles ``h_*`` (:mod:`couplers.sensing.streams`)."""
    n, n_s = xy.shape[0], mount_x.size
    clutter = stream(h_clutter)
    counts = np.empty(n * n_s, dtype=np.int64)
    for i in range(n):
        for s in range(n_s):
            counts[i * n_s + s] = clutter.poisson(clutter_rate[s])
    c = 0
    for k in range(counts.size):
        c += counts[k]
    u_r = clutter.random(c)
    u_a = clutter.random(c)
    cw = clutter.standard_normal((c, 4))
    origins, target, pair, dist, sensor, c_owner, c_sensor, c_dist, c_ang = _fov_stage(
        xy, direction, mount_x, boresight, along, features, pair_owner, pair_feature, range_m, cos_half, full, counts,
        n_s, u_r, u_a, heading, yaw_deg, fov_deg)
    u = stream(h_detect).random(pair.size)
    w = stream(h_noise).standard_normal((pair.size, 4))
    line_of, clear, seg, need = _occlusion_stage(pair, sensor, groups, pair_owner.size, origins, pair_owner, target,
                                                 observer_occluder, use_vehicles, corners, use_buildings, x0, y0,
                                                 cell, near, b_start, b_ids, b_boxes, b_margin)
    return origins, pair, dist, sensor, c_owner, c_sensor, c_dist, c_ang, cw, u, w, line_of, clear, seg, need


@njit(cache=True)
def _rows_stage(h_shuffle, pair, dist, sensor, n_pairs, clear, line_of, u, w, pair_owner, pair_feature, features,
                x_true, range_m, pd_near, pd_far, sigma_p_m, sigma_growth, sigma_v, origins, c_owner, c_sensor, c_dist,
                c_cos, c_sin, cw, feature_class, classed):
    """:func:`_detection_stage`, one uniform key per row from the shuffle stream of the handle ``h_shuffle``, the
    class of each detection (``feature_class`` of its feature if ``classed``, else CLASS_STATIC) and
    :func:`_shuffle_stage`. Returns (z, owner, R, feature, sensor, class, pairs in a field of view, of them
    visible, detected)."""
    (t_owner, t_feat, t_sensor, t_sig, t_sv, t_z, c_z, c_sig, c_sv, n_fov, n_vis, n_det) = _detection_stage(
        pair, dist, sensor, n_pairs, clear, line_of, u, w, pair_owner, pair_feature, features, x_true, range_m,
        pd_near, pd_far, sigma_p_m, sigma_growth, sigma_v, origins, c_owner, c_sensor, c_dist, c_cos, c_sin, cw)
    keys = stream(h_shuffle).random(t_owner.size + c_owner.size)
    t_klass = np.full(t_feat.size, CLASS_STATIC, dtype=np.int8)
    if classed:
        for r in range(t_feat.size):
            t_klass[r] = feature_class[t_feat[r]]
    z, owner, R, feature, sensor_rows, klass = _shuffle_stage(keys, t_z, c_z, t_owner, c_owner, t_feat, t_sensor,
                                                              c_sensor, t_sig, c_sig, t_sv, c_sv, t_klass)
    return z, owner, R, feature, sensor_rows, klass, n_fov, n_vis, n_det


@njit(cache=True)
def _fov_stage(xy, direction, mount_x, boresight, along, features, pair_owner, pair_feature, range_m, cos_half,
               full, counts, n_sensors, u_r, u_a, heading, yaw_deg, fov_deg):
    """Mount points (S, N, 2) xy + mount_x direction, the pairs' targets, the candidates of the fields of view
    (:func:`_fov_select`, boresight ``direction`` for the sensors ``along`` the heading) and the clutter's
    geometry (:func:`_clutter_geometry`)."""
    n_s, n = mount_x.size, xy.shape[0]
    origins = np.empty((n_s, n, 2))
    bore = np.empty((n_s, n, 2))
    for s in range(n_s):
        for i in range(n):
            for j in range(2):
                origins[s, i, j] = xy[i, j] + mount_x[s] * direction[i, j]
                bore[s, i, j] = direction[i, j] if along[s] else boresight[s, i, j]
    target = np.empty((pair_feature.size, 2))
    for p in range(pair_feature.size):
        target[p, 0] = features[pair_feature[p], 0]
        target[p, 1] = features[pair_feature[p], 1]
    pair, dist, sensor = _fov_select(origins, bore, pair_owner, target, range_m, cos_half, full)
    c_owner, c_sensor, c_dist, c_ang = _clutter_geometry(counts, n_sensors, u_r, u_a, heading, range_m, yaw_deg,
                                                         fov_deg)
    return origins, target, pair, dist, sensor, c_owner, c_sensor, c_dist, c_ang


@njit(cache=True)
def line_segments(line, pair, sensor, pair_owner, origins, target, observer_occluder):
    """The sight lines ``line`` (candidate indices) as segments (L, 4) from the sensor's origin to the target,
    and the observer's own footprint of each (L,), which never hides its own lines."""
    m = line.size
    seg = np.empty((m, 4))
    skip_a = np.empty(m, dtype=np.int64)
    for r in range(m):
        c = line[r]
        i = pair_owner[pair[c]]
        seg[r, 0] = origins[sensor[c], i, 0]
        seg[r, 1] = origins[sensor[c], i, 1]
        seg[r, 2] = target[pair[c], 0]
        seg[r, 3] = target[pair[c], 1]
        skip_a[r] = observer_occluder[i]
    return seg, skip_a


@njit(cache=True)
def clear_of_vehicles(seg, skip_a, skip_b, use_vehicles, corners):
    """(clear (L,), the indices of the clear lines): the sight lines ``seg`` no vehicle footprint hides (the
    observer's ``skip_a`` and the target's ``skip_b`` footprints excepted; -1: none), all clear without
    ``use_vehicles`` or footprints."""
    m = seg.shape[0]
    clear = np.ones(m, dtype=np.bool_)
    if use_vehicles and m > 0 and corners.shape[0] > 0:
        order, start, x0_b, width, xmin, xmax, ymin, ymax, max_wx = _occluder_buckets(corners, OCCLUDER_BUCKET_M)
        hidden = _occluded_by_quads_bucketed(seg, skip_a, skip_b, corners, order, start, x0_b, width, xmin, xmax,
                                             ymin, ymax, max_wx, _rectangles(corners))
        for r in range(m):
            clear[r] = not hidden[r]
    n_clear = 0
    for r in range(m):
        if clear[r]:
            n_clear += 1
    rows = np.empty(n_clear, dtype=np.int64)
    q = 0
    for r in range(m):
        if clear[r]:
            rows[q] = r
            q += 1
    return clear, rows


@njit(cache=True)
def _occlusion_stage(pair, sensor, groups, n_pairs, origins, pair_owner, target, observer_occluder, use_vehicles,
                     corners, use_buildings, x0, y0, cell, near, b_start, b_ids, b_boxes, b_margin):
    """The distinct sight lines (:func:`_distinct_lines`, :func:`_sight_lines`), cleared of those a vehicle
    footprint other than the observer's hides (:func:`_occluded_by_quads_bucketed`); of the clear ones, the
    lines that may meet a building (:func:`_needs_building_test`). Returns (line of each candidate, clear
    (L,), segments (L, 4), the lines for the building query)."""
    line, line_of = _distinct_lines(pair, sensor, groups, n_pairs)
    m = line.size
    seg, skip_a = line_segments(line, pair, sensor, pair_owner, origins, target, observer_occluder)
    no_target = np.full(m, -1, dtype=np.int64)  # the targets are features, not footprints
    clear, rows = clear_of_vehicles(seg, skip_a, no_target, use_vehicles, corners)
    if not use_buildings or rows.size == 0:
        return line_of, clear, seg, np.empty(0, dtype=np.int64)
    needs = _needs_building_test(seg[rows], x0, y0, cell, near, b_start, b_ids, b_boxes, b_margin)
    return line_of, clear, seg, rows[needs]


@njit(cache=True)
def _detection_stage(pair, dist, sensor, n_pairs, clear, line_of, u, w, pair_owner, pair_feature, features, x_true,
                     range_m, pd_near, pd_far, sigma_p_m, sigma_growth, sigma_v, origins, c_owner, c_sensor, c_dist,
                     c_cos, c_sin, cw):
    """:func:`_merge_detections` of the visible candidates, their rows (:func:`_detected_rows`), the clutter
    rows (:func:`_clutter_rows`) and the pair counts (:func:`_pair_counts`)."""
    visible = np.empty(pair.size, dtype=np.bool_)
    for c in range(pair.size):
        visible[c] = clear[line_of[c]]
    detected = np.empty(pair.size, dtype=np.bool_)
    sig, first = _merge_detections(pair, dist, sensor, detected, n_pairs, range_m, pd_near, pd_far, sigma_p_m,
                                   sigma_growth, u, visible)
    t_owner, t_feat, t_sensor, t_sig, t_sv, t_z = _detected_rows(first, pair, sensor, pair_owner, pair_feature,
                                                                 features, x_true, w, sig, sigma_v)
    c_z, c_sig, c_sv = _clutter_rows(origins, c_owner, c_sensor, c_dist, c_cos, c_sin, x_true, cw, range_m,
                                     sigma_p_m, sigma_growth, sigma_v)
    n_fov, n_vis = _pair_counts(pair, visible, n_pairs)
    return t_owner, t_feat, t_sensor, t_sig, t_sv, t_z, c_z, c_sig, c_sv, n_fov, n_vis, first.size


@njit(cache=True)
def _shuffle_stage(keys, t_z, c_z, t_owner, c_owner, t_feat, t_sensor, c_sensor, t_sig, c_sig, t_sv, c_sv, t_klass):
    """:func:`couplers.sensing.rows.shuffle_within_owner` of the detections then the clutter rows with the uniform
    ``keys``, and the rows in that order (:func:`_shuffled_rows`)."""
    owner = np.empty(t_owner.size + c_owner.size, dtype=np.int64)
    owner[:t_owner.size] = t_owner
    owner[t_owner.size:] = c_owner
    perm = _order_by_owner_then_key(owner, keys)
    return _shuffled_rows(perm, t_z, c_z, t_owner, c_owner, t_feat, t_sensor, c_sensor, t_sig, c_sig, t_sv, c_sv,
                          t_klass)


@njit(cache=True)
def _pair_counts(pair, visible, n_pairs):
    """(pairs with a candidate, pairs with a visible candidate): the counts of ``np.bincount`` > 0."""
    fov = np.zeros(n_pairs, dtype=np.bool_)
    vis = np.zeros(n_pairs, dtype=np.bool_)
    for c in range(pair.size):
        fov[pair[c]] = True
        if visible[c]:
            vis[pair[c]] = True
    return int(fov.sum()), int(vis.sum())


@njit(cache=True)
def _shuffled_rows(perm, t_z, c_z, t_owner, c_owner, t_feat, t_sensor, c_sensor, t_sig, c_sig, t_sv, c_sv, t_klass):
    """The detections then the clutter rows, in the order ``perm``: z, owner, R (``gnss_cov`` of sigma_p,
    sigma_v: blockdiag(sp^2 I, sv^2 I)), feature (-1 for clutter), sensor, class (clutter CLASS_STATIC)."""
    m, d = perm.size, t_owner.size
    z = np.empty((m, 4))
    owner = np.empty(m, dtype=np.int64)
    R = np.zeros((m, 4, 4))
    feature = np.empty(m, dtype=np.int64)
    sensor = np.empty(m, dtype=np.int64)
    klass = np.empty(m, dtype=np.int8)
    for r in range(m):
        k = perm[r]
        if k < d:
            z[r] = t_z[k]
            owner[r], feature[r], sensor[r], klass[r] = t_owner[k], t_feat[k], t_sensor[k], t_klass[k]
            sp, sv = t_sig[k], t_sv[k]
        else:
            k -= d
            z[r] = c_z[k]
            owner[r], feature[r], sensor[r], klass[r] = c_owner[k], -1, c_sensor[k], CLASS_STATIC
            sp, sv = c_sig[k], c_sv[k]
        R[r, 0, 0] = R[r, 1, 1] = sp * sp
        R[r, 2, 2] = R[r, 3, 3] = sv * sv
    return z, owner, R, feature, sensor, klass
