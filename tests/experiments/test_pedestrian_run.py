"""The shipped pedestrian config runs end to end and its saved config round-trips."""

from pathlib import Path

import pandas as pd

from experiments.cli import main
from experiments.config import load_config

PROJECT = Path(__file__).resolve().parents[2]
CONFIG = PROJECT / "experiments" / "arterial_ped_tlr.toml"


def test_arterial_ped_config_runs_and_round_trips(tmp_path):
    cfg = load_config(CONFIG)
    assert cfg.features is not None and cfg.features.pedestrians
    assert cfg.sensors.features == cfg.features
    assert cfg.icp.pedestrian_sigma_par == 0.05
    out = tmp_path / "run"
    assert main(["run", str(CONFIG), "--out", str(out), "--duration", "30", "--quiet"]) == 0
    assoc = pd.read_parquet(out / "association.parquet")
    assert set(assoc["method"]) == {"icp_known_da", "icp_da_lc"}
    saved = load_config(out / "config.toml")
    assert saved.features == cfg.features and saved.icp == cfg.icp
