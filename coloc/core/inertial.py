"""Body-frame inertial input (opt-in ``[inertial]``): what an on-board IMU gives, and
how an estimator turns it into the net-frame input a_{t-1} of model (1) with its *own* heading.

The frame carries, per vehicle, :class:`ImuFrame` (``Frame.imu``):

* ``accel_body`` (N, 2): [longitudinal, lateral] acceleration over (t - Ts, t], in the vehicle frame
  at the mid-step heading (x forward, y to the left), so that a turn shows as lateral acceleration;
* ``yaw_rate`` (N,): mean yaw rate over (t - Ts, t], rad/s, counter-clockwise positive.

An estimator rotates it into the net frame by :func:`net_frame_input`:

    psi_0   = atan2(vy, vx) of the vehicle's previous *estimate*   if its speed >= min_speed,
            = the heading it kept from the previous step            otherwise (dead reckoning);
    psi_mid = psi_0 + r Ts / 2                                      (mid-interval heading)
    a_{t-1} = R(psi_mid) accel_body                                 (the input of model (1))
    psi_t   = psi_0 + r Ts                                          (kept for the next step)

with r the measured yaw rate. With ``hold`` (``[motion] imu_heading = "held"``) a vehicle below
min_speed keeps its heading unchanged instead (r taken as 0 for it: psi_mid = psi_t = psi_0), so that a
gyroscope's bias is not integrated over a stop. A vehicle that (re)enters starts its kept heading from
the velocity of its fast-start prior (it is not predicted at that step). The estimator never sees the true heading;
the kept headings are a small per-vehicle memory the estimator carries between steps, in the order
of its vehicle rows.

Discretisation: the coupler defines ``accel_body`` as the change of the velocity vector over the step
rotated into the body frame at the mid-step heading (couplers/sensing/inertial.py), so R(psi_mid) inverts it
exactly when psi_0 and r are true. Against a continuous IMU in a steady turn at yaw rate w and speed
v (lateral specific force v w), the step's mean net-frame acceleration |dv| / Ts = 2 v sin(w Ts / 2) / Ts
is smaller by the relative amount 1 - sinc(w Ts / 2) <= (w Ts)^2 / 24: 0.2 % for a 90 deg turn in 5 s
at Ts = 0.75 s (tests/coloc/test_inertial.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # coloc.core.frame imports this module for ImuFrame
    from coloc.core.frame import Frame


@dataclass(frozen=True)
class ImuFrame:
    """One step of the vehicles' body-frame IMU (rows in ``Frame.vehicle_ids`` order)."""

    accel_body: np.ndarray  # (N, 2) [longitudinal, lateral] m/s^2, mean over (t - Ts, t]
    yaw_rate: np.ndarray  # (N,) rad/s, counter-clockwise, mean over (t - Ts, t]


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(a, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi


def rotate(vec: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """R(angle) vec for each row: (N, 2) rotated counter-clockwise by (N,) angles."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.empty_like(vec, dtype=float)
    out[:, 0] = c * vec[:, 0] - s * vec[:, 1]
    out[:, 1] = s * vec[:, 0] + c * vec[:, 1]
    return out


def net_frame_input(
    imu: ImuFrame,
    dt: float,
    velocity: np.ndarray,
    kept_heading: np.ndarray,
    fresh: np.ndarray,
    min_speed: float,
    hold: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Net-frame input a_{t-1} of model (1) from the body-frame IMU and the estimated heading.

    ``velocity`` (N, 2): each vehicle's previous estimated velocity (its posterior at t - Ts; for a
    ``fresh`` vehicle, the velocity of its fast-start prior); ``kept_heading`` (N,): the heading the
    estimator kept for it after the previous step (NaN: none). Returns (accel (N, 2), heading (N,)):
    the input rotated at the mid-interval heading, and the heading at t to keep for the next step.
    ``hold``: slow vehicles keep their heading (no yaw-rate integration; module docstring). Rows of
    fresh vehicles get the heading of the prior's velocity and an input rotated by it (not
    used: a fresh vehicle is not predicted)."""
    v = np.asarray(velocity, dtype=float).reshape(-1, 2)
    fresh = np.asarray(fresh, dtype=bool)
    r = np.asarray(imu.yaw_rate, dtype=float)
    from_velocity = np.arctan2(v[:, 1], v[:, 0])
    kept = np.asarray(kept_heading, dtype=float)
    slow = (np.hypot(v[:, 0], v[:, 1]) < min_speed) & np.isfinite(kept) & ~fresh
    psi0 = np.where(slow, kept, from_velocity)
    step = np.where(fresh | (slow if hold else False), 0.0, r * dt)
    accel = rotate(np.asarray(imu.accel_body, dtype=float).reshape(-1, 2), psi0 + 0.5 * step)
    return accel, wrap_angle(psi0 + step)


def carried_heading(previous: np.ndarray | None, idx: np.ndarray) -> np.ndarray:
    """The kept headings of the previous step in the current row order (``idx`` from
    :func:`coloc.core.vehicles.match_ids`); NaN for vehicles without one."""
    out = np.full(idx.shape[0], np.nan)
    if previous is not None and previous.size:
        ok = idx >= 0
        out[ok] = previous[idx[ok]]
    return out


def estimator_input(
    frame: "Frame", idx: np.ndarray, previous_velocity: np.ndarray, previous_heading: np.ndarray | None, min_speed: float,
    hold: bool = False,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The input a_{t-1} an estimator uses this step, and the headings it keeps (rows in frame order).

    Without ``frame.imu`` (no ``[inertial]``): ``frame.accel`` exactly, and None. With it: the
    body-frame IMU rotated by the estimator's own heading (:func:`net_frame_input`).
    ``previous_velocity`` (M, 2): the estimator's velocity estimates of the previous step, in its
    previous row order; ``idx`` (N,): the row of each current vehicle there (-1: new)."""
    if frame.imu is None:
        return frame.accel, None
    fresh = (idx < 0) | np.asarray(frame.entered, dtype=bool)
    n = idx.shape[0]
    vel = np.empty((n, 2))
    keep = ~fresh
    vel[keep] = np.asarray(previous_velocity, dtype=float)[idx[keep]]
    vel[fresh] = np.asarray(frame.prior_z, dtype=float)[fresh, 2:4]
    return net_frame_input(frame.imu, float(frame.dt), vel, carried_heading(previous_heading, idx), fresh, min_speed,
                           hold)
