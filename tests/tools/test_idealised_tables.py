"""tools/idealised_tables.py: arms read from the run folders' names (the preset by the sweep's own factor), and
the paired differences against the reference arm equal a direct computation."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
from idealised_tables import markdown, method_table, paired_rows, run_key, run_rows  # noqa: E402


def _write(folder: Path, name: str, rmse: dict, nees: dict, inside: dict) -> None:
    methods = {m: {"rmse_pos_m": rmse[m], "p95_pos_m": 2 * rmse[m], "n": 10,
                   "by_zone": {"B": {"rmse_pos_m": rmse[m] + 1, "p95_pos_m": 2 * rmse[m] + 1, "n": 5}},
                   "nees_pos": {"mean": nees[m], "inside_95": inside[m],
                                "by_zone": {"B": {"mean": nees[m] * 2, "inside_95": inside[m] / 2}}}}
               for m in rmse}
    run = folder / "runs" / name
    run.mkdir(parents=True)
    (run / "summary.json").write_text(json.dumps({"methods": methods, "wall_seconds": 1.0}))


def test_arms_and_paired_differences(tmp_path):
    (tmp_path / "sweep.toml").write_text('[sweep]\nname = "x"\n[sweep.factors]\n'
                                         'arm = [{label = "sci", preset = true}, {label = "paper", set = {}}]\n')
    sci = {11: 0.50, 12: 0.47, 13: 0.55}
    paper = {11: 0.48, 12: 0.46, 13: 0.50}
    for seed in sci:
        _write(tmp_path, f"control=tlr,preset,seed={seed}", {"icp_known_da": sci[seed]}, {"icp_known_da": 2.0},
               {"icp_known_da": 0.95})
        _write(tmp_path, f"control=tlr,arm=paper,seed={seed}", {"icp_known_da": paper[seed]},
               {"icp_known_da": 90.0}, {"icp_known_da": 0.2})
    _write(tmp_path, "not-a-run", {"icp_known_da": 9.0}, {"icp_known_da": 9.0}, {"icp_known_da": 0.0})
    rows = run_rows(tmp_path)
    assert set(rows["arm"]) == {"arm=sci", "arm=paper"} and set(rows["control"]) == {"tlr"}
    mt = method_table(rows)
    r = mt[(mt.arm == "arm=sci") & (mt.zone == "all")].iloc[0]
    assert r.seeds == 3 and abs(r.rmse - np.mean(list(sci.values()))) < 1e-12 and r.in_band
    assert not mt[(mt.arm == "arm=paper") & (mt.zone == "all")].iloc[0].in_band
    pr = paired_rows(rows, "arm=paper")
    p = pr[(pr.zone == "all") & (pr.stat == "rmse")].iloc[0]
    d = np.array([sci[s] - paper[s] for s in sorted(sci)])
    half = stats.t.ppf(0.975, 2) * d.std(ddof=1) / np.sqrt(3)
    assert abs(p["mean"] - d.mean()) < 1e-12 and abs(p.hi - (d.mean() + half)) < 1e-12
    ratio = np.array([100 * sci[s] / paper[s] for s in sorted(sci)])
    assert abs(p.pct - (ratio.mean() - 100)) < 1e-9
    text = markdown(rows, "arm=paper")
    assert "TLR, arm=sci: seeds 11-13 (3)" in text and "against arm=paper" in text


def test_a_sweep_without_grid_or_factors(tmp_path):
    """Run folders named ``seed=N`` (no grid, no factor): the preset arm, the control from the run's config."""
    (tmp_path / "sweep.toml").write_text('[sweep]\nname = "x"\n')
    for seed in (11, 12):
        _write(tmp_path, f"seed={seed}", {"joint_oracle": 0.4}, {"joint_oracle": 1.8}, {"joint_oracle": 0.97})
        (tmp_path / "runs" / f"seed={seed}" / "config.toml").write_text('[scenario]\ncontrol = "vsr"\n')
    rows = run_rows(tmp_path)
    assert set(rows["arm"]) == {"preset"} and set(rows["control"]) == {"vsr"} and set(rows["seed"]) == {11, 12}
    # the --shared rows' ident reads the same key from the folder
    assert run_key(tmp_path / "runs" / "seed=11", "preset") == {"control": "vsr", "arm": "preset", "seed": 11}
