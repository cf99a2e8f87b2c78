"""``[gnss_model] degraded_*`` (coloc.methods.report_calibration): the calibrated report's algebra, and a method
given it through the registry equal to the same estimator given calibrated frames; off by default."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from coloc.core.models import MotionParams
from coloc.inference.params import IcpParams
from coloc.methods.gnss_bias import GnssModelParams
from coloc.methods.icp_da_lc import LcParams
from coloc.methods.icp_da_pf import PfParams
from coloc.methods.registry import GNSS, ICP_KNOWN_DA, MethodParams, build_method
from coloc.methods.report_calibration import ReportCalibrated, calibrated_report, gate_noise_scale
from tests.coloc.test_gnss_bias import scripted_run

CAL = GnssModelParams(bias_model="two_state", common_sigma_m=1.0, degraded_above_m=2.0,
                      degraded_position_scale=2.0, degraded_velocity_scale=3.0)


def _spd(rng, n, pos_std):
    a = rng.normal(size=(n, 4, 4)) * 0.3
    r = np.einsum("nij,nkj->nik", a, a) + 0.01 * np.eye(4)
    r[:, :2, :2] += (pos_std ** 2)[:, None, None] * np.eye(2)
    return r


def test_rows_above_the_threshold_are_scaled_by_the_congruence_the_others_kept():
    rng = np.random.default_rng(3)
    pos_std = rng.uniform(0.5, 6.0, 200)
    r = _spd(rng, 200, pos_std)
    r0 = r.copy()
    out = calibrated_report(r, 2.0, 2.0, 3.0)
    np.testing.assert_array_equal(r, r0)  # the frame's report is not changed in place
    std = np.sqrt(0.5 * (r[:, 0, 0] + r[:, 1, 1]))
    above = std > 2.0
    assert 20 < above.sum() < 180
    d = np.diag([2.0, 2.0, 3.0, 3.0])
    np.testing.assert_array_equal(out[~above], r[~above])
    np.testing.assert_allclose(out[above], d @ r[above] @ d, rtol=1e-14, atol=0)
    assert np.all(np.linalg.eigvalsh(out) > 0)
    assert calibrated_report(np.zeros((0, 4, 4)), 2.0, 2.0, 3.0).shape == (0, 4, 4)


def _params(model):
    motion = MotionParams(sigma_along=0.3, sigma_cross=0.1)
    return MethodParams(motion=motion, icp=IcpParams(motion=motion), lc=LcParams(), pf=PfParams(), gnss_model=model)


def test_off_by_default_and_on_only_with_a_threshold_and_a_factor():
    assert not GnssModelParams().calibrates_report
    assert not replace(CAL, degraded_above_m=0.0).calibrates_report
    assert not replace(CAL, degraded_position_scale=1.0, degraded_velocity_scale=1.0).calibrates_report
    assert not isinstance(build_method(GNSS.name, _params(replace(CAL, degraded_above_m=0.0))), ReportCalibrated)
    wrapped = build_method(GNSS.name, _params(CAL))
    assert isinstance(wrapped, ReportCalibrated) and not hasattr(wrapped, "step_with_association")
    known = build_method(ICP_KNOWN_DA.name, _params(CAL))
    assert isinstance(known, ReportCalibrated) and callable(known.step_with_association)


def test_the_wrapped_method_equals_its_estimator_on_calibrated_frames():
    frames = scripted_run(7, 120, CAL)
    wrapped = build_method(GNSS.name, _params(CAL))
    plain = build_method(GNSS.name, _params(replace(CAL, degraded_above_m=0.0)))
    assert wrapped.name == plain.name == GNSS.name
    n_scaled = 0
    for f in frames:
        cal = calibrated_report(f.gnss_R, 2.0, 2.0, 3.0)
        n_scaled += int((cal != f.gnss_R).any(axis=(1, 2)).sum())
        a = wrapped.step(f)
        b = plain.step(replace(f, gnss_R=cal))
        assert a.mean.tobytes() == b.mean.tobytes() and a.cov.tobytes() == b.cov.tobytes()
    assert n_scaled > 0  # the scripted reports cross the threshold


@pytest.mark.parametrize("bad", [-1.0, float("nan")])
def test_bad_values_are_refused(bad):
    with pytest.raises(ValueError):
        replace(CAL, degraded_above_m=bad)
    with pytest.raises(ValueError):
        replace(CAL, degraded_velocity_scale=bad)


def test_the_gate_finds_the_calibrated_rows_and_takes_them_back():
    """gate_noise_scale on a calibrated report: 1 / s^2 exactly on the rows the calibration scaled, 1 elsewhere;
    so S - (1 - g) R_n is the innovation covariance with the receiver's own report on every row."""
    rng = np.random.default_rng(8)
    raw = _spd(rng, 400, rng.uniform(0.3, 6.0, 400))
    model = replace(CAL, gate_on="report")
    cal = calibrated_report(raw, model.degraded_above_m, model.degraded_position_scale, model.degraded_velocity_scale)
    scaled = np.sqrt(0.5 * (raw[:, 0, 0] + raw[:, 1, 1])) > model.degraded_above_m
    assert 50 < scaled.sum() < 350
    g = gate_noise_scale(cal, model)
    np.testing.assert_array_equal(g, np.where(scaled, 0.25, 1.0))
    np.testing.assert_allclose(g[:, None, None] * cal[:, :2, :2], raw[:, :2, :2], rtol=1e-14)
    assert (gate_noise_scale(cal, CAL) == 1.0).all()  # gate_on = "calibrated": the report the update takes
    assert (gate_noise_scale(cal, replace(model, degraded_above_m=0.0)) == 1.0).all()  # no calibration


def test_the_gate_on_the_report_excludes_more_of_the_scaled_rows_only():
    """The own-sensor track with gate_on = "report": the same exclusions on the rows the calibration left, more
    on the scaled ones (the receiver's own claim is tighter), and the update of an accepted fix unchanged."""
    from coloc.methods.gnss_bias2 import H8, two_state_predict_update

    rng = np.random.default_rng(9)
    n = 600
    raw = _spd(rng, n, rng.uniform(0.5, 5.0, n))
    cal = calibrated_report(raw, CAL.degraded_above_m, CAL.degraded_position_scale, CAL.degraded_velocity_scale)
    mean = rng.normal(scale=10.0, size=(n, 8))
    a = rng.normal(size=(n, 8, 8)) * 0.4
    cov = np.einsum("nij,nkj->nik", a, a) + 0.2 * np.eye(8)
    z = mean @ H8.T + rng.normal(scale=1.0, size=(n, 4)) * np.sqrt(np.diagonal(cal, axis1=1, axis2=2)) * 1.6
    args = (np.zeros((n, 2)), z, cal, np.ones(n, bool), 0.1, MotionParams())
    m0, p0, ex0 = two_state_predict_update(mean, cov, *args, CAL, np.zeros(n, np.int64))
    m1, p1, ex1 = two_state_predict_update(mean, cov, *args, replace(CAL, gate_on="report"), np.zeros(n, np.int64))
    scaled = np.sqrt(0.5 * (raw[:, 0, 0] + raw[:, 1, 1])) > CAL.degraded_above_m
    np.testing.assert_array_equal(ex1[~scaled], ex0[~scaled])
    assert (ex1 >= ex0).all() and (ex1 & ~ex0 & scaled).sum() > 5
    same = ex1 == ex0
    np.testing.assert_array_equal(m1[same], m0[same])
    np.testing.assert_array_equal(p1[same], p0[same])
