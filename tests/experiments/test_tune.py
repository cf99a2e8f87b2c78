"""coloc tune: the grid's candidates on the tuning seeds only; the chosen values in an extends overlay whose
header records what was tuned, on which seeds, with which objective and scores."""
from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from experiments.cli import main
from experiments.config import load_config

ROOT = Path(__file__).resolve().parents[2]

SWEEP = f"""
[sweep]
name = "tune_test"
base = "{ROOT / 'experiments' / 'crossroad.toml'}"
tune_seeds = [5, 6]
eval_seeds = [1, 2, 3]
methods = ["gnss"]
objective = {{method = "gnss", statistic = "rmse_pos_m"}}
[sweep.set]
"run.duration_s" = 15.0
[sweep.grid]
"crossroad.accel_sigma" = [0.0, 0.5, 2.0]
"""


@pytest.fixture(scope="module")
def tuned(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tune")
    p = tmp / "tune.toml"
    p.write_text(SWEEP)
    assert main(["tune", str(p), "--out", str(tmp / "out"), "--workers", "1", "--quiet"]) == 0
    return tmp / "out"


@pytest.mark.slow
def test_tune_runs_the_tuning_seeds_only_and_picks_the_best(tuned):
    runs = sorted(d.name for d in (tuned / "runs").iterdir())
    assert runs and all(r.endswith(("seed=5", "seed=6")) for r in runs) and len(runs) == 6
    sweep = pd.read_parquet(tuned / "sweep.parquet")
    assert set(sweep["seed"]) == {5, 6}
    means = sweep[sweep["method"] == "gnss"].groupby("crossroad.accel_sigma")["rmse_pos_m"].mean()
    best = float(means.idxmin())
    cfg = load_config(tuned / "tuned.toml")
    assert cfg.crossroad.accel_sigma == best
    assert cfg.run.duration_s != 15.0  # [sweep.set] conditions the tuning runs only
    text = (tuned / "tuned.toml").read_text()
    assert "tuning seeds: [5, 6]" in text and "candidates crossroad.accel_sigma = [0.0, 0.5, 2.0]" in text
    assert "objective: mean over the tuning seeds of gnss's rmse_pos_m" in text
    assert f"{means.min():.4f}" in text
    scores = pd.read_parquet(tuned / "tuning.parquet")
    assert list(scores.sort_values("rank")["crossroad.accel_sigma"])[0] == best
    assert "accel_sigma = " in (tuned / "tuned.resolved.toml").read_text()


@pytest.mark.parametrize("edit, field", [
    (lambda s: s.replace("tune_seeds = [5, 6]\neval_seeds = [1, 2, 3]", "seeds = [1, 2]"), "sweep.tune_seeds"),
    (lambda s: s.replace('objective = {method = "gnss", statistic = "rmse_pos_m"}\n', ""), "sweep.objective"),
    (lambda s: s.replace('{method = "gnss"', '{method = "icp_da_lc"'), "sweep.objective.method"),
    (lambda s: s.replace("eval_seeds = [1, 2, 3]", "eval_seeds = [1, 5]"), "sweep.eval_seeds"),
    (lambda s: s.replace('"crossroad.accel_sigma"', '"crossroad.sigma_nope"'), "sweep.grid.crossroad.sigma_nope"),
])
def test_tune_bad_input_is_one_line(tmp_path, capsys, edit, field):
    p = tmp_path / "tune.toml"
    p.write_text(edit(SWEEP))
    assert main(["tune", str(p), "--out", str(tmp_path / "out"), "--dry-run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("coloc: error: ") and field in err[0], err
    assert not (tmp_path / "out").exists()
