"""Detections as the sensor reports them (opt-in ``[perception] detections = "range_bearing"``): range,
bearing and range rate in each sensor's own frame, with noise in those coordinates.

:func:`couplers.sensing.perception.perceive` decides which features each vehicle detects (field of view,
P_D, occlusion, merge, clutter, shuffle) exactly as with ``detections = "net_xy"``; this module then
re-expresses every row in the frame of the sensor that reported it and replaces the net-frame noise by
the sensor's own (``sigma_r_m``, ``sigma_b_deg``, ``sigma_rdot_mps`` of each ``[[perception.sensors]]``).
Per row k of vehicle i (position x_i, [scenario] reference_point, true heading psi_i, velocity v_i), sensor s (mount
``mount_x_m`` along the heading, boresight yaw ``yaw_deg``):

    o   = x_i + mount_x u(psi_i)                         (the sensor's mount point)
    p   = x_F - o,  w = v_F - v_i                        (relative position and velocity, net frame)
    r   = |p| + sigma_r n_r
    b   = wrap(atan2(p_y, p_x) - psi_i - yaw) + sigma_b n_b
    rdot = p . w / |p| + sigma_rdot n_rdot

with x_F, v_F the true feature state for a detected feature; for a false detection (clutter) the point the
perception drew (its net-frame row, noise included: a uniformly drawn false alarm moved by a small
Gaussian is still a false alarm) and v_F = 0 (clutter looks like a static object). The sensor's velocity
is the vehicle's: the lever arm's rotation (yaw rate x mount_x) is neglected (zero for a mount at the
reference point), unless ``[perception] lever_arm_range_rate = true``: then the sensor moves with its mount
point, v_o = v_i + omega_i mount_x u_perp(psi_i) (u_perp(a) = [-sin a, cos a]), and

    rdot = p . (v_F - v_o) / |p| + sigma_rdot n_rdot

with omega_i the true yaw rate over the step, wrap(psi_i(t) - psi_i(t - Ts)) / Ts from SUMO's headings of
this step and the previous one (the rate :mod:`couplers.sensing.inertial` gives the IMU; 0 for a vehicle
that entered this step). The rows then come as :class:`coloc.core.detections.MountSensorDetections`, which
tells an estimator the range rate is the sensor's own. n ~ N(0, I3) per row from the perception's
"range_bearing" stream
(:func:`couplers.sensing.perception.effect_rng`), drawn in row order after the shuffle: every other
stream, and so every other measurement, is unchanged.

The frame then carries the rows in ``Frame.v2f_sensor`` (:class:`coloc.core.detections.SensorDetections`),
and ``v2f_z`` / ``v2f_R`` are NaN: they would carry the true heading.

Default noise (``SensorSpec``): Continental ARS 408-21 datasheet, near range: range accuracy +-0.10 m
(far range +-0.40 m), azimuth accuracy +-0.3 deg at boresight (+-1 deg at +-45 deg, +-5 deg at +-60 deg;
far range +-0.1 deg), velocity accuracy 0.1 km/h = 0.028 m/s; each "+-" read as one standard deviation
(assumption). The values are the datasheet's as quoted in the project's brief; they could not be checked
against the datasheet itself here. The 360 deg surround sensor takes the same near-range values (assumption).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numba import njit

from coloc.core.detections import MountSensorDetections, SensorDetections
from coloc.core.vehicles import match_ids
from coloc.core.frame import Frame
from couplers.sensing import streams
from couplers.sensing.inertial import true_body_motion
from couplers.sensing.road_users import KIND_PEDESTRIAN, KIND_VEHICLE
from couplers.sensing.perception import PERCEPTION_STREAM_TAG, Detections, PerceptionParams, effect_rng
from couplers.sensing.streams import StreamHandles, stream

RANGE_BEARING_STREAM = "range_bearing"


def wrap(a: np.ndarray) -> np.ndarray:
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(a, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi


def sensor_frame_rows(
    rel: np.ndarray, heading: np.ndarray, mount_x: np.ndarray, yaw: np.ndarray, w: np.ndarray,
    sigma_r: np.ndarray, sigma_b: np.ndarray, sigma_rdot: np.ndarray, yaw_rate: np.ndarray | None = None,
    cos_sin: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(range, bearing, range rate) (O,) of relative states ``rel`` (O, 4) = x_F - x_V (from the vehicle
    position), seen by a sensor ``mount_x`` (O,) along ``heading`` (O,) with boresight ``heading + yaw``;
    ``w`` (O, 3) standard normal draws scaled by the sigmas (module docstring). ``yaw_rate`` (O,): the owner's
    yaw rate, whose lever arm moves the sensor (``lever_arm_range_rate``); None: the vehicle's velocity.
    ``cos_sin``: numpy's cos and sin of ``heading`` when the caller has them (gathered from its vehicles' rows:
    an elementwise function of the same values)."""
    rel = np.asarray(rel, dtype=float)
    psi = np.asarray(heading, dtype=float)
    cp, sp = (np.cos(psi), np.sin(psi)) if cos_sin is None else cos_sin
    px = rel[:, 0] - mount_x * cp
    py = rel[:, 1] - mount_x * sp
    d = np.hypot(px, py)
    safe = np.maximum(d, 1e-300)
    if yaw_rate is None:
        rdot = (px * rel[:, 2] + py * rel[:, 3]) / safe
    else:  # v_F - v_o = (v_F - v_i) - omega mount_x u_perp(psi)
        arm = np.asarray(yaw_rate, dtype=float) * mount_x
        rdot = (px * (rel[:, 2] + arm * sp) + py * (rel[:, 3] - arm * cp)) / safe
    b = wrap(np.arctan2(py, px) - psi - yaw)
    return d + sigma_r * w[:, 0], b + sigma_b * w[:, 1], rdot + sigma_rdot * w[:, 2]


def relative_states(det: Detections, x_true: np.ndarray, features_true: np.ndarray) -> np.ndarray:
    """(O, 4) x_F - x_V of every row without noise: the true feature state of a detection, the drawn point
    (its net-frame row) and zero velocity of a false detection; another road user (a row without a feature)
    keeps its net-frame row, whose position and velocity noise it then carries as well. One numba pass
    (:func:`_relative_states`); :func:`relative_states_reference` is the numpy reference."""
    kind = getattr(det, "kind", None)
    return _relative_states(np.ascontiguousarray(det.owner, dtype=np.int64),
                            np.ascontiguousarray(det.feature, dtype=np.int64),
                            np.ascontiguousarray(det.z, dtype=np.float64).reshape(-1, 4),
                            np.ascontiguousarray(x_true, dtype=np.float64).reshape(-1, 4),
                            np.ascontiguousarray(features_true, dtype=np.float64).reshape(-1, 4),
                            np.zeros(0, dtype=np.int8) if kind is None else np.ascontiguousarray(kind, dtype=np.int8),
                            kind is not None)


@njit(cache=True)
def _relative_states(owner, feat, z, x_true, features_true, kind, has_kind):
    """:func:`relative_states_reference` row by row (the same subtractions and copies)."""
    rel = np.empty((owner.size, 4))
    for k in range(owner.size):
        i, f = owner[k], feat[k]
        if f >= 0:
            for j in range(4):
                rel[k, j] = features_true[f, j] - x_true[i, j]
            continue
        rel[k, 0], rel[k, 1] = z[k, 0], z[k, 1]
        if has_kind and (kind[k] == KIND_VEHICLE or kind[k] == KIND_PEDESTRIAN):
            rel[k, 2], rel[k, 3] = z[k, 2], z[k, 3]
        else:
            rel[k, 2], rel[k, 3] = -x_true[i, 2], -x_true[i, 3]
    return rel


_NO_KIND = np.zeros(0, dtype=np.int8)
_NO_RATE = np.zeros(0)


@njit(cache=True)
def _range_bearing_geometry(owner, sensor, feat, z, x_true, features_true, kind, has_kind, heading, cos_h, sin_h,
                            mount_s, yaw_s, sr_s, sb_s, srd_s):
    """Per row: the mount point's offset to the target (px, py) of :func:`sensor_frame_rows`, the relative state of
    :func:`relative_states`, and the row's heading, its cos / sin (``cos_h`` / ``sin_h`` per vehicle, numpy's),
    mount, yaw and sigmas gathered by owner and sensor (the same subtractions and products as the reference)."""
    o = owner.size
    rel = _relative_states(owner, feat, z, x_true, features_true, kind, has_kind)
    px = np.empty(o)
    py = np.empty(o)
    psi = np.empty(o)
    cp = np.empty(o)
    sp = np.empty(o)
    mount = np.empty(o)
    yaw = np.empty(o)
    sr = np.empty(o)
    sb = np.empty(o)
    srd = np.empty(o)
    for k in range(o):
        i, s = owner[k], sensor[k]
        psi[k], cp[k], sp[k] = heading[i], cos_h[i], sin_h[i]
        mount[k], yaw[k], sr[k], sb[k], srd[k] = mount_s[s], yaw_s[s], sr_s[s], sb_s[s], srd_s[s]
        px[k] = rel[k, 0] - mount[k] * cp[k]
        py[k] = rel[k, 1] - mount[k] * sp[k]
    return px, py, rel, psi, cp, sp, mount, yaw, sr, sb, srd


@njit(cache=True)
def _range_bearing_rows(px, py, d, ang, rel, psi, cp, sp, mount, yaw, w, sr, sb, srd, owner, yaw_rate, lever_arm):
    """(range, bearing, range rate) of :func:`sensor_frame_rows` from numpy's ``d`` = hypot(px, py) and ``ang`` =
    arctan2(py, px): the same operations in the same order (np.maximum's NaN kept, :func:`wrap` with numba's
    float ``%``, which is Python's, as numpy's remainder); ``yaw_rate`` (N,) per vehicle under ``lever_arm``."""
    o = px.size
    r = np.empty(o)
    b = np.empty(o)
    rdot = np.empty(o)
    two_pi = 2.0 * np.pi
    for k in range(o):
        safe = 1e-300 if d[k] < 1e-300 else d[k]  # np.maximum(d, 1e-300), NaN kept
        if lever_arm:
            arm = yaw_rate[owner[k]] * mount[k]
            rd = (px[k] * (rel[k, 2] + arm * sp[k]) + py[k] * (rel[k, 3] - arm * cp[k])) / safe
        else:
            rd = (px[k] * rel[k, 2] + py[k] * rel[k, 3]) / safe
        a = ang[k] - psi[k] - yaw[k]
        r[k] = d[k] + sr[k] * w[k, 0]
        b[k] = ((a + np.pi) % two_pi - np.pi) + sb[k] * w[k, 1]
        rdot[k] = rd + srd[k] * w[k, 2]
    return r, b, rdot


@njit(cache=True)
def _range_bearing_rows_drawn(h, px, py, d, ang, rel, psi, cp, sp, mount, yaw, sr, sb, srd, owner, yaw_rate,
                              lever_arm):
    """:func:`_range_bearing_rows` with its (O, 3) noise normals drawn here from the stream of handle ``h`` (numpy's
    ``standard_normal((O, 3))`` on it, couplers.sensing.streams)."""
    w = stream(h).standard_normal((px.size, 3))
    return _range_bearing_rows(px, py, d, ang, rel, psi, cp, sp, mount, yaw, w, sr, sb, srd, owner, yaw_rate,
                               lever_arm)


_NO_W = np.empty((0, 3))


def relative_states_reference(det: Detections, x_true: np.ndarray, features_true: np.ndarray) -> np.ndarray:
    """:func:`relative_states` in numpy (its reference in the tests)."""
    owner = np.asarray(det.owner, dtype=np.int64)
    feat = np.asarray(det.feature, dtype=np.int64)
    rel = np.empty((owner.size, 4))
    real = feat >= 0
    rel[real] = np.asarray(features_true, dtype=float)[feat[real]] - np.asarray(x_true, dtype=float)[owner[real]]
    rel[~real, :2] = np.asarray(det.z, dtype=float)[~real, :2]
    rel[~real, 2:] = -np.asarray(x_true, dtype=float)[owner[~real], 2:]
    kind = getattr(det, "kind", None)
    if kind is not None:  # other road users move: their net-frame row's relative velocity (couplers.sensing.road_users)
        kind = np.asarray(kind)
        moving = ~real & ((kind == KIND_VEHICLE) | (kind == KIND_PEDESTRIAN))
        rel[moving, 2:] = np.asarray(det.z, dtype=float)[moving, 2:]
    return rel


class SensorFrameRows:
    """The range-bearing re-expression of a run's detections, with its own random stream."""

    def __init__(self, params: PerceptionParams, seed: int):
        self.params = params
        self.rng = effect_rng(seed, PERCEPTION_STREAM_TAG, RANGE_BEARING_STREAM)
        self.handles = StreamHandles(self, ("rng",))  # the same stream, drawn in a kernel
        specs = params.sensors
        self._mount = np.array([s.mount_x_m for s in specs], dtype=float)
        self._yaw = np.deg2rad([s.yaw_deg for s in specs])
        self._sr = np.array([s.sigma_r_m for s in specs], dtype=float)
        self._sb = np.deg2rad([s.sigma_b_deg for s in specs])
        self._srd = np.array([s.sigma_rdot_mps for s in specs], dtype=float)
        self.lever_arm = bool(params.lever_arm_range_rate)
        self._ids = np.empty(0, dtype=object)  # the previous step's vehicles and true headings (lever arm only)
        self._heading = np.empty(0)

    def detections(self, det: Detections, x_true: np.ndarray, heading: np.ndarray,
                   features_true: np.ndarray, yaw_rate: np.ndarray | None = None) -> SensorDetections:
        """The rows in the sensors' frames; ``yaw_rate`` (N,) per vehicle: the sensors move with their lever arm
        (:class:`MountSensorDetections`), None: with the vehicle."""
        owner = np.ascontiguousarray(det.owner, dtype=np.int64)
        # the noise normals: numpy's, or where numba's draws are numpy's the same drawn in the rows' kernel
        in_kernel = streams.available()
        w = _NO_W if in_kernel else self.rng.standard_normal((owner.size, 3))
        heading = np.ascontiguousarray(heading, dtype=np.float64)
        kind = getattr(det, "kind", None)
        # The rows of sensor_frame_rows(relative_states(...), ...) (its reference, tested bit for bit): the
        # gathers, relative states and mount offsets in one kernel, numpy's hypot and arctan2 on its output, the
        # rest in a second kernel. cos / sin once per vehicle (numpy's), gathered per row in the kernel.
        px, py, rel, psi, cp, sp, mount, yaw, sr, sb, srd = _range_bearing_geometry(
            owner, np.ascontiguousarray(det.sensor, dtype=np.int64), np.ascontiguousarray(det.feature, dtype=np.int64),
            np.ascontiguousarray(det.z, dtype=np.float64).reshape(-1, 4),
            np.ascontiguousarray(x_true, dtype=np.float64).reshape(-1, 4),
            np.ascontiguousarray(features_true, dtype=np.float64).reshape(-1, 4),
            _NO_KIND if kind is None else np.ascontiguousarray(kind, dtype=np.int8), kind is not None,
            heading, np.cos(heading), np.sin(heading), self._mount, self._yaw, self._sr, self._sb, self._srd)
        om = _NO_RATE if yaw_rate is None else np.ascontiguousarray(yaw_rate, dtype=np.float64)
        rows = (px, py, np.hypot(px, py), np.arctan2(py, px), rel, psi, cp, sp, mount, yaw)
        tail = (sr, sb, srd, owner, om, yaw_rate is not None)
        r, b, rdot = (_range_bearing_rows_drawn(self.handles["rng"], *rows, *tail) if in_kernel
                      else _range_bearing_rows(*rows, w, *tail))
        cls = SensorDetections if yaw_rate is None else MountSensorDetections
        return cls(range=r, bearing=b, range_rate=rdot, mount_x=mount, yaw=yaw, sigma_range=sr, sigma_bearing=sb,
                   sigma_range_rate=srd)

    def true_yaw_rate(self, ids: np.ndarray, entered: np.ndarray, heading: np.ndarray, dt: float) -> np.ndarray:
        """(N,) wrap(psi - psi_prev) / dt per vehicle from this step's and the previous call's true headings (0 for
        a vehicle that entered or was not there; module docstring), and the headings kept for the next call."""
        heading = np.asarray(heading, dtype=float)
        idx = match_ids(self._ids, ids)
        prev = np.full(heading.shape, np.nan)
        ok = (idx >= 0) & ~np.asarray(entered, dtype=bool)
        prev[ok] = self._heading[idx[ok]]
        self._ids, self._heading = np.asarray(ids, dtype=object), heading.copy()
        return true_body_motion(np.zeros((heading.size, 2)), heading, prev, dt)[1]

    def apply(self, frame: Frame, det: Detections, x_true: np.ndarray, heading: np.ndarray,
              features_true: np.ndarray) -> Frame:
        """``frame`` with ``v2f_sensor`` set and ``v2f_z`` / ``v2f_R`` NaN (rows in ``det``'s order, which is
        the frame's)."""
        return replace(frame, **self.fields(frame, det, x_true, heading, features_true))

    def fields(self, frame: Frame, det: Detections, x_true: np.ndarray, heading: np.ndarray,
               features_true: np.ndarray) -> dict:
        """The fields :meth:`apply` sets, for a caller that sets others in the same ``replace``."""
        return self.frame_fields(det, x_true, heading, features_true, frame.vehicle_ids, frame.entered,
                                 float(frame.dt), frame.v2f_z, frame.v2f_R)

    def frame_fields(self, det: Detections, x_true: np.ndarray, heading: np.ndarray, features_true: np.ndarray,
                     ids: np.ndarray, entered: np.ndarray, dt: float, v2f_z: np.ndarray | None = None,
                     v2f_R: np.ndarray | None = None) -> dict:
        """:meth:`fields` before the frame exists (its vehicles ``ids``, ``entered``, step ``dt``; the net-frame
        rows ``v2f_z`` / ``v2f_R`` it would carry, by default ``det``'s), for a caller that builds the frame with
        them."""
        om = self.true_yaw_rate(ids, entered, heading, dt) if self.lever_arm else None
        sd = self.detections(det, x_true, heading, features_true, om)
        v2f_z = det.z if v2f_z is None else v2f_z
        v2f_R = det.R if v2f_R is None else v2f_R
        return dict(v2f_sensor=sd, v2f_z=np.full_like(v2f_z, np.nan), v2f_R=np.full_like(v2f_R, np.nan))
