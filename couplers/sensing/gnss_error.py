"""Realistic GNSS position error: first-order Gauss-Markov error per vehicle plus
NLOS / multipath bias episodes (``model = "per_vehicle"``, the default), or errors that nearby vehicles
share (``model = "field"``, at the end); ``model = "satellites"`` is a receiver at pseudorange level
(couplers.sensing.gnss_satellites). Opt-in through the ``[gnss_error]`` config table.

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
  min); 30 s is also the centre value of the realistic-sensing study.
* Bias magnitude, mean 10 m (exponential: median 7 m, 95th percentile 30 m): NLOS reception in
  urban canyons gives pseudorange errors of tens of metres and position errors of 10-50 m (L.-T.
  Hsu, "Analysis and modeling GPS NLOS effect in highly urbanized area", GPS Solutions 22:7, 2018;
  heavy-tailed NLOS pseudorange errors in a dense urban canyon: Peretic et al., ION, "Empirical
  Analysis of Multipath and Non-Line-of-Sight Errors on Receiver Measurements in an Urban
  Environment"). Start rates (zone C 1 / min, zone B 0.25 / min, A none) and the mean duration
  (10 s) are assumptions: no measured rate of episodes was found; with them a vehicle in zone C is
  biased ~14 % of the time. Density rate 3 / min per unit plan-area fraction: 1 / min at 0.30, the
  built-up fraction from which ``coloc net import`` classes a cell C (couplers.net.importer).

``model = "field"`` (:class:`FieldErrorProcess`): errors that nearby receivers share. Per axis,

    e_i = sigma_p(zone_i) (sqrt(s) c + sqrt(1 - s) (sqrt(f) F(p_i) + sqrt(1 - f) u_i)) + b_cell(p_i)

* c: the common part, one unit Gauss-Markov process per axis for the whole net (``common_tau_s``),
  ``s = common_share`` of the variance. Atmosphere, broadcast orbit and satellite clock errors are
  nearly the same for receivers tens of kilometres apart (that is why differential GNSS works; NovAtel
  OEM4 Family Installation and Operation User Manual, Appendix C "GPS Overview": "errors ... highly
  correlated for adjacent receivers ... up to tens of kilometers"). In the single-frequency L1 C/A
  range error budget without SA (Parkinson and Spilker, "Global Positioning System: Theory and
  Applications" vol. I, 1996, ch. 11, the "standard error model": ephemeris 2.1, satellite clock 2.1,
  ionosphere 4.0, troposphere 0.7, multipath 1.4, receiver 0.5 m, UERE 5.3 m) these common terms
  are 5.0 m of the 5.3 m, 92 % of the variance, in the open. In urban canyons multipath and NLOS
  grow and receivers a street apart track different satellites, so the common share falls; the
  preset's 0.5 is our assumption between the two. The common part is scaled by the zone's sigma
  like the rest: the same range errors map into larger position errors under the poorer geometry
  of a canyon (position error = DOP x range error), so two vehicles in one zone share it exactly and
  vehicles of different zones share it in proportion to their sigmas. ``common_tau_s`` 600 s is an
  assumption: the common terms change with satellite elevation over tens of minutes (a stationary
  receiver's horizontal error keeps a slow component over the 70 minutes D. L. Wilson plots for a
  Garmin 12XL, http://www.erols.com/dlwilson/gpscorr.htm, beside the ~1 min one ``tau_s`` models).
* F: a unit random field over the net, ``f = field_share`` of the rest: multipath and masking that
  receivers on the same street see alike. Exponential covariance exp(-d / ``field_corr_length_m``)
  from ``field_features`` random Fourier features (Rahimi and Recht, "Random features for large-scale
  kernel machines", NIPS 2007; the 2-D exponential kernel's spectral density is a Student t with one
  degree of freedom), their coefficients Gauss-Markov in time (``field_tau_s``: the pattern at a
  fixed place changes as the satellites move). The variance at every point is exactly 1 whatever
  the number of features; the correlation of two points d apart, for the drawn frequencies, is the
  mean of cos(omega . d) (:func:`field_correlation`), whose expectation is exp(-d / L). 50 m (a
  street block) and 300 s are assumptions: no published correlation length of two vehicles'
  position errors on one street was found.
* u_i: the receiver's own part (noise, its own multipath), a unit process correlated over distance
  travelled and time: a_i = exp(-d_i / ``local_corr_length_m`` - Ts / ``tau_s``), d_i the distance the
  vehicle moved this step. A standing receiver keeps it for tau_s (30 s: the stationary receivers
  above), a moving one loses it over 20 m (assumption: code multipath of a moving antenna varies
  within metres, P. D. Groves, "Principles of GNSS, Inertial, and Multisensor Integrated Navigation
  Systems", 2nd ed. 2013, ch. 9, smoothed by the receiver's own filter). It is driven by the same
  standard normal draws as the per-vehicle model's state.
* b_cell: NLOS bias episodes of square cells of ``nlos_cell_m``: each cell a vehicle has visited runs
  its own episodes (start probability 1 - exp(-lambda Ts) per step outside one, lambda of the zone of
  the first vehicle seen in it or of the building density at its centre, durations and biases as
  above); every vehicle in the cell while an episode lasts gets its bias. The episode parameters are
  the per-vehicle model's; 50 m is our assumption (a street block).
* Each vehicle's error outside episodes has the zone's variance sigma_p^2 per axis. Two receivers d
  apart in one zone, outside episodes, correlate by s + (1 - s) f exp(-d / L) in expectation
  (:func:`expected_correlation`).
* Streams: "common" (c), "field_features" (the frequencies), "field" (the coefficients),
  "nlos_cell_start", "nlos_cell_duration", "nlos_cell_bias", each ``SeedSequence([seed, 0x6E5,
  crc32(name)])``; u's draws are the idealised GNSS stream's, as above.
* Calibration and measured statistics: docs/validation/realistic_sensing.md, "GNSS error model and
  its calibration".
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
#: The ``[gnss_error] model`` values: each vehicle's error on its own, the shared field, or a receiver at
#: pseudorange level (couplers.sensing.gnss_satellites).
GNSS_MODELS = ("per_vehicle", "field", "satellites")
NLOS_MODES = ("block", "delay", "reflect")
#: The ``[gnss_error] velocity`` values under "satellites": the zone's white Doppler error, or a range-rate
#: least-squares velocity from the same satellites as the fix.
VELOCITY_MODES = ("zone", "doppler")
#: The ``[gnss_error] reported_covariance`` values under "satellites": the receiver's budget through the
#: geometry (DOP), or that scaled by the fit's a-posteriori variance factor (couplers.sensing.gnss_satellites).
REPORTED_COVARIANCE_MODES = ("dop", "residual")
#: The ``[gnss_error] draws`` values under "satellites": the receiver noise, multipath and Doppler normals drawn
#: for every satellite of the constellation (the streams do not depend on the sky), or only for those above the
#: elevation mask (couplers.sensing.gnss_satellites, "Random streams").
DRAW_MODES = ("all", "visible")


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
    # "per_vehicle" (the model above, each vehicle on its own) or "field" (FieldErrorProcess: a common part,
    # a spatial field and the receiver's own part; NLOS episodes per cell). The keys below are the field
    # model's; "per_vehicle" does not read them. Sources and assumptions: module docstring, "field".
    model: str = "per_vehicle"
    common_share: float = 0.5
    common_tau_s: float = 600.0
    field_share: float = 0.5
    field_corr_length_m: float = 50.0
    field_tau_s: float = 300.0
    field_features: int = 64
    local_corr_length_m: float = 20.0
    nlos_cell_m: float = 50.0
    # "satellites" (couplers.sensing.gnss_satellites, sources and assumptions there); the other models do not
    # read these keys, and "satellites" reads none of the keys above.
    elevation_mask_deg: float = 10.0
    antenna_height_m: float = 1.5
    nlos: str = "delay"
    constellation_time_s: float = 0.0
    sv_clock_orbit_m: float = 0.5
    iono_vertical_m: float = 1.0
    tropo_zenith_m: float = 0.1
    sv_tau_s: float = 1800.0
    code_noise_a_m: float = 0.3
    code_noise_b_m: float = 0.3
    multipath_m: float = 0.5
    multipath_corr_length_m: float = 10.0
    rx_ure_m: float = 1.0
    rx_iono_m: float = 1.0
    rx_tropo_m: float = 0.3
    rx_code_a_m: float = 0.3
    rx_code_b_m: float = 0.3
    raim_pfa: float = 1e-3
    velocity: str = "zone"
    doppler_noise_mps: float = 0.05
    rx_doppler_mps: float = 0.05
    reported_covariance: str = "dop"
    draws: str = "all"
    # "satellites": the frames carry each receiver's WLS gains and satellites (coloc.core.frame.OracleGnss), what
    # joint_oracle is told; the runner sets it for a run whose methods include joint_oracle (off: no channel)
    oracle_channel: bool = False

    def __post_init__(self):
        def finite(v):
            return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

        if self.model not in GNSS_MODELS:
            raise InputError(None, "model", f"unknown model {self.model!r} (available: {', '.join(GNSS_MODELS)})")
        if not (finite(self.elevation_mask_deg) and 0.0 <= self.elevation_mask_deg < 90.0):
            raise InputError(None, "elevation_mask_deg", f"must be in [0, 90) deg, got {self.elevation_mask_deg!r}")
        if self.nlos not in NLOS_MODES:
            raise InputError(None, "nlos", f"unknown value {self.nlos!r} (available: {', '.join(NLOS_MODES)})")
        if self.velocity not in VELOCITY_MODES:
            raise InputError(None, "velocity",
                             f"unknown value {self.velocity!r} (available: {', '.join(VELOCITY_MODES)})")
        if self.reported_covariance not in REPORTED_COVARIANCE_MODES:
            raise InputError(None, "reported_covariance", f"unknown value {self.reported_covariance!r} "
                                                          f"(available: {', '.join(REPORTED_COVARIANCE_MODES)})")
        if self.draws not in DRAW_MODES:
            raise InputError(None, "draws", f"unknown value {self.draws!r} (available: {', '.join(DRAW_MODES)})")
        for key in ("antenna_height_m", "multipath_corr_length_m"):
            if not (finite(getattr(self, key)) and getattr(self, key) > 0):
                raise InputError(None, key, f"must be positive and finite, got {getattr(self, key)!r}")
        for key in ("constellation_time_s", "sv_clock_orbit_m", "iono_vertical_m", "tropo_zenith_m", "sv_tau_s",
                    "code_noise_a_m", "code_noise_b_m", "multipath_m", "rx_ure_m", "rx_iono_m", "rx_tropo_m",
                    "rx_code_a_m", "rx_code_b_m", "doppler_noise_mps"):
            if not (finite(getattr(self, key)) and getattr(self, key) >= 0):
                raise InputError(None, key, f"must be >= 0 and finite, got {getattr(self, key)!r}")
        if not (finite(self.rx_doppler_mps) and self.rx_doppler_mps > 0):
            raise InputError(None, "rx_doppler_mps", f"must be positive and finite (the receiver's Doppler weights), "
                                                     f"got {self.rx_doppler_mps!r}")
        if not (finite(self.raim_pfa) and 0.0 <= self.raim_pfa < 1.0):
            raise InputError(None, "raim_pfa", f"must be in [0, 1) (0: no fault exclusion), got {self.raim_pfa!r}")
        if self.model == "satellites" and self.rx_ure_m ** 2 + self.rx_iono_m ** 2 + self.rx_tropo_m ** 2 \
                + self.rx_code_a_m ** 2 + self.rx_code_b_m ** 2 == 0:
            raise InputError(None, "rx_code_a_m", "the receiver's error budget is zero: no weights for its fix")
        for key in ("common_share", "field_share"):
            if not (finite(getattr(self, key)) and 0.0 <= getattr(self, key) <= 1.0):
                raise InputError(None, key, f"must be in [0, 1], got {getattr(self, key)!r}")
        for key in ("common_tau_s", "field_tau_s"):
            if not (finite(getattr(self, key)) and getattr(self, key) >= 0):
                raise InputError(None, key, f"must be >= 0 and finite (0 = white), got {getattr(self, key)!r}")
        for key in ("field_corr_length_m", "local_corr_length_m", "nlos_cell_m"):
            if not (finite(getattr(self, key)) and getattr(self, key) > 0):
                raise InputError(None, key, f"must be positive and finite, got {getattr(self, key)!r}")
        if isinstance(self.field_features, bool) or not isinstance(self.field_features, int) \
                or not 1 <= self.field_features <= 4096:
            raise InputError(None, "field_features", f"must be an integer in [1, 4096], got {self.field_features!r}")
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


# --- the "field" model ---------------------------------------------------------------------------------------


def exponential_kernel_frequencies(rng: np.random.Generator, m: int, length_m: float) -> np.ndarray:
    """(m, 2) random Fourier frequencies (rad/m) of the 2-D exponential covariance exp(-d / length_m): its
    spectral density is the bivariate Student t with one degree of freedom and scale 1 / length_m, drawn as
    z / (length_m |g|) with z ~ N(0, I2), g ~ N(0, 1). ``mean(cos(omega . d))`` over the frequencies tends
    to exp(-|d| / length_m)."""
    z = rng.standard_normal((m, 2))
    g = rng.standard_normal(m)
    return z / (length_m * np.maximum(np.abs(g), 1e-300))[:, None]


def field_correlation(omega: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Correlation of the unit field between two points ``d`` (..., 2) apart, for the drawn frequencies:
    mean over features of cos(omega . d) (exactly, not its expectation exp(-|d| / L))."""
    return np.cos(np.asarray(d, dtype=float) @ omega.T).mean(axis=-1)


def expected_correlation(params: GnssErrorParams, d: np.ndarray) -> np.ndarray:
    """Expected correlation (per axis) of two receivers' errors ``d`` m apart, same zone, outside NLOS
    episodes, own parts independent: common_share + (1 - common_share) field_share exp(-d / L)."""
    s, f = params.common_share, params.field_share
    return s + (1.0 - s) * f * np.exp(-np.asarray(d, dtype=float) / params.field_corr_length_m)


#: The field model's cell lookup array (:meth:`FieldErrorProcess._lut_add`): margin in cells around the cells seen,
#: largest size, and the largest cell key it holds (beyond: the dict alone). Speed only: rows are the dict's.
LUT_MARGIN = 8
LUT_MAX_CELLS = 1_000_000
LUT_KEY_BOUND = 1 << 40


class FieldErrorProcess:
    """``[gnss_error] model = "field"``: receiver errors that nearby vehicles share (module docstring).

    Per axis, e_i = sigma_p(zone_i) (sqrt(s) c + sqrt(1 - s) (sqrt(f) F(p_i) + sqrt(1 - f) u_i)) + b_cell(p_i):
    c the common unit Gauss-Markov process (``common_tau_s``), F a unit random field over the net (random
    Fourier features of the exponential covariance, ``field_corr_length_m``, coefficients Gauss-Markov in
    time with ``field_tau_s``), u_i the receiver's own unit process, correlated over distance travelled and
    time (a = exp(-d_i / local_corr_length_m - Ts / tau_s)), b the bias of an NLOS episode of the vehicle's
    cell (``nlos_cell_m``), shared by every vehicle in that cell while it lasts. Each vehicle's error has
    the zone's variance sigma_p^2 per axis outside episodes. Same interface as :class:`GnssErrorProcess`."""

    STREAMS = ("common", "field_features", "field", "nlos_cell_start", "nlos_cell_duration", "nlos_cell_bias")

    def __init__(self, params: GnssErrorParams, seed: int, dt: float, buildings: Buildings | None = None):
        self.params = p = params
        self.dt = float(dt)
        for name in self.STREAMS:
            setattr(self, name, effect_rng(seed, GNSS_ERROR_STREAM_TAG, name))
        self.a_common = gauss_markov_coefficient(self.dt, p.common_tau_s)
        self.a_field = gauss_markov_coefficient(self.dt, p.field_tau_s)
        self.omega = exponential_kernel_frequencies(self.field_features, p.field_features, p.field_corr_length_m)
        self.c = self.common.standard_normal(2)  # stationary from the start
        self.coef = self.field.standard_normal((2, p.field_features, 2))  # (cos/sin, feature, axis)
        self.density = (building_density_grid(buildings, p.nlos_density_radius_m)
                        if buildings is not None and len(buildings) else None)
        self._ids = np.empty(0, dtype=object)
        self._xy = np.empty((0, 2))
        self._u = np.empty((0, 2))
        self._bias_now = np.empty((0, 2))
        m = self.omega.shape[0]
        self._phase, self._cos, self._sin = np.empty((0, m)), np.empty((0, m)), np.empty((0, m))  # field_at's
        # NLOS cells, created at their first visit and evolved every step from then on
        self._cells: dict[tuple[int, int], int] = {}
        self._lut = np.empty((0, 0), dtype=np.int64)  # the same map as a plain array over the cells' range
        self._lut_origin = (0, 0)  # cell key of the array's [0, 0]
        self._cell_p = np.empty(0)  # start probability per step
        self._cell_end = np.empty(0)  # episode end (s), -inf outside one
        self._cell_bias = np.empty((0, 2))

    def field_at(self, xy: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) unit field F at the points ``xy`` with the current coefficients (one column per axis).
        ``idx`` (the rows of these vehicles at the previous call, -1 new): a row whose phases equal, bit for bit,
        those of its previous row takes that row's cosines and sines instead of computing them again (vehicles
        standing still); the result is the same."""
        phase = np.asarray(xy, dtype=float).reshape(-1, 2) @ self.omega.T  # (N, M)
        if idx is None:
            cos, sin = np.cos(phase), np.sin(phase)
        else:
            cos, sin = np.empty_like(phase), np.empty_like(phase)
            same = np.zeros(len(phase), dtype=bool)
            carried = np.flatnonzero(idx >= 0)
            if carried.size:
                same[carried] = (phase[carried] == self._phase[idx[carried]]).all(axis=1)
            old, new = np.flatnonzero(same), np.flatnonzero(~same)
            cos[old], sin[old] = self._cos[idx[old]], self._sin[idx[old]]
            cos[new], sin[new] = np.cos(phase[new]), np.sin(phase[new])
            self._phase, self._cos, self._sin = phase, cos, sin
        return (cos @ self.coef[0] + sin @ self.coef[1]) / math.sqrt(self.omega.shape[0])

    def _cell_rows(self, zone: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Row of each vehicle's NLOS cell; new cells get their start probability (building density at the
        cell centre when the net has buildings, else the rate of the zone of the first vehicle seen in it).
        Known cells are looked up in a plain array over the cells' range (:meth:`_lut_rows`); only the vehicles
        in a cell not seen before go through the dict, in vehicle order (rows are numbered by first visit)."""
        p, cells = self.params, self._cells
        keys = np.floor(np.asarray(xy, dtype=float) / p.nlos_cell_m).astype(np.int64)
        rows = self._lut_rows(keys)
        new_p = []
        for i in np.flatnonzero(rows < 0).tolist():
            key = (int(keys[i, 0]), int(keys[i, 1]))
            r = cells.get(key)
            if r is None:
                r = cells[key] = len(cells)
                self._lut_add(key, r)
                if self.density is not None:
                    centre = (np.array(key, dtype=float) + 0.5) * p.nlos_cell_m
                    rate = p.nlos_rate_per_density_per_min * float(self.density.at(centre[None])[0])
                else:
                    rate = float(zone_rates(p, np.asarray(zone, dtype=object).reshape(-1)[i:i + 1])[0])
                new_p.append(float(episode_start_probability(rate, self.dt)))
            rows[i] = r
        if new_p:
            k = len(new_p)
            self._cell_p = np.concatenate([self._cell_p, new_p])
            self._cell_end = np.concatenate([self._cell_end, np.full(k, -np.inf)])
            self._cell_bias = np.concatenate([self._cell_bias, np.zeros((k, 2))])
        return rows

    def _lut_rows(self, keys: np.ndarray) -> np.ndarray:
        """(N,) row of each cell key (N, 2) in the lookup array, -1 where the key is outside it or not a cell yet."""
        rows = np.full(len(keys), -1, dtype=np.int64)
        lut, (kx0, ky0) = self._lut, self._lut_origin
        if lut.size == 0 or len(keys) == 0:
            return rows
        ix, iy = keys[:, 0] - kx0, keys[:, 1] - ky0
        inside = (ix >= 0) & (ix < lut.shape[0]) & (iy >= 0) & (iy < lut.shape[1])
        rows[inside] = lut[ix[inside], iy[inside]]
        return rows

    def _lut_add(self, key: tuple[int, int], row: int) -> None:
        """Enter cell ``key`` -> ``row`` into the lookup array, growing it (with a margin of LUT_MARGIN cells) to
        the range of every cell so far; past LUT_MAX_CELLS cells the array stops growing and the dict answers."""
        lut, (kx0, ky0) = self._lut, self._lut_origin
        ix, iy = key[0] - kx0, key[1] - ky0
        if lut.size and 0 <= ix < lut.shape[0] and 0 <= iy < lut.shape[1]:
            lut[ix, iy] = row
            return
        ks = np.array(list(self._cells), dtype=np.int64)  # every cell, this one included
        if (ks < -LUT_KEY_BOUND).any() or (ks > LUT_KEY_BOUND).any():
            return  # a position far off the net (or not finite): the dict alone
        lo, hi = ks.min(axis=0) - LUT_MARGIN, ks.max(axis=0) + LUT_MARGIN + 1
        if int(np.prod(hi - lo)) > LUT_MAX_CELLS:
            return
        self._lut = np.full(tuple(hi - lo), -1, dtype=np.int64)
        self._lut[ks[:, 0] - lo[0], ks[:, 1] - lo[1]] = np.fromiter(self._cells.values(), dtype=np.int64,
                                                                     count=len(self._cells))
        self._lut_origin = (int(lo[0]), int(lo[1]))

    def _step_cells(self, t: float) -> None:
        """Episodes of every known cell: those past their end stop; a cell outside one starts one with its
        probability (draws for every cell, so the streams do not depend on which cells are in one)."""
        p, k = self.params, self._cell_p.size
        active = self._cell_end > t + 1e-9
        self._cell_bias[~active] = 0.0
        self._cell_end[~active] = -np.inf
        start = (self.nlos_cell_start.random(k) < self._cell_p) & ~active
        dur = self.nlos_cell_duration.exponential(p.nlos_mean_duration_s, size=k)
        mag = self.nlos_cell_bias.exponential(p.nlos_bias_mean_m, size=k) if p.nlos_bias_mean_m > 0 else np.zeros(k)
        ang = self.nlos_cell_bias.uniform(-np.pi, np.pi, size=k)
        self._cell_end[start] = t + dur[start]
        mag, ang = mag[start], ang[start]  # elementwise: the same values as over every cell, then selected
        self._cell_bias[start] = np.stack([mag * np.cos(ang), mag * np.sin(ang)], axis=1)

    def step(self, t: float, ids: np.ndarray, entered: np.ndarray, w: np.ndarray, sigma_p: np.ndarray,
             zone: np.ndarray, xy: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) position error of this step (see :meth:`GnssErrorProcess.step`; ``w`` drives the receivers'
        own parts)."""
        p = self.params
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        w = np.asarray(w, dtype=float).reshape(-1, 2)
        if idx is None:
            idx = match_ids(self._ids, ids)
        idx = np.asarray(idx, dtype=np.int64)
        # common part and field coefficients: one Gauss-Markov step each
        b_c = math.sqrt(1.0 - self.a_common ** 2)
        self.c = self.a_common * self.c + b_c * self.common.standard_normal(2)
        b_f = math.sqrt(1.0 - self.a_field ** 2)
        self.coef = self.a_field * self.coef + b_f * self.field.standard_normal(self.coef.shape)
        # own part: correlated over the distance travelled this step and over time (tau_s)
        carried = (idx >= 0) & ~np.asarray(entered, dtype=bool)
        u = w.copy()
        if carried.any():
            prev = idx[carried]
            d = np.hypot(*(xy[carried] - self._xy[prev]).T)
            expo = d / p.local_corr_length_m + (self.dt / p.tau_s if p.tau_s > 0 else np.inf)
            a = np.exp(-expo)[:, None]
            u[carried] = a * self._u[prev] + np.sqrt(1.0 - a * a) * w[carried]
        rows = self._cell_rows(zone, xy)
        self._step_cells(float(t))
        bias = self._cell_bias[rows]
        s, f = p.common_share, p.field_share
        local = math.sqrt(f) * self.field_at(xy, idx) + math.sqrt(1.0 - f) * u
        unit = math.sqrt(s) * self.c[None, :] + math.sqrt(1.0 - s) * local
        error = np.asarray(sigma_p, dtype=float)[:, None] * unit + bias
        self._ids, self._xy, self._u, self._bias_now = np.asarray(ids, dtype=object), xy, u, bias
        return error

    @property
    def in_episode(self) -> np.ndarray:
        """(N,) bool for the vehicles of the last step: inside a bias episode of their cell."""
        return np.any(self._bias_now != 0.0, axis=1)


def gnss_error_process(params: GnssErrorParams, seed: int, dt: float, buildings: Buildings | None = None,
                       net_path=None):
    """The process of ``params.model``: :class:`GnssErrorProcess` ("per_vehicle"), :class:`FieldErrorProcess`
    ("field") or :class:`couplers.sensing.gnss_satellites.SatelliteErrorProcess` ("satellites", seen from the
    geographic reference of the net file ``net_path``)."""
    if params.model == "satellites":
        from couplers.sensing.gnss_satellites import SatelliteErrorProcess

        return SatelliteErrorProcess(params, seed, dt, buildings, net_path)
    cls = FieldErrorProcess if params.model == "field" else GnssErrorProcess
    return cls(params, seed, dt, buildings)
