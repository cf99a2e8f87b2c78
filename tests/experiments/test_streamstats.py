"""Statistics from rows read twice in batches equal numpy's over the whole arrays, bit for bit."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from experiments.rowstream import _Codes, position_nees
from experiments.scoring import coverage_summary, method_summary, nees_summary
from experiments.streamstats import N_BINS, EstimateStats, PairwiseSum, Sample, bin_index


def _same(a: float, b: float) -> bool:
    return a == b or (np.isnan(a) and np.isnan(b))


def _sample(x: np.ndarray, batch: int, **kw) -> Sample:
    s = Sample(**kw)
    for i in range(0, x.size, batch):
        s.first(x[i:i + batch])
    for i in range(0, x.size, batch):
        s.second(x[i:i + batch])
    s.finish()
    return s


@pytest.mark.parametrize("n", [0, 1, 2, 7, 8, 9, 127, 128, 129, 136, 1000, 8193, 40001])
@pytest.mark.parametrize("batch", [1, 13, 1 << 18])
def test_sample_equals_numpy(n, batch):
    """RMSE (pairwise sum of the squares in numpy's tree), np.quantile and np.median: the same floats
    whatever the batch size; values over 12 decades, repeated values and zeros."""
    if n > 9000 and batch == 1:
        pytest.skip("one value per batch: slow, covered by the smaller sizes")
    rng = np.random.default_rng(n)
    x = rng.exponential(1.0, n) * rng.choice([1e-9, 1e-3, 1.0, 1e3], n)
    if n > 20:
        x[:5] = 0.0
        x[10:15] = x[9]
    s = _sample(x, batch, quantiles=(0.5, 0.95), median=True)
    assert _same(s.rmse(), float(np.sqrt(np.mean(x * x))) if n else np.nan)
    for q in (0.5, 0.95):
        assert _same(s.quantile(q), float(np.quantile(x, q)) if n else np.nan)
    assert _same(s.median(), float(np.median(x)) if n else np.nan)
    m = _sample(x, batch, squares=False)
    assert _same(m.mean(), float(x.mean()) if n else np.nan)


def test_nan_and_inf_as_numpy():
    x = np.array([1.0, 2.0, np.nan, 3.0] * 50)
    s = _sample(x, 7, quantiles=(0.95,))
    assert np.isnan(s.rmse()) and np.isnan(s.quantile(0.95))
    y = np.append(np.arange(300.0), [np.inf, 2.0 ** 40, 1e-12])
    s = _sample(y, 11, quantiles=(0.5, 0.95, 1.0))
    for q in (0.5, 0.95, 1.0):
        assert _same(s.quantile(q), float(np.quantile(y, q)))
    assert s.rmse() == np.inf


def test_bins_are_monotonic_and_kept_values_few():
    """The histogram bin of a value grows with it; the second pass keeps the values of a few bins only."""
    x = np.sort(np.random.default_rng(2).exponential(1.0, 100_000))
    b = bin_index(x)
    assert np.all(np.diff(b) >= 0) and b.min() >= 0 and b.max() < N_BINS
    assert bin_index(np.array([0.0, -0.0, -1.0]))[0] == 0 == bin_index(np.array([-1.0]))[0]
    s = Sample(quantiles=(0.5, 0.95))
    s.first(x)
    s.second(x)
    kept = sum(a.size for v in s._kept.values() for a in v)
    assert 0 < kept < 0.02 * x.size


def test_pairwise_sum_refuses_other_counts():
    p = PairwiseSum(10)
    p.add(np.ones(4))
    with pytest.raises(ValueError):
        _ = p.value
    with pytest.raises(ValueError):
        p.add(np.ones(7))


def _estimates(n: int, infra: bool) -> pd.DataFrame:
    rng = np.random.default_rng(11)
    ex, ey = rng.normal(size=n) * 2, rng.normal(size=n)
    d = pd.DataFrame({
        "method": np.repeat(["gnss", "icp_da_lc"], [n // 2, n - n // 2]), "t": np.tile(np.arange(n // 2 + 1), 2)[:n] * 0.75,
        "err_pos": np.hypot(ex, ey), "err_vel": rng.random(n), "err_along": ex, "err_cross": ey,
        "zone": rng.choice(["urban", "open", "canyon"], n), "area": rng.choice(["3", "1", "2"], n),
        "px": ex + 1.0, "py": ey, "px_true": np.ones(n), "py_true": np.zeros(n),
        "var_px": rng.uniform(0.5, 4.0, n), "var_py": rng.uniform(0.5, 4.0, n), "cov_pxy": rng.uniform(-0.2, 0.2, n)})
    d.loc[rng.random(n) < 0.01, "var_px"] = 0.0  # singular covariances: no NEES
    d.loc[rng.random(n) < 0.001, "cov_pxy"] = np.nan
    if infra:
        d["covered"] = rng.random(n) < 0.4
        d["rsu"] = np.where(d["covered"], rng.choice(["rsu_b", "rsu_a"], n), "")
    return d


@pytest.mark.parametrize("infra", [False, True])
@pytest.mark.parametrize("batch", [97, 1 << 18])
def test_estimate_stats_equal_the_whole_table_summary(tmp_path, infra, batch):
    """The summary blocks from a Parquet file read in batches (as experiments.rowstream reads its spill
    files) equal method_summary / nees_summary / coverage_summary of the whole table, bit for bit."""
    d = _estimates(20011, infra)
    path = tmp_path / "estimates.parquet"
    pq.write_table(pa.Table.from_pandas(d, preserve_index=False), path, row_group_size=4096)
    t0 = 30.0
    for method in ("gnss", "icp_da_lc"):
        codes = {k: _Codes() for k in ("zone", "area", "rsu")}
        stats = EstimateStats(infra)
        for second in (False, True):
            for b in pq.ParquetFile(path).iter_batches(batch_size=batch):
                df = b.to_pandas()
                df = df[(df["method"] == method) & (df["t"] >= t0)]
                cols = {c: df[c].to_numpy() for c in ("err_pos", "err_vel", "err_along", "err_cross")}
                cols["nees"] = position_nees(*(df[c].to_numpy() for c in ("err_along", "err_cross", "var_px",
                                                                           "var_py", "cov_pxy")))
                for k in ("zone", "area") + (("rsu",) if infra else ()):
                    cols[k] = codes[k].encode(df[k].to_numpy())
                if infra:
                    cols["covered"] = df["covered"].to_numpy()
                stats.feed(cols, second)
        block, cov, steps = stats.blocks(codes["zone"].names, codes["area"].names, codes["rsu"].names)

        whole = d[(d["method"] == method) & (d["t"] >= t0)].reset_index(drop=True)
        whole["zone"] = whole["zone"].astype("category")
        whole["area"] = whole["area"].astype("category")
        want = method_summary(whole)
        nees = position_nees(*(whole[c].to_numpy() for c in ("err_along", "err_cross", "var_px", "var_py",
                                                             "cov_pxy")))
        want["nees_pos"] = nees_summary(nees, whole["zone"])
        assert block == want
        assert list(block["by_zone"]) == ["canyon", "open", "urban"] and list(block["by_area"]) == ["1", "2", "3"]
        assert 0 < block["nees_pos"]["n"] < block["n"]
        if infra:
            whole["rsu"] = whole["rsu"].astype("category")
            want_cov = coverage_summary(whole, [method])
            assert cov == want_cov["methods"][method]
            assert steps == want_cov["rsu_vehicle_steps"]
        else:
            assert cov is None and steps is None
