"""`coloc run` end to end on the test cross, reproducibility, and bad-input handling."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from experiments.cli import main

PROJECT = Path(__file__).resolve().parents[2]

CONFIG = """
[run]
name = "cross_test"
seed = {seed}
duration_s = {duration}
methods = ["gnss"]

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


def write_config(tmp_path, net, seed=1, duration=90.0, extra="", name="cfg.toml"):
    path = tmp_path / name
    path.write_text(CONFIG.format(seed=seed, duration=duration, net=net, extra=extra))
    return path


@pytest.fixture(scope="module")
def two_runs(cross_net, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("runs")
    cfg = write_config(tmp, cross_net)
    outs = []
    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        assert main(["run", str(cfg), "--out", str(tmp / name), "--seed", str(seed), "--quiet"]) == 0
        outs.append(tmp / name)
    return outs


def test_run_writes_every_output(two_runs):
    out = two_runs[0]
    for name in ("config.toml", "estimates.parquet", "association.parquet", "traffic.parquet", "summary.json", "report.html"):
        assert (out / name).is_file(), name
    est = pd.read_parquet(out / "estimates.parquet")
    expected = ["run", "method", "t", "vehicle", "px", "py", "vx", "vy", "px_true", "py_true", "vx_true", "vy_true",
                "err_pos", "err_vel", "err_along", "err_cross", "zone", "area"]
    assert list(est.columns[: len(expected)]) == expected
    assert set(est["method"]) == {"gnss"} and est["t"].max() == pytest.approx(90.0)
    summary = json.loads((out / "summary.json").read_text())
    for key in ("config", "seed", "sumo_version", "git", "methods", "association", "traffic"):
        assert key in summary
    g = summary["methods"]["gnss"]
    assert g["rmse_pos_m"] > 0 and g["p95_pos_m"] >= g["p50_pos_m"]
    # Zone C (15 m) is worse than zone A (3 m) for the GNSS tracker.
    assert g["by_zone"]["C"]["rmse_pos_m"] > 2 * g["by_zone"]["A"]["rmse_pos_m"]
    resolved = (out / "config.toml").read_text()
    assert "sumo_version" in resolved and "sigma_cross = 0.1" in resolved and "v2v_range_m = 250.0" in resolved
    assert not list(out.parent.glob(".*partial*"))


def test_same_seed_is_byte_identical_and_other_seed_differs(two_runs):
    a, b, c = (p / "estimates.parquet" for p in two_runs)
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() != c.read_bytes()
    assert (two_runs[0] / "traffic.parquet").read_bytes() == (two_runs[1] / "traffic.parquet").read_bytes()


def test_resolved_config_reruns_identically(two_runs, tmp_path):
    """The saved config.toml is a complete input: re-running it reproduces the estimates."""
    saved = two_runs[0] / "config.toml"
    assert main(["run", str(saved), "--out", str(tmp_path / "again"), "--quiet"]) == 0
    assert (tmp_path / "again" / "estimates.parquet").read_bytes() == (two_runs[0] / "estimates.parquet").read_bytes()


def _cli(args, cwd):
    return subprocess.run([sys.executable, "-m", "experiments.cli", *args], cwd=cwd, capture_output=True, text=True)


@pytest.mark.parametrize(
    "mutate, needle",
    [
        (lambda t: t.replace("[motion]", "[motion]\nsigma_sideways = 1.0"), "motion.sigma_sideways"),
        (lambda t: t.replace("seed = 1", 'seed = "one"'), "run.seed"),
        (lambda t: t.replace('methods = ["gnss"]', 'methods = ["gnss", "magic"]'), "run.methods[1]"),
        (lambda t: t + "\n[nonsense]\nx = 1\n", "nonsense"),
        (lambda t: t.replace("[run]", "[run\n"), "not valid TOML"),
        (lambda t: t + '\n[icp]\nfeature_message = "final"\n', "icp.feature_message"),
    ],
)
def test_bad_config_one_clear_message(cross_net, tmp_path, mutate, needle):
    cfg = write_config(tmp_path, cross_net)
    cfg.write_text(mutate(cfg.read_text()))
    res = _cli(["run", str(cfg), "--out", str(tmp_path / "out")], PROJECT)
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    assert needle in res.stderr and str(cfg) in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out*"))


def test_missing_net_file_names_file_and_field(cross_net, tmp_path):
    net = tmp_path / "net"
    shutil.copytree(cross_net, net)
    (net / "tlr.net.xml").unlink()
    cfg = write_config(tmp_path, net)
    res = _cli(["run", str(cfg), "--out", str(tmp_path / "out")], PROJECT)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "scenario.toml: files.net" in res.stderr
    assert not (tmp_path / "out").exists()


def test_zones_leaving_the_net_uncovered(cross_net, tmp_path):
    net = tmp_path / "net"
    shutil.copytree(cross_net, net)
    zones = json.loads((net / "zones.geojson").read_text())
    zones["features"] = zones["features"][:1]  # only the west half remains
    (net / "zones.geojson").write_text(json.dumps(zones))
    cfg = write_config(tmp_path, net)
    res = _cli(["run", str(cfg), "--out", str(tmp_path / "out")], PROJECT)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "zones.geojson" in res.stderr and "uncovered" in res.stderr
    assert not (tmp_path / "out").exists()


def test_missing_config_and_bad_report_dir(tmp_path):
    res = _cli(["run", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "o")], PROJECT)
    assert res.returncode == 2 and "nope.toml" in res.stderr and "Traceback" not in res.stderr
    res = _cli(["report", str(tmp_path)], PROJECT)
    assert res.returncode == 2 and "summary.json" in res.stderr


def test_failed_run_keeps_previous_output(cross_net, tmp_path):
    """An existing output folder survives a run that fails on bad input."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("old")
    cfg = write_config(tmp_path, cross_net)
    cfg.write_text(cfg.read_text().replace('control = "tlr"', 'control = "allgreen"'))
    assert main(["run", str(cfg), "--out", str(out), "--quiet"]) == 2
    assert (out / "keep.txt").read_text() == "old"


def test_known_association_bound_runs_and_reports_features(cross_net, tmp_path):
    """icp_known_da gets the true association from the runner (not the frame) and its
    feature-track errors land in features.parquet and summary.json."""
    cfg = write_config(tmp_path, cross_net, duration=60.0, extra="[icp]\nconsensus_iterations = 30\n")
    out = tmp_path / "out"
    assert main(["run", str(cfg), "--out", str(out), "--methods", "gnss,icp_known_da", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["methods"]) == {"gnss", "icp_known_da"}
    feats = pd.read_parquet(out / "features.parquet")
    assert set(feats["method"]) == {"icp_known_da"} and len(feats) > 0
    assert summary["methods"]["icp_known_da"]["features"]["n"] == len(feats)
    assert "consensus_iterations = 30" in (out / "config.toml").read_text()


def test_progress_off_a_terminal_is_one_line_per_five_simulated_minutes(cross_net, tmp_path, capsys):
    """Logs of sweeps and CI stay readable: no carriage-return bar when stderr is not a terminal."""
    cfg = write_config(tmp_path, cross_net, duration=600.0)
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and "\r" not in "".join(lines)
    assert lines[0].startswith("cross_test: 300 s simulated, step ") and "s left" in lines[0]
    assert lines[1].startswith("cross_test: 600 s simulated, step 800 of 800 (100 %)")  # 0.75 s steps
    assert main(["run", str(cfg), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert capsys.readouterr().err == ""


def test_version_names_coloc_sumo_and_python(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("coloc ") and ", SUMO 1." in out and ", Python 3." in out


def test_a_run_no_longer_than_its_warm_up_says_so_instead_of_a_traceback(cross_net, tmp_path, capsys):
    """Nothing scored (every estimate inside [analysis] warmup_s): the summary's numbers are None; the
    command prints what happened and exits 0 (the folder holds every row)."""
    cfg = write_config(tmp_path, cross_net, duration=30.0, extra="[analysis]\nwarmup_s = 600.0\n")
    assert main(["run", str(cfg), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "gnss: no estimate scored (none after the warm-up, analysis.warmup_s = 600 s: run longer)" in out
