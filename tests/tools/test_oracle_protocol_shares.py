"""tools/oracle_protocol_shares.py: every method scored on the oracle's samples, the share of its gain and the
bootstrap interval over seeds."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
from oracle_protocol_shares import CHI2_2_95, main, seed_scores, share_interval, share_of_gain  # noqa: E402

SIGMA = {"gnss": 2.0, "icp_known_da": 1.5, "icp_da_lc": 1.6}


def _seed(rng, oracle_sigma=1.0):
    t = np.repeat(0.75 * np.arange(1, 401), 6)
    veh = np.tile([f"v{i}" for i in range(6)], 400)
    zone = np.where(np.tile(np.arange(6), 400) < 3, "A", "C")
    truth = rng.uniform(0, 500, (t.size, 2))
    rows = []
    for m, s in SIGMA.items():
        e = rng.standard_normal((t.size, 2)) * s
        rows.append(pd.DataFrame({"method": m, "t": t, "vehicle": veh, "px": truth[:, 0] + e[:, 0],
                                  "py": truth[:, 1] + e[:, 1], "px_true": truth[:, 0], "py_true": truth[:, 1],
                                  "zone": zone, "var_px": s * s, "cov_pxy": 0.0, "var_py": s * s}))
    run = pd.concat(rows, ignore_index=True)
    late = t > 150  # the oracle scores part of the run's samples only
    e = rng.standard_normal((late.sum(), 2)) * oracle_sigma
    oracle = pd.DataFrame({"method": "joint_oracle_fix", "t": t[late] + 1e-9, "vehicle": veh[late],
                           "x": truth[late, 0] + e[:, 0], "y": truth[late, 1] + e[:, 1],
                           "cov_xx": oracle_sigma ** 2, "cov_xy": 0.0, "cov_yy": oracle_sigma ** 2})
    return oracle, run, late


def test_every_method_on_the_oracles_samples():
    oracle, run, late = _seed(np.random.default_rng(4))
    got = seed_scores(oracle, run, tuple(SIGMA))
    n = int(late.sum())
    for m in (*SIGMA, "joint_oracle_fix"):
        assert got[m]["all"]["n"] == n and got[m]["A"]["n"] + got[m]["C"]["n"] == n
    sel = run[run["method"] == "icp_da_lc"]["t"].to_numpy() > 150
    sub = run[run["method"] == "icp_da_lc"][sel]
    err2 = (sub["px"] - sub["px_true"]) ** 2 + (sub["py"] - sub["py_true"]) ** 2
    assert got["icp_da_lc"]["all"]["rmse"] == pytest.approx(np.sqrt(err2.mean()))
    assert got["icp_da_lc"]["all"]["p95"] == pytest.approx(np.percentile(np.sqrt(err2), 95))
    assert got["icp_da_lc"]["all"]["nees_mean"] == pytest.approx(err2.mean() / 1.6 ** 2)
    assert got["icp_da_lc"]["all"]["inside"] == pytest.approx((err2 / 1.6 ** 2 <= CHI2_2_95).mean())


def test_a_missing_run_row_is_an_error():
    oracle, run, _ = _seed(np.random.default_rng(5))
    run = run.drop(run[(run["method"] == "icp_da_lc")].index[-1])
    with pytest.raises(ValueError, match="icp_da_lc"):
        seed_scores(oracle, run, tuple(SIGMA))


def test_share_and_interval():
    g, x, r = np.array([2.0, 2.2, 1.8]), np.array([1.6, 1.7, 1.5]), np.array([1.4, 1.6, 1.2])
    assert share_of_gain(g, x, r) == pytest.approx((2.0 - 1.6) / (2.0 - 1.4))
    assert share_of_gain(g, x, g - 0.01) is None
    lo, hi = share_interval(g, x, r, np.random.default_rng(0))
    assert lo <= share_of_gain(g, x, r) <= hi
    # identical seeds: no spread
    lo, hi = share_interval(np.full(5, 2.0), np.full(5, 1.7), np.full(5, 1.4), np.random.default_rng(0))
    assert lo == pytest.approx(0.5) and hi == pytest.approx(0.5)


def test_cli(tmp_path, capsys):
    pairs = []
    for s in (1, 2):
        oracle, run, _ = _seed(np.random.default_rng(10 + s))
        oracle.to_parquet(tmp_path / f"o{s}.parquet")
        (tmp_path / f"run{s}").mkdir()
        run.to_parquet(tmp_path / f"run{s}" / "estimates.parquet")
        pairs.append(f"{tmp_path / f'o{s}.parquet'}:{tmp_path / f'run{s}'}")
    assert main(pairs + ["--label", "TLR"]) == 0
    out = capsys.readouterr().out
    assert "| TLR seed, zone |" in out and "| o1 A |" in out and "| `icp_da_lc` | all |" in out
    # gnss 2.0, LC 1.6, oracle 1.0: a share near 40 % in RMSE
    line = next(ln for ln in out.splitlines() if ln.startswith("| `icp_da_lc` | all |"))
    assert 30 <= int(line.split("|")[3].split("%")[0]) <= 50
