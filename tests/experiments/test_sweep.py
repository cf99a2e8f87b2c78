"""`coloc sweep`: spec validation, a tiny sweep on a LocalCluster, resume after kill -9, a running scheduler."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from couplers.errors import InputError
from couplers.publish import MARKER
from experiments.cli import main
from experiments.sweep.run import expand_runs, load_sweep

PROJECT = Path(__file__).resolve().parents[2]

BASE = """
[run]
name = "base"
methods = ["gnss", "icp_known_da"]
duration_s = {duration}

[scenario]
kind = "{kind}"

[{kind}]
{extra}
"""

SWEEP = """
[sweep]
name = "tiny"
base = "base.toml"
seeds = {seeds}
{more}

[sweep.grid]
{grid}
"""


def write_sweep(tmp: Path, grid='"single_road.feature_spacing_m" = [0.5, 3.0]', seeds="[1, 2]", more="",
                kind="single_road", extra="", duration=12.0, name="sweep.toml") -> Path:
    (tmp / "base.toml").write_text(BASE.format(kind=kind, extra=extra, duration=duration))
    path = tmp / name
    path.write_text(SWEEP.format(seeds=seeds, more=more, grid=grid))
    return path


def _cli(args):
    return subprocess.run([sys.executable, "-m", "experiments.cli", *args], cwd=PROJECT, capture_output=True, text=True)


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(grid='"single_road.spacing" = [1.0]'), "sweep.grid.single_road.spacing"),
        (dict(grid='"roads.feature_spacing_m" = [1.0]'), "sweep.grid.roads.feature_spacing_m"),
        (dict(grid='"single_road.feature_spacing_m" = [0.5, "wide"]'), "sweep.grid.single_road.feature_spacing_m[1]"),
        (dict(grid='"single_road.feature_spacing_m" = 0.5'), "sweep.grid.single_road.feature_spacing_m"),
        (dict(grid='"single_road.feature_spacing_m" = []'), "sweep.grid.single_road.feature_spacing_m"),
        (dict(grid='"single_road.n_vehicles" = [2, 0]'), "sweep.grid.single_road.n_vehicles[1]"),
        (dict(grid='"run.seed" = [1, 2]'), "sweep.grid.run.seed"),
        (dict(grid='"lc.eta_threshold" = [0.5, 7.0]'), "sweep.grid.lc.eta_threshold[1]"),
        (dict(seeds="{start = 1}"), "sweep.seeds.count"),
        (dict(seeds="[]"), "sweep.seeds"),
        (dict(seeds="[1, 1]"), "sweep.seeds"),
        (dict(seeds='"many"'), "sweep.seeds"),
        (dict(more="repeats = 3"), "sweep.repeats"),
        (dict(more='methods = ["gnss", "magic"]'), "sweep.methods"),
        (dict(more='[sweep.set]\n"single_road.headway_m" = -1.0'), "sweep.set.single_road.headway_m"),
        (dict(more='[sweep.set]\n"motion.sigma_along" = 1.0'), "sweep.set.motion.sigma_along"),
        (dict(more='base = "missing.toml"'), None),  # duplicate key: not valid TOML
    ],
)
def test_bad_sweep_names_file_and_field(tmp_path, kwargs, field):
    path = write_sweep(tmp_path, **kwargs)
    with pytest.raises(InputError) as err:
        expand_runs(load_sweep(path))
    assert err.value.path == str(path) and err.value.field == field


def test_missing_base_and_bad_base_name_their_files(tmp_path):
    path = write_sweep(tmp_path)
    path.write_text(path.read_text().replace('base = "base.toml"', 'base = "nope.toml"'))
    with pytest.raises(InputError) as err:
        load_sweep(path)
    assert err.value.field == "sweep.base"
    path = write_sweep(tmp_path, extra="n_lanes = 2")
    with pytest.raises(InputError) as err:
        expand_runs(load_sweep(path))
    assert err.value.path == str(tmp_path / "base.toml") and err.value.field == "single_road.n_lanes"


def test_runs_are_the_product_with_readable_ids(tmp_path):
    grid = '"single_road.feature_spacing_m" = [0.5, 3.0]\n"lc.eta_threshold" = [0.5, 1.0]'
    path = write_sweep(tmp_path, grid=grid, seeds="{start = 5, count = 3}")
    _, runs = expand_runs(load_sweep(path))
    assert len(runs) == 12 and len({r.run_id for r in runs}) == 12
    assert runs[0].run_id == "feature_spacing_m=0.5,eta_threshold=0.5,seed=5"
    assert runs[0].cfg.run.seed == 5 and runs[-1].cfg.run.seed == 7
    assert runs[-1].cfg.single_road.feature_spacing_m == 3.0 and runs[-1].cfg.lc.eta_threshold == 1.0
    # TOML's nested form of dotted keys is the same sweep.
    nested = write_sweep(tmp_path, grid="[sweep.grid.single_road]\nfeature_spacing_m = [0.5, 3.0]\n"
                                        "[sweep.grid.lc]\neta_threshold = [0.5, 1.0]",
                         seeds="{start = 5, count = 3}", name="nested.toml")
    assert [r.run_id for r in expand_runs(load_sweep(nested))[1]] == [r.run_id for r in runs]


def test_shipped_sweeps_are_valid():
    for name in ("fig7_single_road.toml", "fig8_9_crossroad_nf.toml", "fig10_11_crossroad_vf.toml"):
        spec = load_sweep(PROJECT / "experiments" / "sweeps" / name)
        _, runs = expand_runs(spec)
        assert len(runs) >= 1000 and "icp_da_lc" in runs[0].cfg.run.methods
    res = _cli(["sweep", str(PROJECT / "experiments/sweeps/fig8_9_crossroad_nf.toml"), "--out", "/nonexistent/x",
                "--dry-run"])
    assert res.returncode == 0 and "1600 runs" in res.stdout
    vf = expand_runs(load_sweep(PROJECT / "experiments/sweeps/fig10_11_crossroad_vf.toml"))[1]
    assert {r.cfg.crossroad.n_features for r in vf} == {20}  # Sec. V-B: Nf = 20 moving features
    assert {r.cfg.icp.feature_sigma_par for r in vf} == {0.01, 0.02, 0.05}  # vf / 100


def test_every_shipped_sweep_file_loads_and_expands():
    files = sorted((PROJECT / "experiments" / "sweeps").rglob("*.toml"))
    assert len(files) >= 10
    for path in files:  # a file that fails here fails for the user at `coloc sweep`
        _, runs = expand_runs(load_sweep(path))
        assert runs, path.name
    pf = expand_runs(load_sweep(PROJECT / "experiments/sweeps/fig7_single_road_pf.toml"))[1]
    assert {r.cfg.single_road.feature_spacing_m for r in pf} == {0.5, 3.0}
    assert {(r.cfg.pf.vehicle_particles, r.cfg.pf.feature_particles) for r in pf} == {(5000, 5000)}
    assert "icp_da_pf" in pf[0].cfg.run.methods


def test_paper_presets_switch_every_literal_reading_on():
    """experiments/sweeps/paper/: each Sec. V study with the paper's rules (README, departures), and
    otherwise the same grid and seeds as the project's sweep of the same name."""
    for path in sorted((PROJECT / "experiments" / "sweeps" / "paper").glob("*.toml")):
        spec, runs = expand_runs(load_sweep(path))
        ours_spec, ours = expand_runs(load_sweep(PROJECT / "experiments" / "sweeps" / path.name))
        assert len(runs) == len(ours), path.name
        for r in runs:
            kind = r.cfg.scenario.kind
            assert r.cfg.lc.pairing == "paper" and r.cfg.lc.new_feature_density == 1.0
            assert r.cfg.icp.stop_on == "vehicles_and_features"
            assert getattr(r.cfg, kind).start == "gnss_fix"
        for r in ours:
            assert r.cfg.lc.pairing == "gated" and r.cfg.icp.stop_on == "vehicles"
            assert getattr(r.cfg, r.cfg.scenario.kind).start == "fast_start"


def test_bad_sweep_through_the_cli_is_one_line(tmp_path):
    path = write_sweep(tmp_path, grid='"single_road.spacing" = [1.0]')
    res = _cli(["sweep", str(path), "--out", str(tmp_path / "out")])
    assert res.returncode == 2 and "Traceback" not in res.stderr and res.stderr.strip().count("\n") == 0
    assert "sweep.grid.single_road.spacing" in res.stderr and str(path) in res.stderr
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- a tiny sweep


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tiny")
    spec = write_sweep(tmp)
    out = tmp / "out"
    from experiments.sweep.run import run_sweep

    res = run_sweep(spec, out, workers=2, progress=False)  # raises with the failing run's message, if any
    assert (res.n_runs, res.computed, res.present) == (4, 4, 0)
    return spec, out


def test_tiny_sweep_outputs(tiny):
    spec, out = tiny
    runs = sorted(p.name for p in (out / "runs").iterdir())
    assert runs == [f"feature_spacing_m={df},seed={s}" for df in ("0.5", "3.0") for s in (1, 2)]
    table = pd.read_parquet(out / "sweep.parquet")
    assert len(table) == 4 * 2  # 4 runs x 2 methods
    assert list(table.columns[:5]) == ["run_id", "seed", "single_road.feature_spacing_m", "method", "rmse_pos_m"]
    assert table["single_road.feature_spacing_m"].dtype == "float64"
    known = table[table["method"] == "icp_known_da"]
    assert (known["correct_pct"] == 100.0).all() and table.loc[table["method"] == "gnss", "correct_pct"].isna().all()
    assert known["feature_rmse_pos_m"].notna().all()

    curves = pd.read_parquet(out / "curves.parquet")
    assert set(curves["curve"]) == {"time", "feature_time", "association", "overall", "feature_overall"}
    assert (curves["n_runs"] == 2).all()
    # The pooled RMSE equals the RMSE over the runs' estimates (mean of squares over runs and vehicles).
    est = pd.concat([pd.read_parquet(out / "runs" / r / "estimates.parquet") for r in runs
                     if r.startswith("feature_spacing_m=0.5")])
    for method, g in est.groupby("method"):
        ov = curves[(curves["curve"] == "overall") & (curves["method"] == method)
                    & (curves["single_road.feature_spacing_m"] == 0.5)]
        assert ov["rmse_pos_m"].item() == pytest.approx(((g["err_pos"] ** 2).mean()) ** 0.5)
        at = g[g["t"] == 10.0]
        tc = curves[(curves["curve"] == "time") & (curves["method"] == method) & (curves["x"] == 10.0)
                    & (curves["single_road.feature_spacing_m"] == 0.5)]
        assert tc["rmse_pos_m"].item() == pytest.approx(((at["err_pos"] ** 2).mean()) ** 0.5)
        assert tc["n_samples"].item() == len(at) == 4  # 2 vehicles x 2 runs
    html = (out / "report.html").read_text()
    assert "rmse_time.png" in html and "association.png" in html and "2 Monte Carlo runs per setting" in html
    assert (out / "figures" / "rmse_time.png").is_file()


def test_rerun_computes_nothing_and_writes_identical_files(tiny):
    spec, out = tiny
    before = {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*/summary.json")}
    data = {n: (out / n).read_bytes() for n in ("sweep.parquet", "curves.parquet")}
    assert main(["sweep", str(spec), "--out", str(out), "--quiet"]) == 0
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*/summary.json")} == before
    assert {n: (out / n).read_bytes() for n in data} == data
    html = (out / "report.html").read_text()
    assert main(["report", str(out)]) == 0  # `coloc report DIR` rebuilds a sweep's report from its files
    assert (out / "report.html").read_text() == html


def test_other_sweep_into_the_same_folder_is_refused(tiny):
    spec, out = tiny
    other = spec.parent / "other.toml"
    other.write_text(spec.read_text().replace("seeds = [1, 2]", "seeds = [1, 2, 3]"))
    res = _cli(["sweep", str(other), "--out", str(out)])
    assert res.returncode == 2 and "sweep.seeds" in res.stderr and "different sweep" in res.stderr
    assert len(list((out / "runs").iterdir())) == 4


def test_sweep_on_a_running_scheduler_gives_the_same_files(tiny, tmp_path):
    from dask.distributed import LocalCluster

    spec, ref = tiny
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        out = tmp_path / "out"
        assert main(["sweep", str(spec), "--out", str(out), "--scheduler", cluster.scheduler_address, "--quiet"]) == 0
    for name in ("sweep.parquet", "curves.parquet"):
        assert (out / name).read_bytes() == (ref / name).read_bytes(), name


def test_unreachable_scheduler_is_an_input_error(tmp_path):
    from experiments.sweep.run import run_sweep

    spec = write_sweep(tmp_path)
    with pytest.raises(InputError) as err:
        run_sweep(spec, tmp_path / "o", scheduler="tcp://127.0.0.1:9", progress=False, connect_timeout="1s")
    assert err.value.field == "--scheduler" and "cannot connect" in err.value.message
    assert not (tmp_path / "o").exists()  # nothing written before the scheduler answered


# --------------------------------------------------------------------------- resume after kill -9


def test_killed_sweep_resumes_with_every_run_once(tmp_path):
    # 8 runs of ~145 steps each on one worker: the sweep is killed after the first run lands.
    spec = write_sweep(tmp_path, seeds="{start = 1, count = 4}", extra="road_length_m = 1000.0", duration=3600.0)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "experiments.cli", "sweep", str(spec), "--out", str(out), "--workers", "1", "--quiet"]
    proc = subprocess.Popen(cmd, cwd=PROJECT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    runs_dir = out / "runs"
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            if runs_dir.is_dir() and any(not p.name.startswith(".") for p in runs_dir.iterdir()):
                break
            assert proc.poll() is None, "the sweep ended before any run landed"
            time.sleep(0.02)
        else:
            pytest.fail("no run folder appeared")
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the coloc process and its Dask workers
        proc.wait()
    done = {p.name: (p / "summary.json").stat().st_mtime_ns for p in runs_dir.iterdir() if not p.name.startswith(".")}
    assert 1 <= len(done) < 8
    assert not (out / "sweep.parquet").exists()
    # A killed run leaves a hidden partial folder when the kill lands mid-write; make sure there is one.
    (runs_dir / ".feature_spacing_m=3.0,seed=4.partial-999999").mkdir(exist_ok=True)

    res = subprocess.run(cmd, cwd=PROJECT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    names = sorted(p.name for p in runs_dir.iterdir())
    assert len(names) == 8 and not any(n.startswith(".") for n in names)  # each once, no partial folders
    assert all((runs_dir / n / "summary.json").is_file() for n in names)
    assert {n: (runs_dir / n / "summary.json").stat().st_mtime_ns for n in done} == done  # not recomputed
    assert f"{len(done)} already present" in res.stdout
    assert len(pd.read_parquet(out / "sweep.parquet")) == 16
    assert not [p for p in out.iterdir() if p.name.startswith(".") and p.name not in (".coloc-sweep.lock", MARKER)]


def test_sumo_sweep_runs_in_worker_processes(cross_net, tmp_path):
    """SUMO runs (libsumo: one simulation per process) in a sweep: traffic kept, no distance curve."""
    (tmp_path / "base.toml").write_text(f"""
[run]
name = "cross"
duration_s = 30.0
methods = ["gnss"]
[scenario]
kind = "sumo"
net_dir = "{cross_net}"
[motion]
sigma_cross = 0.1
""")
    spec = tmp_path / "sweep.toml"
    spec.write_text(SWEEP.format(seeds="[1, 2]", more="", grid='"scenario.control" = ["tlr", "vsr"]'))
    out = tmp_path / "out"
    from experiments.sweep.run import run_sweep

    assert run_sweep(spec, out, workers=2, progress=False).computed == 4
    table = pd.read_parquet(out / "sweep.parquet")
    assert len(table) == 4 and list(table["scenario.control"]) == ["tlr", "tlr", "vsr", "vsr"]
    assert set(pd.read_parquet(out / "curves.parquet")["curve"]) == {"time", "overall"}
    assert len(pd.read_parquet(out / "runs" / "control=vsr,seed=2" / "traffic.parquet")) > 0


# --------------------------------------------------------------------------- [infra] keys


INFRA_BASE = """
[run]
name = "cross_infra"
duration_s = {duration}
methods = {methods}
[scenario]
kind = "sumo"
net_dir = "{net}"
[motion]
sigma_cross = 0.1
{infra}
"""

INFRA_TABLE = """
[infra]
rsu_junctions = ["C"]
rsu_range_m = 80.0
"""


def write_infra_sweep(tmp: Path, net, grid='"infra.rsu_range_m" = [40.0, 120.0]', more="", infra=INFRA_TABLE,
                      methods='["gnss", "sme"]', duration=40.0) -> Path:
    (tmp / "base.toml").write_text(INFRA_BASE.format(duration=duration, net=net, infra=infra, methods=methods))
    path = tmp / "sweep.toml"
    path.write_text(SWEEP.format(seeds="[1]", more=more, grid=grid))
    return path


@pytest.mark.parametrize("kwargs, field, needle", [
    (dict(grid='"infra.range" = [40.0]'), "sweep.grid.infra.range", "keys of [infra]"),
    (dict(grid='"infra.rsu_range_m" = [40.0, -1.0]'), "sweep.grid.infra.rsu_range_m[1]", "positive"),
    (dict(grid='"infra.rsu_junctions" = [["C"], ["C", "X9"]]'), "sweep.grid.infra.rsu_junctions[1]", "X9"),
    (dict(grid='"infra.rsu_range_m" = [40.0]', infra="", methods='["gnss"]'), "sweep.grid.infra.rsu_range_m[0]",
     "no [infra] table"),
    (dict(grid='"infra.rsu_range_m" = [40.0]', infra="", methods='["gnss"]',
          more='[sweep.set]\n"infra.rsu_junctions" = ["C"]'), "sweep.set.infra.rsu_junctions", "no [infra] table"),
    (dict(more='[sweep.set]\n"infra.sme_max_vehicles" = 0'), "sweep.set.infra.sme_max_vehicles", ">= 1"),
])
def test_bad_infra_sweep_names_the_field(cross_net, tmp_path, kwargs, field, needle):
    path = write_infra_sweep(tmp_path, cross_net, **kwargs)
    with pytest.raises(InputError) as err:
        expand_runs(load_sweep(path))
    assert err.value.path == str(path) and err.value.field == field and needle in err.value.message


def test_infra_sweep_runs_and_reports_within_coverage(cross_net, tmp_path):
    """Two short SUMO runs sweeping the RSU range: each run's saved config is the resolved one with its
    range, and sweep.parquet has the within-coverage columns (more covered vehicle-steps at 120 m)."""
    import tomllib

    from experiments.sweep.run import run_sweep

    spec = write_infra_sweep(tmp_path, cross_net)
    out = tmp_path / "out"
    assert run_sweep(spec, out, workers=1, progress=False, write_report=False).computed == 2
    for r in (40.0, 120.0):
        saved = tomllib.loads((out / "runs" / f"rsu_range_m={r},seed=1" / "config.toml").read_text())
        assert saved["infra"]["rsu_range_m"] == r and saved["infra"]["rsu_junctions"] == ["C"]
        assert saved["infra"]["fg_window_steps"] == 8  # fully resolved: defaults spelled out
    table = pd.read_parquet(out / "sweep.parquet")
    assert list(table["infra.rsu_range_m"]) == [40.0, 40.0, 120.0, 120.0]
    assert list(table["method"]) == ["gnss", "sme"] * 2
    assert {"covered_rmse_pos_m", "covered_p95_pos_m", "covered_n"} <= set(table.columns)
    n = table.groupby("infra.rsu_range_m")["covered_n"].agg(["min", "max"])
    assert (n["min"] == n["max"]).all() and 0 < n.loc[40.0, "min"] < n.loc[120.0, "min"]  # same rows per method
    assert table["covered_rmse_pos_m"].notna().all()


def test_shipped_infra_range_sweep_is_valid():
    spec = load_sweep(PROJECT / "experiments" / "sweeps" / "infra_range.toml")
    _, runs = expand_runs(spec)
    assert len(runs) == 9 and runs[0].run_id == "rsu_range_m=40.0,seed=1"
    assert sorted({r.cfg.infra.rsu_range_m for r in runs}) == [40.0, 70.0, 100.0]
    assert {r.cfg.run.duration_s for r in runs} == {300.0} and {r.seed for r in runs} == {1, 2, 3}
    assert {r.cfg.infra.rsu_junctions for r in runs} == {("JP1", "JP2", "JP3")}
    assert set(runs[0].cfg.run.methods) == {"gnss", "rsu_bp", "sme", "fg_topology_new"}
