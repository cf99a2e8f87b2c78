"""`coloc run` on the SME and factor-graph study configs: files, reproducibility, bad input."""

import json
import tomllib
from pathlib import Path

import pandas as pd
import pytest

from experiments.cli import main

PROJECT = Path(__file__).resolve().parents[2]

SME = """
[study]
kind = "sme"
runs = 3
n_steps = 25
{extra}
"""

FG = """
[study]
kind = "fg_topology"
runs = 3
vehicles = [2, 3]
workers = {workers}
[scenario]
n_steps = 30
{extra}
"""


def write(tmp_path, text, name="cfg.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_sme_study_end_to_end_and_byte_identical(tmp_path, capsys):
    cfg = write(tmp_path, SME.format(extra=""))
    assert main(["run", str(cfg), "--out", str(tmp_path / "a"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "sme: 3 runs x 25 steps" in out and "report.html" in out
    a = tmp_path / "a"
    for f in ("config.toml", "summary.json", "results.parquet", "curves.parquet", "example.parquet", "report.html",
              "figures/rmse_time.png", "figures/trajectories.png"):
        assert (a / f).is_file(), f
    resolved = tomllib.loads((a / "config.toml").read_text())
    assert resolved["sensors"] == {"gps_var": 50.0, "sensor_var": 10.0}
    assert resolved["provenance"]["git"]
    summary = json.loads((a / "summary.json").read_text())
    assert len(summary["by_pose"]) == 3
    res = pd.read_parquet(a / "results.parquet")
    assert set(res.method) == {"sme", "kf", "sme_no_topology", "sme_linearized"}
    assert len(res) == 3 * 3 * 4
    assert main(["run", str(cfg), "--out", str(tmp_path / "b"), "--quiet"]) == 0
    for f in ("results.parquet", "curves.parquet", "example.parquet"):
        assert (a / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    assert main(["run", str(cfg), "--out", str(tmp_path / "c"), "--quiet", "--seed", "2"]) == 0
    assert (a / "results.parquet").read_bytes() != (tmp_path / "c" / "results.parquet").read_bytes()


def test_fg_study_end_to_end_and_independent_of_workers(tmp_path, capsys):
    one = write(tmp_path, FG.format(workers=1, extra=""), "one.toml")
    two = write(tmp_path, FG.format(workers=2, extra=""), "two.toml")
    assert main(["run", str(one), "--out", str(tmp_path / "one"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "N=2: fg_topology_new" in out and "[5.211]" in out  # printed next to the paper's Table I
    d = tmp_path / "one"
    for f in ("config.toml", "summary.json", "results.parquet", "timings.parquet", "curves.parquet",
              "example.parquet", "report.html", "figures/rmse_time.png", "figures/trajectories.png"):
        assert (d / f).is_file(), f
    summary = json.loads((d / "summary.json").read_text())
    assert summary["table"]["2"]["paper"]["fg_topology_new"]["mean_final_rmse_m"] == 5.211
    assert summary["table"]["2"]["paper"]["kf_gps_odom"]["mean_seconds"] == 0.010
    html = (d / "report.html").read_text()
    assert "Table I" in html and "Table II" in html and "8.423" in html
    res = pd.read_parquet(d / "results.parquet")
    assert len(res) == 2 * 3 * 4 and res.rmse_m.gt(0).all()
    assert main(["run", str(two), "--out", str(tmp_path / "two"), "--quiet"]) == 0
    for f in ("results.parquet", "curves.parquet", "example.parquet"):
        assert (d / f).read_bytes() == (tmp_path / "two" / f).read_bytes(), f


@pytest.mark.parametrize(
    "text, field, words",
    [
        (SME.format(extra="[sensors]\ngps_var = -1.0"), "sensors.gps_var", "must be > 0"),
        (SME.format(extra="[sensors]\ngps_variance = 1.0"), "sensors.gps_variance", "unknown key"),
        (SME.format(extra="[scenario]\nsensor_poses = [[1.0, 2.0]]"), "scenario.sensor_poses", "[x_m, y_m, heading_deg]"),
        (SME.format(extra="[filter]\npseudo_noise = \"ukf\""), "filter.pseudo_noise", "must be one of"),
        (FG.format(workers=1, extra="[sensors]\nradar_var = \"small\""), "sensors.radar_var", "expected a number"),
        (FG.format(workers=1, extra="[solver]\nmax_iterations = 0"), "solver.max_iterations", "must be >= 1"),
        (FG.format(workers=1, extra="[solver]\ntopology_noise = \"z\""), "solver.topology_noise", "must be one of"),
        (FG.format(workers=1, extra="[extras]\nx = 1"), "extras", "unknown table"),
        (FG.format(workers=0, extra=""), "study.workers", "must be >= 1"),
        ("[study]\nkind = \"fg_topology\"\nvehicles = [1]\n", "study.vehicles", ">= 2"),
        ("[study]\nkind = \"fg_topology\"\nmethods = [\"icp\"]\n", "study.methods", "unknown method"),
    ],
)
def test_bad_input_names_file_and_field_and_writes_nothing(tmp_path, capsys, text, field, words):
    cfg = write(tmp_path, text)
    out = tmp_path / "out"
    assert main(["run", str(cfg), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("coloc: error: ") and str(cfg) in err and field in err and words in err
    assert "Traceback" not in err
    assert not out.exists()
    assert not any(p.name.startswith(".out") for p in tmp_path.iterdir())


def test_shipped_study_configs_resolve():
    """The shipped configs load with the paper's parameters (not run here: see the study reports)."""
    from experiments.studies import fg_topology, sme
    from experiments.studies.study_config import resolve

    f = resolve(tomllib.loads((PROJECT / "experiments/fg_topology.toml").read_text()), Path("x"), fg_topology.SPEC)
    assert f["sensors"] == {"odom_var": 1.0, "gps_var": 9.0, "radar_var": 0.1}
    assert f["study"]["runs"] == 1000 and f["study"]["vehicles"] == [2, 3, 4] and f["scenario"]["n_steps"] == 250
    assert f["solver"]["topology_noise"] == "z2"
    s = resolve(tomllib.loads((PROJECT / "experiments/sme.toml").read_text()), Path("x"), sme.SPEC)
    assert s["sensors"] == {"gps_var": 50.0, "sensor_var": 10.0}
    assert s["scenario"]["process_sigma"] == 0.5 and s["scenario"]["dt"] == 1.0
