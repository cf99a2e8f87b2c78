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
from coloc.methods.report_calibration import ReportCalibrated, calibrated_report
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
