"""Realistic inertial input: a body-frame IMU per vehicle, opt-in through the
``[inertial]`` config table. Without it the frame's ``accel`` is the true net-frame change of velocity
plus white noise (a perfect heading), exactly as before.

Model, per vehicle i and step k (Ts = the step), :class:`coloc.core.inertial.ImuFrame` in the frame:

* True body-frame motion (:func:`true_body_motion`): yaw rate r_k = wrap(psi_k - psi_{k-1}) / Ts and
  acceleration a_body,k = R(psi_mid)^T (v_k - v_{k-1}) / Ts (the net-frame change of velocity rotated
  into the body frame), psi_mid = psi_{k-1} + r_k Ts / 2, with psi SUMO's
  heading. Longitudinal is along the heading, lateral to its left: a turn shows as lateral
  (centripetal) acceleration. Rotating back by the true psi_mid gives today's net-frame input
  exactly (the discretisation against a continuous IMU: :mod:`coloc.core.inertial`). A vehicle that
  (re)enters has no previous step: zero true motion (it is not predicted at that step).
* Measured = true + bias + white noise, per axis (accelerometer: longitudinal and lateral; gyroscope:
  yaw):
  - white noise: the mean over the step of white noise of density N (unit/sqrt(Hz)), standard
    deviation N / sqrt(Ts) (:func:`white_noise`; the Allan-variance convention, sigma(tau) = N / sqrt(tau));
  - bias = turn-on bias + drift. The turn-on bias, N(0, turn_on_sigma^2), is drawn when the vehicle
    enters (or re-enters after a teleport) and stays constant while it is in the net
    (:func:`turn_on_bias`). The drift is a first-order Gauss-Markov process sampled exactly,
    b_k = a b_{k-1} + sigma sqrt(1 - a^2) w_k, a = exp(-Ts / tau) (:func:`gauss_markov_bias`), with
    stationary standard deviation sigma and correlation a^m at lag m; it starts stationary
    (b = sigma w) when the vehicle enters: its IMU has been running before.
  No gravity: the net is flat (no road slope, no pitch or roll), and no scale-factor or
  misalignment errors.

Random streams: one ``numpy.random.Generator`` per effect, ``SeedSequence([seed, 0x1A0, crc32(effect
name)])`` for "accel_noise", "accel_drift", "accel_turn_on", "gyro_noise", "gyro_drift",
"gyro_turn_on": independent of every other stream (couplers.sensing.sensors.SensorNoise, [perception],
[gnss_error], [v2x]), so GNSS, V2F and prior draws are the same with or without ``[inertial]``. Each
draws for every vehicle of the frame at every step (turn-on draws too, used only for those that
enter), so a stream does not depend on who entered.

Default sources (:class:`InertialParams`): the IMU defaults of the RotorS simulator's Gazebo IMU
plugin (ethz-asl/rotors_simulator, ``rotors_gazebo_plugins/include/rotors_gazebo_plugins/
gazebo_imu_plugin.h``, "Default values for use with ADIS16448 IMU", the same in PX4's
PX4-SITL_gazebo ``gazebo_imu_plugin.h``), whose model is the one above (noise density, Gauss-Markov
bias with a correlation time, turn-on bias):
* gyroscope: noise density 2 * 35 / 3600 deg/s/sqrt(Hz) = 0.01944 deg/s/sqrt(Hz); bias random walk
  2 * 4 / 3600 deg/s^2/sqrt(Hz) with correlation time 1000 s, i.e. a stationary drift sigma of
  rw sqrt(tau / 2) = 0.0497 deg/s; turn-on bias sigma 0.5 deg/s;
* accelerometer: noise density 2 * 2e-3 = 0.004 m/s^2/sqrt(Hz); bias random walk 2 * 3e-3 m/s^3/sqrt(Hz)
  with correlation time 300 s, i.e. stationary drift sigma 6e-3 sqrt(150) = 0.0735 m/s^2; turn-on bias
  sigma 20 mg = 0.196 m/s^2.
The ADIS16448 is an industrial MEMS IMU; automotive MEMS parts are in the same class (e.g. Bosch's
CISS module quotes 120 ug/sqrt(Hz) and 0.014 deg/s/sqrt(Hz) noise densities with +-50 mg and +-1 deg/s
zero offsets for its BMA280 / BMG160). Vehicle vibration is not modelled (our choice: none).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from coloc.core.inertial import ImuFrame, wrap_angle
from coloc.core.vehicles import match_ids
from couplers.errors import InputError
from couplers.sensing import streams
from couplers.sensing.streams import StreamHandles, stream
from couplers.sensing.perception import effect_rng

INERTIAL_STREAM_TAG = 0x1A0


@dataclass(frozen=True)
class InertialParams:
    """The ``[inertial]`` table: a body-frame IMU per vehicle (sources in the module docstring)."""

    # RotorS / PX4 SITL Gazebo IMU plugin defaults "for use with ADIS16448" (module docstring); the drift
    # sigmas are its bias random walks rw converted to a stationary std, rw sqrt(tau / 2).
    accel_noise_density: float = 0.004  # m/s^2/sqrt(Hz): 2 * 2e-3
    accel_bias_sigma: float = 0.0735  # m/s^2: 2 * 3e-3 m/s^3/sqrt(Hz) * sqrt(300 / 2)
    accel_bias_tau_s: float = 300.0  # s
    accel_turn_on_sigma: float = 0.196  # m/s^2: 20 mg
    gyro_noise_density: float = 0.01944  # deg/s/sqrt(Hz): 2 * 35 / 3600 (70 deg/h/sqrt(Hz))
    gyro_bias_sigma: float = 0.0497  # deg/s: 2 * 4 / 3600 deg/s^2/sqrt(Hz) * sqrt(1000 / 2)
    gyro_bias_tau_s: float = 1000.0  # s
    gyro_turn_on_sigma: float = 0.5  # deg/s

    def __post_init__(self):
        for key in ("accel_noise_density", "accel_bias_sigma", "accel_turn_on_sigma",
                    "gyro_noise_density", "gyro_bias_sigma", "gyro_turn_on_sigma"):
            val = getattr(self, key)
            if not (_finite(val) and val >= 0):
                raise InputError(None, key, f"must be >= 0 and finite, got {val!r}")
        for key in ("accel_bias_tau_s", "gyro_bias_tau_s"):
            val = getattr(self, key)
            if not (_finite(val) and val > 0):
                raise InputError(None, key, f"must be positive and finite (the bias correlation time), got {val!r}")


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def true_body_motion(accel_net: np.ndarray, heading: np.ndarray, prev_heading: np.ndarray, dt: float,
                     ) -> tuple[np.ndarray, np.ndarray]:
    """True (accel_body (N, 2), yaw_rate (N,)) over the step: r = wrap(psi - psi_prev) / Ts and the
    net-frame change of velocity ``accel_net`` rotated into the body frame at psi_mid = psi_prev + r Ts / 2.
    Rows with a NaN ``prev_heading`` (vehicles that entered) get zero motion."""
    new = ~np.isfinite(prev_heading)
    prev = np.where(new, heading, prev_heading)
    dpsi = wrap_angle(heading - prev)
    mid = prev + 0.5 * dpsi
    c, s = np.cos(mid), np.sin(mid)
    a = np.asarray(accel_net, dtype=float)
    body = np.stack([c * a[:, 0] + s * a[:, 1], -s * a[:, 0] + c * a[:, 1]], axis=1)  # R(mid)^T a
    body[new] = 0.0
    return body, dpsi / dt


def white_noise(rng: np.random.Generator, shape: tuple[int, ...], density: float, dt: float) -> np.ndarray:
    """Mean over a step of ``dt`` of white noise of ``density`` (unit/sqrt(Hz)): N(0, density^2 / dt)."""
    return rng.standard_normal(shape) * (density / math.sqrt(dt))


def turn_on_bias(rng: np.random.Generator, shape: tuple[int, ...], sigma: float) -> np.ndarray:
    """Turn-on biases N(0, sigma^2), one per vehicle (and axis) drawn for every row."""
    return rng.standard_normal(shape) * sigma


def gauss_markov_bias(prev: np.ndarray, w: np.ndarray, fresh: np.ndarray, sigma: float, a: float) -> np.ndarray:
    """b_k = a b_{k-1} + sigma sqrt(1 - a^2) w_k (exact first-order Gauss-Markov sampling, stationary
    std ``sigma``, lag-m correlation a^m); rows ``fresh`` start stationary, b = sigma w."""
    out = a * prev + sigma * math.sqrt(1.0 - a * a) * w
    out[fresh] = sigma * w[fresh]
    return out


def _carried(prev: np.ndarray, idx: np.ndarray, fresh: np.ndarray, fill: float) -> np.ndarray:
    """prev[idx] for the vehicles carried over, ``fill`` for the fresh ones."""
    out = np.full(idx.shape + prev.shape[1:], fill)
    cont = ~fresh
    out[cont] = prev[idx[cont]]
    return out


@njit(cache=True)
def _imu_axes(idx, fresh, true, on_new, on_prev, drift_prev, w, noise, sigma, b, a):
    """One sensor's axes (N, A): turn-on bias (drawn for fresh rows, carried otherwise), the Gauss-Markov
    drift (:func:`gauss_markov_bias`, b = sigma sqrt(1 - a^2)) and the measurement
    true + turn-on + drift + noise. Returns (turn_on, drift, measured)."""
    n, axes = true.shape
    on = np.empty((n, axes))
    drift = np.empty((n, axes))
    meas = np.empty((n, axes))
    for i in range(n):
        for j in range(axes):
            if fresh[i]:
                on[i, j] = on_new[i, j]
                drift[i, j] = sigma * w[i, j]
            else:
                on[i, j] = on_prev[idx[i], j]
                drift[i, j] = a * drift_prev[idx[i], j] + b * w[i, j]
            meas[i, j] = true[i, j] + on[i, j] + drift[i, j] + noise[i, j]
    return on, drift, meas


@njit(cache=True)
def _turn_angles(idx, entered, heading, prev_heading):
    """The step's angles before numpy's trigonometry: for each vehicle whether it is fresh (new or
    re-entered), whether it has no previous heading (``new`` of :func:`true_body_motion`: fresh, or a
    non-finite carried heading), dpsi = wrap(psi - psi_prev) and psi_mid = psi_prev + dpsi / 2, with the
    operations of :func:`true_body_motion` and :func:`coloc.core.inertial.wrap_angle` (numba's float ``%``
    is Python's, which is numpy's remainder). Returns (fresh, new, dpsi, mid)."""
    n = idx.size
    fresh = np.empty(n, dtype=np.bool_)
    new = np.empty(n, dtype=np.bool_)
    dpsi = np.empty(n)
    mid = np.empty(n)
    for i in range(n):
        fresh[i] = idx[i] < 0 or entered[i]
        prev = np.nan if fresh[i] else prev_heading[idx[i]]
        new[i] = not math.isfinite(prev)
        if new[i]:
            prev = heading[i]
        dpsi[i] = (heading[i] - prev + np.pi) % (2.0 * np.pi) - np.pi
        mid[i] = prev + 0.5 * dpsi[i]
    return fresh, new, dpsi, mid


@njit(cache=True)
def _imu_step(idx, fresh, new, dpsi, c, s, accel_net, dt, scale,
              a_on_new, a_on_prev, a_drift_prev, w_accel, n_accel, a_sig, a_b, a_a,
              g_on_new, g_on_prev, g_drift_prev, w_gyro, n_gyro, g_sig, g_b, g_a):
    """:func:`true_body_motion` from the angles of :func:`_turn_angles` and their numpy cos / sin ``c``, ``s``
    (accel_body = R(mid)^T a, zero for ``new`` rows; yaw rate dpsi / dt), then :func:`_imu_axes` of the
    accelerometer (2 axes) and the gyroscope (1 axis), same operations in the same order. The turn-on and
    white-noise draws come as standard normals, scaled here by ``scale`` (accel turn-on sigma, gyro turn-on
    sigma, accel and gyro white-noise sigma), the products :func:`turn_on_bias` and :func:`white_noise` form.
    Returns (a_on, a_drift, accel (N, 2), g_on, g_drift, yaw_rate (N,))."""
    n = idx.size
    a_on_new = a_on_new * scale[0]
    g_on_new = g_on_new * scale[1]
    n_accel = n_accel * scale[2]
    n_gyro = n_gyro * scale[3]
    body = np.empty((n, 2))
    yaw = np.empty((n, 1))
    for i in range(n):
        if new[i]:
            body[i, 0] = 0.0
            body[i, 1] = 0.0
        else:
            body[i, 0] = c[i] * accel_net[i, 0] + s[i] * accel_net[i, 1]
            body[i, 1] = -s[i] * accel_net[i, 0] + c[i] * accel_net[i, 1]
        yaw[i, 0] = dpsi[i] / dt
    a_on, a_drift, accel = _imu_axes(idx, fresh, body, a_on_new, a_on_prev, a_drift_prev, w_accel, n_accel,
                                     a_sig, a_b, a_a)
    g_on, g_drift, yaw_rate = _imu_axes(idx, fresh, yaw, g_on_new.reshape(n, 1), g_on_prev.reshape(-1, 1),
                                        g_drift_prev.reshape(-1, 1), w_gyro.reshape(n, 1), n_gyro.reshape(n, 1),
                                        g_sig, g_b, g_a)
    return a_on, a_drift, accel, g_on[:, 0], g_drift[:, 0], yaw_rate[:, 0]


@njit(cache=True)
def _imu_step_drawn(h_a_on, h_g_on, h_a_drift, h_g_drift, h_a_noise, h_g_noise, idx, fresh, new, dpsi, c, s,
                    accel_net, dt, scale, a_on_prev, a_drift_prev, a_sig, a_b, a_a, g_on_prev, g_drift_prev, g_sig,
                    g_b, g_a):
    """:func:`_imu_step` with its standard normal draws taken here from the streams of the handles ``h_*``
    (:mod:`couplers.sensing.streams`), one draw per stream and step as :meth:`InertialProcess.step_reference`
    takes them: turn-on biases (N, 2) and (N,), drift drivers, white noise."""
    n = idx.size
    a_on_new = stream(h_a_on).standard_normal((n, 2))
    g_on_new = stream(h_g_on).standard_normal(n)
    w_accel = stream(h_a_drift).standard_normal((n, 2))
    w_gyro = stream(h_g_drift).standard_normal(n)
    n_accel = stream(h_a_noise).standard_normal((n, 2))
    n_gyro = stream(h_g_noise).standard_normal(n)
    return _imu_step(idx, fresh, new, dpsi, c, s, accel_net, dt, scale, a_on_new, a_on_prev, a_drift_prev, w_accel,
                     n_accel, a_sig, a_b, a_a, g_on_new, g_on_prev, g_drift_prev, w_gyro, n_gyro, g_sig, g_b, g_a)


class InertialProcess:
    """Per-vehicle IMU state (previous heading, biases) across the steps of one run."""

    STREAMS = ("accel_noise", "accel_drift", "accel_turn_on", "gyro_noise", "gyro_drift", "gyro_turn_on")

    def __init__(self, params: InertialParams, seed: int, dt: float):
        self.params = params
        self.dt = float(dt)
        self.a_accel = math.exp(-self.dt / params.accel_bias_tau_s)
        self.a_gyro = math.exp(-self.dt / params.gyro_bias_tau_s)
        for name in self.STREAMS:
            setattr(self, f"{name}_rng", effect_rng(seed, INERTIAL_STREAM_TAG, name))
        self.handles = StreamHandles(self, tuple(f"{name}_rng" for name in self.STREAMS))  # drawn in kernels
        self._ids = np.empty(0, dtype=object)
        self._heading = np.empty(0)
        self.accel_turn_on = np.empty((0, 2))  # current vehicles' biases, rows of the last step
        self.accel_drift = np.empty((0, 2))
        self.gyro_turn_on = np.empty(0)  # rad/s
        self.gyro_drift = np.empty(0)

    def step(self, ids: np.ndarray, entered: np.ndarray, heading: np.ndarray, accel_net: np.ndarray,
             idx: np.ndarray | None = None) -> ImuFrame:
        """The step's IMU measurements; ``accel_net`` (N, 2) the true net-frame change of velocity / Ts
        (zero rows for vehicles that entered), ``heading`` (N,) the true heading. ``idx``: the row of each
        vehicle among the ``ids`` of the previous call, -1 if new (``match_ids(previous ids, ids)``, which the
        SUMO coupler has from ``SumoTraffic.step``); None: matched here.

        :meth:`step_reference` is the same step in numpy (:func:`true_body_motion`, :func:`_imu_axes`)."""
        if not streams.available():  # numba's draws differ from numpy's here: the numpy step
            return self.step_reference(ids, entered, heading, accel_net)
        p, dt = self.params, self.dt
        if idx is None:
            idx = match_ids(self._ids, ids)
        heading = np.ascontiguousarray(heading, dtype=float)
        fresh, new, dpsi, mid = _turn_angles(np.asarray(idx, dtype=np.int64), np.asarray(entered, dtype=bool),
                                             heading, self._heading)
        c, s = np.cos(mid), np.sin(mid)  # numpy's, as true_body_motion's
        # every stream draws for every vehicle (turn-on biases too, used only by the vehicles that enter), in the
        # kernel (couplers.sensing.streams); the standard normals are scaled there as turn_on_bias / white_noise
        # scale them
        rad = math.pi / 180.0
        scale = np.array([p.accel_turn_on_sigma, p.gyro_turn_on_sigma * rad, p.accel_noise_density / math.sqrt(dt),
                          (p.gyro_noise_density * rad) / math.sqrt(dt)])
        a_sig, g_sig = p.accel_bias_sigma, p.gyro_bias_sigma * rad
        h = self.handles
        a_on, a_drift, accel, g_on, g_drift, yaw_rate = _imu_step_drawn(
            h["accel_turn_on_rng"], h["gyro_turn_on_rng"], h["accel_drift_rng"], h["gyro_drift_rng"],
            h["accel_noise_rng"], h["gyro_noise_rng"],
            idx, fresh, new, dpsi, c, s, np.ascontiguousarray(accel_net, dtype=float), dt, scale,
            self.accel_turn_on, self.accel_drift, a_sig, a_sig * math.sqrt(1.0 - self.a_accel * self.a_accel),
            self.a_accel, self.gyro_turn_on, self.gyro_drift, g_sig,
            g_sig * math.sqrt(1.0 - self.a_gyro * self.a_gyro), self.a_gyro)
        self._ids, self._heading = np.asarray(ids, dtype=object), heading.copy()
        self.accel_turn_on, self.accel_drift = a_on, a_drift
        self.gyro_turn_on, self.gyro_drift = g_on, g_drift
        return ImuFrame(accel_body=accel, yaw_rate=yaw_rate)

    def step_reference(self, ids: np.ndarray, entered: np.ndarray, heading: np.ndarray,
                       accel_net: np.ndarray) -> ImuFrame:
        """:meth:`step` with the body motion in numpy (the reference of the fused kernels)."""
        p, dt = self.params, self.dt
        n = len(ids)
        idx = match_ids(self._ids, ids)
        fresh = (idx < 0) | np.asarray(entered, dtype=bool)
        prev_heading = _carried(self._heading, idx, fresh, np.nan)
        body, yaw = true_body_motion(accel_net, heading, prev_heading, dt)
        rad = math.pi / 180.0
        # every stream draws for every vehicle (turn-on biases too, used only by the vehicles that enter)
        a_on_new = turn_on_bias(self.accel_turn_on_rng, (n, 2), p.accel_turn_on_sigma)
        g_on_new = turn_on_bias(self.gyro_turn_on_rng, (n,), p.gyro_turn_on_sigma * rad)
        w_accel = self.accel_drift_rng.standard_normal((n, 2))
        w_gyro = self.gyro_drift_rng.standard_normal(n)
        n_accel = white_noise(self.accel_noise_rng, (n, 2), p.accel_noise_density, dt)
        n_gyro = white_noise(self.gyro_noise_rng, (n,), p.gyro_noise_density * rad, dt)
        a_sig, g_sig = p.accel_bias_sigma, p.gyro_bias_sigma * rad
        a_on, a_drift, accel = _imu_axes(idx, fresh, body, a_on_new, self.accel_turn_on, self.accel_drift, w_accel,
                                         n_accel, a_sig, a_sig * math.sqrt(1.0 - self.a_accel * self.a_accel),
                                         self.a_accel)
        g_on, g_drift, yaw_rate = _imu_axes(idx, fresh, yaw[:, None], g_on_new[:, None], self.gyro_turn_on[:, None],
                                            self.gyro_drift[:, None], w_gyro[:, None], n_gyro[:, None], g_sig,
                                            g_sig * math.sqrt(1.0 - self.a_gyro * self.a_gyro), self.a_gyro)
        self._ids, self._heading = np.asarray(ids, dtype=object), np.asarray(heading, dtype=float).copy()
        self.accel_turn_on, self.accel_drift = a_on, a_drift
        self.gyro_turn_on, self.gyro_drift = g_on[:, 0], g_drift[:, 0]
        return ImuFrame(accel_body=accel, yaw_rate=yaw_rate[:, 0])

    @property
    def accel_bias(self) -> np.ndarray:
        """(N, 2) total accelerometer bias of the last step's vehicles, m/s^2."""
        return self.accel_turn_on + self.accel_drift

    @property
    def gyro_bias(self) -> np.ndarray:
        """(N,) total gyroscope bias of the last step's vehicles, rad/s."""
        return self.gyro_turn_on + self.gyro_drift
