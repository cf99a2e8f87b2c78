"""The run report's digest of estimates.parquet (per-step sums, error histograms) against the row-level
computations it replaces: equal sums, CDF points within their stated bound, the same at any batch size."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from experiments.report import load
from experiments.report.digest import CDF_BITS, ErrorHistogram, digest_estimates
from experiments.report.figures import _binned_rmse, _binned_rmse_steps, _quantile_curves
from experiments.report.styles import _CDF_GRID
from experiments.rowstream import position_nees
from experiments.scoring import CHI2_2_95

from tests.experiments.test_report_load import _estimates

#: A CDF point lies in the bin of the exact quantile: at most 2^-CDF_BITS of it away (bins of
#: 2^-CDF_BITS of their lower edge), plus the rounding of the interpolation.
BOUND = 2.0 ** -CDF_BITS


def _write(tmp_path, n: int = 2001) -> tuple[pd.DataFrame, object]:
    d = _estimates(np.random.default_rng(3), n)
    d["err_pos"] = d["err_pos"] * np.random.default_rng(4).choice([0.01, 1.0, 30.0], n)
    path = tmp_path / "estimates.parquet"
    pq.write_table(pa.Table.from_pandas(d, preserve_index=False), path, row_group_size=900)
    return d, path


@pytest.mark.parametrize("batch_rows", [97, 1 << 18])
def test_digest_equals_the_row_level_statistics(tmp_path, monkeypatch, batch_rows):
    monkeypatch.setattr(load, "BATCH_ROWS", batch_rows)
    d, path = _write(tmp_path)
    t0 = 150.0
    dig = digest_estimates(path, t0)
    assert sorted(dig.methods) == sorted(d["method"].unique()) and dig.t_min == d["t"].min()
    assert dig.labels == {"zone": ["A", "B", "C"], "area": ["1", "2"]}

    # RMSE over time: the per-step sums give the row-level binned RMSE (to rounding of the sums' order)
    rows = d.assign(method=d["method"].astype("category"))
    want = _binned_rmse(rows, ["err_pos", "err_vel"], 60.0)
    got = _binned_rmse_steps(dig.steps, {"err_pos": "pos", "err_vel": "vel"}, 60.0)
    pd.testing.assert_frame_equal(got.sort_index(), want.sort_index(), check_exact=False, rtol=1e-12,
                                  check_index_type=False, check_categorical=False)
    area = rows[rows["area"] == "2"]
    want = _binned_rmse(area, ["err_along", "err_cross"], 60.0)
    sub = dig.area_steps[dig.area_steps["area"] == "2"]
    got = _binned_rmse_steps(sub, {"err_along": "along", "err_cross": "cross"}, 60.0)
    pd.testing.assert_frame_equal(got.sort_index(), want.sort_index(), check_exact=False, rtol=1e-12,
                                  check_index_type=False, check_categorical=False)

    # NEES: the sums of the finite values, how many inside the 95 % ellipse
    nees = position_nees((d.px - d.px_true).to_numpy(), (d.py - d.py_true).to_numpy(), d.var_px.to_numpy(),
                         d.var_py.to_numpy(), d.cov_pxy.to_numpy())
    ok = np.isfinite(nees)
    assert dig.steps["n_nees"].sum() == ok.sum()
    assert dig.steps["inside"].sum() == np.count_nonzero(nees[ok] <= CHI2_2_95)
    assert dig.steps["nees"].sum() == pytest.approx(nees[ok].sum(), rel=1e-12)

    # CDF curves: every point in the bin of the exact quantile of the scored finite errors
    scored = d[d["t"] >= t0]
    for group in ("zone", "area"):
        exact = _quantile_curves(scored.assign(method=scored["method"].astype("category"),
                                               **{group: scored[group].astype("category")}), group)
        hists = dig.cdf[group]
        assert set(hists) == set(exact)
        for key, q in exact.items():
            got = hists[key].quantiles(_CDF_GRID)
            assert np.all(np.abs(got - q) <= BOUND * q + 1e-12), key
            assert got[0] == q[0] and got[-1] == q[-1]  # the smallest and largest error, exactly
            assert hists[key].n == np.isfinite(scored[(scored[group] == key[0]) & (scored["method"] == key[1])]
                                              ["err_pos"]).sum()


def test_digest_does_not_depend_on_the_batch_size(tmp_path, monkeypatch):
    _d, path = _write(tmp_path)
    out = []
    for rows in (61, 1000, 1 << 18):
        monkeypatch.setattr(load, "BATCH_ROWS", rows)
        dig = digest_estimates(path, None)
        steps = dig.steps.sort_values(["method", "t"]).reset_index(drop=True)
        out.append((steps, {g: {k: (h.counts.copy(), h.lo, h.hi) for k, h in c.items()} for g, c in dig.cdf.items()}))
    for steps, cdf in out[1:]:
        pd.testing.assert_frame_equal(steps, out[0][0], check_exact=False, rtol=1e-12)
        for g in cdf:
            for k, (counts, lo, hi) in cdf[g].items():
                ref = out[0][1][g][k]
                assert np.array_equal(counts, ref[0]) and (lo, hi) == ref[1:]


def test_histogram_quantiles_within_the_bound():
    """Values over six decades, ties and a lone outlier: every CDF point within 2^-10 of the exact one."""
    rng = np.random.default_rng(9)
    x = np.concatenate([rng.lognormal(0.0, 2.0, 50_000), np.full(500, 1.25), [1e5]])
    h = ErrorHistogram()
    for part in np.array_split(rng.permutation(x), 17):
        h.add(part)
    q = np.quantile(x, _CDF_GRID)
    got = h.quantiles(_CDF_GRID)
    assert np.all(np.abs(got - q) <= BOUND * q)
    assert got[-1] == 1e5 and got[0] == x.min()
