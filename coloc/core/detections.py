"""Sensor-frame detections (opt-in ``[perception] detections = "range_bearing"``): what a radar reports,
and how an estimator turns it into model (4)'s relative measurement with its *own* heading estimate.

The frame carries, per V2F row, :class:`SensorDetections` (``Frame.v2f_sensor``): range r, bearing b in
the sensor's frame (relative to the vehicle heading plus the sensor's mounting yaw, counter-clockwise),
range rate rdot (radial velocity, positive when the target moves away), the sensor's mounting
(``mount_x`` along the heading from the vehicle position, ``yaw``) and the noise std of r, b and rdot.
``Frame.v2f_z`` / ``Frame.v2f_R`` are then NaN: the net-frame rows would carry the true heading.

Conversion (:func:`to_net_frame`), with psi the estimator's heading of the owner vehicle, u(a) =
[cos a, sin a] and u_perp(a) = [-sin a, cos a], phi = psi + yaw + b the line of sight in the net frame:

    z_p = mount_x u(psi) + r u(phi)                      (position of model (4): x_F - x_V)
    z_v = rdot u(phi) + 0 u_perp(phi)                    (velocity: radial component measured)

and, to first order in the noise of (r, b, rdot) and in the heading error (variance ``heading_var``),

    R = J diag(sigma_r^2, sigma_b^2, sigma_rdot^2, heading_var) J^T + sigma_t^2 [0; u_perp(phi)][0; u_perp(phi)]^T
        + E[(cos d - 1)^2] z z^T,   d ~ N(0, heading_var)

with J = d z / d (r, b, rdot, psi): columns [u(phi); 0], [r u_perp(phi); rdot u_perp(phi)], [0; u(phi)],
[mount_x u_perp(psi) + r u_perp(phi); rdot u_perp(phi)]. A 1 deg heading error at 50 m moves z_p by 0.87 m.
The last term is second order in the heading error: z is a body-frame vector rotated by psi, so an error d
rotates z by d, and the part along z, (cos d - 1) z, is missed by J (a bias of r heading_var / 2 toward the
vehicle, 0.05 m at 80 m and 2 deg, against sigma_r = 0.1 m).

Lever arm (:class:`MountSensorDetections`, the frames of ``[perception] lever_arm_range_rate = true``): the
range rate is then the sensor's own, relative to its mount point, which moves with the vehicle's velocity plus
omega mount_x u_perp(psi) (omega the yaw rate). The radial component of the relative velocity of model (4) is
then

    rdot_c = rdot + omega mount_x sin(yaw + b)           (u(phi) . u_perp(psi) = sin(phi - psi))

and z_v = rdot_c u(phi) + 0 u_perp(phi); the Jacobian gains d z_v / d omega = [0; mount_x sin(yaw + b) u(phi)]
and, in the bearing's column, omega mount_x cos(yaw + b) u(phi) in the velocity part, with rdot_c in place of
rdot everywhere else. omega is the estimator's own: the IMU's gyroscope ``Frame.imu.yaw_rate`` with variance
:data:`GYRO_YAW_RATE_SIGMA` ^2 carried into R through that Jacobian, like the heading's. A frame without an IMU
gives the estimator no yaw rate of its own: omega is taken as 0 without variance, i.e. the rows are converted
as without the lever arm (up to 2.25 m x 0.3 rad/s = 0.7 m/s of radial velocity missed in a sharp turn).

Tangential velocity: a radar measures the radial component only. Model (4) needs a 2-D relative
velocity, so the tangential component is carried as 0 with std :data:`TANGENTIAL_SIGMA_MPS` = 30 m/s: the
relative velocity of anything in view in urban traffic is bounded by two vehicles closing at 50 km/h
each (27.8 m/s), so 0 +- 30 m/s holds the truth within one std while adding almost no information
(1/900 per row against 1/sigma_rdot^2 ~ 1300 along the line of sight). Every estimator then keeps its
4-D model (4) unchanged; the rows' tangential information is what a radar has: next to none.

Heading estimate (:func:`heading_from_velocity`, :class:`HeadingMemory`): psi = atan2(vy, vx) of the
estimator's velocity estimate of the owner at t (its belief after prediction and the GNSS update,
before any V2F row), var = g P_vv g^T with g = [-vy, vx] / |v|^2 (first-order atan2). Below
``heading_min_speed`` ([motion], the rule of :mod:`coloc.core.inertial`) the direction of the velocity
is noise: the vehicle keeps the heading (and variance) it last had above that speed, held (not
dead-reckoned by ``Frame.imu``'s yaw rate: a slow vehicle mostly stands in a queue, where a gyro's
turn-on bias of 0.5 deg/s would turn the heading by 30 deg a minute), its variance growing by
(0.01 rad/s Ts)^2 a step (an assumed slow rotation while crawling);
a vehicle that has never been fast enough takes the velocity's direction with its first-order variance
capped at pi^2 / 3 (a heading uniform on the circle), so its rows carry almost no information across
the line of sight.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

if TYPE_CHECKING:  # coloc.core.frame imports this module for SensorDetections
    from coloc.core.frame import Frame

__all__ = ["SensorDetections", "MountSensorDetections", "TANGENTIAL_SIGMA_MPS", "to_net_frame",
           "heading_from_velocity", "HeadingMemory", "with_net_detections", "HEADING_VAR_UNKNOWN",
           "GYRO_YAW_RATE_SIGMA"]

#: Std of the unobserved tangential relative velocity (m/s): see the module docstring.
TANGENTIAL_SIGMA_MPS = 30.0
#: Variance of a heading uniform on the circle, pi^2 / 3 (rad^2): the cap of an unknown heading.
HEADING_VAR_UNKNOWN = float(np.pi ** 2 / 3.0)
#: Yaw rate (rad/s) whose square times Ts^2 the kept heading's variance of a slow vehicle grows by per step.
YAW_RATE_SIGMA = 0.01
#: Std (rad/s) an estimator assumes for its gyroscope's yaw rate in the lever-arm term of the range rate: the
#: turn-on bias of 0.5 deg/s (RotorS' default gyroscope, the value the heading rule below also cites), which
#: dominates the white noise of a step's mean rate.
GYRO_YAW_RATE_SIGMA = float(np.radians(0.5))


@dataclass(frozen=True)
class SensorDetections:
    """The V2F rows as the sensors report them (rows aligned with ``Frame.v2f_owner``)."""

    range: np.ndarray  # (O,) m, from the sensor's mount point
    bearing: np.ndarray  # (O,) rad, from the sensor's boresight (heading + yaw), counter-clockwise
    range_rate: np.ndarray  # (O,) m/s, d range / dt (positive: receding)
    mount_x: np.ndarray  # (O,) m, mount point along the heading from the vehicle position (known calibration)
    yaw: np.ndarray  # (O,) rad, boresight relative to the heading (known calibration)
    sigma_range: np.ndarray  # (O,) m, noise std (the sensor's datasheet)
    sigma_bearing: np.ndarray  # (O,) rad
    sigma_range_rate: np.ndarray  # (O,) m/s

    #: The range rate is relative to the sensor's own mount point (yaw rate x lever arm included): False here.
    range_rate_at_mount: ClassVar[bool] = False


@dataclass(frozen=True)
class MountSensorDetections(SensorDetections):
    """:class:`SensorDetections` whose range rate is relative to the sensor's mount point, which moves with the
    vehicle's yaw rate times the lever arm (module docstring, "Lever arm")."""

    range_rate_at_mount: ClassVar[bool] = True


def _rows_and_directions(det: SensorDetections, heading: np.ndarray, rdot: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The net-frame rows z (O, 4) of model (4) from range, bearing, the mounting and the range rate ``rdot``
    (the vehicle's radial component), and the directions of R = J diag(...) J^T written out: e = u(phi),
    n = u_perp(phi), g = d z_p / d psi = mount u_perp(psi) + r n (each (O, 2))."""
    r = np.asarray(det.range, dtype=float)
    mount = np.asarray(det.mount_x, dtype=float)
    psi = np.asarray(heading, dtype=float)
    phi = psi + np.asarray(det.yaw, dtype=float) + np.asarray(det.bearing, dtype=float)
    c, s = np.cos(phi), np.sin(phi)
    ch, sh = np.cos(psi), np.sin(psi)
    z = np.empty((r.shape[0], 4))
    z[:, 0] = mount * ch + r * c
    z[:, 1] = mount * sh + r * s
    z[:, 2] = rdot * c
    z[:, 3] = rdot * s
    e = np.stack([c, s], axis=1)
    n = np.stack([-s, c], axis=1)
    g = np.stack([-mount * sh - r * s, mount * ch + r * c], axis=1)
    return z, e, n, g


def to_net_frame(
    det: SensorDetections, heading: np.ndarray, heading_var: np.ndarray,
    tangential_sigma: float = TANGENTIAL_SIGMA_MPS, yaw_rate: np.ndarray | None = None,
    yaw_rate_var: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Model (4)'s (z (O, 4), R (O, 4, 4)) from sensor-frame rows and the owner's heading estimate per
    row (``heading``, ``heading_var`` (O,)); the equations are in the module docstring. Vectorised over
    the rows. ``yaw_rate``, ``yaw_rate_var`` (O,): the owner's yaw rate estimate and its variance, for rows
    whose range rate is the sensor's own (:func:`to_net_frame_lever_arm`); None: the range rate is taken as
    relative to the vehicle."""
    if yaw_rate is not None:
        return to_net_frame_lever_arm(det, heading, heading_var, yaw_rate,
                                      np.zeros_like(np.asarray(yaw_rate, dtype=float)) if yaw_rate_var is None
                                      else yaw_rate_var, tangential_sigma)
    r = np.asarray(det.range, dtype=float)
    rdot = np.asarray(det.range_rate, dtype=float)
    hv = np.asarray(heading_var, dtype=float)
    z, e, n, g = _rows_and_directions(det, heading, rdot)
    o = r.shape[0]
    ee = e[:, :, None] * e[:, None, :]
    nn = n[:, :, None] * n[:, None, :]
    var_r = np.asarray(det.sigma_range, dtype=float) ** 2
    var_b = np.asarray(det.sigma_bearing, dtype=float) ** 2
    var_rd = np.asarray(det.sigma_range_rate, dtype=float) ** 2
    R = np.empty((o, 4, 4))
    R[:, :2, :2] = (var_r[:, None, None] * ee + (var_b * r * r)[:, None, None] * nn
                    + hv[:, None, None] * g[:, :, None] * g[:, None, :])
    R[:, 2:, 2:] = (var_rd[:, None, None] * ee
                    + ((var_b + hv) * rdot * rdot + float(tangential_sigma) ** 2)[:, None, None] * nn)
    R[:, :2, 2:] = (var_b * r * rdot)[:, None, None] * nn + (hv * rdot)[:, None, None] * g[:, :, None] * n[:, None, :]
    R[:, 2:, :2] = R[:, :2, 2:].transpose(0, 2, 1)
    # Second order in the heading error d: z(psi + d) = Rot(d) z(psi), whose part along z, (cos d - 1) z, the
    # Jacobian misses; its mean square E[(cos d - 1)^2] for d ~ N(0, heading_var) is added along z (it
    # matters once r heading_var / 2 nears sigma_r: 2 deg at 80 m).
    k2 = 0.5 * (1.0 + np.exp(-2.0 * hv)) - 2.0 * np.exp(-0.5 * hv) + 1.0
    R += k2[:, None, None] * z[:, :, None] * z[:, None, :]
    return z, R


def to_net_frame_lever_arm(
    det: SensorDetections, heading: np.ndarray, heading_var: np.ndarray, yaw_rate: np.ndarray,
    yaw_rate_var: np.ndarray, tangential_sigma: float = TANGENTIAL_SIGMA_MPS,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`to_net_frame` for a range rate relative to the sensor's mount point (module docstring, "Lever
    arm"): rdot_c = rdot + omega mount_x sin(yaw + b), and the yaw rate's variance through its Jacobian."""
    r = np.asarray(det.range, dtype=float)
    mount = np.asarray(det.mount_x, dtype=float)
    hv = np.asarray(heading_var, dtype=float)
    om = np.asarray(yaw_rate, dtype=float)
    ov = np.asarray(yaw_rate_var, dtype=float)
    ab = np.asarray(det.yaw, dtype=float) + np.asarray(det.bearing, dtype=float)  # phi - psi
    sab, cab = np.sin(ab), np.cos(ab)
    rdot = np.asarray(det.range_rate, dtype=float) + om * mount * sab  # the vehicle's radial component
    q = om * mount * cab  # d rdot_c / d b
    arm = mount * sab  # d rdot_c / d omega
    z, e, n, g = _rows_and_directions(det, heading, rdot)
    o = r.shape[0]
    ee = e[:, :, None] * e[:, None, :]
    nn = n[:, :, None] * n[:, None, :]
    en = e[:, :, None] * n[:, None, :]
    ne = n[:, :, None] * e[:, None, :]
    var_r = np.asarray(det.sigma_range, dtype=float) ** 2
    var_b = np.asarray(det.sigma_bearing, dtype=float) ** 2
    var_rd = np.asarray(det.sigma_range_rate, dtype=float) ** 2

    def col(v):
        return v[:, None, None]

    R = np.empty((o, 4, 4))
    R[:, :2, :2] = col(var_r) * ee + col(var_b * r * r) * nn + col(hv) * g[:, :, None] * g[:, None, :]
    # velocity: bearing column rdot_c n + q e, heading column rdot_c n, range rate e, yaw rate arm e
    R[:, 2:, 2:] = (col(var_rd + var_b * q * q + ov * arm * arm) * ee + col(var_b * rdot * q) * (en + ne)
                    + col((var_b + hv) * rdot * rdot + float(tangential_sigma) ** 2) * nn)
    R[:, :2, 2:] = (col(var_b * r * rdot) * nn + col(var_b * r * q) * ne
                    + col(hv * rdot) * g[:, :, None] * n[:, None, :])
    R[:, 2:, :2] = R[:, :2, 2:].transpose(0, 2, 1)
    k2 = 0.5 * (1.0 + np.exp(-2.0 * hv)) - 2.0 * np.exp(-0.5 * hv) + 1.0  # as in to_net_frame
    R += k2[:, None, None] * z[:, :, None] * z[:, None, :]
    return z, R


def heading_from_velocity(velocity: np.ndarray, vel_cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(heading (N,), variance (N,)): atan2(vy, vx) and g P_vv g^T with g = [-vy, vx] / |v|^2, capped at
    :data:`HEADING_VAR_UNKNOWN`."""
    v = np.asarray(velocity, dtype=float).reshape(-1, 2)
    p = np.asarray(vel_cov, dtype=float).reshape(-1, 2, 2)
    s2 = np.maximum(v[:, 0] ** 2 + v[:, 1] ** 2, 1e-300)
    gx, gy = -v[:, 1] / s2, v[:, 0] / s2
    var = gx * gx * p[:, 0, 0] + 2.0 * gx * gy * p[:, 0, 1] + gy * gy * p[:, 1, 1]
    var = np.where(s2 > 1e-18, np.minimum(var, HEADING_VAR_UNKNOWN), HEADING_VAR_UNKNOWN)  # at rest: unknown
    return np.arctan2(v[:, 1], v[:, 0]), var


@dataclass(frozen=True)
class HeadingMemory:
    """The heading (and variance) each vehicle last had above the minimum speed, in the order of the
    estimator's vehicle rows of the previous step (``carry`` maps it to the current rows)."""

    heading: np.ndarray  # (M,) rad; NaN: never fast enough
    var: np.ndarray  # (M,) rad^2

    def carry(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h = np.full(idx.shape[0], np.nan)
        v = np.full(idx.shape[0], np.nan)
        ok = idx >= 0
        h[ok] = self.heading[idx[ok]]
        v[ok] = self.var[idx[ok]]
        return h, v


def vehicle_headings(
    frame: "Frame", mean: np.ndarray, cov: np.ndarray, idx: np.ndarray, memory: HeadingMemory | None,
    min_speed: float,
) -> tuple[np.ndarray, np.ndarray, HeadingMemory]:
    """The estimator's heading and its variance per vehicle (frame order), and the memory to keep.

    ``mean`` (N, 4), ``cov`` (N, 4, 4): the estimator's belief of each vehicle at t (frame order);
    ``idx`` (N,): each vehicle's row in the previous step (-1: new); fresh vehicles (``frame.entered``)
    forget their memory. Slow-vehicle rule: the module docstring."""
    psi, var = heading_from_velocity(mean[:, 2:4], cov[:, 2:4, 2:4])
    fresh = (idx < 0) | np.asarray(frame.entered, dtype=bool)
    if memory is None:
        kept_h, kept_v = np.full(psi.shape, np.nan), np.full(psi.shape, np.nan)
    else:
        kept_h, kept_v = memory.carry(np.where(fresh, -1, idx))
    # Held, not dead-reckoned by an IMU's yaw rate: a slow vehicle is mostly standing in a queue, where the
    # gyro's bias alone (0.5 deg/s turn-on, RotorS) would turn it by 30 deg a minute; the variance grows by
    # a yaw rate of YAW_RATE_SIGMA per step instead.
    kept_v = kept_v + (YAW_RATE_SIGMA * float(frame.dt)) ** 2
    speed = np.hypot(mean[:, 2], mean[:, 3])
    slow = (speed < min_speed) & np.isfinite(kept_h)
    psi = np.where(slow, kept_h, psi)
    var = np.where(slow, kept_v, var)
    fast = speed >= min_speed
    new_memory = HeadingMemory(np.where(fast | slow, psi, np.nan), np.where(fast | slow, var, np.nan))
    return psi, var, new_memory


def with_net_detections(
    frame: "Frame", mean: np.ndarray, cov: np.ndarray, idx: np.ndarray, memory: HeadingMemory | None,
    min_speed: float,
) -> tuple["Frame", HeadingMemory | None]:
    """``frame`` with ``v2f_z`` / ``v2f_R`` formed from ``frame.v2f_sensor`` by the estimator's own
    heading (:func:`vehicle_headings`, :func:`to_net_frame`), and the heading memory to keep. A frame
    without sensor-frame rows comes back unchanged (and the memory None)."""
    from dataclasses import replace

    det = frame.v2f_sensor
    if det is None:
        return frame, None
    psi, var, memory = vehicle_headings(frame, np.asarray(mean, dtype=float), np.asarray(cov, dtype=float),
                                        np.asarray(idx, dtype=np.int64), memory, min_speed)
    owner = np.asarray(frame.v2f_owner, dtype=np.int64)
    if det.range_rate_at_mount and frame.imu is not None:  # the lever arm with the estimator's own gyroscope
        om = np.asarray(frame.imu.yaw_rate, dtype=float)[owner]
        z, R = to_net_frame(det, psi[owner], var[owner], yaw_rate=om,
                            yaw_rate_var=np.full(om.shape, GYRO_YAW_RATE_SIGMA ** 2))
    else:  # no yaw rate of its own: omega = 0 without variance (module docstring)
        z, R = to_net_frame(det, psi[owner], var[owner])
    return replace(frame, v2f_z=z, v2f_R=R), memory
