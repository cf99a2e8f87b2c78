"""Time bins of the report: a partial last bin (an hour sampled up to t = 3600 s) is not an interval."""
from __future__ import annotations

import numpy as np
import pandas as pd

from experiments.report.figures import _binned_rmse


def _frame(t_end: float, dt: float = 0.75) -> pd.DataFrame:
    t = np.arange(0.0, t_end + dt / 2, dt)
    return pd.DataFrame({"method": "gnss", "t": t, "err_pos": np.ones_like(t)})


def test_an_hour_up_to_3600_has_twelve_five_minute_bins():
    r = _binned_rmse(_frame(3600.0), ["err_pos"], 300.0)
    mids = r.loc["gnss"].index.to_numpy()
    assert len(mids) == 12
    assert mids[-1] == 3450.0  # [3300, 3600): the t = 3600 s sample alone makes no 13th bin


def test_an_hour_sampled_before_3600_keeps_its_last_full_bin():
    t = np.arange(0.0, 3600.0, 0.75)  # last sample 3599.25 s
    df = pd.DataFrame({"method": "gnss", "t": t, "err_pos": np.ones_like(t)})
    assert len(_binned_rmse(df, ["err_pos"], 300.0).loc["gnss"]) == 12


def test_a_run_shorter_than_one_bin_keeps_its_bin():
    assert len(_binned_rmse(_frame(100.0), ["err_pos"], 300.0).loc["gnss"]) == 1


def test_traffic_intervals_of_an_hour_are_twelve_full_ones():
    from couplers.traffic.sumo import TrafficStats

    for t0 in (0.0, 0.75):  # with or without a sample at the begin itself
        st = TrafficStats(step_length=0.75, origin=0.0)
        for t in np.arange(t0, 3600.0 + 0.1, 0.75):
            st.add(float(t), 10, 1, 0, 1.0, 0)
        st.flush()
        starts = [r["interval_start_s"] for r in st.rows]
        assert starts == [300.0 * k for k in range(12)]
        assert all(r["interval_end_s"] - r["interval_start_s"] <= 300.0 + 0.75 for r in st.rows)
