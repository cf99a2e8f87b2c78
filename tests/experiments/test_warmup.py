"""[analysis] warmup_s: the scored statistics leave out t < begin + warmup_s; the files keep every row."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from experiments.config import load_config
from experiments.runner import run_experiment

ROOT = Path(__file__).resolve().parents[2]


def _cfg(tmp_path: Path, extra: str):
    src = (ROOT / "experiments" / "crossroad.toml").read_text()
    p = tmp_path / "cfg.toml"
    p.write_text(src + "\n" + extra)
    return load_config(p, {"run.duration_s": 40.0})


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("warmup")
    out = {}
    for name, extra in (("plain", ""), ("warm", "[analysis]\nwarmup_s = 15.0\n")):
        d = tmp / name
        d.mkdir()
        cfg = _cfg(d, extra)
        run_experiment(cfg, d / "run", progress=False, write_report=False)
        out[name] = d / "run"
    return out


def _rmse(x):
    return float(np.sqrt(np.mean(np.asarray(x, dtype=float) ** 2)))


def test_scores_equal_a_manual_filter_of_the_estimates(runs):
    s = json.loads((runs["warm"] / "summary.json").read_text())
    assert s["analysis"] == {"warmup_s": 15.0, "scored_from_s": 15.0}
    est = pd.read_parquet(runs["warm"] / "estimates.parquet")
    assert est["t"].min() < 15.0  # the file keeps the warm-up rows
    kept = est[est["t"] >= 15.0]
    for method, block in s["methods"].items():
        rows = kept[kept["method"] == method]
        assert block["n"] == len(rows) < (est["method"] == method).sum()
        assert block["rmse_pos_m"] == pytest.approx(_rmse(rows["err_pos"]), rel=1e-12)
        assert block["p95_pos_m"] == pytest.approx(float(np.quantile(rows["err_pos"], 0.95)), rel=1e-12)
        for zone, zb in block["by_zone"].items():
            zr = rows[rows["zone"].astype(str) == zone]
            assert zb["n"] == len(zr)
            assert zb["rmse_pos_m"] == pytest.approx(_rmse(zr["err_pos"]), rel=1e-12)
    assoc = pd.read_parquet(runs["warm"] / "association.parquet")
    for method, block in s["association"].items():
        a = assoc[(assoc["method"] == method) & (assoc["t"] >= 15.0)]
        assert (block["correct"], block["wrong"], block["discarded"]) == \
            (int(a["correct"].sum()), int(a["wrong"].sum()), int(a["discarded"].sum()))


def test_warmup_leaves_the_files_and_a_plain_summary_unchanged(runs):
    for f in ("estimates.parquet", "association.parquet"):
        assert (runs["plain"] / f).read_bytes() == (runs["warm"] / f).read_bytes()
    plain = json.loads((runs["plain"] / "summary.json").read_text())
    assert "analysis" not in plain
    est = pd.read_parquet(runs["plain"] / "estimates.parquet")
    for method, block in plain["methods"].items():
        assert block["n"] == int((est["method"] == method).sum())


def test_warmup_out_of_range_is_one_line(tmp_path):
    from couplers.errors import InputError

    with pytest.raises(InputError) as exc:
        _cfg(tmp_path, "[analysis]\nwarmup_s = -5.0\n")
    assert "analysis.warmup_s" in str(exc.value)
