"""tools/protocol_tables.py: the seeds for a stated half-width, and the tables from a sweep folder's
summary.json files against a direct computation."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
from protocol_tables import (markdown, method_table, paired_rows, run_rows, seeds_for_half_width,  # noqa: E402
                             shared_rows, shared_table)


@pytest.mark.parametrize("sd", [0.05, 0.2, 0.37, 1.0, 2.5])
def test_seeds_for_half_width_is_the_smallest_n(sd):
    n = seeds_for_half_width(sd, 0.15)
    half = lambda k: stats.t.ppf(0.975, k - 1) * sd / math.sqrt(k)  # noqa: E731
    assert half(n) <= 0.15
    if n > 2:
        assert half(n - 1) > 0.15


def test_seeds_for_half_width_edge_cases():
    assert seeds_for_half_width(0.0) == 2
    assert seeds_for_half_width(math.nan) == -1
    # the textbook value: sd 1, half-width 0.5 -> 18 (t_17 = 2.110, 2.110 / sqrt(18) = 0.497)
    assert seeds_for_half_width(1.0, 0.5) == 18


def _summary(rmse: dict, p95: dict, nees: dict, inside: dict) -> dict:
    methods = {}
    for m in rmse:
        methods[m] = {"rmse_pos_m": rmse[m], "p95_pos_m": p95[m], "n": 10,
                      "by_zone": {"A": {"rmse_pos_m": rmse[m] + 1, "p95_pos_m": p95[m] + 1, "n": 5}},
                      "nees_pos": {"mean": nees[m], "inside_95": inside[m],
                                   "by_zone": {"A": {"mean": nees[m] * 2, "inside_95": inside[m] / 2}}}}
    return {"methods": methods, "wall_seconds": 1.0}


def test_tables_from_a_folder(tmp_path):
    rng = np.random.default_rng(7)
    seeds = range(11, 16)
    truth = {}
    for seed in seeds:
        r = {"gnss": 5 + rng.normal(), "icp_known_da": 4 + rng.normal(), "icp_da_lc": 4.5 + rng.normal()}
        p = {k: 2 * v for k, v in r.items()}
        nees = {k: 2 + rng.random() for k in r}
        inside = {k: 0.9 + 0.05 * rng.random() for k in r}
        truth[seed] = (r, p, nees, inside)
        d = tmp_path / "runs" / f"rule=split_ci,control=tlr,seed={seed}"
        d.mkdir(parents=True)
        (d / "summary.json").write_text(json.dumps(_summary(r, p, nees, inside)))
    # an unfinished run (no summary.json) and a foreign folder are ignored
    (tmp_path / "runs" / "rule=bp,control=tlr,seed=11").mkdir()
    rows = run_rows(tmp_path)
    assert set(rows["zone"]) == {"all", "A"} and set(rows["rule"]) == {"split_ci"}
    mt = method_table(rows)
    lc_all = mt[(mt.method == "icp_da_lc") & (mt.zone == "all")].iloc[0]
    assert lc_all.seeds == 5
    assert lc_all.rmse == pytest.approx(np.mean([truth[s][0]["icp_da_lc"] for s in seeds]))
    assert lc_all.anees == pytest.approx(np.mean([truth[s][2]["icp_da_lc"] for s in seeds]))
    lo, hi = stats.chi2.ppf([0.025, 0.975], 10) / 5
    assert (lc_all.band_lo, lc_all.band_hi) == pytest.approx((lo, hi))
    pr = paired_rows(rows)
    r = pr[(pr.zone == "A") & (pr.a == "icp_da_lc") & (pr.stat == "p95")].iloc[0]
    d = np.array([2 * truth[s][0]["icp_da_lc"] - 2 * truth[s][0]["gnss"] for s in seeds])
    ci = stats.t.interval(0.95, len(d) - 1, loc=d.mean(), scale=stats.sem(d))
    assert (r["mean"], r.ci_lo, r.ci_hi) == pytest.approx((d.mean(), *ci))
    assert r.a_better == int((d < 0).sum())
    assert r.seeds_needed == seeds_for_half_width(float(d.std(ddof=1)))
    text = markdown(rows)
    assert "seeds 11-15 (5)" in text and "LC - GNSS" in text and "known DA - GNSS" in text


def test_a_sweep_without_the_fusion_arm_is_the_shipped_arm(tmp_path):
    """experiments/sweeps/realistic_protocol.toml without a fusion.rule grid names its runs control=...,seed=...:
    they are read as the shipped (split CI) arm, side by side with a folder that names the arm."""
    r = {"gnss": 5.0, "icp_known_da": 4.0, "icp_da_lc": 4.5}
    s = _summary(r, {k: 2 * v for k, v in r.items()}, {k: 2.0 for k in r}, {k: 0.95 for k in r})
    for name in ("control=vsr,seed=12", "rule=bp,control=tlr,seed=12"):
        d = tmp_path / "runs" / name
        d.mkdir(parents=True)
        (d / "summary.json").write_text(json.dumps(s))
    rows = run_rows(tmp_path)
    assert set(zip(rows["rule"], rows["control"])) == {("split_ci", "vsr"), ("bp", "tlr")}
    assert set(rows["seed"]) == {12}


def test_shared_columns_from_the_estimates(tmp_path):
    """--shared: runs whose vehicles share a constant error of known size, whitened by a known covariance:
    each run's shared moment is its drawn error's, the pooled fraction the moments' ratio, the correlation
    time far longer than the run (the shared part does not change) and the band inside_share_band's for that fraction."""
    import pandas as pd

    from experiments.sweep.consistency import inside_share_band

    rng = np.random.default_rng(3)
    f, steps, n, sigma = 0.6, 400, 20, 2.0
    drawn = {}
    for seed in (11, 12):
        c = drawn[seed] = rng.standard_normal(2) * math.sqrt(f) * sigma
        t = np.repeat(600.0 + np.arange(steps), n)
        e = c + rng.standard_normal((steps * n, 2)) * math.sqrt(1 - f) * sigma
        est = pd.DataFrame({"method": "gnss", "t": t, "zone": "A", "px": e[:, 0], "py": e[:, 1], "px_true": 0.0,
                            "py_true": 0.0, "var_px": sigma ** 2, "var_py": sigma ** 2, "cov_pxy": 0.0})
        d = tmp_path / "runs" / f"control=tlr,seed={seed}"
        d.mkdir(parents=True)
        est.to_parquet(d / "estimates.parquet")
        (d / "summary.json").write_text(json.dumps({**_summary({"gnss": 1.0}, {"gnss": 2.0}, {"gnss": 2.0},
                                                               {"gnss": 0.95}), "analysis": {"scored_from_s": 600.0}}))
    rows = shared_rows(tmp_path)
    assert len(rows) == 4  # 2 runs x ("all", "A")
    for _, r in rows.iterrows():
        # per sample: |c|^2 / sigma^2 shared, about that plus 2 (1 - f) in all (400 steps: a few per cent)
        want = float((drawn[r.seed] ** 2).sum()) / sigma ** 2
        assert r.shared_m / (steps * n) == pytest.approx(want, abs=0.05), (r.seed, r.shared_m / (steps * n), want)
        assert r.total_m / (steps * n) == pytest.approx(want + 2 * (1 - f), rel=0.05)
    tab = shared_table(rows)
    a = tab[tab.zone == "A"].iloc[0]
    ra = rows[rows.zone == "A"]
    pooled = ra["shared_m"].sum() / ra["total_m"].sum()
    assert a.shared == pytest.approx(pooled)
    assert a.tau_s > 20 * steps  # the shared part does not change: rho at the lag is 1 but for sampling noise
    assert (a.inside_lo, a.inside_hi) == pytest.approx(inside_share_band([pooled, pooled]))
    text = markdown(run_rows(tmp_path), tab)
    assert "band of inside" in text and "| A | GNSS |" in text
