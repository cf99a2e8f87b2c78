"""The reports read a run's Parquet files batch by batch: the same figures' data as reading them whole."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from experiments.report import load
from experiments.report.figures import _binned_rmse
from experiments.rowstream import position_nees


def _estimates(rng: np.random.Generator, n: int) -> pd.DataFrame:
    t = (np.arange(n) // 4) * 0.75
    px, py = rng.normal(size=n) * 5, rng.normal(size=n) * 5
    ex, ey = rng.normal(size=n), rng.normal(size=n)
    var_px, var_py = rng.uniform(0.5, 2.0, n), rng.uniform(0.5, 2.0, n)
    cov = rng.uniform(-0.3, 0.3, n)
    err = np.hypot(ex, ey)
    err[rng.random(n) < 0.01] = np.nan
    return pd.DataFrame({
        "method": rng.choice(["gnss", "icp_da_lc", "icp_known_da"], n), "t": t, "err_pos": err,
        "err_vel": rng.random(n), "err_along": ex, "err_cross": ey, "zone": rng.choice(["A", "B", "C"], n),
        "area": rng.choice(["1", "2"], n), "px": px + ex, "py": py + ey, "px_true": px, "py_true": py,
        "var_px": var_px, "var_py": var_py, "cov_pxy": cov})


@pytest.mark.parametrize("batch_rows", [7, 100, 1 << 18])
def test_estimates_read_in_batches_equal_the_whole_read(tmp_path, monkeypatch, batch_rows):
    monkeypatch.setattr(load, "BATCH_ROWS", batch_rows)
    d = _estimates(np.random.default_rng(3), 2003)
    path = tmp_path / "estimates.parquet"
    pq.write_table(pa.Table.from_pandas(d, preserve_index=False), path, row_group_size=500)
    got = load._read_estimates(path, load._EST_COLS, nees=True)
    want = load._read_parquet(path, load._EST_COLS)
    pd.testing.assert_frame_equal(got.drop(columns="nees"), want)
    np.testing.assert_array_equal(got["nees"].to_numpy(), position_nees(
        (d.px - d.px_true).to_numpy(), (d.py - d.py_true).to_numpy(), d.var_px.to_numpy(), d.var_py.to_numpy(),
        d.cov_pxy.to_numpy()))
    assert list(got.columns) == [*load._EST_COLS, "nees"]
    without = load._read_estimates(path, ["method", "t", "err_pos"], nees=False)
    assert list(without.columns) == ["method", "t", "err_pos"]


@pytest.mark.parametrize("batch_rows", [5, 64, 1 << 18])
def test_feature_step_sums_give_the_row_level_binned_rmse(tmp_path, monkeypatch, batch_rows):
    monkeypatch.setattr(load, "BATCH_ROWS", batch_rows)
    rng = np.random.default_rng(7)
    n = 3001
    feats = pd.DataFrame({"method": rng.choice(["icp_known_da", "icp_da_lc"], n),
                          "t": np.sort(rng.integers(0, 400, n)) * 0.75, "track": rng.integers(0, 50, n),
                          "feature": rng.integers(0, 50, n), "err_pos": rng.exponential(1.0, n)})
    feats.loc[rng.random(n) < 0.02, "err_pos"] = np.nan
    path = tmp_path / "features.parquet"
    pq.write_table(pa.Table.from_pandas(feats, preserve_index=False), path, row_group_size=700)
    steps = load._read_feature_steps(path)
    assert len(steps) <= feats.groupby(["method", "t"]).ngroups
    assert int(steps["n"].sum()) == int(np.isfinite(feats.err_pos).sum())
    rows = load._read_parquet(path, ["method", "t", "err_pos"])
    for width in (30.0, 60.0, 300.0):
        a = _binned_rmse(steps, ["err_pos"], width)
        b = _binned_rmse(rows, ["err_pos"], width)
        assert list(a.index) == list(b.index)
        np.testing.assert_allclose(a["err_pos"].to_numpy(), b["err_pos"].to_numpy(), rtol=1e-12)


def test_absent_files_read_as_none(tmp_path):
    assert load._read_estimates(tmp_path / "estimates.parquet", load._EST_COLS, nees=True) is None
    assert load._read_feature_steps(tmp_path / "features.parquet") is None
