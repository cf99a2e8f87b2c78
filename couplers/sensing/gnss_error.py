"""Realistic GNSS position error (issue 21 item 4): first-order Gauss-Markov error per vehicle plus
NLOS / multipath bias episodes. Opt-in through the ``[gnss_error]`` config table.

Position error of vehicle i at step k (net x/y, per axis):

    e_k = sigma_p(zone_k) u_k + b_k

* u_k is a unit-variance first-order Gauss-Markov (Ornstein-Uhlenbeck) process sampled exactly:
  u_k = a u_{k-1} + sqrt(1 - a^2) w_k, a = exp(-Ts / tau_s), w_k ~ N(0, I2). A vehicle that enters
  (or re-enters after a teleport) starts stationary, u = w. ``tau_s = 0`` gives a = 0, u_k = w_k:
  today's white noise exactly, since w_k is the draw the idealised coupler uses (the position
  columns of the GNSS stream of couplers.sensing.sensors.SensorNoise).
* Zone changes: the state is kept normalised (u), so the error is rescaled by the ratio of the new
  zone's sigma_p to the old one's at the step the vehicle crosses; the stationary standard deviation
  is the zone's sigma_p at every step, and the correlation of u is unbroken.
* Velocity error: white, N(0, sigma_v(zone)^2) per axis, as today (same draws): receivers derive
  velocity from Doppler, whose errors are nearly uncorrelated from one fix to the next.
* NLOS / multipath bias episodes: a vehicle outside an episode starts one during a step with
  probability 1 - exp(-lambda Ts), lambda the start rate at its position: per zone
  (``nlos_zones`` / ``nlos_rate_per_min``; zones not listed: 0), or, when the net folder has
  ``buildings.geojson``, ``nlos_rate_per_density_per_min`` times the building plan-area fraction
  within ``nlos_density_radius_m`` of the vehicle. An episode lasts an exponential time of mean
  ``nlos_mean_duration_s`` (drawn at its start) and adds a constant horizontal bias b of uniform
  direction and exponential magnitude of mean ``nlos_bias_mean_m``; it ends after its duration
  (velocity unaffected).
* The frame's ``gnss_R`` stays the nominal zone covariance (what a receiver reports): the mismatch
  is what the user wants to see.

Random streams: the Gauss-Markov driving noise is the idealised GNSS stream (see above); the episode
starts, durations and biases each have their own generator, ``SeedSequence([seed, 0x6E5,
crc32(effect name)])`` for "nlos_start", "nlos_duration", "nlos_bias".

Default sources:
* ``tau_s`` 30 s: stationary single-frequency receivers show position errors correlated over tens
  of seconds to minutes, better modelled by an Ornstein-Uhlenbeck process than by white noise
  (Sensors 2020, 20(21), 6050, "Comparison of Enhanced Noise Model Performance Based on Analysis of
  Civilian GPS Data"; D. L. Wilson's autocorrelation of Garmin 12XL horizontal errors bends at ~1
  min); 30 s is also the issue's study value.
* Bias magnitude, mean 10 m (exponential: median 7 m, 95th percentile 30 m): NLOS reception in
  urban canyons gives pseudorange errors of tens of metres and position errors of 10-50 m (L.-T.
  Hsu, "Analysis and modeling GPS NLOS effect in highly urbanized area", GPS Solutions 22:7, 2018;
  heavy-tailed NLOS pseudorange errors in a dense urban canyon: Peretic et al., ION, "Empirical
  Analysis of Multipath and Non-Line-of-Sight Errors on Receiver Measurements in an Urban
  Environment"). Start rates (zone C 1 / min, zone B 0.25 / min, A none) and the mean duration
  (10 s) are assumptions: no measured rate of episodes was found; with them a vehicle in zone C is
  biased ~14 % of the time. Density rate 3 / min per unit plan-area fraction: 1 / min at 0.30, the
  built-up fraction from which ``coloc net import`` classes a cell C (couplers.net.importer).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from coloc.core.vehicles import match_ids
from couplers.errors import InputError
from couplers.net.buildings import Buildings
from couplers.sensing import streams
from couplers.sensing.streams import StreamHandles, stream
from couplers.sensing.perception import effect_rng
from couplers.net.zones import CellGrid, _grid_values

GNSS_ERROR_STREAM_TAG = 0x6E5


@dataclass(frozen=True)
class GnssErrorParams:
    """The ``[gnss_error]`` table (sources of the defaults in the module docstring)."""

    tau_s: float = 30.0
    nlos_zones: tuple[str, ...] = ("B", "C")
    nlos_rate_per_min: tuple[float, ...] = (0.25, 1.0)
    nlos_rate_per_density_per_min: float = 3.0
    nlos_density_radius_m: float = 50.0
    nlos_mean_duration_s: float = 10.0
    nlos_bias_mean_m: float = 10.0

    def __post_init__(self):
        def finite(v):
            return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

        if not (finite(self.tau_s) and self.tau_s >= 0):
            raise InputError(None, "tau_s", f"must be >= 0 and finite (0 = white noise), got {self.tau_s!r}")
        if len(self.nlos_zones) != len(self.nlos_rate_per_min):
            raise InputError(None, "nlos_rate_per_min", f"needs one rate per zone of nlos_zones "
                                                        f"({len(self.nlos_zones)}), got {len(self.nlos_rate_per_min)}")
        if len(set(self.nlos_zones)) != len(self.nlos_zones):
            raise InputError(None, "nlos_zones", "a zone is listed twice")
        for i, r in enumerate(self.nlos_rate_per_min):
            if not (finite(r) and r >= 0):
                raise InputError(None, f"nlos_rate_per_min[{i}]", f"must be >= 0 and finite, got {r!r}")
        for key in ("nlos_rate_per_density_per_min", "nlos_bias_mean_m"):
            if not (finite(getattr(self, key)) and getattr(self, key) >= 0):
                raise InputError(None, key, f"must be >= 0 and finite, got {getattr(self, key)!r}")
        for key in ("nlos_density_radius_m", "nlos_mean_duration_s"):
            if not (finite(getattr(self, key)) and getattr(self, key) > 0):
                raise InputError(None, key, f"must be positive and finite, got {getattr(self, key)!r}")


def gauss_markov_coefficient(dt: float, tau_s: float) -> float:
    """a = exp(-Ts / tau) of the exact discretisation (0 for tau = 0: white noise)."""
    return 0.0 if tau_s == 0 else math.exp(-dt / tau_s)


def gauss_markov_step(u_prev: np.ndarray, w: np.ndarray, a: float) -> np.ndarray:
    """u_k = a u_{k-1} + sqrt(1 - a^2) w_k: unit stationary variance, correlation a per step."""
    if a == 0.0:
        return w.copy()
    return a * u_prev + math.sqrt(1.0 - a * a) * w


def episode_start_probability(rate_per_min: np.ndarray, dt: float) -> np.ndarray:
    """Probability that a Poisson start process of ``rate_per_min`` fires within a step of ``dt`` s."""
    return -np.expm1(-np.asarray(rate_per_min, dtype=float) * dt / 60.0)


def zone_rates(params: GnssErrorParams, zone: np.ndarray) -> np.ndarray:
    """Episode start rate (per minute) of each vehicle from its GNSS zone name (unlisted zones: 0)."""
    zone = np.asarray(zone, dtype=object).reshape(-1)
    rates = np.zeros(zone.size)
    for name, rate in zip(params.nlos_zones, params.nlos_rate_per_min):  # a few zones, all vehicles at once
        rates[zone == name] = rate
    return rates


def building_density_grid(buildings: Buildings, radius_m: float, cell_m: float = 5.0) -> CellGrid:
    """Plan-area fraction of buildings within ``radius_m`` of each cell centre: buildings rasterised at
    ``cell_m`` (cell centres inside a footprint), then averaged over a disc by FFT convolution."""
    import shapely
    from scipy.signal import fftconvolve

    xmin, ymin, xmax, ymax = shapely.total_bounds(buildings.polygons)
    pad = radius_m + cell_m
    x0, y0 = xmin - pad, ymin - pad
    nx = int(math.ceil((xmax + pad - x0) / cell_m))
    ny = int(math.ceil((ymax + pad - y0) / cell_m))
    cx = x0 + (np.arange(nx) + 0.5) * cell_m
    cy = y0 + (np.arange(ny) + 0.5) * cell_m
    gx, gy = np.meshgrid(cx, cy)
    union = shapely.union_all(buildings.polygons)
    built = shapely.intersects_xy(union, gx.ravel(), gy.ravel()).reshape(ny, nx).astype(float)
    k = int(math.ceil(radius_m / cell_m))
    ky, kx = np.mgrid[-k:k + 1, -k:k + 1]
    disc = ((kx * cell_m) ** 2 + (ky * cell_m) ** 2 <= radius_m ** 2).astype(float)
    frac = fftconvolve(built, disc / disc.sum(), mode="same")
    return CellGrid(x0=x0, y0=y0, cell=cell_m, values=np.clip(frac, 0.0, 1.0))


@njit(cache=True)
def _carry(idx, entered, w, u_prev, bias_prev, end_prev, a, b, t):
    """The state carried to this step: u = w for vehicles that (re)enter, else a u_prev + b w (b =
    sqrt(1 - a^2); a = 0: u = w), and the bias and end of a running episode (bias 0 and end -inf
    outside one). Returns (u, bias, end, active)."""
    n = idx.size
    u = w.copy()
    bias = np.zeros((n, 2))
    end = np.full(n, -np.inf)
    active = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        r = idx[i]
        if r < 0 or entered[i]:
            continue
        if a != 0.0:
            u[i, 0] = a * u_prev[r, 0] + b * w[i, 0]
            u[i, 1] = a * u_prev[r, 1] + b * w[i, 1]
        if end_prev[r] > t + 1e-9:
            active[i] = True
            end[i] = end_prev[r]
            bias[i, 0] = bias_prev[r, 0]
            bias[i, 1] = bias_prev[r, 1]
    return u, bias, end, active


@njit(cache=True)
def _start_episodes(start, mag, cos_a, sin_a, dur, t, bias, end):
    """In place, for the k-th vehicle where ``start``: bias = mag (cos_a[k], sin_a[k]), end = t + dur
    (``bias[start] = mag[start, None] * [cos, sin]``, ``end[start] = t + dur[start]``)."""
    k = 0
    for i in range(start.size):
        if start[i]:
            bias[i, 0] = mag[i] * cos_a[k]
            bias[i, 1] = mag[i] * sin_a[k]
            end[i] = t + dur[i]
            k += 1


@njit(cache=True)
def _carry_with_grid(idx, entered, w, u_prev, bias_prev, end_prev, a, b, t, xy, x0, y0, cell, p_grid):
    """:func:`_carry` and the start probability of each vehicle's cell (:func:`couplers.net.zones._grid_values`
    of the per-cell probabilities)."""
    u, bias, end, active = _carry(idx, entered, w, u_prev, bias_prev, end_prev, a, b, t)
    return u, bias, end, active, _grid_values(xy, x0, y0, cell, p_grid)


@njit(cache=True)
def _episode_draws(h_start, h_duration, h_bias, mean_duration_s, bias_mean_m, p_start, active):
    """The episode draws of one step for every vehicle, from the streams of the handles ``h_*``
    (:mod:`couplers.sensing.streams`) as :meth:`GnssErrorProcess.step_reference` takes them: start = (u < p_start)
    and not ``active``, durations Exp(mean_duration_s), magnitudes Exp(bias_mean_m) (none drawn, zeros, for a mean
    of 0) and angles U(-pi, pi). Returns (start, dur, mag, the angles of the starting vehicles in row order)."""
    n = p_start.size
    u = stream(h_start).random(n)
    dur = stream(h_duration).exponential(mean_duration_s, n)
    bias = stream(h_bias)
    mag = bias.exponential(bias_mean_m, n) if bias_mean_m > 0 else np.zeros(n)
    ang = bias.uniform(-np.pi, np.pi, n)
    start = np.empty(n, dtype=np.bool_)
    k = 0
    for i in range(n):
        start[i] = u[i] < p_start[i] and not active[i]
        if start[i]:
            k += 1
    ang_start = np.empty(k)
    k = 0
    for i in range(n):
        if start[i]:
            ang_start[k] = ang[i]
            k += 1
    return start, dur, mag, ang_start


@njit(cache=True)
def _carry_with_grid_drawn(idx, entered, w, u_prev, bias_prev, end_prev, a, b, t, xy, x0, y0, cell, p_grid,
                           h_start, h_duration, h_bias, mean_duration_s, bias_mean_m):
    """:func:`_carry_with_grid` and :func:`_episode_draws`: (u, bias, end, start, dur, mag, starting angles)."""
    u, bias, end, active, p_start = _carry_with_grid(idx, entered, w, u_prev, bias_prev, end_prev, a, b, t, xy, x0,
                                                     y0, cell, p_grid)
    start, dur, mag, ang = _episode_draws(h_start, h_duration, h_bias, mean_duration_s, bias_mean_m, p_start, active)
    return u, bias, end, start, dur, mag, ang


@njit(cache=True)
def _episodes_and_error(start, mag, cos_a, sin_a, dur, t, bias, end, sigma, u):
    """:func:`_start_episodes` (in place) and the position error :func:`_scaled_plus`."""
    _start_episodes(start, mag, cos_a, sin_a, dur, t, bias, end)
    return _scaled_plus(sigma, u, bias)


@njit(cache=True)
def _scaled_plus(sigma, u, bias):
    """sigma[:, None] * u + bias."""
    out = np.empty_like(u)
    for i in range(u.shape[0]):
        out[i, 0] = sigma[i] * u[i, 0] + bias[i, 0]
        out[i, 1] = sigma[i] * u[i, 1] + bias[i, 1]
    return out


class GnssErrorProcess:
    """Per-vehicle state of the realistic GNSS error across the steps of one run."""

    STREAMS = ("nlos_start", "nlos_duration", "nlos_bias")

    def __init__(self, params: GnssErrorParams, seed: int, dt: float, buildings: Buildings | None = None):
        self.params = params
        self.dt = float(dt)
        self.a = gauss_markov_coefficient(self.dt, params.tau_s)
        for name in self.STREAMS:
            setattr(self, name, effect_rng(seed, GNSS_ERROR_STREAM_TAG, name))
        self.handles = StreamHandles(self, self.STREAMS)  # the same streams drawn in step's kernels
        self.density = (building_density_grid(buildings, params.nlos_density_radius_m)
                        if buildings is not None and len(buildings) else None)
        # The start probability of each density cell, computed once: per step a lookup instead of the rate and
        # expm1 of every vehicle (the same numpy expressions on the same cell values, so the same probabilities;
        # outside the grid the lookup's 0 is the probability of a zero rate).
        self._p_start_grid = (None if self.density is None else dataclasses.replace(
            self.density, values=episode_start_probability(
                self.params.nlos_rate_per_density_per_min * self.density.values, self.dt)))
        self._ids = np.empty(0, dtype=object)
        self._u = np.empty((0, 2))
        self._bias = np.empty((0, 2))
        self._end = np.empty(0)  # episode end time (s); -inf outside an episode

    def start_rates(self, zone: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Episode start rate per minute of each vehicle: building density when the net has buildings,
        else per zone."""
        if self.density is not None:
            return self.params.nlos_rate_per_density_per_min * self.density.at(xy)
        return zone_rates(self.params, zone)

    def start_probabilities(self, zone: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """(N,) probability that each vehicle starts an episode this step (:func:`episode_start_probability`
        of :meth:`start_rates`; with buildings a lookup of the per-cell probabilities)."""
        if self._p_start_grid is not None:
            return self._p_start_grid.at(xy)
        return episode_start_probability(self.start_rates(zone, xy), self.dt)

    def step(self, t: float, ids: np.ndarray, entered: np.ndarray, w: np.ndarray, sigma_p: np.ndarray,
             zone: np.ndarray, xy: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) position error of this step; ``w`` (N, 2) the standard normal driving draws. ``idx``: the row
        of each vehicle among the ``ids`` of the previous call, -1 if new (``match_ids(previous ids, ids)``,
        which the SUMO coupler has from ``SumoTraffic.step``); None: matched here. The episode draws are taken
        in the kernels (:func:`_episode_draws`, :mod:`couplers.sensing.streams`); :meth:`step_reference` takes
        them in numpy."""
        if not streams.available():
            return self.step_reference(t, ids, entered, w, sigma_p, zone, xy, idx=idx)
        if idx is None:
            idx = match_ids(self._ids, ids)
        w = np.ascontiguousarray(w, dtype=float)
        # Carried state; episodes past their end stop (bias 0, end -inf until a new start). Vehicles outside an
        # episode may start one (draws for every vehicle, so the streams do not depend on who is in one).
        args = (np.asarray(idx, dtype=np.int64), np.asarray(entered, dtype=bool), w, self._u, self._bias, self._end,
                self.a, math.sqrt(1.0 - self.a * self.a), float(t))
        h, p = self.handles, self.params
        draws = (h["nlos_start"], h["nlos_duration"], h["nlos_bias"], p.nlos_mean_duration_s, p.nlos_bias_mean_m)
        if self._p_start_grid is not None:  # with the start probability of each vehicle's cell
            g = self._p_start_grid
            u, bias, end, start, dur, mag, ang = _carry_with_grid_drawn(
                *args, np.ascontiguousarray(np.asarray(xy, dtype=float).reshape(-1, 2)), g.x0, g.y0, g.cell,
                g.values, *draws)
        else:
            u, bias, end, active = _carry(*args)
            start, dur, mag, ang = _episode_draws(*draws, self.start_probabilities(zone, xy), active)
        # numpy's cos / sin of the starting vehicles' angles
        error = _episodes_and_error(start, mag, np.cos(ang), np.sin(ang), dur, float(t), bias, end,
                                    np.asarray(sigma_p, dtype=float), u)
        self._ids, self._u, self._bias, self._end = np.asarray(ids, dtype=object), u, bias, end
        return error

    def step_reference(self, t: float, ids: np.ndarray, entered: np.ndarray, w: np.ndarray, sigma_p: np.ndarray,
                       zone: np.ndarray, xy: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        """:meth:`step` with the episode draws in numpy (the reference of its kernels, and the step where numba's
        draws differ from numpy's)."""
        n = len(ids)
        if idx is None:
            idx = match_ids(self._ids, ids)
        w = np.ascontiguousarray(w, dtype=float)
        # Carried state; episodes past their end stop (bias 0, end -inf until a new start). Vehicles outside an
        # episode may start one (draws for every vehicle, so the streams do not depend on who is in one).
        args = (np.asarray(idx, dtype=np.int64), np.asarray(entered, dtype=bool), w, self._u, self._bias, self._end,
                self.a, math.sqrt(1.0 - self.a * self.a), float(t))
        if self._p_start_grid is not None:  # with the start probability of each vehicle's cell
            g = self._p_start_grid
            u, bias, end, active, p_start = _carry_with_grid(
                *args, np.ascontiguousarray(np.asarray(xy, dtype=float).reshape(-1, 2)), g.x0, g.y0, g.cell, g.values)
        else:
            u, bias, end, active = _carry(*args)
            p_start = self.start_probabilities(zone, xy)
        start = (self.nlos_start.random(n) < p_start) & ~active
        dur = self.nlos_duration.exponential(self.params.nlos_mean_duration_s, size=n)
        mag = self.nlos_bias.exponential(self.params.nlos_bias_mean_m, size=n) if self.params.nlos_bias_mean_m > 0 \
            else np.zeros(n)
        ang = self.nlos_bias.uniform(-np.pi, np.pi, size=n)
        a = ang[start]  # numpy's cos / sin of the starting vehicles' angles (as gathered before)
        error = _episodes_and_error(start, mag, np.cos(a), np.sin(a), dur, float(t), bias, end,
                                    np.asarray(sigma_p, dtype=float), u)
        self._ids, self._u, self._bias, self._end = np.asarray(ids, dtype=object), u, bias, end
        return error

    @property
    def in_episode(self) -> np.ndarray:
        """(N,) bool for the vehicles of the last step: inside a bias episode."""
        return np.any(self._bias != 0.0, axis=1)
