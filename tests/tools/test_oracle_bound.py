"""tools/oracle_bound.py: the oracle's rows joined to a run's truth and zones, RMSE and bound per zone."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
from oracle_bound import bound_rows, main  # noqa: E402


def _pair(tmp_path, rng):
    t = np.repeat(600.0 + 0.75 * np.arange(200), 5)
    veh = np.tile([f"v{i}" for i in range(5)], 200)
    zone = np.where(np.tile(np.arange(5), 200) < 2, "A", "C")
    var = np.where(zone == "A", 1.0, 4.0)
    err = rng.standard_normal((t.size, 2)) * np.sqrt(var)[:, None]
    truth = rng.uniform(0, 500, (t.size, 2))
    oracle = pd.DataFrame({"method": "joint_oracle_fix", "t": t + 1e-9, "vehicle": veh, "x": truth[:, 0] + err[:, 0],
                           "y": truth[:, 1] + err[:, 1], "cov_xx": var, "cov_xy": 0.0, "cov_yy": var})
    rows = []
    for method in ("gnss", "icp_da_lc"):  # the zones and truth come from the gnss rows only
        rows.append(pd.DataFrame({"method": method, "t": t, "vehicle": veh, "px_true": truth[:, 0],
                                  "py_true": truth[:, 1], "zone": zone if method == "gnss" else "B"}))
    run = pd.concat(rows, ignore_index=True)
    return oracle, run, err, zone, var


def test_bound_and_rmse_per_zone(tmp_path):
    oracle, run, err, zone, var = _pair(tmp_path, np.random.default_rng(2))
    got = {r["zone"]: r for r in bound_rows(oracle, run)}
    assert set(got) == {"all", "A", "C"} and got["all"]["n"] == len(oracle)
    for z in ("A", "C"):
        sel = zone == z
        assert got[z]["rmse"] == pytest.approx(np.sqrt((err[sel] ** 2).sum(axis=1).mean()))
        assert got[z]["bound"] == pytest.approx(np.sqrt(2 * var[sel].mean()))
    assert got["all"]["bound"] == pytest.approx(np.sqrt(2 * var.mean()))


def test_cli_prints_the_tables(tmp_path, capsys):
    oracle, run, *_ = _pair(tmp_path, np.random.default_rng(3))
    oracle.to_parquet(tmp_path / "o.parquet")
    (tmp_path / "run").mkdir()
    run.to_parquet(tmp_path / "run" / "estimates.parquet")
    assert main([f"{tmp_path / 'o.parquet'}:{tmp_path / 'run'}"]) == 0
    out = capsys.readouterr().out
    assert "| o.parquet | A |" in out and "bound over the seeds" in out
