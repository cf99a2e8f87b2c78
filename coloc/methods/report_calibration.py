"""The receiver's accuracy report, calibrated: ``[gnss_model] degraded_above_m``, ``degraded_position_scale``,
``degraded_velocity_scale``.

A receiver scales its reported covariance from the residuals of its least-squares fix (DOP times the residuals'
size). Where few signals remain and some arrive by reflection, that report under-states the error: a reflected
signal's extra path is partly absorbed into the solution, so the residuals do not show it, and the extra path's
rate enters the Doppler velocity as a bias that persists as long as the vehicle drives along the same facade
(Hsu, GPS Solutions 22:7, 2018: NLOS delays of tens of metres in a canyon; the mass-market receivers' reported
accuracy is a residual statistic, Kaplan and Hegarty, "Understanding GPS/GNSS", 3rd ed., 2017, Sec. 7.3). An
integrator calibrates the report against a reference trajectory (a drive test with a reference system) and keeps
the result as a table: above a reported per-axis position standard deviation of ``degraded_above_m`` the fix's
position covariance is taken ``degraded_position_scale`` squared times larger and its velocity covariance
``degraded_velocity_scale`` squared times larger (the velocity factor also stands for the time correlation of
the path-rate error, which a white measurement cannot carry: the white-equivalent variance of a correlated
error, as the GNSS benchmark's bias state does for the position). Below the threshold the report is taken as it
is. The estimator reads only the report (``frame.gnss_R``), never the truth or the world's parameters.

:func:`calibrated_report` is the math; :func:`report_calibrated` gives a method's estimator the calibrated
frames (``coloc.methods.registry.build_method`` wraps every method that takes ``[gnss_model]``; the joint oracle,
told the world's error structure, is not wrapped).

Opt-in (default off); the realistic presets take it, with a threshold of 2 m and both factors 2, chosen with every
method on tuning seeds 101-110 together with ICP-DA-LC's reset to its own-sensor track: without that reset a
velocity factor lets a run of reflected fixes carry a platoon off, and ICP-DA-LC develops a tail of a few far-off
vehicles in the canyons (docs/validation/consistency.md, "Every method on ten tuning seeds").
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np


def calibrated_report(gnss_r: np.ndarray, above_m: float, position_scale: float,
                      velocity_scale: float) -> np.ndarray:
    """(N, 4, 4): the reports ``gnss_r`` with the position block times ``position_scale``^2 and the velocity
    block times ``velocity_scale``^2 (the cross blocks by their product) where the reported per-axis position
    std, sqrt(trace(R_pos) / 2), exceeds ``above_m``; the other rows as given. A congruence D R D with D =
    diag(s_p, s_p, s_v, s_v), so a positive definite report stays positive definite."""
    r = np.array(gnss_r, dtype=float, copy=True)
    if len(r) == 0:
        return r
    std = np.sqrt(0.5 * (r[:, 0, 0] + r[:, 1, 1]))
    rows = std > above_m
    if rows.any():
        d = np.array([position_scale, position_scale, velocity_scale, velocity_scale])
        r[rows] *= d[None, :, None] * d[None, None, :]
    return r


def gate_noise_scale(r_cal: np.ndarray, model) -> np.ndarray:
    """(N,) the factor that takes a calibrated report's position block back to the receiver's own: 1 /
    ``degraded_position_scale``^2 on the rows the calibration scaled, 1 elsewhere, where ``model.gate_on`` is
    "report" and the model calibrates the report; ones otherwise. The estimator sees only the calibrated report
    ``r_cal`` (N, 4, 4), so the rows are found from it: with a scale s >= 1 the calibration takes a reported
    per-axis std above ``degraded_above_m`` (a) to s times that, above s a, and leaves the others at or below
    a, so a calibrated std above s a marks a scaled row (none falls in (a, s a])."""
    r_cal = np.asarray(r_cal, dtype=float)
    g = np.ones(len(r_cal))
    if getattr(model, "gate_on", "calibrated") != "report" or not model.calibrates_report or len(r_cal) == 0:
        return g
    s = float(model.degraded_position_scale)
    std = np.sqrt(0.5 * (r_cal[:, 0, 0] + r_cal[:, 1, 1]))
    g[std > s * model.degraded_above_m] = 1.0 / (s * s)
    return g


class ReportCalibrated:
    """An estimator that is given frames whose ``gnss_R`` is :func:`calibrated_report` of the received one;
    everything else (its name, its statistics, its feature tracks) is the wrapped estimator's."""

    def __init__(self, inner, model):
        self.inner = inner
        self.model = model

    def _frame(self, frame):
        m = self.model
        return replace(frame, gnss_R=calibrated_report(frame.gnss_R, m.degraded_above_m, m.degraded_position_scale,
                                                       m.degraded_velocity_scale))

    def step(self, frame):
        return self.inner.step(self._frame(frame))

    def __getattr__(self, name):
        inner = self.__dict__.get("inner")
        if inner is None or name.startswith("__"):
            raise AttributeError(name)
        return getattr(inner, name)


class ReportCalibratedKnown(ReportCalibrated):
    """:class:`ReportCalibrated` for an estimator told the association (it has ``step_with_association``)."""

    def step_with_association(self, frame, v2f_feature):
        return self.inner.step_with_association(self._frame(frame), v2f_feature)


def report_calibrated(inner, model) -> ReportCalibrated:
    """``inner`` given the calibrated report, with the same steps as ``inner`` (``step_with_association`` only
    where it has one, so that callers that test for it still tell the two kinds apart)."""
    known = callable(getattr(inner, "step_with_association", None))
    return (ReportCalibratedKnown if known else ReportCalibrated)(inner, model)
