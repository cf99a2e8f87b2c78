"""[sweep] tune_seeds / eval_seeds and the paired differences (DIR/paired.parquet)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from couplers.errors import InputError
from experiments.sweep.paired import paired_ci
from experiments.sweep.run import load_sweep

PROJECT = Path(__file__).resolve().parents[2]

BASE = """
[run]
name = "base"
methods = ["gnss", "icp_known_da", "icp_da_lc"]
duration_s = 6.0

[scenario]
kind = "single_road"
"""


def _write(tmp: Path, seeds: str) -> Path:
    (tmp / "base.toml").write_text(BASE)
    p = tmp / "sweep.toml"
    p.write_text(f'[sweep]\nname = "proto"\nbase = "base.toml"\n{seeds}\n\n[sweep.grid]\n'
                 '"single_road.feature_spacing_m" = [3.0]\n')
    return p


@pytest.mark.parametrize("seeds, field", [
    ("tune_seeds = [1, 2]\neval_seeds = [2, 3]", "sweep.eval_seeds"),
    ("tune_seeds = [1]", "sweep.eval_seeds"),
    ("eval_seeds = [1]", "sweep.tune_seeds"),
    ("seeds = [1]\ntune_seeds = [2]\neval_seeds = [3]", "sweep.tune_seeds"),
    ("tune_seeds = []\neval_seeds = [3]", "sweep.tune_seeds"),
])
def test_bad_seed_split_names_file_and_field(tmp_path, seeds, field):
    with pytest.raises(InputError) as exc:
        load_sweep(_write(tmp_path, seeds))
    assert exc.value.field == field


def test_overlapping_seeds_through_the_cli_is_one_line_exit_2(tmp_path):
    p = _write(tmp_path, "tune_seeds = [1, 2]\neval_seeds = [2, 3]")
    r = subprocess.run([sys.executable, "-m", "experiments.cli", "sweep", str(p), "--out", str(tmp_path / "o")],
                       cwd=PROJECT, capture_output=True, text=True)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(p) in lines[0] and "sweep.eval_seeds" in lines[0]
    assert not (tmp_path / "o").exists()


def test_eval_seeds_only_in_the_tables_and_paired_intervals(tmp_path):
    from experiments.sweep.run import run_sweep

    p = _write(tmp_path, "tune_seeds = [1]\neval_seeds = [2, 3, 4]")
    spec = load_sweep(p)
    assert spec.seeds == (1, 2, 3, 4) and spec.scored_seeds == (2, 3, 4)
    out = tmp_path / "out"
    run_sweep(p, out, workers=1, progress=False)
    assert (out / "runs" / "feature_spacing_m=3.0,seed=1").is_dir()  # the tuning seed ran
    table = pd.read_parquet(out / "sweep.parquet")
    assert sorted(set(table["seed"])) == [2, 3, 4]
    resolved = (out / "sweep.toml").read_text()
    assert "tune_seeds = [1]" in resolved and "eval_seeds = [2, 3, 4]" in resolved
    paired = pd.read_parquet(out / "paired.parquet")
    rmse = {(s, m): json.loads((out / "runs" / f"feature_spacing_m=3.0,seed={s}" / "summary.json").read_text())
            ["methods"][m]["rmse_pos_m"] for s in (2, 3, 4) for m in ("gnss", "icp_known_da", "icp_da_lc")}
    for b in ("gnss", "icp_known_da"):
        row = paired[(paired["zone"] == "all") & (paired["a"] == "icp_da_lc") & (paired["b"] == b)].iloc[0]
        want = paired_ci([rmse[(s, "icp_da_lc")] for s in (2, 3, 4)], [rmse[(s, b)] for s in (2, 3, 4)])
        assert row["seeds"] == 3
        assert (row["mean"], row["ci_lo"], row["ci_hi"]) == tuple(pytest.approx(w, rel=1e-9) for w in want[:3])
    html = (out / "report.html").read_text()
    assert "Paired differences per setting and zone" in html and "evaluation seeds [2, 3, 4]" in html
