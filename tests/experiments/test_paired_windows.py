"""tools/paired_windows.py: window MSE per run and the paired difference over seeds, in closed form."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scriptload import load_script

pw = load_script("tools/paired_windows.py")


def _sweep(folder: Path, seeds, err_a, err_b):
    """A sweep folder with one grid column, methods a / b, errors constant per run (err_x[seed])."""
    rows = []
    for df in (0.5, 3.0):
        for s in seeds:
            run_id = f"df={df},seed={s}"
            t = np.arange(0.0, 31.0)
            est = pd.concat([pd.DataFrame({"method": m, "t": t, "err_pos": np.where(t < 20, e[s], 2 * e[s]) + df})
                             for m, e in (("a", err_a), ("b", err_b))])
            (folder / "runs" / run_id).mkdir(parents=True)
            est.to_parquet(folder / "runs" / run_id / "estimates.parquet")
            rows += [{"run_id": run_id, "seed": s, "df": df, "method": m, "rmse_pos_m": 0.0, "n": 31,
                      "covered_rmse_pos_m": 0.0} for m in "ab"]  # columns after "method" are not swept
    pd.DataFrame(rows).to_parquet(folder / "sweep.parquet")


def test_paired_difference_in_closed_form(tmp_path):
    err_a, err_b = {1: 1.0, 2: 2.0, 3: 4.0}, {1: 2.0, 2: 2.0, 3: 2.0}
    _sweep(tmp_path / "s1", [1, 2], err_a, err_b)
    _sweep(tmp_path / "s2", [3], err_a, err_b)
    mse = pw.window_mse([tmp_path / "s1", tmp_path / "s2"], pw.parse_windows("0:19,20:30"))
    table = pw.paired(mse, "a", "b").set_index(["df", "window"])
    for df in (0.5, 3.0):
        for w, k in ((0, 1.0), (1, 2.0)):
            a = np.array([(k * err_a[s] + df) ** 2 for s in (1, 2, 3)])
            b = np.array([(k * err_b[s] + df) ** 2 for s in (1, 2, 3)])
            row = table.loc[(df, w)]
            assert row.seeds == 3 and row.a_lower_on == 1
            assert row.rmse_a == pytest.approx(np.sqrt(a.mean()), rel=1e-12)
            assert row.rmse_b == pytest.approx(np.sqrt(b.mean()), rel=1e-12)
            assert row.dmse_mean == pytest.approx((a - b).mean(), rel=1e-12)
            assert row.dmse_se == pytest.approx((a - b).std(ddof=1) / np.sqrt(3), rel=1e-12)


def test_a_run_in_two_folders_is_refused(tmp_path, capsys):
    _sweep(tmp_path / "s1", [1], {1: 1.0}, {1: 1.0})
    assert pw.main([str(tmp_path / "s1"), str(tmp_path / "s1"), "--a", "a", "--b", "b"]) == 2
    assert "also in an earlier folder" in capsys.readouterr().err
