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
from protocol_tables import markdown, method_table, paired_rows, run_rows, seeds_for_half_width  # noqa: E402


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
