"""`coloc run` on an rsu_bp study config: outputs, reproducibility, worker independence, bad input."""

import json

import pandas as pd
import pytest

from experiments.cli import main

SMALL = """
[study]
kind = "rsu_bp"
name = "tiny"
seed = 4
runs = 2
workers = {workers}

[study.scenario]
n_steps = 16

[study.filter]
n_particles = 80

[study.sweep]
v2f_var = [0.5, 1.0]
v2f_var_runs = 1
n_features = [0, 2]
n_features_runs = 1
{extra}
"""


def write(tmp_path, workers=1, extra="", name="study.toml"):
    path = tmp_path / name
    path.write_text(SMALL.format(workers=workers, extra=extra))
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("rsu_bp")
    cfg1 = write(tmp, workers=1, name="one.toml")
    cfg2 = write(tmp, workers=2, name="two.toml")
    outs = {}
    for key, cfg, extra_args in (("a", cfg1, []), ("b", cfg2, []), ("c", cfg1, ["--seed", "5"])):
        assert main(["run", str(cfg), "--out", str(tmp / key), "--quiet", *extra_args]) == 0
        outs[key] = tmp / key
    return outs


def test_outputs(runs):
    out = runs["a"]
    for name in ("config.toml", "results.parquet", "summary.json", "report.html", "figures/fig3_rmse_cdf.png",
                 "figures/fig4_rmse_v2f_var.png", "figures/fig5_rmse_features.png"):
        assert (out / name).is_file(), name
    res = pd.read_parquet(out / "results.parquet")
    assert set(res["method"]) == {"rsu_bp", "gnss_kf"}
    assert set(res["vehicle"]) == {"1", "2"}
    # base: 2 runs; v2f_var: 0.5 (1 run) + 1.0 (reused base run 0); n_features: 0 and 2 (1 run each)
    assert (res["point"] == "base").sum() == 2 * 2 * 2
    assert (res["point"] == "v2f_var").sum() == 2 * 2 * 2
    assert (res["point"] == "n_features").sum() == 2 * 2 * 2
    base0 = res[(res["point"] == "base") & (res["run"] == 0)].drop(columns="point").reset_index(drop=True)
    reused = res[(res["point"] == "v2f_var") & (res["v2f_var"] == 1.0)].drop(columns="point").reset_index(drop=True)
    pd.testing.assert_frame_equal(base0, reused)
    # the GNSS-only KF does not depend on the features or on the V2F variance (same scenario seeds)
    kf = res[(res["method"] == "gnss_kf") & (res["run"] == 0)].groupby("vehicle")["rmse_pos_m"].nunique()
    assert (kf == 1).all()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["study"] == "rsu_bp" and summary["base"]["runs"] == 2
    veh = summary["base"]["vehicles"]
    assert set(veh) == {"1", "2"} and veh["2"]["gnss_var_m2"] == 15.0
    assert [e["v2f_var"] for e in summary["v2f_var_sweep"]] == [0.5, 1.0]
    assert [e["n_features"] for e in summary["n_features_sweep"]] == [0, 2]
    assert summary["n_features_sweep"][0]["association_correct_pct"] is None
    html = (out / "report.html").read_text()
    assert html.count("<figure") == 3 and "Fig. 3" in html
    cfg = (out / "config.toml").read_text()
    assert "[study.filter]" in cfg and "da_iterations = 5" in cfg and "git = " in cfg


def test_same_seed_identical_and_workers_do_not_matter(runs):
    assert (runs["a"] / "results.parquet").read_bytes() == (runs["b"] / "results.parquet").read_bytes()
    assert (runs["a"] / "results.parquet").read_bytes() != (runs["c"] / "results.parquet").read_bytes()
    assert "seed = 5" in (runs["c"] / "config.toml").read_text()


def test_unknown_subtable(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(SMALL.format(workers=1, extra="").replace("[study.filter]", "[study.filer]"))
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "study.filer" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "old, new, field",
    [
        ("n_particles = 80", "n_particles = 80\nparticles = 3", "study.filter.particles"),
        ("n_particles = 80", "n_particles = 1", "study.filter.n_particles"),
        ("n_particles = 80", "n_particles = 80\ndt = 1.0", "study.filter.dt"),
        ("v2f_var = [0.5, 1.0]", "v2f_var = [0.5, -1.0]", "study.sweep.v2f_var"),
        ("n_steps = 16", "n_steps = \"many\"", "study.scenario.n_steps"),
        ("runs = 2", "runs = 0", "study.runs"),
    ],
)
def test_bad_input_names_file_and_field(tmp_path, capsys, old, new, field):
    path = tmp_path / "bad.toml"
    path.write_text(SMALL.format(workers=1, extra="").replace(old, new))
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and field in err and "Traceback" not in err
    assert not out.exists() and not list(tmp_path.glob(".out*"))


def test_rebuild_report(runs, tmp_path):
    import shutil

    from experiments.studies.rsu_bp import rebuild_report

    copy = tmp_path / "copy"
    shutil.copytree(runs["a"], copy)
    shutil.rmtree(copy / "figures")
    (copy / "report.html").unlink()
    assert rebuild_report(copy) == copy / "report.html"
    assert (copy / "figures" / "fig5_rmse_features.png").is_file()
    assert (copy / "report.html").read_text().count("<figure") == 3
