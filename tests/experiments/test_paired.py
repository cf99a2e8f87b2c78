"""Paired differences with the paired t interval, against scipy."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from experiments.sweep.paired import paired_ci, paired_table


def test_paired_ci_equals_scipy_ttest_rel_interval():
    rng = np.random.default_rng(7)
    a = rng.normal(3.0, 1.0, 5)
    b = a + rng.normal(0.8, 0.3, 5)
    mean, lo, hi, n = paired_ci(a, b)
    ci = stats.ttest_rel(a, b).confidence_interval(0.95)
    assert n == 5
    assert mean == pytest.approx(float(np.mean(a - b)), rel=1e-12)
    assert (lo, hi) == (pytest.approx(ci.low, rel=1e-10), pytest.approx(ci.high, rel=1e-10))
    lo90, hi90 = paired_ci(a, b, 0.9)[1:3]
    assert lo < lo90 < hi90 < hi


def test_paired_ci_on_known_data():
    # d = 1, 2, 3: mean 2, sd 1, t_{2, 0.975} = 4.302652729...: half width 4.3027 / sqrt(3) = 2.4841
    mean, lo, hi, n = paired_ci([2.0, 4.0, 6.0], [1.0, 2.0, 3.0])
    assert (mean, n) == (2.0, 3)
    assert hi - mean == pytest.approx(4.302652729911275 / math.sqrt(3), rel=1e-9)
    assert mean - lo == pytest.approx(hi - mean)


def test_paired_ci_drops_unpaired_and_needs_two_seeds():
    mean, lo, hi, n = paired_ci([1.0, np.nan, 3.0], [0.5, 1.0, 2.0])
    assert n == 2 and mean == pytest.approx(0.75)
    mean, lo, hi, n = paired_ci([1.0], [0.5])
    assert n == 1 and mean == 0.5 and math.isnan(lo) and math.isnan(hi)


def test_paired_table_per_setting_and_zone():
    rows = []
    for zone in ("A", "B"):
        for seed in (1, 2, 3, 4):
            for method, v in (("gnss", 8.0 + seed), ("icp_known_da", 1.0 + 0.1 * seed), ("icp_da_lc", 3.0 + 0.5 * seed)):
                rows.append({"zone": zone, "seed": seed, "method": method, "rmse_pos_m": v + (zone == "B")})
    t = paired_table(pd.DataFrame(rows), ["zone"])
    assert len(t) == 4 and set(t["seeds"]) == {4}
    lg = t[(t.zone == "A") & (t.b == "gnss")].iloc[0]
    ref = stats.ttest_rel([3.5, 4.0, 4.5, 5.0], [9.0, 10.0, 11.0, 12.0]).confidence_interval()
    assert lg["mean"] == pytest.approx(-6.25)
    assert (lg.ci_lo, lg.ci_hi) == (pytest.approx(ref.low), pytest.approx(ref.high))
