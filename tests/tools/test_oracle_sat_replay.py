"""tools/oracle_sat_replay.py: the late start's first frame (every vehicle entering from its fix, as
``[scenario] start = "gnss_fix"``) and the per-seed table's format."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "coloc"))

from coloc.methods.joint_oracle import JointOracle  # noqa: E402
from test_joint_oracle import PARAMS  # noqa: E402
from test_joint_oracle_satellites import WORLD, _scene  # noqa: E402
from tools.oracle_sat_replay import late_start_frame, seed_table  # noqa: E402


def test_late_start_frame_enters_every_vehicle_from_its_fix():
    fr = _scene(np.random.default_rng(3), n=3, steps=3)[2]
    before = (fr.entered.copy(), fr.prior_z.copy())
    late = late_start_frame(fr)
    assert late.entered.all() and late.prior_has_fix.all()
    np.testing.assert_array_equal(late.prior_z, fr.gnss_z)
    np.testing.assert_array_equal(late.prior_R, fr.gnss_R)
    assert not before[0].any() and np.isnan(before[1]).all()  # the recorded frame is left as it was
    np.testing.assert_array_equal(fr.entered, before[0])
    # the oracle started on it: every vehicle's position prior is its fix, not the fix counted twice
    est = JointOracle(params=PARAMS, world=WORLD)
    e = est.step_with_association(late, np.empty(0, np.int64))
    assert np.isfinite(e.mean).all()
    twice = JointOracle(params=PARAMS, world=WORLD)
    from dataclasses import replace

    e2 = twice.step_with_association(replace(late, prior_has_fix=np.zeros(3, bool)), np.empty(0, np.int64))
    assert (np.linalg.eigvalsh(e.cov[:, :2, :2] - e2.cov[:, :2, :2]) > 0).any()


def test_seed_table_format():
    res = {"table": {"gnss/A": dict(n=4, rmse=1.0, p95=2.0, nees=1.5, median_nees=1.0, inside=0.9),
                     "joint_oracle/all": dict(n=8, rmse=0.5, p95=1.0, nees=2.0, median_nees=1.4, inside=0.95)}}
    t = seed_table(res)
    assert t["gnss"]["A"] == dict(rmse=1.0, p95=2.0, nees_mean=1.5, inside=0.9, n=4)
    assert t["joint_oracle"]["all"]["nees_mean"] == 2.0
