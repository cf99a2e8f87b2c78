"""[analysis] warmup_start = "traffic": SUMO drives the warm-up alone, sensing and estimation start at its end.

The window of such a run is the same traffic as the window of a run sensed from the begin (SUMO does not
see the sensing), its rows start one step after begin + warmup_s, and the run is byte-reproducible."""
from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from experiments.config import load_config
from experiments.runner import run_experiment

ROOT = Path(__file__).resolve().parents[2]
WARMUP_S, DURATION_S = 30.0, 60.0
TRUTH = ["t", "vehicle", "px_true", "py_true", "vx_true", "vy_true", "zone", "area"]


def _run(tmp: Path, name: str, start: str) -> Path:
    d = tmp / name
    d.mkdir()
    p = d / "cfg.toml"
    p.write_text(f'extends = "{ROOT / "experiments" / "arterial_tlr.toml"}"\n'
                 f'[run]\nmethods = ["gnss", "icp_known_da"]\n'
                 f'[analysis]\nwarmup_s = {WARMUP_S}\nwarmup_start = "{start}"\n[report]\nfigures = false\n')
    cfg = load_config(p, {"run.duration_s": DURATION_S, "run.seed": 2})
    run_experiment(cfg, d / "run", progress=False, write_report=False)
    return d / "run"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("warmup_start")
    return {"sensed": _run(tmp, "sensed", "sensed"), "traffic": _run(tmp, "traffic", "traffic"),
            "again": _run(tmp, "again", "traffic")}


@pytest.mark.slow
def test_traffic_window_is_the_sensed_runs_traffic(runs):
    traffic = pd.read_parquet(runs["traffic"] / "estimates.parquet")
    sensed = pd.read_parquet(runs["sensed"] / "estimates.parquet")
    step = 0.75
    assert traffic["t"].min() == pytest.approx(WARMUP_S + step)  # the first frame: one step after the warm-up
    assert sensed["t"].min() == pytest.approx(step)
    window = sensed[sensed["t"] > WARMUP_S + 1e-9].reset_index(drop=True)
    assert len(window) == len(traffic) > 0
    pd.testing.assert_frame_equal(traffic[TRUTH], window[TRUTH])  # SUMO's trajectories: the same, bit for bit
    # the estimates are not: every vehicle enters at the window's start with its prior (no warm-up track)
    assert not traffic["px"].equals(window["px"])


@pytest.mark.slow
def test_traffic_start_is_byte_reproducible_and_stated(runs):
    for f in ("estimates.parquet", "association.parquet", "traffic.parquet"):
        assert (runs["traffic"] / f).read_bytes() == (runs["again"] / f).read_bytes(), f
    s = json.loads((runs["traffic"] / "summary.json").read_text())
    assert s["analysis"] == {"warmup_s": WARMUP_S, "warmup_start": "traffic", "scored_from_s": WARMUP_S}
    est = pd.read_parquet(runs["traffic"] / "estimates.parquet")
    for method, block in s["methods"].items():
        assert block["n"] == int((est["method"] == method).sum())  # every row of the window is scored
    # the 5-minute statistics cover the sensed window only; the demand's counters the whole run
    sensed = json.loads((runs["sensed"] / "summary.json").read_text())
    assert s["traffic"]["inserted"] == sensed["traffic"]["inserted"]
    assert "warmup_start" not in sensed["analysis"]  # the default's summary is as before
