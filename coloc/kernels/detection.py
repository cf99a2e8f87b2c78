"""P_D of (vehicle, track) pairs in one numba pass: :func:`coloc.core.detection.expected_detection_probability`
(the reference, whose docstring gives the model) on index pairs into the vehicles' estimates and the
tracks' predictions, without gathering them first, with the same floating-point operations in the same
order (the scalars of each sensor, e.g. cos(fov / 2), computed by numpy as the reference computes them);
tests compare the two byte for byte."""

from __future__ import annotations

import numpy as np
from numba import njit

from coloc.core.detection import DetectionModel


def sensor_constants(model: DetectionModel) -> tuple[np.ndarray, ...]:
    """Per sensor, as the reference computes them: mount_x, range, pd_near, pd_far, whether the field of
    view is the full circle, cos(fov / 2) - 1e-12, cos(yaw), sin(yaw), fov / 360."""
    ns = len(model.fov_deg)
    cos_half, cos_yaw, sin_yaw, share = np.zeros(ns), np.zeros(ns), np.zeros(ns), np.zeros(ns)
    full = np.zeros(ns, dtype=np.bool_)
    for s in range(ns):
        full[s] = model.fov_deg[s] >= 360.0
        if not full[s]:
            cos_half[s] = np.cos(np.deg2rad(model.fov_deg[s]) / 2.0) - 1e-12
            yaw = np.deg2rad(model.yaw_deg[s])
            cos_yaw[s], sin_yaw[s] = np.cos(yaw), np.sin(yaw)
            share[s] = model.fov_deg[s] / 360.0
    f64 = [np.asarray(getattr(model, k), dtype=np.float64) for k in ("mount_x_m", "range_m", "pd_near", "pd_far")]
    return (*f64, full, cos_half, cos_yaw, sin_yaw, share)


def detection_probability_pairs(v_mean: np.ndarray, t_mean: np.ndarray, vi: np.ndarray, ti: np.ndarray,
                                model: DetectionModel) -> np.ndarray:
    """``expected_detection_probability(v_mean[vi], t_mean[ti, :2], model)``, byte for byte."""
    return _pairs_kernel(np.ascontiguousarray(v_mean, dtype=np.float64), np.ascontiguousarray(t_mean, dtype=np.float64),
                         np.ascontiguousarray(vi, dtype=np.int64), np.ascontiguousarray(ti, dtype=np.int64),
                         *sensor_constants(model), float(model.heading_min_speed), float(model.visibility))


@njit(cache=True)
def _pairs_kernel(v_mean, t_mean, vi, ti, mount_x, range_m, pd_near, pd_far, full, cos_half, cos_yaw, sin_yaw,
                  share, heading_min_speed, visibility):
    p = vi.size
    out = np.empty(p)
    for a in range(p):
        i, k = vi[a], ti[a]
        speed = np.hypot(v_mean[i, 2], v_mean[i, 3])
        known = speed >= heading_min_speed
        ux, uy = 1.0, 0.0
        if known:  # np.maximum(speed, 1e-300) of a speed that is not NaN here
            den = speed if speed > 1e-300 else 1e-300
            ux, uy = v_mean[i, 2] / den, v_mean[i, 3] / den
        miss = 1.0
        for s in range(mount_x.size):
            ox = v_mean[i, 0] + mount_x[s] * ux
            oy = v_mean[i, 1] + mount_x[s] * uy
            dx, dy = t_mean[k, 0] - ox, t_mean[k, 1] - oy
            d = np.hypot(dx, dy)
            rng = range_m[s]
            pd = 0.0
            if d <= rng:
                q = d / rng
                if q > 1.0:  # np.minimum(d / rng, 1.0); q is not NaN here
                    q = 1.0
                pd = pd_near[s] + (pd_far[s] - pd_near[s]) * q
            if full[s]:
                seen = 1.0
            elif known:
                bx = ux * cos_yaw[s] - uy * sin_yaw[s]
                by = ux * sin_yaw[s] + uy * cos_yaw[s]
                dd = d if d > 1e-300 else 1e-300  # np.maximum(d, 1e-300): with d NaN the test below is False either way
                cos_angle = (dx * bx + dy * by) / dd
                seen = 1.0 if (cos_angle >= cos_half[s]) or (d == 0.0) else 0.0
            else:
                seen = share[s]
            miss *= 1.0 - pd * seen
        out[a] = (1.0 - miss) if visibility == 1.0 else visibility * (1.0 - miss)
    return out
