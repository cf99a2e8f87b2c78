"""Consistency in every report: the 2-D position NEES of summary.json can be recomputed from estimates.parquet
(its var_px, var_py, cov_pxy) with pandas, after the run's warm-up; and the across-seed band of a sweep."""

import json

import numpy as np
import pandas as pd
import pytest

from experiments.config import load_config
from experiments.runner import run_experiment
from experiments.scoring import CHI2_2_95

CROSS = """
[run]
name = "cross"
seed = 4
duration_s = 30.0
methods = ["gnss", "icp_known_da", "icp_da_lc"]

[scenario]
kind = "crossroad"

[crossroad]
n_features = 10

[analysis]
warmup_s = 6.0
"""


def test_nees_recomputed_from_the_parquet_equals_the_summary(tmp_path):
    cfg_path = tmp_path / "cross.toml"
    cfg_path.write_text(CROSS)
    out = tmp_path / "run"
    run_experiment(load_config(cfg_path), out, progress=False, write_report=False)
    summary = json.loads((out / "summary.json").read_text())
    est = pd.read_parquet(out / "estimates.parquet")
    assert "cov_pxy" in est.columns and (est["cov_pxy"] != 0).any()  # the cross term is written, and used
    t0 = summary["analysis"]["scored_from_s"]
    est = est[est["t"] >= t0 - 1e-9]
    ex, ey = est["px"] - est["px_true"], est["py"] - est["py_true"]
    det = est["var_px"] * est["var_py"] - est["cov_pxy"] ** 2
    est = est.assign(nees=(est["var_py"] * ex**2 - 2 * est["cov_pxy"] * ex * ey + est["var_px"] * ey**2) / det)
    for method, rows in est.groupby("method"):
        block = summary["methods"][method]["nees_pos"]
        for key, sel in [(None, rows), *((z, g) for z, g in rows.groupby("zone"))]:
            want = block if key is None else block["by_zone"][key]
            assert want["n"] == len(sel)
            assert want["mean"] == pytest.approx(sel["nees"].mean(), rel=1e-12)
            assert want["median"] == pytest.approx(sel["nees"].median(), rel=1e-12)
            assert want["inside_95"] == pytest.approx((sel["nees"] <= CHI2_2_95).mean(), rel=1e-12)
    # the scored rows leave out the warm-up: without it the statistics differ
    assert len(est) < len(pd.read_parquet(out / "estimates.parquet", columns=["t"]))


def test_anees_band_holds_a_consistent_average_at_its_level():
    """S independent runs of a consistent estimator (each run's time average: one chi-square(2) sample, the
    widest case, or the mean of 50 independent ones, a narrower one): the average falls inside the band
    95 % of the time (binomial, two-sided 0.1 %) in the first case and at least that often in the second."""
    from experiments.sweep.consistency import anees_band

    rng = np.random.default_rng(11)
    trials, s = 20_000, 5
    lo, hi = anees_band(s)
    one = rng.chisquare(2, (trials, s)).mean(axis=1)
    share = np.mean((one >= lo) & (one <= hi))
    assert abs(share - 0.95) < 3.29 * np.sqrt(0.95 * 0.05 / trials)
    many = rng.chisquare(2, (trials, s, 50)).mean(axis=(1, 2))
    assert np.mean((many >= lo) & (many <= hi)) > 0.99
    # the price of counting a run as one sample: with 5 seeds the band is [0.65, 4.10], so a covariance a third
    # of the truth (NEES tripled) is outside, half of it (doubled) is not
    assert (lo, hi) == (pytest.approx(0.6494, abs=1e-3), pytest.approx(4.0966, abs=1e-3))
    assert not lo <= 3.0 * one.mean() <= hi


def test_sweep_consistency_table_equals_the_runs_summaries(tmp_path):
    from experiments.sweep.consistency import consistency_row
    from experiments.sweep.run import run_sweep

    (tmp_path / "base.toml").write_text('[run]\nname = "base"\nmethods = ["gnss", "icp_known_da"]\n'
                                        'duration_s = 6.0\n\n[scenario]\nkind = "single_road"\n')
    p = tmp_path / "sweep.toml"
    p.write_text('[sweep]\nname = "nees"\nbase = "base.toml"\nseeds = [1, 2, 3]\n\n[sweep.grid]\n'
                 '"single_road.feature_spacing_m" = [3.0]\n')
    out = tmp_path / "out"
    run_sweep(p, out, workers=1, progress=False)
    table = pd.read_parquet(out / "consistency.parquet")
    runs = [json.loads((out / "runs" / f"feature_spacing_m=3.0,seed={s}" / "summary.json").read_text())
            for s in (1, 2, 3)]
    for method in ("gnss", "icp_known_da"):
        row = table[(table["method"] == method) & (table["zone"] == "all")].iloc[0]
        blocks = [r["methods"][method]["nees_pos"] for r in runs]
        want = consistency_row([b["mean"] for b in blocks], [b["inside_95"] for b in blocks])
        assert row["seeds"] == 3 and bool(row["inside_band"]) == want["inside_band"]
        for c in ("anees", "band_lo", "band_hi", "t_lo", "t_hi", "inside_95"):
            assert row[c] == pytest.approx(want[c], rel=1e-12)
    assert "Consistency across seeds" in (out / "report.html").read_text()
