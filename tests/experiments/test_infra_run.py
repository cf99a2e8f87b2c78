"""Infrastructure mode end to end: [infra] config, `coloc run` with rsu_bp / sme / fg_topology_new,
the within-coverage summary and report; bad input; the shipped arterial infra configs (slow)."""

import json
from pathlib import Path

import pandas as pd
import pytest

from experiments.cli import main
from experiments.config import load_config

PROJECT = Path(__file__).resolve().parents[2]

CONFIG = """
[run]
name = "cross_infra"
seed = {seed}
duration_s = {duration}
methods = {methods}

[scenario]
kind = "sumo"
net_dir = "{net}"
control = "tlr"

[motion]
sigma_cross = 0.1

[report]
track_area = "3"
{extra}
"""

INFRA = """
[infra]
rsu_junctions = {junctions}
rsu_range_m = 80.0
rsu_bp_particles = 60
fg_window_steps = 5
"""

ALL = '["gnss", "rsu_bp", "sme", "fg_topology_new"]'


def write(tmp_path, net, methods=ALL, junctions='["C"]', infra=True, seed=1, duration=60.0, extra=""):
    path = tmp_path / f"cfg{seed}.toml"
    text = CONFIG.format(seed=seed, duration=duration, methods=methods, net=net,
                         extra=extra + (INFRA.format(junctions=junctions) if infra else ""))
    path.write_text(text)
    return path


def test_unknown_junction_is_one_clear_message(cross_net, tmp_path, capsys):
    cfg = write(tmp_path, cross_net, junctions='["C", "X9"]')
    assert main(["run", str(cfg), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "infra.rsu_junctions[1]" in err and "X9" in err and str(cfg) in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("method", ["rsu_bp", "sme", "fg_topology_new"])
def test_infra_method_needs_infra_table(cross_net, tmp_path, capsys, method):
    cfg = write(tmp_path, cross_net, methods=f'["gnss", "{method}"]', infra=False)
    assert main(["run", str(cfg), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "run.methods[1]" in err and "[infra]" in err


@pytest.mark.parametrize("table, needle", [
    ('[infra]\nrsu_junctions = []\n', "infra.rsu_junctions"),
    ('[infra]\nrsu_junctions = ["C"]\nrsu_range_m = -1.0\n', "infra.rsu_range_m"),
    ('[infra]\nrsu_junctions = ["C"]\nrsu_bp_detection_prob = 1.5\n', "infra.rsu_bp_detection_prob"),
    ('[infra]\nrsu_junctions = ["C"]\nbogus = 1\n', "infra.bogus"),
    ('[infra]\nrsu_junctions = ["C"]\nrsu_bp_birth_max_std_m = 0.0\n', "infra.rsu_bp_birth_max_std_m"),
])
def test_bad_infra_values(cross_net, tmp_path, capsys, table, needle):
    cfg = write(tmp_path, cross_net, methods='["gnss"]', infra=False, extra=table)
    assert main(["run", str(cfg), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert needle in capsys.readouterr().err


@pytest.fixture(scope="module")
def infra_runs(cross_net, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("infra")
    outs = []
    for name in ("a", "b"):
        cfg = write(tmp, cross_net)
        assert main(["run", str(cfg), "--out", str(tmp / name), "--quiet"]) == 0
        outs.append(tmp / name)
    plain = write(tmp, cross_net, methods='["gnss"]', infra=False, seed=1)
    assert main(["run", str(plain), "--out", str(tmp / "plain"), "--quiet"]) == 0
    return outs + [tmp / "plain"]


def test_every_infra_method_runs_and_is_scored_within_coverage(infra_runs):
    a, _, plain = infra_runs
    s = json.loads((a / "summary.json").read_text())
    cov = s["within_rsu_coverage"]
    assert set(cov["methods"]) == {"gnss", "rsu_bp", "sme", "fg_topology_new"}
    n = {m: b["n"] for m, b in cov["methods"].items()}
    assert len(set(n.values())) == 1 and n["gnss"] > 200  # the same covered vehicle-steps for each method
    assert cov["rsu_vehicle_steps"] == {"C": n["gnss"]}
    for m in ("rsu_bp", "sme", "fg_topology_new"):
        assert cov["methods"][m]["rmse_pos_m"] > 0 and set(cov["methods"][m]["by_area"]) <= {"1", "2", "3", "4"}
    assert cov["methods"]["sme"]["stats"]["topology_updates"] > 0
    est = pd.read_parquet(a / "estimates.parquet")
    assert est[["px", "py", "vx", "vy"]].notna().all().all()
    assert est["covered"].sum() == 4 * n["gnss"] and set(est.loc[est["covered"], "rsu"]) == {"C"}
    # Outside coverage the infrastructure methods report their GNSS tracker: the gnss estimate exactly.
    out = est[~est["covered"]].set_index(["t", "vehicle", "method"])["px"].unstack("method")
    assert (out["sme"] == out["gnss"]).all() and (out["rsu_bp"] == out["gnss"]).all()
    html = (a / "report.html").read_text()
    assert "Within RSU coverage" in html and "Covered vehicle-steps per RSU" in html
    # A run without [infra] keeps the old schema, and the gnss estimates are the same bytes.
    est_plain = pd.read_parquet(plain / "estimates.parquet")
    assert "covered" not in est_plain.columns
    g = est[est["method"] == "gnss"].reset_index(drop=True)
    pd.testing.assert_frame_equal(g[est_plain.columns].drop(columns="run"), est_plain.drop(columns="run"))


def test_infra_runs_byte_identical(infra_runs):
    a, b, _ = infra_runs
    assert (a / "estimates.parquet").read_bytes() == (b / "estimates.parquet").read_bytes()


def test_birth_gate_reaches_the_method(cross_net, tmp_path):
    """[infra] rsu_bp_birth_max_std_m is rsu_bp's birth gate; its default is the method's own 1.5 m."""
    from coloc.methods.infra import InfraMethodParams
    from experiments.runner import infra_method_params

    default = infra_method_params(load_config(write(tmp_path, cross_net)))
    assert default.feature_birth_max_std_m == InfraMethodParams().feature_birth_max_std_m == 1.5
    cfg = write(tmp_path, cross_net, infra=False,
                extra='[infra]\nrsu_junctions = ["C"]\nrsu_bp_birth_max_std_m = 4.0\n')
    assert infra_method_params(load_config(cfg)).feature_birth_max_std_m == 4.0


def test_shipped_infra_configs_validate():
    for control in ("tlr", "vsr"):
        cfg = load_config(PROJECT / "experiments" / f"arterial_{control}_infra.toml")
        assert cfg.infra is not None and cfg.scenario.control == control
        assert set(cfg.run.methods) >= {"gnss", "icp_da_lc", "rsu_bp", "sme", "fg_topology_new"}


@pytest.mark.slow
@pytest.mark.parametrize("control", ["tlr", "vsr"])
def test_shipped_infra_configs_end_to_end(tmp_path, control):
    """Every method runs in both arterial configs (first 180 s of their 600 s, to keep `make test`
    short) and the report places them side by side."""
    out = tmp_path / control
    assert main(["run", str(PROJECT / "experiments" / f"arterial_{control}_infra.toml"), "--out", str(out),
                 "--duration", "180", "--quiet"]) == 0
    s = json.loads((out / "summary.json").read_text())
    cov = s["within_rsu_coverage"]
    assert set(cov["methods"]) == {"gnss", "icp_da_lc", "rsu_bp", "sme", "fg_topology_new"}
    assert set(cov["rsu_vehicle_steps"]) == {"JP1", "JP2", "JP3"}
    rmse = {m: b["rmse_pos_m"] for m, b in cov["methods"].items()}
    # Measured (seed 1, the whole 600 s), RMSE within coverage [m]: TLR gnss 2.19, icp_da_lc 0.49, rsu_bp 0.95,
    # sme 2.10, fg_topology_new 1.68; VSR gnss 2.17, icp_da_lc 0.64, rsu_bp 1.01, sme 1.84, fg 1.58.
    for m in ("icp_da_lc", "rsu_bp", "sme", "fg_topology_new"):
        assert rmse[m] < rmse["gnss"], rmse
    assert "Within RSU coverage" in (out / "report.html").read_text()


def test_comparison_report_has_the_coverage_table(infra_runs, tmp_path):
    a, b, plain = infra_runs
    assert main(["report", str(a), str(plain), "--out", str(tmp_path / "cmp")]) == 0
    html = (tmp_path / "cmp" / "report.html").read_text()
    assert "Within RSU coverage: position RMSE / p95 [m] per area" in html and "FG topology (new)" in html
