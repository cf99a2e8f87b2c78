"""Controlled scenarios (Brambilla Sec. V) as run configs: tables, derived model, runs, association scoring."""

import dataclasses
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from coloc.inference.params import IcpParams
from coloc.methods.icp_da_pf import IcpDaPf, PfParams
from couplers.errors import InputError
from experiments.cli import main
from experiments.config import config_from_dict, load_config
from experiments.runner import frame_source

PROJECT = Path(__file__).resolve().parents[2]

SINGLE = """
[run]
name = "single"
seed = 3
methods = ["gnss", "icp_known_da"]

[scenario]
kind = "single_road"

[single_road]
feature_spacing_m = 3.0
"""


def _cfg(tmp_path, text=SINGLE, name="cfg.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- config


@pytest.mark.parametrize(
    "text, field",
    [
        (SINGLE + "n_lanes = 2\n", "single_road.n_lanes"),  # unknown key
        (SINGLE.replace("feature_spacing_m = 3.0", 'feature_spacing_m = "wide"'), "single_road.feature_spacing_m"),
        (SINGLE.replace("feature_spacing_m = 3.0", "n_vehicles = 0"), "single_road.n_vehicles"),
        (SINGLE + "\n[crossroad]\nn_features = 3\n", "crossroad"),  # table of another kind
        (SINGLE.replace("single_road", "crossroad").replace("feature_spacing_m = 3.0", "centre = [1.0]"),
         "crossroad.centre"),
        (SINGLE.replace("single_road", "crossroad").replace("feature_spacing_m = 3.0", "n_features = 2.5"),
         "crossroad.n_features"),
        (SINGLE + "\n[lc]\neta = 0.5\n", "lc.eta"),
        (SINGLE + "\n[lc]\neta_threshold = 1.5\n", "lc.eta_threshold"),
        (SINGLE + "\n[lc]\nbp_iterations = true\n", "lc.bp_iterations"),
        (SINGLE + "\n[motion]\nsigma_along = 0.35\n", "motion.sigma_along"),  # differs from the scenario's 0.2
        (SINGLE + "\n[sensors]\nv2f_range_m = 75.0\n", "sensors.v2f_range_m"),
        (SINGLE.replace('kind = "single_road"', 'kind = "single_road"\ncontrol = "vsr"'), "scenario.control"),
        (SINGLE.replace('kind = "single_road"', 'kind = "highway"'), "scenario.kind"),
    ],
)
def test_bad_scenario_tables_name_file_and_field(tmp_path, text, field):
    path = _cfg(tmp_path, text)
    with pytest.raises(InputError) as err:
        load_config(path)
    assert err.value.field == field and err.value.path == str(path)


def test_bad_table_through_the_cli_is_one_line(tmp_path):
    path = _cfg(tmp_path, SINGLE + "n_lanes = 2\n")
    res = subprocess.run([sys.executable, "-m", "experiments.cli", "run", str(path), "--out", str(tmp_path / "o")],
                         cwd=PROJECT, capture_output=True, text=True)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.strip().count("\n") == 0 and "single_road.n_lanes" in res.stderr and str(path) in res.stderr
    assert not (tmp_path / "o").exists()


def test_model_sensors_and_lc_range_are_the_scenarios(tmp_path):
    cfg = load_config(_cfg(tmp_path, SINGLE.replace("single_road", "crossroad")
                           .replace("feature_spacing_m = 3.0", "feature_speed_mps = 2.0\nv2f_range_m = 60.0")))
    assert (cfg.motion.sigma_along, cfg.motion.sigma_cross) == (0.35, 0.001)
    assert cfg.sensors == cfg.crossroad.sensor_params() and cfg.sensors.v2f_range_m == 60.0
    assert cfg.lc.sensing_range_m == 60.0  # lc.sensing_range_m defaults to the V2F range in force
    assert cfg.icp.feature_sigma_par == pytest.approx(0.02)  # vf / 100 (Sec. V-B)
    # Explicit, equal values are accepted; an explicit lc range is kept.
    cfg2 = load_config(_cfg(tmp_path, SINGLE + "\n[motion]\nsigma_along = 0.2\n[lc]\nsensing_range_m = 30.0\n", "b.toml"))
    assert cfg2.motion.sigma_along == 0.2 and cfg2.lc.sensing_range_m == 30.0
    # SUMO configs: the lc range follows [sensors].
    data = {"run": {"name": "x"}, "scenario": {"net_dir": str(PROJECT / "sumo_nets" / "arterial")},
            "sensors": {"v2f_range_m": 42.0}}
    assert config_from_dict(data, tmp_path / "s.toml").lc.sensing_range_m == 42.0


def test_shipped_scenario_configs_load():
    for name, kind in (("single_road.toml", "single_road"), ("crossroad.toml", "crossroad")):
        cfg = load_config(PROJECT / "experiments" / name)
        assert cfg.scenario.kind == kind and "icp_da_lc" in cfg.run.methods
    assert load_config(PROJECT / "experiments" / "single_road.toml").lc.eta_threshold == 1.0  # Sec. V-A


# --------------------------------------------------------------------------- runs


@pytest.fixture(scope="module")
def single_runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("single")
    cfg = _cfg(tmp, SINGLE)
    outs = []
    for name in ("a", "b"):
        assert main(["run", str(cfg), "--out", str(tmp / name), "--quiet"]) == 0
        outs.append(tmp / name)
    return outs


def test_single_road_run_writes_everything_and_is_byte_identical(single_runs):
    a, b = single_runs
    for name in ("config.toml", "estimates.parquet", "association.parquet", "traffic.parquet", "features.parquet",
                 "summary.json", "report.html"):
        assert (a / name).is_file(), name
    for name in ("estimates.parquet", "association.parquet", "features.parquet", "traffic.parquet"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    est = pd.read_parquet(a / "estimates.parquet")
    assert set(est["method"]) == {"gnss", "icp_known_da"}
    assert est["t"].max() == pytest.approx(29.0) and set(est["vehicle"]) == {"v0", "v1"}
    assert len(pd.read_parquet(a / "traffic.parquet")) == 0  # no SUMO, schema only
    summary = json.loads((a / "summary.json").read_text())
    assert summary["traffic"] is None and summary["sumo_version"] is None
    g, k = summary["methods"]["gnss"], summary["methods"]["icp_known_da"]
    assert k["rmse_pos_m"] < g["rmse_pos_m"]
    # Communication (coloc.inference.comm): GNSS sends nothing; two neighbours sharing features broadcast.
    assert g["comm"]["messages_per_vehicle_step"] == 0 and g["comm"]["bytes_per_vehicle_step"] == 0
    assert k["comm"]["messages_per_vehicle_step"] > 0 and k["comm"]["rounds_per_step"] > 0
    assert k["comm"]["vehicle_steps"] == k["n"]
    assert "<h3>Communication</h3>" in (a / "report.html").read_text()
    saved = tomllib.loads((a / "config.toml").read_text())
    assert "net_dir" not in saved["scenario"] and saved["motion"]["sigma_along"] == 0.2
    assert "= single_road.sigma_along" in (a / "config.toml").read_text()


def test_known_association_is_scored_all_correct(single_runs):
    a = single_runs[0]
    summary = json.loads((a / "summary.json").read_text())
    assoc = summary["association"]
    assert set(assoc) == {"icp_known_da"}  # gnss pairs nothing
    s = assoc["icp_known_da"]
    assert s["correct"] > 0 and s["wrong"] == 0 and s["discarded"] == 0 and s["correct_pct"] == 100.0
    table = pd.read_parquet(a / "association.parquet")
    assert list(table.columns) == ["method", "t", "correct", "wrong", "discarded"]
    assert set(table["method"]) == {"icp_known_da"} and table["correct"].sum() == s["correct"]
    feats = pd.read_parquet(a / "features.parquet")
    assert (feats["track"] == feats["feature"]).all()


def test_saved_config_reruns_identically(single_runs, tmp_path):
    assert main(["run", str(single_runs[0] / "config.toml"), "--out", str(tmp_path / "again"), "--quiet"]) == 0
    assert ((tmp_path / "again" / "estimates.parquet").read_bytes()
            == (single_runs[0] / "estimates.parquet").read_bytes())


def test_crossroad_run_capped_with_ring_areas_and_report_without_net(tmp_path):
    text = SINGLE.replace("single_road", "crossroad").replace("feature_spacing_m = 3.0", "n_features = 10")
    text = text.replace("seed = 3", "seed = 3\nduration_s = 12.0")
    out = tmp_path / "out"
    assert main(["run", str(_cfg(tmp_path, text)), "--out", str(out), "--quiet"]) == 0
    est = pd.read_parquet(out / "estimates.parquet")
    assert est["t"].max() == pytest.approx(12.0)
    assert est["area"].str.fullmatch(r"\d+-\d+").all() and (est["zone"] == "-").all()
    html = (out / "report.html").read_text()
    assert "cdf_area.png" in html and "controlled scenario" in html and "map.png" not in html
    assert main(["report", str(out)]) == 0  # rebuilding needs no net folder either


def test_icp_da_lc_run_is_scored(tmp_path):
    out = tmp_path / "o"
    assert main(["run", str(_cfg(tmp_path, SINGLE)), "--out", str(out), "--methods", "gnss,icp_da_lc", "--quiet"]) == 0
    s = json.loads((out / "summary.json").read_text())["association"]["icp_da_lc"]
    assert s["correct"] + s["wrong"] + s["discarded"] > 0
    assert s["correct_pct"] + s["wrong_pct"] + s["discarded_pct"] == pytest.approx(100.0)
    table = pd.read_parquet(out / "association.parquet")
    assert set(table["method"]) == {"icp_da_lc"} and table["correct"].sum() == s["correct"]


def test_particle_known_association_method_is_the_pf_told_the_truth(tmp_path):
    """icp_known_da_pf in a run = IcpDaPf.step_with_association on the same frames, scored like the bound."""
    text = SINGLE.replace("seed = 3", "seed = 3\nduration_s = 12.0") + (
        "\n[pf]\nvehicle_particles = 200\nfeature_particles = 200\n")
    path = _cfg(tmp_path, text)
    out = tmp_path / "o"
    assert main(["run", str(path), "--out", str(out), "--methods", "icp_known_da_pf", "--quiet"]) == 0
    est = pd.read_parquet(out / "estimates.parquet")
    cfg = load_config(path)
    ref = IcpDaPf(params=IcpParams(motion=cfg.motion, **dataclasses.asdict(cfg.icp)), lc=cfg.lc,
                  pf=PfParams(seed=cfg.run.seed, **dataclasses.asdict(cfg.pf)))
    rows = []
    with frame_source(cfg) as source:
        for frame in source.frames():
            res = ref.step_with_association(frame.without_truth(), frame.truth.v2f_feature)
            rows.append(res.mean[:, :2])
    assert np.array_equal(est[["px", "py"]].to_numpy(), np.concatenate(rows))
    summary = json.loads((out / "summary.json").read_text())
    s = summary["association"]["icp_known_da_pf"]
    assert s["correct"] > 0 and s["correct_pct"] == 100.0
    feats = pd.read_parquet(out / "features.parquet")
    assert len(feats) and (feats["track"] == feats["feature"]).all()


@pytest.mark.parametrize("workers", [0, 1])
def test_the_estimators_are_let_go_before_the_tables(tmp_path, monkeypatch, workers):
    """After the loop the runner holds no estimator while it writes the Parquet files (the PF's kept kernel
    matrices are 2 GB on the arterial: the TLR hour peaked at 4.42 GB when they were still held); with
    workers, none of those that stepped in the runner's own process."""
    import gc
    import weakref

    import coloc.methods.registry as registry
    import experiments.runner as runner

    refs = []
    build, build_one = runner.build_estimators, registry.build_method

    def recording_build(cfg):
        ests = build(cfg)
        refs.extend(weakref.ref(e) for e in ests)
        return ests

    def recording_build_one(*args, **kwargs):
        est = build_one(*args, **kwargs)
        refs.append(weakref.ref(est))
        return est

    alive_at_tables = []
    table = runner.StreamLog.write_estimates

    def checking_table(self, *args, **kwargs):
        gc.collect()
        alive_at_tables.append([r() is not None for r in refs])
        return table(self, *args, **kwargs)

    monkeypatch.setattr(runner, "build_estimators", recording_build)
    monkeypatch.setattr(registry, "build_method", recording_build_one)
    monkeypatch.setattr(runner.StreamLog, "write_estimates", checking_table)
    cfg = load_config(_cfg(tmp_path, SINGLE.replace('"icp_known_da"]', '"icp_known_da", "icp_da_lc"]')))
    runner.run_experiment(cfg, tmp_path / "out", progress=False, write_report=False, workers=workers)
    # workers = 1: gnss and icp_known_da step beside the scenario, icp_da_lc in the worker
    assert len(refs) == (3 if workers == 0 else 2) and alive_at_tables == [[False] * len(refs)]
