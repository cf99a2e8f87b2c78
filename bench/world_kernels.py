"""The realistic world's own kernels on recorded inputs: the reflections (``reflect_kernel``) and the road users'
targets stage (``_targets_stage``), their work counted and two versions timed on the same inputs in one process.

    python bench/world_kernels.py capture [--duration 300] [--seed 1] [--out /tmp/world_kernels.pkl]
    python bench/world_kernels.py counts [--first 80] [--last 400]
    python bench/world_kernels.py replay --old DIR [--rounds 6] [--first 80] [--last 400] [--what reflect,targets]

``capture`` runs the TLR realistic preset (experiments/arterial_tlr_realistic.toml) and records every call's
arguments (the stream handles of the targets stage are not kept: replay draws from scratch generators).
``counts`` replays the calls through copies of c3bf628's kernels with counters (candidates, facades, legs,
footprints, walk samples ...) and prints their means per step. ``replay`` times, per step, the kernels of this
checkout and of the checkout ``DIR`` (its ``couplers/sensing`` modules loaded under other names), alternating
their order by step and round, checks that both return the same bytes (the targets stage: what reaches the
rows, :func:`_detectable`), and prints the medians of the per-step process times (steps first+1 .. last) and of
their per-step differences. docs/performance.md, "sixth pass", has what it measured.

Not a test: it asserts only that both versions agree, and prints numbers.
"""

from __future__ import annotations

import argparse
import importlib.util
import pickle
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _copy(v):
    if isinstance(v, np.ndarray):
        return v.copy()
    if isinstance(v, tuple):
        return tuple(_copy(x) for x in v)
    return v


def capture(duration: float, seed: int, out: Path) -> None:
    import couplers.sensing.gnss_satellites as gsat
    import couplers.sensing.road_users as ru
    from couplers.net.folder import load_net_folder
    from couplers.sumo_coupler import SumoCoupler
    from experiments.config import load_config
    from experiments.runner import sumo_scenario

    rec = {"reflect": [], "targets": []}
    step = [0]
    inner_r, inner_t = gsat.reflect_kernel, ru._targets_stage

    def spy_r(*args):
        rec["reflect"].append((step[0], _copy(args)))
        return inner_r(*args)

    def spy_t(*args):
        rec["targets"].append((step[0], (None, None) + _copy(args[2:])))
        return inner_t(*args)

    inner_rows = ru._target_rows

    def spy_rows(*args):  # the detection's constants, which the stage takes too since its lines' pre-check
        s, a = rec["targets"][-1]
        rec["targets"][-1] = (s, a + (args[13].copy(), args[14].copy(), args[9].copy()))
        return inner_rows(*args)

    gsat.reflect_kernel, ru._targets_stage, ru._target_rows = spy_r, spy_t, spy_rows
    cfg = load_config(ROOT / "experiments" / "arterial_tlr_realistic.toml",
                      {"run.duration_s": duration, "run.seed": seed})
    with SumoCoupler(sumo_scenario(cfg, load_net_folder(cfg.net_dir)), cfg.sensors) as coupler:
        for _ in coupler.frames():
            step[0] += 1
    with open(out, "wb") as f:
        pickle.dump(rec, f)
    print(f"{step[0]} frames, {len(rec['reflect'])} reflection calls, {len(rec['targets'])} targets calls -> {out}")


def _load_old(old: Path):
    """The kernels of checkout ``old``: its gnss_reflect, occlusion, perception_kernels and road_users modules
    under the names old_*, their imports of each other rewritten (the rest from this checkout)."""
    names = ("occlusion", "perception_kernels", "gnss_reflect", "road_users")
    tmp = Path("/tmp") / f"world_kernels_old_{abs(hash(str(old.resolve()))) % 10 ** 8}"
    tmp.mkdir(exist_ok=True)
    mods = {}
    for name in names:
        src = (old / "couplers" / "sensing" / f"{name}.py").read_text()
        for other in names:
            src = src.replace(f"couplers.sensing.{other} import", f"old_{other} import")
        path = tmp / f"old_{name}.py"
        if not path.exists() or path.read_text() != src:
            path.write_text(src)
        spec = importlib.util.spec_from_file_location(f"old_{name}", path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[f"old_{name}"] = mod
        spec.loader.exec_module(mod)
        mods[name] = mod
    return mods


def _fit(args: tuple, f) -> tuple:
    """The targets stage's captured arguments for ``f``: those of the checkout's ``_targets_stage`` (32), then the
    detection's pd_near, pd_far and target P_D (captured from ``_target_rows``), which later stages take."""
    n = f.py_func.__code__.co_argcount
    return args[:n]


def _detectable(out: tuple, args: tuple) -> tuple:
    """What of the targets stage's result reaches the rows: the candidates, their draws, lines and segments, and
    per candidate "its line is clear and its uniform passes its detection test" (``_target_rows``' test; a line on
    which no candidate passes may be left untested)."""
    pair, dist, sensor, u, w, line_of, clear, seg = out[:8]
    pair_target, range_m = args[9], args[10]
    pd_near, pd_far, target_pd = args[32:35]
    frac = np.minimum(np.maximum(dist / range_m[sensor], 0.0), 1.0)
    fixed = target_pd[pair_target[pair]]
    first = np.full(pair_target.size, -1, dtype=np.int64)
    first[pair[::-1]] = np.arange(pair.size)[::-1]
    pd = pd_near[sensor] + (pd_far[sensor] - pd_near[sensor]) * frac
    passes = np.where(fixed >= 0, u[first[pair]] < fixed, u < pd)
    return pair, dist, sensor, u, w, line_of, seg, clear[line_of] & passes


def _same(a, b) -> bool:
    if isinstance(a, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def replay(path: Path, old: Path, rounds: int, first: int, last: int, what: str) -> None:
    import couplers.sensing.gnss_reflect as new_r
    import couplers.sensing.road_users as new_t
    from couplers.sensing.perception import effect_rng
    from couplers.sensing.streams import handle

    with open(path, "rb") as f:
        rec = pickle.load(f)
    mods = _load_old(old)
    kernels = {"reflect": (mods["gnss_reflect"].reflect_kernel, new_r.reflect_kernel),
               "targets": (mods["road_users"]._targets_stage, new_t._targets_stage)}
    for name in what.split(","):
        calls = [(s, a) for s, a in rec[name] if first < s <= last]
        f_old, f_new = kernels[name]
        times = {0: {}, 1: {}}
        for f in (f_old, f_new):  # compiled and warm before the clock
            a = calls[0][1]
            if name == "targets":
                g1, g2 = effect_rng(0, 1, "d"), effect_rng(0, 1, "n")
                a = _fit((handle(g1), handle(g2)) + a[2:], f)
            f(*a)
        for r in range(rounds):
            for j, (s, args) in enumerate(calls):
                out = [None, None]
                for v in ((0, 1) if (j + r) % 2 == 0 else (1, 0)):
                    f = (f_old, f_new)[v]
                    a = args
                    if name == "targets":  # the same draws for both versions
                        g1, g2 = effect_rng(j, 1, "d"), effect_rng(j, 1, "n")
                        a = _fit((handle(g1), handle(g2)) + args[2:], f)
                    t0 = time.process_time()
                    out[v] = f(*a)
                    dt = time.process_time() - t0
                    times[v][s] = times[v].get(s, 0.0) + dt
                if name == "targets" and r == 0:
                    out = [_detectable(o, args) for o in out]
                if r == 0 and not _same(out[0], out[1]):
                    raise SystemExit(f"{name}: step {s}: the two versions differ")
        med = [1e6 * np.median(np.array(list(times[v].values()))) / rounds for v in (0, 1)]
        mean = [1e6 * np.mean(np.array(list(times[v].values()))) / rounds for v in (0, 1)]
        steps = sorted(times[0])
        diff = np.array([times[1][s] - times[0][s] for s in steps]) / rounds * 1e6
        print(f"{name}: {len(calls)} calls, per step median old {med[0]:.1f} us new {med[1]:.1f} us, "
              f"mean old {mean[0]:.1f} new {mean[1]:.1f}, new - old per step: median {np.median(diff):.1f} "
              f"mean {diff.mean():.1f} us ({rounds} rounds, identical outputs)")


# --- counting copies of the kernels (the same control flow, with counters) -------------------------------------

R_NAMES = ("vehicles with a blocked satellite", "blocked (vehicle, satellite) pairs", "candidate buildings scanned",
           "buildings below the roof at their box distance", "facade-distance blocks computed", "facades examined",
           "facades not through the antenna", "facades facing the satellite", "specular points below the roof",
           "specular points on the facade (candidate paths)", "pairs with a candidate path",
           "leg 1 tests", "leg 1 grid cells", "leg 1 grid entries", "leg 1 buildings listed",
           "leg 1 buildings past the box test", "leg 1 edges tested", "leg 1 blocked",
           "leg 2 tests", "leg 2 grid cells", "leg 2 grid entries", "leg 2 buildings listed",
           "leg 2 buildings past the box test", "leg 2 edges tested", "leg 2 blocked", "reflections found")


def _counting_kernels():
    import math

    from numba import njit

    from couplers.sensing.gnss_reflect import _cell_index, _ray_box_span
    from couplers.sensing.gnss_sky import BOX_MARGIN_M, _box_distance

    @njit
    def leg_c(sx, sy, dx, dy, t0, t1, x0, y0, cell, nx, ny, gstart, gids, cx, cy, radius, boxes, heights,
              h_ant, seen, stamp, out, cnt, o):
        ax, ay = sx + t0 * dx, sy + t0 * dy
        bx, by = sx + t1 * dx, sy + t1 * dy
        cx0 = max(_cell_index(min(ax, bx) - BOX_MARGIN_M, x0, cell, nx), 0)
        cx1 = min(_cell_index(max(ax, bx) + BOX_MARGIN_M, x0, cell, nx), nx - 1)
        cy0 = max(_cell_index(min(ay, by) - BOX_MARGIN_M, y0, cell, ny), 0)
        cy1 = min(_cell_index(max(ay, by) + BOX_MARGIN_M, y0, cell, ny), ny - 1)
        m = 0
        for gy in range(cy0, cy1 + 1):
            for gx in range(cx0, cx1 + 1):
                c = gy * nx + gx
                cnt[o] += 1
                for g in range(gstart[c], gstart[c + 1]):
                    cnt[o + 1] += 1
                    b = gids[g]
                    if seen[b] == stamp:
                        continue
                    seen[b] = stamp
                    if heights[b] > h_ant and _box_distance(cx, cy, boxes[b]) <= radius:
                        out[m] = b
                        m += 1
        cnt[o + 2] += m
        return m

    @njit
    def hits_c(px, py, dx, dy, tan_el, h_ant, t_lo, t_hi, skip_edge, cand, m, edges, estart, boxes, heights, cnt,
               o):
        for q in range(m):
            b = cand[q]
            hb = heights[b]
            t_in, t_out = _ray_box_span(px, py, dx, dy, boxes[b, 0] - BOX_MARGIN_M, boxes[b, 1] - BOX_MARGIN_M,
                                        boxes[b, 2] + BOX_MARGIN_M, boxes[b, 3] + BOX_MARGIN_M)
            t_in, t_out = max(t_in, t_lo), min(t_out, t_hi)
            if t_in > t_out or t_in * tan_el + h_ant >= hb:
                continue
            cnt[o] += 1
            for e in range(estart[b], estart[b + 1]):
                if e == skip_edge:
                    continue
                cnt[o + 1] += 1
                ax, ay = edges[e, 0] - px, edges[e, 1] - py
                ex, ey = edges[e, 2] - edges[e, 0], edges[e, 3] - edges[e, 1]
                den = dx * ey - dy * ex
                if den == 0.0:
                    continue
                t = (ax * ey - ay * ex) / den
                u = (ax * dy - ay * dx) / den
                if t_lo < t < t_hi and 0.0 <= u <= 1.0 and t * tan_el + h_ant < hb:
                    cnt[o + 2] += 1
                    return True
        return False

    @njit
    def reflect_c(xy, blocked, cstart, cids, cbd, radius, edges, estart, boxes, heights, de, dn, tan_el, cos_el,
                  h_ant, lines, fx0, fy0, fcell, fnx, fny, fstart, fids, cnt):
        n, s = blocked.shape
        nb = heights.size
        seen = np.full(nb, -1, dtype=np.int64)
        cand2 = np.empty(nb, dtype=np.int64)
        geo_of = np.full(nb, -1, dtype=np.int64)
        ne = edges.shape[0]
        c_ex = np.empty(ne)
        c_e = np.empty(ne, dtype=np.int64)
        c_t = np.empty(ne)
        c_n = np.empty((ne, 2))
        c_c = np.empty(ne)
        f_d = np.empty(ne)
        f_s = np.empty(ne)
        h_max = 0.0
        for b in range(nb):
            h_max = max(h_max, heights[b])
        stamp = 0
        eps = 1e-6
        for i in range(n):
            px, py = xy[i, 0], xy[i, 1]
            any_blocked = False
            for k in range(s):
                if blocked[i, k]:
                    any_blocked = True
                    break
            if not any_blocked:
                continue
            cnt[0] += 1
            c0 = cstart[i]
            m = cstart[i + 1] - c0
            cand, bdist = cids[c0:c0 + m], cbd[c0:c0 + m]
            for k in range(s):
                if not blocked[i, k] or tan_el[k] <= 0.0:
                    continue
                cnt[1] += 1
                ux, uy = de[k], dn[k]
                nc = 0
                for q in range(m):
                    cnt[2] += 1
                    b = cand[q]
                    hb = heights[b]
                    if bdist[q] * tan_el[k] + h_ant >= hb:
                        continue
                    cnt[3] += 1
                    if geo_of[b] != i:
                        cnt[4] += 1
                        geo_of[b] = i
                        for e in range(estart[b], estart[b + 1]):
                            f_d[e] = -1.0
                            if lines[e, 2] == 0.0:
                                continue
                            d = (edges[e, 0] - px) * lines[e, 3] + (edges[e, 1] - py) * lines[e, 4]
                            sg = 1.0
                            if d < 0.0:
                                sg, d = -1.0, -d
                            if d < eps:
                                continue
                            f_d[e], f_s[e] = d, sg
                    for e in range(estart[b], estart[b + 1]):
                        cnt[5] += 1
                        d = f_d[e]
                        if d < 0.0:
                            continue
                        cnt[6] += 1
                        nxw, nyw = f_s[e] * lines[e, 3], f_s[e] * lines[e, 4]
                        cphi = -(ux * nxw + uy * nyw)
                        if cphi <= eps:
                            continue
                        cnt[7] += 1
                        t = d / cphi
                        if t * tan_el[k] + h_ant >= hb:
                            continue
                        cnt[8] += 1
                        ax, ay, ex, ey, ln = edges[e, 0], edges[e, 1], lines[e, 0], lines[e, 1], lines[e, 2]
                        qx, qy = px + t * (ux + 2.0 * cphi * nxw), py + t * (uy + 2.0 * cphi * nyw)
                        w = ((qx - ax) * ex + (qy - ay) * ey) / (ln * ln)
                        if w < 0.0 or w > 1.0:
                            continue
                        cnt[9] += 1
                        c_ex[nc] = 2.0 * d * cos_el[k] * cphi
                        c_e[nc] = e
                        c_t[nc] = t
                        c_n[nc, 0], c_n[nc, 1] = nxw, nyw
                        c_c[nc] = cphi
                        nc += 1
                if nc == 0:
                    continue
                cnt[10] += 1
                order = np.argsort(c_ex[:nc])
                t_top = (h_max - h_ant) / tan_el[k] * (1.0 + 1e-9) + BOX_MARGIN_M
                for j in order:
                    e, t, cphi = c_e[j], c_t[j], c_c[j]
                    nxw, nyw = c_n[j, 0], c_n[j, 1]
                    rx, ry = ux + 2.0 * cphi * nxw, uy + 2.0 * cphi * nyw
                    cnt[11] += 1
                    m1 = leg_c(px, py, rx, ry, 0.0, t, fx0, fy0, fcell, fnx, fny, fstart, fids, px, py, radius,
                               boxes, heights, h_ant, seen, stamp, cand2, cnt, 12)
                    stamp += 1
                    if hits_c(px, py, rx, ry, tan_el[k], h_ant, eps, t - eps, e, cand2, m1, edges, estart, boxes,
                              heights, cnt, 15):
                        continue
                    d = t * cphi
                    ix, iy = px + 2.0 * d * nxw, py + 2.0 * d * nyw
                    cnt[18] += 1
                    m2 = leg_c(ix, iy, ux, uy, t, max(t, t_top), fx0, fy0, fcell, fnx, fny, fstart, fids, ix,
                               iy, radius, boxes, heights, h_ant, seen, stamp, cand2, cnt, 19)
                    stamp += 1
                    if hits_c(ix, iy, ux, uy, tan_el[k], h_ant, t + eps, np.inf, e, cand2, m2, edges, estart,
                              boxes, heights, cnt, 22):
                        continue
                    cnt[25] += 1
                    break

    return reflect_c


def counts(path: Path, first: int, last: int) -> None:
    """The work of the reflections kernel per step (means over the steps of the window)."""
    with open(path, "rb") as f:
        rec = pickle.load(f)
    reflect_c = _counting_kernels()
    calls = [(s, a) for s, a in rec["reflect"] if first < s <= last]
    cnt = np.zeros(len(R_NAMES), dtype=np.int64)
    for _, a in calls:
        reflect_c(*a, cnt)
    steps = len({s for s, _ in calls})
    print(f"reflections: {len(calls)} calls over {steps} steps; per step:")
    for name, c in zip(R_NAMES, cnt):
        print(f"  {name:>48}: {c / steps:10.1f}")
    sizes = [a[1].shape for _, a in calls]
    print(f"  vehicles x satellites per call: mean {np.mean([n for n, _ in sizes]):.1f} x "
          f"{np.mean([s for _, s in sizes]):.1f}; blocked share {np.mean([a[1].mean() for _, a in calls]):.3f}")


T_NAMES = ("targets calls", "pairs (vehicle, target)", "candidates in a field of view", "distinct sight lines",
           "vehicle buckets scanned", "footprints in the buckets", "footprints in the x window",
           "footprints past the box test", "side shortcut decided", "exact quad tests", "lines hidden by vehicles",
           "clear lines to the building walk", "walk samples", "samples in a near cell", "grid entries",
           "boxes tested", "boxes met", "polygon edges tested", "lines hidden by buildings")


def _counting_targets():
    import math

    from numba import njit

    from couplers.sensing.occlusion import (_quad_hides, _sampling, _segment_box, _segment_meets_box,
                                            _segment_meets_polygon, _segments_meet)

    @njit
    def quads_c(seg, skip_a, skip_b, quads, order, start, x0, width, xmin, xmax, ymin, ymax, max_wx, rectangle,
                cnt):
        m = seg.shape[0]
        nb = start.size - 1
        out = np.zeros(m, dtype=np.bool_)
        for i in range(m):
            ax, ay, bx, by, sx0, sx1, sy0, sy1, side_margin = _segment_box(seg, i)
            x_lo = sx0 - max_wx
            f0 = math.floor((x_lo - x0) / width)
            f1 = math.floor((sx1 - x0) / width)
            if math.isfinite(f0) and math.isfinite(f1):
                if f1 < 0 or f0 > nb - 1:
                    continue
                b0, b1 = int(max(f0, 0.0)), int(min(f1, nb - 1.0))
            else:
                b0, b1 = 0, nb - 1
            cnt[4] += b1 - b0 + 1
            for r in range(start[b0], start[b1 + 1]):
                cnt[5] += 1
                q = order[r]
                if q == skip_a[i] or q == skip_b[i] or xmin[q] < x_lo or xmin[q] > sx1:
                    continue
                cnt[6] += 1
                if xmax[q] < sx0 or ymax[q] < sy0 or ymin[q] > sy1:
                    continue
                cnt[7] += 1
                # the shortcut alone, counted
                if rectangle[q]:
                    dx, dy = bx - ax, by - ay
                    above = 0
                    below = 0
                    for k in range(4):
                        p1 = dx * (quads[q, k, 1] - ay)
                        p2 = dy * (quads[q, k, 0] - ax)
                        o = p1 - p2
                        bound = side_margin + 1e-12 * (abs(p1) + abs(p2))
                        if o > bound:
                            above += 1
                        elif o < -bound:
                            below += 1
                    if above == 4 or below == 4:
                        cnt[8] += 1
                        continue
                cnt[9] += 1
                if _quad_hides(quads, q, rectangle[q], ax, ay, bx, by, side_margin):
                    out[i] = True
                    break
        for i in range(m):
            if out[i]:
                cnt[10] += 1
        return out

    @njit
    def buildings_c(seg, x0, y0, cell, near, start, ids, boxes, margin, edge_start, edges, cnt):
        m = seg.shape[0]
        ny, nx = near.shape
        out = np.zeros(m, dtype=np.int8)
        seen = np.full(boxes.shape[0], -1, dtype=np.int64)
        cnt[11] += m
        for i in range(m):
            ax, ay, bx, by = seg[i, 0], seg[i, 1], seg[i, 2], seg[i, 3]
            gx, gy, sx, sy, k_max = _sampling(ax, ay, bx, by, x0, y0, cell)
            if k_max < 0:
                out[i] = 2
                continue
            for k in range(k_max + 1):
                cnt[12] += 1
                fx = math.floor(gx + sx * k)
                fy = math.floor(gy + sy * k)
                if not (0 <= fx < nx and 0 <= fy < ny) or not near[int(fy), int(fx)]:
                    continue
                cnt[13] += 1
                c = int(fy) * nx + int(fx)
                for q in range(start[c], start[c + 1]):
                    cnt[14] += 1
                    b = ids[q]
                    if seen[b] == i:
                        continue
                    seen[b] = i
                    cnt[15] += 1
                    if _segment_meets_box(ax, ay, bx, by, boxes[b, 0] - margin, boxes[b, 1] - margin,
                                          boxes[b, 2] + margin, boxes[b, 3] + margin):
                        cnt[16] += 1
                        cnt[17] += edge_start[b + 1] - edge_start[b]
                        if _segment_meets_polygon(ax, ay, bx, by, edges, edge_start[b], edge_start[b + 1]):
                            out[i] = 1
                            break
                if out[i]:
                    break
        for i in range(m):
            if out[i] == 1:
                cnt[18] += 1
        return out

    return quads_c, buildings_c


def target_counts(path: Path, first: int, last: int) -> None:
    """The work of the targets stage per step (means over the steps of the window)."""
    from couplers.sensing.occlusion import OCCLUDER_BUCKET_M, _occluder_buckets, _rectangles
    from couplers.sensing.perception_kernels import _distinct_lines, _fov_stage, line_segments

    with open(path, "rb") as f:
        rec = pickle.load(f)
    quads_c, buildings_c = _counting_targets()
    calls = [(s, a) for s, a in rec["targets"] if first < s <= last]
    cnt = np.zeros(len(T_NAMES), dtype=np.int64)
    for _, a in calls:
        (_, _, xy, direction, mount_x, boresight, along, targets, pair_owner, pair_target, range_m, cos_half, full,
         heading, yaw_deg, fov_deg, groups, observer_occluder, target_occluder, use_vehicles, corners,
         use_buildings, x0, y0, cell, near, b_start, b_ids, b_boxes, b_margin, edge_start, edges) = a[:32]
        n_s = mount_x.size
        origins, target, pair, dist, sensor, _, _, _, _ = _fov_stage(
            xy, direction, mount_x, boresight, along, targets, pair_owner, pair_target, range_m, cos_half, full,
            np.zeros(xy.shape[0] * n_s, dtype=np.int64), n_s, np.empty(0), np.empty(0), heading, yaw_deg, fov_deg)
        line, line_of = _distinct_lines(pair, sensor, groups, pair_owner.size)
        seg, skip_a = line_segments(line, pair, sensor, pair_owner, origins, target, observer_occluder)
        skip_b = np.array([target_occluder[pair_target[pair[c]]] for c in line], dtype=np.int64)
        cnt[0] += 1
        cnt[1] += pair_owner.size
        cnt[2] += pair.size
        cnt[3] += line.size
        hidden = np.zeros(line.size, dtype=bool)
        if use_vehicles and line.size and corners.shape[0]:
            bk = _occluder_buckets(corners, OCCLUDER_BUCKET_M)
            hidden = quads_c(seg, skip_a, skip_b, corners, *bk, _rectangles(corners), cnt)
        rows = np.flatnonzero(~hidden)
        if use_buildings and rows.size:
            buildings_c(seg[rows], x0, y0, cell, near, b_start, b_ids, b_boxes, b_margin, edge_start, edges, cnt)
    steps = len({s for s, _ in calls})
    print(f"targets stage: {len(calls)} calls over {steps} steps; per step:")
    for name, c in zip(T_NAMES, cnt):
        print(f"  {name:>48}: {c / steps:10.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("capture", "replay", "counts"))
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("/tmp/world_kernels.pkl"))
    ap.add_argument("--old", type=Path, default=Path("/work/main"))
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--first", type=int, default=80)
    ap.add_argument("--last", type=int, default=400)
    ap.add_argument("--what", default="reflect,targets")
    args = ap.parse_args()
    if args.mode == "capture":
        capture(args.duration, args.seed, args.out)
    elif args.mode == "counts":
        counts(args.out, args.first, args.last)
        target_counts(args.out, args.first, args.last)
    else:
        replay(args.out, args.old, args.rounds, args.first, args.last, args.what)


if __name__ == "__main__":
    main()
