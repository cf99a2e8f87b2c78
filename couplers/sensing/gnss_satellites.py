"""``[gnss_error] model = "satellites"``: a receiver at pseudorange level. Each vehicle's fix is the weighted
least-squares solution of its own pseudoranges to the GPS + Galileo satellites it receives, and the covariance it
reports is the receiver's own (DOP times its error budget), which is what the estimators get as ``gnss_R``.

Sky and line of sight: :mod:`couplers.sensing.gnss_sky` (constellation, geographic reference, buildings).

Pseudorange error of vehicle i to satellite s (m), at elevation el_s:

    eps_is = c_s + I_s F(el_s) + T m(el_s) + sigma_n(el_s) w_is + sigma_mp(el_s) u_is + nlos_is

* c_s: broadcast clock and orbit error of the satellite (``sv_clock_orbit_m``), I_s: the vertical ionospheric
  delay left after the broadcast (Klobuchar) model at that satellite's pierce point (``iono_vertical_m``), T: the
  zenith tropospheric delay left after the receiver's model (``tropo_zenith_m``, one value for the net). Each a
  unit first-order Gauss-Markov process (correlation time ``sv_tau_s``) times its sigma, shared by every receiver
  of the net: the few km of a net change neither the satellite nor the pierce point appreciably (the reason
  differential GNSS works). Mapping functions: F(el) = 1 + 16 (0.53 - E)^3, E the elevation in semicircles, the
  Klobuchar obliquity factor (IS-GPS-200, 20.3.3.5.2.5); m(el) = 1.001 / sqrt(0.002001 + sin^2 el) (RTCA DO-229,
  A.4.2.4, the SBAS tropospheric mapping).
* Receiver noise, white per epoch: sigma_n^2 = a^2 + b^2 / sin(el) with ``code_noise_a_m`` / ``code_noise_b_m``
  (the elevation model of RTKLIB 2.4.2 pntpos.c ``varerr``; a = b = 0.3 m are its defaults, err[1..2] 0.003 m
  times eratio 100).
* Multipath: sigma_mp = ``multipath_m`` / sin(el), a unit process u_is per (vehicle, satellite) correlated over
  the distance the vehicle travels, a = exp(-d / ``multipath_corr_length_m``), not over time (a standing vehicle
  keeps its multipath). The 1 / sin(el) growth and the 0.5 m at zenith are assumptions (code multipath of a car
  roof antenna grows toward the horizon); the 10 m correlation length is an assumption (code multipath of a moving
  antenna varies within metres: P. D. Groves, Principles of GNSS, Inertial, and Multisensor Integrated Navigation
  Systems, 2nd ed. 2013, ch. 9).
* NLOS (the buildings of the net folder, :func:`couplers.sensing.gnss_sky.line_of_sight`): ``nlos = "block"``:
  a blocked satellite is not received; ``"delay"``: it is received by a reflection, with the extra path
  2 d cos(el), d the horizontal distance from the antenna to the blocking facade along the satellite's azimuth
  (the reflection model of L.-T. Hsu, "Analysis and modeling GPS NLOS effect in highly urbanized area", GPS
  Solutions 22:7, 2018, gamma = d sec(el) (1 + cos 2 el) = 2 d cos(el), with the reflector across the street
  taken at the blocking facade's distance: alike in a street canyon of even width; our simplification);
  ``"reflect"``: received off the facade that gives the shortest clear single-bounce specular path, extra path
  2 d cos(el) cos(dphi), d that facade's perpendicular distance and dphi the angle between the satellite's azimuth
  and the facade's normal (image method; Hsu's model for a general azimuth), not received when no facade gives
  one (:func:`couplers.sensing.gnss_sky.reflections`). Deterministic geometry: receivers a few metres apart in
  one street see the same facades, hence alike delays.

Receiver (:func:`_wls_kernel`): states east, north, up and clock (one clock for both systems: the broadcast
GPS-Galileo time offset applied), the satellites above ``elevation_mask_deg`` and received, weights 1 / sigma_rx^2
from the receiver's own budget (in the form of RTKLIB pntpos.c ``rescode``, not the world's values):

    sigma_rx^2 = rx_ure_m^2 + (rx_iono_m F(el))^2 + (rx_tropo_m / (sin el + 0.1))^2 + rx_code_a_m^2
                 + rx_code_b_m^2 / sin(el)

(RTKLIB: ephemeris variance from the broadcast URA, ionosphere 0.5 times the Klobuchar delay (ERR_BRDCI),
troposphere ERR_SAAS = 0.3 m over sin(el) + 0.1, code as above.) The fix is linearised about the truth: its error
is the WLS solution dx = (H^T W H)^-1 H^T W eps, H's rows (-e_s, 1) with e_s the unit vector to the satellite
(metres of error against tens of thousands of km of range: the linearisation error is far below a millimetre).
Fault exclusion (RAIM): the weighted sum of squared residuals against the chi-square quantile 1 - ``raim_pfa``
with m - 4 degrees of freedom (RTKLIB's table is alpha = 0.001, our default); while it fails and at least six
satellites remain, the satellite of the largest normalised residual (r_j^2 / (sigma_j^2 - h_j P h_j^T), Baarda's
w-test) is excluded and the fix recomputed. ``raim_pfa = 0``: no test. The reported covariance is the 2 x 2
east-north block of (H^T W H)^-1 of the satellites used (``reported_covariance = "dop"``, the default: RTKLIB's
pntpos reports this Qr). ``reported_covariance = "residual"``: that block times the a-posteriori variance factor
of the weighted least squares, s0^2 = r^T W r / (m - 4) (r the residuals, m the satellites used; the estimate of
the unit weight's variance of least-squares adjustment: the residuals tell the receiver how far its budget
understates its errors. A receiver that reports it: Trimble's GSOF "Position VCV" record gives the inverted
normal matrix with the solution's "unit variance" and the range residual RMS over the degrees of freedom
(help.fieldsystems.trimble.com/alloy/gsof-messages-position-vcv.htm); the residual-based consistency of P. D.
Groves, Principles of GNSS, Inertial, and Multisensor Integrated Navigation Systems, 2nd ed. 2013, ch. 17, is
quoted from memory), when above 1 and m > 4
(never below the budget's; four satellites leave no residual). After a fault exclusion the factor is the larger
of the final fit's and the fit's before the first exclusion (our rule, an assumption: a receiver that had to
exclude a satellite keeps the evidence that its set was contaminated, as NLOS signals come in groups in a
street). The fix itself is the same under both values. Fewer than four satellites: no fix; the receiver holds
its last fix (the vehicle has moved on) and reports :data:`NO_FIX_SIGMA_M` per axis; a vehicle with no fix yet
gets a fix drawn at that sigma around it (its own stream).

Velocity (``velocity = "doppler"``; ``"zone"``, the default, keeps the zone's white Doppler error as the other
models): the range-rate WLS (east, north, up velocity and clock drift) over the satellites of the vehicle's fix,
range-rate error white with sigma^2 = ``doppler_noise_mps``^2 (1 + 1 / sin el) plus, for a reflected signal, the
rate of its extra path g . v (the antenna's image moves with the mirrored velocity: moving toward the reflecting
wall shortens the path); weights and the reported 2 x 2 covariance from the receiver's ``rx_doppler_mps`` in the
same form, with the fix's fault exclusion (chi-square residual test at ``raim_pfa``, worst range rate excluded
while at least six remain; an assumption: a receiver screening its range rates as its ranges), and under
``reported_covariance = "residual"`` the same variance factor of its range-rate residuals. 0.05 m/s for both: a mass-market receiver's datasheet velocity accuracy (u-blox NEO-M8 data sheet,
0.05 m/s at 50 %, quoted from memory) with the elevation form of the code noise (assumption). Vehicles without
a fix keep the zone's Doppler error.

Random streams (``SeedSequence([seed, 0x6E5, crc32(name)])``): "sv_common" (c, I, T), "code_noise" (w),
"multipath" (u), "no_fix", "doppler_noise" (drawn only under ``velocity = "doppler"``). Under ``draws = "all"`` (the
default) every step draws w, u's innovations and the range-rate noise for every satellite (visible or not) and every
vehicle, so the streams do not depend on the geometry (inside kernels through :mod:`couplers.sensing.streams`, the
same numbers in the same order, where numba's draws are numpy's). ``draws = "visible"`` draws them only for the satellites
above the elevation mask (the only ones a receiver uses), (N, M) each step with M of the 48 above the mask, taking
the same normals for the same terms: each term keeps its distribution, the streams' values go to other terms. A
satellite's multipath process u of a vehicle is carried while the satellite stays above the mask and starts from a
fresh draw when it rises, as for a vehicle that enters (its stationary law; under "all" it evolves below the mask
unseen); the columns below the mask are 0 and never read.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numba import njit

from coloc.core.vehicles import match_ids
from couplers.errors import InputError
from couplers.net.buildings import Buildings
from couplers.sensing.gnss_reflect import facade_lines, reflect_kernel
from couplers.sensing.gnss_sky import (LOS_GRID_DIVISIONS, BuildingEdges, Sky, building_candidates, clearance_radius,
                                       line_of_sight, los_listed, net_origin, reflections)
from couplers.sensing import streams
from couplers.sensing.perception import effect_rng
from couplers.sensing.streams import StreamHandles, stream

GNSS_ERROR_STREAM_TAG = 0x6E5  # as couplers.sensing.gnss_error
NO_FIX_SIGMA_M = 100.0  # per axis, reported while no fix (large: an estimator all but ignores it)
MIN_SIN_EL = 0.05  # sin of ~2.9 deg: the mapping of satellites under the horizon stays finite (never used)
SKY_BLOCK = 64  # steps whose sky terms are computed at once (SatelliteErrorProcess._sky_step)
_NO_ROWS_F = np.empty(0)
_NO_CANDIDATES = (np.empty((0, 2), dtype=np.int64), (np.zeros(1, dtype=np.int64), np.empty(0, dtype=np.int64),
                                                     np.empty(0)))


def klobuchar_obliquity(el: np.ndarray) -> np.ndarray:
    """F(el) = 1 + 16 (0.53 - E)^3, E = el / pi semicircles (IS-GPS-200, 20.3.3.5.2.5)."""
    return 1.0 + 16.0 * (0.53 - np.asarray(el) / np.pi) ** 3


def tropo_mapping(el: np.ndarray) -> np.ndarray:
    """m(el) = 1.001 / sqrt(0.002001 + sin^2 el) (RTCA DO-229, A.4.2.4)."""
    return 1.001 / np.sqrt(0.002001 + np.sin(np.asarray(el)) ** 2)


def receiver_variance(params, el: np.ndarray) -> np.ndarray:
    """sigma_rx^2 of the receiver's own budget (module docstring) per satellite at elevation ``el``."""
    s = np.maximum(np.sin(el), MIN_SIN_EL)
    p = params
    return (p.rx_ure_m ** 2 + (p.rx_iono_m * klobuchar_obliquity(el)) ** 2 + (p.rx_tropo_m / (s + 0.1)) ** 2
            + p.rx_code_a_m ** 2 + p.rx_code_b_m ** 2 / s)


def open_sky_common_share(params, sky: Sky, t: float) -> tuple[float, float]:
    """Share of the horizontal error variance (east, north) that every receiver of the net shares at run time
    ``t`` in the open (all satellites above the mask used, no exclusion): the correlation of two receivers'
    errors at any separation within the net. The WLS gain K = (H^T W H)^-1 H^T W maps the pseudorange error
    covariance, common (clock/orbit and ionosphere per satellite, one troposphere) plus own (code noise and
    multipath), into position: (K S_common K^T)_jj / (K S K^T)_jj."""
    p = params
    los, _, el = sky.look(p.constellation_time_s + t)
    m = el >= math.radians(p.elevation_mask_deg)
    los, el = los[m], el[m]
    s = np.maximum(np.sin(el), MIN_SIN_EL)
    h = np.c_[-los, np.ones(el.size)]
    w = 1.0 / receiver_variance(p, el)
    k = np.linalg.solve((h.T * w) @ h, h.T * w)
    g = p.tropo_zenith_m * tropo_mapping(el)
    common = np.diag(p.sv_clock_orbit_m ** 2 + (p.iono_vertical_m * klobuchar_obliquity(el)) ** 2) + np.outer(g, g)
    own = np.diag(p.code_noise_a_m ** 2 + p.code_noise_b_m ** 2 / s + (p.multipath_m / s) ** 2)
    cc, ct = k @ common @ k.T, k @ (common + own) @ k.T
    return float(cc[0, 0] / ct[0, 0]), float(cc[1, 1] / ct[1, 1])


def chi2_thresholds(pfa: float, max_dof: int) -> np.ndarray:
    """(max_dof + 1,) chi-square quantiles 1 - pfa by degrees of freedom (index 0 unused; pfa 0: inf)."""
    out = np.full(max_dof + 1, np.inf)
    if pfa > 0:
        from scipy.stats import chi2

        out[1:] = chi2.ppf(1.0 - pfa, np.arange(1, max_dof + 1))
    return out


def missing_heights(buildings: Buildings | None) -> np.ndarray:
    """Indices of the buildings without a height."""
    if buildings is None or not len(buildings):
        return np.empty(0, dtype=np.int64)
    return np.flatnonzero(~np.isfinite(np.asarray(buildings.heights, dtype=float)))


def check_building_heights(net_dir: str | Path) -> None:
    """Under ``model = "satellites"`` every building of the net folder needs its height: InputError naming the
    buildings file and the first feature without one."""
    from couplers.net.folder import BUILDINGS_FILE, load_net_folder

    folder = load_net_folder(net_dir)
    bad = missing_heights(folder.buildings)
    if bad.size:
        name = (folder.scenario.get("files") or {}).get("buildings") or BUILDINGS_FILE
        raise InputError(folder.root / name, f"features[{int(bad[0])}].properties.height",
                         f"missing: [gnss_error] model = \"satellites\" needs every building's height (the line of "
                         f"sight of each satellite); {bad.size} building(s) have none")


@njit(cache=True)
def _inv_spd4(a, out):
    """out = a^-1 for a symmetric positive definite 4 x 4 (Cholesky a = L L^T, then L^-T L^-1); False (out
    untouched) when a pivot is not positive: a geometry without a fix (satellites nearly coplanar with the
    antenna)."""
    low = np.zeros((4, 4))
    for j in range(4):
        d = a[j, j]
        for k in range(j):
            d -= low[j, k] * low[j, k]
        if not d > 1e-12 * a[j, j]:
            return False
        d = math.sqrt(d)
        low[j, j] = d
        for i in range(j + 1, 4):
            v = a[i, j]
            for k in range(j):
                v -= low[i, k] * low[j, k]
            low[i, j] = v / d
    li = np.zeros((4, 4))  # L^-1, lower triangular
    for j in range(4):
        li[j, j] = 1.0 / low[j, j]
        for i in range(j + 1, 4):
            v = 0.0
            for k in range(j, i):
                v -= low[i, k] * li[k, j]
            li[i, j] = v / low[i, i]
    for i in range(4):
        for j in range(4):
            v = 0.0
            for k in range(max(i, j), 4):
                v += li[k, i] * li[k, j]
            out[i, j] = v
    return True


@njit(cache=True)
def _wls_kernel(los, usable, eps, var_rx, thr, posterior=False):
    """Per vehicle: the WLS fix error (east, north) of the usable satellites with fault exclusion, the reported
    2 x 2 covariance, satellites used, satellites excluded, whether there is a fix (module docstring).
    ``posterior``: the reported covariance scaled by the a-posteriori variance factor r^T W r / (m - 4) when
    above 1 and m > 4, the larger of the final fit's and the fit's before any exclusion
    (``reported_covariance = "residual"``, module docstring)."""
    n, s = usable.shape
    err = np.zeros((n, 2))
    cov = np.zeros((n, 2, 2))
    used = np.zeros(n, dtype=np.int64)
    excluded = np.zeros(n, dtype=np.int64)
    ok = np.zeros(n, dtype=np.bool_)
    usedm = np.zeros((n, s), dtype=np.bool_)
    idx = np.empty(s, dtype=np.int64)
    h = np.empty((s, 4))
    for k in range(s):
        h[k, 0], h[k, 1], h[k, 2], h[k, 3] = -los[k, 0], -los[k, 1], -los[k, 2], 1.0
    a = np.empty((4, 4))
    p = np.empty((4, 4))
    b = np.empty(4)
    x = np.empty(4)
    for i in range(n):
        f0 = 1.0
        m = 0
        for k in range(s):
            if usable[i, k]:
                idx[m] = k
                m += 1
        while m >= 4:
            a[:] = 0.0
            b[:] = 0.0
            for j in range(m):
                k = idx[j]
                w = 1.0 / var_rx[k]
                for r in range(4):
                    hw = h[k, r] * w
                    b[r] += hw * eps[i, k]
                    for c in range(4):
                        a[r, c] += hw * h[k, c]
            if not _inv_spd4(a, p):
                break  # degenerate geometry: the fix of the previous set of satellites stands, if any
            for r in range(4):
                x[r] = p[r, 0] * b[0] + p[r, 1] * b[1] + p[r, 2] * b[2] + p[r, 3] * b[3]
            ok[i] = True
            err[i, 0], err[i, 1] = x[0], x[1]
            cov[i, 0, 0], cov[i, 0, 1], cov[i, 1, 0], cov[i, 1, 1] = p[0, 0], p[0, 1], p[1, 0], p[1, 1]
            used[i] = m
            usedm[i, :] = False
            for j in range(m):
                usedm[i, idx[j]] = True
            if m == 4 or not (posterior or np.isfinite(thr[m - 4])):
                break
            wsse = 0.0
            worst, worst_w = -1, -1.0
            for j in range(m):
                k = idx[j]
                r = eps[i, k] - (h[k, 0] * x[0] + h[k, 1] * x[1] + h[k, 2] * x[2] + x[3])
                wsse += r * r / var_rx[k]
                hph = 0.0
                for rr in range(4):
                    for c in range(4):
                        hph += h[k, rr] * p[rr, c] * h[k, c]
                cr = var_rx[k] - hph
                wj = r * r / cr if cr > 1e-12 else 0.0
                if wj > worst_w:
                    worst, worst_w = j, wj
            if posterior:  # the final fit's variance factor, never below the one before any exclusion
                f = wsse / (m - 4)
                if excluded[i] == 0:
                    f0 = f
                f = max(f, f0)
                if f > 1.0:
                    for r in range(2):
                        for c in range(2):
                            cov[i, r, c] = f * p[r, c]
            if not np.isfinite(thr[m - 4]) or wsse <= thr[m - 4] or m <= 5:
                break  # no test, consistent, or too few satellites to exclude one and test again
            for j in range(worst, m - 1):
                idx[j] = idx[j + 1]
            m -= 1
            excluded[i] += 1
        if not ok[i]:
            used[i] = m
    return err, cov, used, excluded, ok, usedm


@njit(cache=True)
def _carried_rows(idx, entered, xy, xy_prev, fix_prev_all):
    """The receivers carried from the previous step (idx >= 0 and not entered): their rows, previous rows, moves
    xy - xy_prev (M, 2), and (N, 2) last fixes, NaN for the others (numpy's mask, flatnonzero and gathers)."""
    n = idx.size
    rows = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        if idx[i] >= 0 and not entered[i]:
            rows[m] = i
            m += 1
    prev = np.empty(m, dtype=np.int64)
    moved = np.empty((m, 2))
    fix_prev = np.full((n, 2), np.nan)
    for r in range(m):
        i, q = rows[r], idx[rows[r]]
        prev[r] = q
        moved[r, 0] = xy[i, 0] - xy_prev[q, 0]
        moved[r, 1] = xy[i, 1] - xy_prev[q, 1]
        fix_prev[i, 0], fix_prev[i, 1] = fix_prev_all[q, 0], fix_prev_all[q, 1]
    return rows[:m], prev, moved, fix_prev


@njit(cache=True)
def _carried_multipath(rows, prev, a, u_prev, z):
    """The multipath draws ``z`` (N, S) with the rows ``rows`` carried from ``u_prev[prev]``: u = a u_prev +
    sqrt(1 - a^2) z, row by row (numpy's a * u_prev + np.sqrt(1.0 - a * a) * z, the same operations)."""
    u = z.copy()
    for r in range(rows.size):
        i, q, ar = rows[r], prev[r], a[r]
        b = np.sqrt(1.0 - ar * ar)
        for k in range(z.shape[1]):
            u[i, k] = ar * u_prev[q, k] + b * z[i, k]
    return u


@njit(cache=True)
def _normals(h, n, s):
    """(n, s) standard normals of the stream of handle ``h`` (numpy's ``standard_normal((n, s))`` on it)."""
    return stream(h).standard_normal((n, s))


@njit(cache=True)
def _drawn_multipath(h, n, s, rows, prev, a, u_prev):
    """:func:`_carried_multipath` of (n, s) normals drawn here from the stream of handle ``h`` (numpy's
    ``standard_normal((n, s))``), carried in place: the same operations on the same values."""
    u = stream(h).standard_normal((n, s))
    for r in range(rows.size):
        i, q, ar = rows[r], prev[r], a[r]
        b = np.sqrt(1.0 - ar * ar)
        for k in range(s):
            u[i, k] = ar * u_prev[q, k] + b * u[i, k]
    return u


@njit(cache=True)
def _spread(x, cols, s):
    """(N, s) zeros with column cols[j] set to x[:, j] (``draws = "visible"``: the draws of the satellites above the
    mask in their columns)."""
    out = np.zeros((x.shape[0], s))
    for i in range(x.shape[0]):
        for j in range(cols.size):
            out[i, cols[j]] = x[i, j]
    return out


@njit(cache=True)
def _carried_multipath_visible(rows, prev, a, u_prev, z, cols, above_prev):
    """``draws = "visible"``: u (N, S), zero off the columns ``cols`` (the satellites above the mask), z[:, j] in
    column cols[j], and for the rows ``rows`` carried from ``u_prev[prev]`` where the satellite was above the mask
    the step before (``above_prev``): a u_prev + sqrt(1 - a^2) z, as :func:`_carried_multipath`."""
    u = _spread(z, cols, u_prev.shape[1])
    for r in range(rows.size):
        i, q, ar = rows[r], prev[r], a[r]
        b = np.sqrt(1.0 - ar * ar)
        for j in range(cols.size):
            k = cols[j]
            if above_prev[k]:
                u[i, k] = ar * u_prev[q, k] + b * z[i, j]
    return u


def wls_gains(los: np.ndarray, used: np.ndarray, var: np.ndarray) -> np.ndarray:
    """(N, 2, S) east/north rows of each receiver's WLS gain (H^T W H)^-1 H^T W over its satellites ``used``
    (N, S), H's rows (-e_s, 1) from ``los`` (S, 3), weights 1 / ``var`` (S,); zero columns for the other
    satellites, all zero for a receiver with fewer than four. The fix error of :func:`_wls_kernel` is
    ``gain @ eps`` (tested to 1e-9): what ``joint_oracle`` is told (``oracle_channel``)."""
    n, s = used.shape
    h = np.c_[-np.asarray(los, dtype=float), np.ones(s)]  # (S, 4)
    hw = used[:, :, None] * (h / np.asarray(var, dtype=float)[:, None])[None]  # (N, S, 4)
    out = np.zeros((n, 2, s))
    ok = used.sum(axis=1) >= 4
    if ok.any():
        a = np.einsum("nsk,sl->nkl", hw[ok], h)
        out[ok] = np.linalg.solve(a, np.swapaxes(hw[ok], 1, 2))[:, :2]
    return out


@njit(cache=True)
def _pseudorange_sum(common, sig_n, white, mp, u):
    """eps = common + sig_n white + mp u per (receiver, satellite), added in that order (numpy's broadcast sum)."""
    n, s = white.shape
    eps = np.empty((n, s))
    for i in range(n):
        for k in range(s):
            eps[i, k] = (common[k] + sig_n[k] * white[i, k]) + mp[k] * u[i, k]
    return eps


@njit(cache=True)
def _assemble(common, sig_n, white, mp, u, above, cols, mode, b, d, cos_c, found, ex, g, want_rate):
    """The (N, S) arrays of :meth:`SatelliteErrorProcess.pseudorange_errors_reference` from its per-satellite
    terms and the line of sight of the columns ``cols`` (the satellites above the mask): eps (the sum of
    :func:`_pseudorange_sum`, plus the extra path where the reference adds one: ``mode`` 2 "delay", 2 d cos(el)
    where blocked, 3 "reflect", the reflection's ``ex``), usable (above the mask, and not blocked under 1
    "block", not blocked without a reflection under 3), blocked, and under 3 with ``want_rate`` the (N, S, 2)
    range-rate coefficients (else (0, S, 2)). ``mode`` 0: no buildings or no receiver."""
    n, s = white.shape
    eps = np.empty((n, s))
    usable = np.empty((n, s), dtype=np.bool_)
    blocked = np.zeros((n, s), dtype=np.bool_)
    full = np.zeros((n if want_rate else 0, s, 2))
    extra = np.zeros(s)
    for i in range(n):
        for k in range(s):
            eps[i, k] = (common[k] + sig_n[k] * white[i, k]) + mp[k] * u[i, k]
            usable[i, k] = above[k]
        if mode == 0:
            continue
        if mode >= 2:  # the reference adds an (N, S) array of extra paths, zero off the columns
            for j in range(cols.size):
                if mode == 2:
                    extra[cols[j]] = 2.0 * d[i, j] * cos_c[j] if b[i, j] else 0.0
                else:
                    extra[cols[j]] = ex[i, j]
            for k in range(s):
                eps[i, k] = eps[i, k] + extra[k]
        for j in range(cols.size):
            k = cols[j]
            blocked[i, k] = b[i, j]
            if mode == 1:
                usable[i, k] = usable[i, k] and not b[i, j]
            elif mode == 3:
                usable[i, k] = usable[i, k] and not (b[i, j] and not found[i, j])
                if want_rate:
                    full[i, k, 0], full[i, k, 1] = g[i, j, 0], g[i, j, 1]
    return eps, usable, blocked, full


@njit(cache=True)
def _nlos_counts(blocked, above, usedm):
    """Per receiver: blocked satellites above the mask, and blocked satellites used in its fix."""
    n, s = blocked.shape
    nlos = np.zeros(n, dtype=np.int64)
    received = np.zeros(n, dtype=np.int64)
    for i in range(n):
        for k in range(s):
            if blocked[i, k]:
                nlos[i] += above[k]
                received[i] += usedm[i, k]
    return nlos, received


@njit(cache=True)
def _range_rate_errors(sig, w, rate, v):
    """(N, S) range-rate errors sig w + rate . v (``rate`` (N, S, 2), or (0, S, 2): no reflected signal)."""
    n, s = w.shape
    out = np.empty((n, s))
    for i in range(n):
        for k in range(s):
            out[i, k] = sig[k] * w[i, k]
            if rate.shape[0]:
                out[i, k] = out[i, k] + (rate[i, k, 0] * v[i, 0] + rate[i, k, 1] * v[i, 1])
    return out


class SatelliteErrorProcess:
    """``[gnss_error] model = "satellites"`` (module docstring). Same ``step`` interface as
    :class:`couplers.sensing.gnss_error.GnssErrorProcess`; after each step ``reported_cov`` (N, 2, 2) is the
    covariance each receiver reports, and ``last`` the step's diagnostics (satellites above the mask, used,
    excluded, NLOS received or blocked, fix or not)."""

    STREAMS = ("sv_common", "code_noise", "multipath", "no_fix", "doppler_noise")

    def __init__(self, params, seed: int, dt: float, buildings: Buildings | None = None,
                 net_path: Path | None = None):
        self.params = p = params
        # ``oracle_frame`` after each step (``[gnss_error] oracle_channel``, set by the runner for a run with
        # joint_oracle): computed from the step's geometry, no random draw, so the frames are otherwise the same
        self.oracle_channel = bool(getattr(p, "oracle_channel", False))
        self._oracle: dict = {}
        self.dt = float(dt)
        for name in self.STREAMS:
            setattr(self, name, effect_rng(seed, GNSS_ERROR_STREAM_TAG, name))
        self.handles = StreamHandles(self, ("code_noise", "multipath", "doppler_noise"))  # drawn in kernels
        self.lat, self.lon, self.origin_how = net_origin(net_path)
        self.sky = Sky.build(self.lat, self.lon)
        bad = missing_heights(buildings)
        if bad.size:
            raise InputError(None, f"features[{int(bad[0])}].properties.height",
                             "missing: model = \"satellites\" needs every building's height")
        self.edges = BuildingEdges.build(buildings) if buildings is not None and len(buildings) else None
        self.radius = (clearance_radius(self.edges.heights, p.antenna_height_m, p.elevation_mask_deg)
                       if self.edges is not None else 0.0)
        s = self.sky.size
        self.a_sv = 0.0 if p.sv_tau_s == 0 else math.exp(-self.dt / p.sv_tau_s)
        self.sv = self.sv_common.standard_normal((s, 2))  # clock+orbit, vertical iono; stationary from the start
        self.tropo = float(self.sv_common.standard_normal())
        self.thr = chi2_thresholds(p.raim_pfa, s)
        self.mask = math.radians(p.elevation_mask_deg)
        self._ids = np.empty(0, dtype=object)
        self._xy = np.empty((0, 2))
        self._u = np.empty((0, s))
        self._above = np.zeros(s, dtype=bool)  # draws = "visible": the satellites above the mask at the last step
        self._fix = np.empty((0, 2))  # absolute x/y of each receiver's last fix (NaN: none yet)
        self.reported_cov = np.empty((0, 2, 2))
        self.last: dict[str, np.ndarray] = {}
        self._geom: tuple = ()  # this step's (los, el, used satellites, NLOS range-rate coefficients, fix, sky)
        self._sky_block: dict = {}  # the sky terms of SKY_BLOCK steps (_sky_step), by run time
        self._sky_times: dict = {}  # run time -> row of the block
        self._sky_next = 0  # the row expected next
        self._sky_k = SKY_BLOCK  # 1 once a time was off the block's grid
        self._sky_now: tuple = (None, {})  # (run time, _sky_step's terms) of the last call
        # the last pseudorange_errors' antenna positions (their bits) and candidate buildings (CSR)
        self._cands: tuple = _NO_CANDIDATES

    @property
    def posterior(self) -> bool:
        """The receivers scale their reported covariance by their residuals (``reported_covariance =
        "residual"``)."""
        return self.params.reported_covariance == "residual"

    @property
    def doppler(self) -> bool:
        """The receivers' velocity comes from their range rates (``velocity = "doppler"``)."""
        return self.params.velocity == "doppler"

    def _sky_terms(self, t: float):
        """(los (S, 3), az, el, above the mask, sin el floored, the common-mode error (S,), the receiver noise
        sigma (S,)) of every satellite at run time ``t``: what every receiver of the step shares."""
        p = self.params
        los, az, el = self.sky.look(p.constellation_time_s + t)
        above = el >= self.mask
        sin_el = np.maximum(np.sin(el), MIN_SIN_EL)
        common = (p.sv_clock_orbit_m * self.sv[:, 0] + p.iono_vertical_m * klobuchar_obliquity(el) * self.sv[:, 1]
                  + p.tropo_zenith_m * tropo_mapping(el) * self.tropo)
        sig_n = np.sqrt(p.code_noise_a_m ** 2 + p.code_noise_b_m ** 2 / sin_el)
        return los, az, el, above, sin_el, common, sig_n

    def _sky_step(self, t: float) -> dict:
        """The terms of run time ``t`` that depend on ``t`` alone: :meth:`_sky_terms`' (the common-mode error aside:
        its processes move every step), the trigonometry the line of sight and reflections take, and the receiver's
        own variances by elevation (pseudorange, range rate) and the Doppler noise sigma. Computed for
        :data:`SKY_BLOCK` steps at once (``t``, ``t + dt``, ...: :meth:`Sky.look_many` and the same numpy
        expressions on (K, S) arrays, elementwise, so each step's values are the ones computed step by step,
        tested); a ``t`` off the block's times (another step length's rounding, a jump) computes its own row and
        every later step's so."""
        if self._sky_now[0] == t:
            return self._sky_now[1]
        j = self._sky_times.get(t)
        if j is None or j != self._sky_next:
            if self._sky_times and self._sky_next < len(self._sky_times):
                self._sky_k = 1  # off the grid before the block ran out
            ts = t + self.dt * np.arange(self._sky_k) if self._sky_k > 1 else np.array([t])
            ts[0] = t
            self._sky_block = self._sky_rows(ts)
            self._sky_times = {float(x): k for k, x in enumerate(ts)}
            j = 0
        self._sky_next = j + 1
        self._sky_now = (t, {key: val[j] for key, val in self._sky_block.items()})
        return self._sky_now[1]

    def _sky_rows(self, ts: np.ndarray) -> dict:
        """The arrays of :meth:`_sky_step` at the run times ``ts`` (K,): (K, S, ...) each."""
        p = self.params
        los, az, el = self.sky.look_many(p.constellation_time_s + ts)
        sin_el = np.maximum(np.sin(el), MIN_SIN_EL)
        return {"los": los, "az": az, "el": el, "above": el >= self.mask, "sin_el": sin_el,
                "obliquity": klobuchar_obliquity(el), "tropo": tropo_mapping(el),
                "sig_n": np.sqrt(p.code_noise_a_m ** 2 + p.code_noise_b_m ** 2 / sin_el),
                "mp": p.multipath_m / sin_el, "sin_az": np.sin(az), "cos_az": np.cos(az), "tan_el": np.tan(el),
                "cos_el": np.cos(el), "var_rx": receiver_variance(p, el),
                "sig_doppler": p.doppler_noise_mps * np.sqrt(1.0 + 1.0 / sin_el),
                "var_rr": p.rx_doppler_mps ** 2 * (1.0 + 1.0 / sin_el)}

    def pseudorange_errors(self, t: float, xy: np.ndarray, u: np.ndarray, white: np.ndarray, rate: list | None = None,
                           prev: np.ndarray | None = None):
        """(eps (N, S), usable (N, S), los (S, 3), el (S,), blocked (N, S)) at run time ``t`` for the current
        common processes and the per-receiver draws. ``rate``: a list that receives, under ``nlos = "reflect"``,
        the (N, S, 2) range-rate coefficients of the received reflections (zero elsewhere). The values of
        :meth:`pseudorange_errors_reference` (tested): numpy's trigonometry on the same arrays, the line of sight
        and reflection kernels called directly, and the (N, S) sums and masks in one kernel
        (:func:`_assemble`). The candidate buildings of each antenna are listed once for both kernels
        (:func:`couplers.sensing.gnss_sky.building_candidates`); ``prev`` (N,): each antenna's row in the previous
        call (-1: none), whose list an antenna at bitwise the same position takes over."""
        p = self.params
        sky = self._sky_step(t)
        los, el, above = sky["los"], sky["el"], sky["above"]
        # _sky_terms' common-mode error, the same expression on the step's elevation terms
        common = (p.sv_clock_orbit_m * self.sv[:, 0] + p.iono_vertical_m * sky["obliquity"] * self.sv[:, 1]
                  + p.tropo_zenith_m * sky["tropo"] * self.tropo)
        xy = np.ascontiguousarray(xy, dtype=np.float64)
        n, s = len(xy), el.size
        mode = 0  # no buildings (or no receiver): every satellite above the mask, no extra path
        cols = np.flatnonzero(above)
        m = cols.size
        b = d = found = ex = g = cos_c = None  # what the kernels below do not compute: zeros (after them)
        if self.edges is not None and n:
            mode = {"block": 1, "delay": 2, "reflect": 3}[p.nlos]
            if self.radius > 0:  # else nothing is blocked (line_of_sight and reflections return before their kernels)
                e = self.edges
                # as line_of_sight and reflections take them: sin / cos of the azimuths, tan / cos of the elevations
                sa, ca, te = sky["sin_az"][cols], sky["cos_az"][cols], sky["tan_el"][cols]
                grid = e.grid(self.radius, LOS_GRID_DIVISIONS)
                h_ant, bits = float(p.antenna_height_m), xy.view(np.int64)
                pxy, cand = self._cands
                rows = np.full(n, -1, dtype=np.int64) if prev is None else np.asarray(prev, dtype=np.int64)
                cand = building_candidates(xy, rows, bits, pxy, *cand, *e.grid(self.radius), float(self.radius),
                                           e.boxes, e.heights, h_ant)
                self._cands = (bits.copy(), cand)  # a copy: the caller's positions may change in place
                b, d = los_listed(xy, *cand, e.edges, e.start, e.boxes, e.heights, sa, ca, te, h_ant)
                if mode >= 2:
                    cos_c = sky["cos_el"][cols]
                if mode == 3:
                    found, ex, g = reflect_kernel(xy, b, *cand, float(self.radius), e.edges, e.start, e.boxes,
                                                  e.heights, sa, ca, te, cos_c, h_ant, facade_lines(e), *grid)
        if b is None:
            b, d = np.zeros((n, m), dtype=np.bool_), np.zeros((n, m))
        if found is None:
            found, ex, g = np.zeros((n, m), dtype=np.bool_), np.zeros((n, m)), np.zeros((n, m, 2))
        if cos_c is None:
            cos_c = np.zeros(m)
        eps, usable, blocked, full = _assemble(common, sky["sig_n"], np.ascontiguousarray(white, dtype=np.float64),
                                               sky["mp"], np.ascontiguousarray(u, dtype=np.float64),
                                               above, cols, mode, b, d, cos_c, found, ex, g,
                                               mode == 3 and rate is not None)
        if mode == 3 and rate is not None:
            rate.append(full)
        return eps, usable, los, el, blocked

    def pseudorange_errors_reference(self, t: float, xy: np.ndarray, u: np.ndarray, white: np.ndarray,
                                     rate: list | None = None):
        """:meth:`pseudorange_errors` in numpy around the line of sight and reflection functions (its reference)."""
        p = self.params
        los, az, el, above, sin_el, common, sig_n = self._sky_terms(t)
        eps = _pseudorange_sum(common, sig_n, np.ascontiguousarray(white, dtype=np.float64), p.multipath_m / sin_el,
                               np.ascontiguousarray(u, dtype=np.float64))
        n = len(xy)
        blocked = np.zeros((n, el.size), dtype=bool)
        if self.edges is not None and n:
            cols = np.flatnonzero(above)
            b, d = line_of_sight(self.edges, xy, az[cols], el[cols], p.antenna_height_m, self.radius)
            blocked[:, cols] = b
            if p.nlos == "delay":
                extra = np.zeros_like(eps)
                extra[:, cols] = np.where(b, 2.0 * d * np.cos(el[cols])[None, :], 0.0)
                eps = eps + extra
            elif p.nlos == "reflect":
                found, ex, g = reflections(self.edges, xy, az[cols], el[cols], b, p.antenna_height_m, self.radius)
                extra = np.zeros_like(eps)
                extra[:, cols] = ex
                eps = eps + extra
                lost = np.zeros_like(blocked)
                lost[:, cols] = b & ~found  # blocked and no valid reflection: not received
                if rate is not None:
                    full = np.zeros((n, el.size, 2))
                    full[:, cols] = g
                    rate.append(full)
        usable = np.broadcast_to(above, eps.shape).copy()
        if p.nlos == "block":
            usable &= ~blocked
        elif p.nlos == "reflect" and self.edges is not None and n:
            usable &= ~lost
        return eps, usable, los, el, blocked

    def step(self, t: float, ids: np.ndarray, entered: np.ndarray, w: np.ndarray, sigma_p: np.ndarray,
             zone: np.ndarray, xy: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) position error of this step's fixes (``w``, ``sigma_p`` and ``zone`` are not read: the error
        comes from the satellites); ``reported_cov`` the covariance the receivers report."""
        p = self.params
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        n, s = len(xy), self.sky.size
        if idx is None:
            idx = match_ids(self._ids, ids)
        idx = np.asarray(idx, dtype=np.int64)
        # satellite common processes: one Gauss-Markov step each
        b_sv = math.sqrt(1.0 - self.a_sv ** 2)
        self.sv = self.a_sv * self.sv + b_sv * self.sv_common.standard_normal((s, 2))
        self.tropo = self.a_sv * self.tropo + b_sv * float(self.sv_common.standard_normal())
        visible = p.draws == "visible"
        # under draws = "all", where numba's draws are numpy's, the normals are drawn inside the kernels below
        # (couplers.sensing.streams: the same numbers in the same order from each stream)
        in_kernel = not visible and streams.available()
        if visible:  # the satellites above the mask only (module docstring, "Random streams")
            above = self._sky_step(t)["above"]
            cols = np.flatnonzero(above)
            white = _spread(self.code_noise.standard_normal((n, cols.size)), cols, s)
            z = self.multipath.standard_normal((n, cols.size))
        elif in_kernel:
            white = _normals(self.handles["code_noise"], n, s)
        else:
            white = self.code_noise.standard_normal((n, s))
            z = self.multipath.standard_normal((n, s))
        # multipath: correlated over the distance travelled this step
        # the rows carried (in the previous step and not entered), their moves and last fixes (NaN for the others)
        rows, prev, moved, fix_prev = _carried_rows(idx, np.asarray(entered, dtype=np.bool_),
                                                    np.ascontiguousarray(xy, dtype=np.float64), self._xy, self._fix)
        a = np.exp(-np.hypot(*moved.T) / p.multipath_corr_length_m) if rows.size else _NO_ROWS_F
        if in_kernel:
            u = _drawn_multipath(self.handles["multipath"], n, s, rows, prev, a, self._u)
        elif rows.size:  # numpy's hypot and exp above, on the (M, 2) moves' columns as before
            u = (_carried_multipath_visible(rows, prev, a, self._u, z, cols, self._above) if visible
                 else _carried_multipath(rows, prev, a, self._u, z))
        else:
            u = _spread(z, cols, s) if visible else z.copy()
        if visible:
            self._above = above
        rate: list = []
        eps, usable, los, el, blocked = self.pseudorange_errors(t, xy, u, white, rate, prev=idx)
        sky = self._sky_step(t)  # the terms pseudorange_errors took
        var_rx = sky["var_rx"]
        err, cov, used, excluded, ok, usedm = _wls_kernel(np.ascontiguousarray(los), usable, np.ascontiguousarray(eps),
                                                   var_rx, self.thr, self.posterior)
        if not ok.all():  # no fix: hold the last one, or one drawn at NO_FIX_SIGMA_M around a newcomer
            lost = np.flatnonzero(~ok)
            held = np.isfinite(fix_prev[lost, 0])
            err[lost[held]] = fix_prev[lost[held]] - xy[lost[held]]
            k = int((~held).sum())
            err[lost[~held]] = NO_FIX_SIGMA_M * self.no_fix.standard_normal((k, 2))
            cov[lost] = np.eye(2) * NO_FIX_SIGMA_M ** 2
        above = sky["above"]
        nlos, nlos_received = _nlos_counts(blocked, above, usedm)
        self.last = {"above": np.full(n, int(above.sum())), "used": used, "excluded": excluded, "fix": ok,
                     "nlos": nlos, "nlos_received": nlos_received}
        self._geom = (los, el, usedm, rate[0] if rate else None, ok, sky)
        if self.oracle_channel:
            self._oracle = {"gain": wls_gains(los, usedm & ok[:, None], var_rx), "used": usedm & ok[:, None],
                            "reflected": blocked & usedm & ok[:, None], "elevation": el.copy(), "fix": ok.copy()}
        self.reported_cov = cov
        self._ids, self._xy, self._u, self._fix = np.asarray(ids, dtype=object), xy, u, xy + err
        return err

    def velocity_error(self, v_true: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``velocity = "doppler"``: ((N, 2) velocity error, (N, 2, 2) reported covariance, (N,) solved) of this
        step's receivers (call after :meth:`step`, ``v_true`` (N, 2) their true velocities), from the range-rate
        WLS over the satellites of each fix (module docstring). Not solved (no fix): the caller keeps the zone's
        Doppler error."""
        p = self.params
        los, el, usedm, rate, ok, sky = self._geom
        n, s = usedm.shape
        if p.draws == "visible":  # the satellites above the mask only (module docstring, "Random streams")
            cols = np.flatnonzero(sky["above"])
            w = _spread(self.doppler_noise.standard_normal((n, cols.size)), cols, s)
        elif streams.available():  # numba's draws are numpy's: the same normals, drawn in a kernel
            w = _normals(self.handles["doppler_noise"], n, s)
        else:
            w = self.doppler_noise.standard_normal((n, s))
        sig = sky["sig_doppler"]  # doppler_noise_mps sqrt(1 + 1 / sin el), sin el floored at MIN_SIN_EL
        # sig w, plus a reflected signal's Doppler, the antenna image's: g . v (numpy's einsum differs from the
        # kernel's sum only in the sign of a zero, which the addition to sig w removes; tested)
        eps_rate = _range_rate_errors(sig, w, np.zeros((0, s, 2)) if rate is None else rate,
                                      np.ascontiguousarray(v_true, dtype=np.float64).reshape(-1, 2))
        var_rr = sky["var_rr"]  # rx_doppler_mps^2 (1 + 1 / sin el)
        # the same WLS and residual test as the fix (H rows (-e_s, 1): velocity and clock drift), over its satellites
        err, cov, _, _, solved, used_v = _wls_kernel(np.ascontiguousarray(los), usedm,
                                                     np.ascontiguousarray(eps_rate), var_rr, self.thr, self.posterior)
        if self.oracle_channel:
            sv = solved & ok
            self._oracle.update(velocity_gain=wls_gains(los, used_v & sv[:, None], var_rr),
                                velocity_used=used_v & sv[:, None], velocity_solved=sv)
        return err, cov, solved & ok

    def oracle_frame(self):
        """The step's :class:`coloc.core.frame.OracleGnss` (``oracle_channel``; call after :meth:`step` and, under
        ``velocity = "doppler"``, :meth:`velocity_error`): each receiver's WLS gains, its satellites, which of
        them came by reflection, the elevations. None without the channel."""
        if not self.oracle_channel or not self._oracle:
            return None
        from coloc.core.frame import OracleGnss

        return OracleGnss(**self._oracle)

    @property
    def in_episode(self) -> np.ndarray:
        """(N,) bool for the vehicles of the last step: at least one blocked satellite above the mask."""
        return np.asarray(self.last.get("nlos", np.zeros(0)), dtype=int) > 0
