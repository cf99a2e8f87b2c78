"""What a vehicle expects its own sensors to detect: the detection model an estimator may use.

A vehicle knows its sensors' datasheet (field of view, range, mounting, detection profile), not
where the features are. :class:`DetectionModel` holds that datasheet as arrays over the sensors;
:func:`expected_detection_probability` gives, for a vehicle's *estimated* position and velocity
and a track's *predicted* position, the probability that at least one sensor detects the track,
P_D = 1 - prod_s (1 - P_D,s(d_s) [track in the field of view of s]), with the same geometry as the
coupler's perception model (couplers.sensing.perception: a sector of opening fov_deg and radius range_m
around the heading turned by yaw_deg, from the mount point mount_x_m along the heading; P_D,s
linear in distance from pd_near at 0 m to pd_far at the range). Occlusion is not predicted (the
vehicle does not know every occluder: unequipped vehicles, buildings); ``visibility`` is the share
of in-view tracks the estimator expects not to be hidden, a constant that scales P_D (1: nothing
is ever hidden, which makes every miss of an occluded track evidence against it).

The heading is the direction of the estimated velocity. Below ``heading_min_speed`` that
direction is noise, so the heading is taken as unknown and uniform: each sensor then detects
with its distance profile times the share of directions it covers, fov_deg / 360.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DetectionModel", "expected_detection_probability"]


@dataclass(frozen=True)
class DetectionModel:
    """The sensors of every vehicle, as tuples over the sensors (same order, same length)."""

    fov_deg: tuple[float, ...]
    range_m: tuple[float, ...]
    yaw_deg: tuple[float, ...]
    mount_x_m: tuple[float, ...]
    pd_near: tuple[float, ...]
    pd_far: tuple[float, ...]
    heading_min_speed: float = 1.0
    visibility: float = 1.0  # P(an in-view track is not occluded), as the estimator expects it

    def __post_init__(self):
        if not 0.0 < self.visibility <= 1.0:
            raise ValueError("visibility must be in (0, 1]")
        n = len(self.fov_deg)
        if n == 0 or any(len(getattr(self, k)) != n for k in ("range_m", "yaw_deg", "mount_x_m", "pd_near", "pd_far")):
            raise ValueError("a detection model needs at least one sensor and equally long tuples")

    @property
    def max_range_m(self) -> float:
        return float(max(r + abs(m) for r, m in zip(self.range_m, self.mount_x_m)))


def expected_detection_probability(
    v_mean: np.ndarray, t_xy: np.ndarray, model: DetectionModel
) -> np.ndarray:
    """P_D of each (vehicle, track) pair: ``v_mean`` (P, 4) the vehicle's estimated state,
    ``t_xy`` (P, 2) the track's predicted position. 0 outside every sensor's field of view."""
    p = v_mean.shape[0]
    speed = np.hypot(v_mean[:, 2], v_mean[:, 3])
    known = speed >= model.heading_min_speed
    ux = np.where(known, v_mean[:, 2] / np.maximum(speed, 1e-300), 1.0)
    uy = np.where(known, v_mean[:, 3] / np.maximum(speed, 1e-300), 0.0)
    miss = np.ones(p)
    for s in range(len(model.fov_deg)):
        ox = v_mean[:, 0] + model.mount_x_m[s] * ux
        oy = v_mean[:, 1] + model.mount_x_m[s] * uy
        dx, dy = t_xy[:, 0] - ox, t_xy[:, 1] - oy
        d = np.hypot(dx, dy)
        rng = model.range_m[s]
        pd = np.where(d <= rng, model.pd_near[s] + (model.pd_far[s] - model.pd_near[s]) * np.minimum(d / rng, 1.0), 0.0)
        half = np.deg2rad(model.fov_deg[s]) / 2.0
        if model.fov_deg[s] >= 360.0:
            seen = np.ones(p)
        else:
            yaw = np.deg2rad(model.yaw_deg[s])
            bx = ux * np.cos(yaw) - uy * np.sin(yaw)
            by = ux * np.sin(yaw) + uy * np.cos(yaw)
            cos_angle = (dx * bx + dy * by) / np.maximum(d, 1e-300)
            inside = (cos_angle >= np.cos(half) - 1e-12) | (d == 0.0)
            seen = np.where(known, inside.astype(float), model.fov_deg[s] / 360.0)
        miss *= 1.0 - pd * seen
    return (1.0 - miss) if model.visibility == 1.0 else model.visibility * (1.0 - miss)
