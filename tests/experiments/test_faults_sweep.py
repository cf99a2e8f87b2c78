"""Faults of sweeps and worker processes: a sweep resumed after its inputs changed, an estimator
worker's error, more sweep workers than runs or cores, net folders that are not net folders.

The bad inputs among them (one line, exit 2, nothing written) are also cases of
``tests/experiments/test_bad_input.py``; here the behaviour around them: what ``--force`` recomputes,
which runs a changed file concerns, what reaches the user from a worker process.
"""

from __future__ import annotations

import dataclasses
import json
import pickle
import shutil
import time
from pathlib import Path

import pytest

from couplers.errors import InputError, recording_reads
from couplers.publish import MARKER, read_manifest, sha256_file
from experiments.cli import main
from filetree import snapshot
from experiments.sweep.run import (INPUTS_FILE, _check_inputs, _inputs_text, cap_workers, expand_runs, load_sweep,
                               run_sweep, sweep_inputs, usable_cores)

BASE = """
[run]
name = "base"
methods = ["gnss"]
duration_s = 12.0

[scenario]
kind = "single_road"

[single_road]
headway_m = {headway}
"""

SWEEP = """
[sweep]
name = "faults"
base = "base.toml"
seeds = [1, 2]
"""


# --------------------------------------------------------------------------- resume after a change


def test_resume_after_a_config_change_is_refused_and_force_recomputes_the_runs_that_read_it(tmp_path):
    """A real sweep (single road, no SUMO): killed after its first run, its base config edited."""
    (tmp_path / "base.toml").write_text(BASE.format(headway=20.0))
    spec = tmp_path / "sweep.toml"
    spec.write_text(SWEEP)
    out = tmp_path / "out"
    res = run_sweep(spec, out, workers=100, progress=False)
    # --workers 100 for 2 runs: at most the runs to compute and the usable cores
    assert (res.computed, res.workers, res.workers_asked) == (2, min(2, usable_cores()), 100)
    record = json.loads((out / INPUTS_FILE).read_text())
    assert list(record["files"]) == [str((tmp_path / "base.toml").resolve())]  # no net folder on a single road
    assert record["runs"] == {r: list(record["files"]) for r in ("seed=1", "seed=2")}
    shutil.rmtree(out / "runs" / "seed=2")  # as if killed after the first run
    kept = (out / "runs" / "seed=1" / "summary.json").stat().st_mtime_ns
    (tmp_path / "base.toml").write_text(BASE.format(headway=25.0))
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}

    with pytest.raises(InputError) as err:
        run_sweep(spec, out, workers=1, progress=False)
    assert err.value.path == str((tmp_path / "base.toml").resolve()) and err.value.field is None
    assert "changed since the sweep" in err.value.message and "seed=1" in err.value.message
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before  # nothing written
    assert (out / "runs" / "seed=1" / "summary.json").stat().st_mtime_ns == kept

    res = run_sweep(spec, out, workers=1, progress=False, force=True)
    assert (res.computed, res.present, res.recomputed) == (2, 0, 1)
    assert (out / "runs" / "seed=1" / "summary.json").stat().st_mtime_ns != kept
    cfg = (out / "runs" / "seed=1" / "config.toml").read_text()
    assert "headway_m = 25.0" in cfg
    assert "headway_m = 25.0" in (out / "runs" / "seed=2" / "config.toml").read_text()
    assert not [p for p in (out / "runs").iterdir() if p.name.startswith(".")]  # no leftover of the old run
    # the record and sweep.toml are those of now: a plain rerun computes nothing
    res = run_sweep(spec, out, workers=1, progress=False)
    assert (res.computed, res.present, res.recomputed) == (0, 2, 0)


def _two_net_sweep(tmp: Path, cross_net: Path) -> Path:
    for name in ("netA", "netB"):
        shutil.copytree(cross_net, tmp / name)
    (tmp / "cfg.toml").write_text("""
[run]
name = "two"
seed = 1
duration_s = 30.0
methods = ["gnss"]

[scenario]
kind = "sumo"
net_dir = "netA"
control = "tlr"

[report]
track_area = "3"
""")
    spec = tmp / "sweep.toml"
    spec.write_text('[sweep]\nname = "two"\nbase = "cfg.toml"\nseeds = [1, 2]\n\n'
                    '[sweep.grid]\n"scenario.net_dir" = ["netA", "netB"]\n')
    return spec


def test_the_sweeps_own_files_are_in_its_manifest_and_a_users_file_of_such_a_name_is_kept(tmp_path):
    """sweep.toml, inputs.json, the tables and the report are listed in the sweep folder's manifest with
    their sha256; a file of such a name coloc cannot prove it wrote is refused before any run, and with
    --force kept aside, never replaced."""
    (tmp_path / "base.toml").write_text(BASE.format(headway=20.0))
    spec = tmp_path / "sweep.toml"
    spec.write_text(SWEEP)
    out = tmp_path / "out"
    run_sweep(spec, out, workers=1, progress=False)
    files = read_manifest(out)["files"]
    top = sorted(p.name for p in out.iterdir() if p.is_file() and p.name != MARKER)
    assert {"sweep.toml", INPUTS_FILE, "sweep.parquet", "curves.parquet", "report.html"} <= set(top)
    assert all(files[name] == sha256_file(out / name) for name in top)  # every top-level file is coloc's

    (out / "sweep.parquet").write_bytes(b"my own table")  # the user's now: its hash is not coloc's
    shutil.rmtree(out / "runs" / "seed=2")  # a run left to compute: it must not start
    before = snapshot(out)
    with pytest.raises(InputError) as err:
        run_sweep(spec, out, workers=1, progress=False)
    assert Path(err.value.path).name == "sweep.parquet" and "cannot prove it wrote it" in err.value.message
    assert snapshot(out) == before

    res = run_sweep(spec, out, workers=1, progress=False, force=True)
    assert res.computed == 1 and (out / "sweep.parquet.before-coloc").read_bytes() == b"my own table"
    assert read_manifest(out)["files"]["sweep.parquet"] == sha256_file(out / "sweep.parquet")
    assert run_sweep(spec, out, workers=1, progress=False).present == 2  # coloc's again: no --force needed

    # a sweep folder of an older coloc (its manifest lists none of these files): --force once, then none
    (out / MARKER).write_text('{"kind": "sweep", "files": {}}\n')
    with pytest.raises(InputError) as err:
        run_sweep(spec, out, workers=1, progress=False)
    assert "--force" in err.value.message
    run_sweep(spec, out, workers=1, progress=False, force=True)
    assert set(top) <= set(read_manifest(out)["files"])
    assert run_sweep(spec, out, workers=1, progress=False).present == 2


def test_a_changed_net_concerns_only_the_runs_on_that_net(tmp_path, cross_net):
    spec_path = _two_net_sweep(tmp_path, cross_net)
    spec = load_sweep(spec_path)
    with recording_reads() as configs:
        _, runs = expand_runs(spec)
    inputs = sweep_inputs(spec, runs, configs)
    by_net = {r.run_id: Path(r.cfg.scenario.net_dir).name for r in runs}
    assert sorted(by_net.values()) == ["netA", "netA", "netB", "netB"]
    for run in runs:  # each run reads its own net's files and the config, not the other net's
        files = inputs["runs"][run.run_id]
        other = "netB" if by_net[run.run_id] == "netA" else "netA"
        assert str((tmp_path / "cfg.toml").resolve()) in files
        assert any(f.endswith(f"{by_net[run.run_id]}/zones.geojson") for f in files)
        assert not any(f"/{other}/" in f for f in files)
    out = tmp_path / "out"
    out.mkdir()
    (out / INPUTS_FILE).write_text(_inputs_text(inputs))
    for run in runs:  # every run finished
        (out / "runs" / run.run_id).mkdir(parents=True)
        (out / "runs" / run.run_id / "summary.json").write_text("{}\n")
    assert _check_inputs(out, inputs, runs, force=False) == (frozenset(), ())

    zones = tmp_path / "netB" / "zones.geojson"
    zones.write_text(zones.read_text().replace('"sigma_p": 3.0', '"sigma_p": 30.0'))
    with recording_reads() as configs:
        _, runs = expand_runs(spec)
    now = sweep_inputs(spec, runs, configs)
    with pytest.raises(InputError) as err:
        _check_inputs(out, now, runs, force=False)
    assert err.value.path == str(zones.resolve()) and "2 finished run(s)" in err.value.message
    redo, ignore = _check_inputs(out, now, runs, force=True)
    assert redo == {r for r, net in by_net.items() if net == "netB"} and ignore == ()
    # an unfinished run is computed with the inputs of now: nothing to refuse for it
    for run_id in redo:
        (out / "runs" / run_id / "summary.json").unlink()
    assert _check_inputs(out, now, runs, force=False) == (frozenset(), ())


def test_a_damaged_inputs_record_is_named(tmp_path):
    (tmp_path / "base.toml").write_text(BASE.format(headway=20.0))
    spec = tmp_path / "sweep.toml"
    spec.write_text(SWEEP)
    out = tmp_path / "out"
    out.mkdir()
    (out / INPUTS_FILE).write_text("{not json")
    with pytest.raises(InputError) as err:
        run_sweep(spec, out, workers=1, progress=False, force=True)
    assert err.value.path == str(out / INPUTS_FILE) and "damaged" in err.value.message


# --------------------------------------------------------------------------- sweep workers


def test_sweep_workers_are_capped_by_the_runs_to_compute_and_the_cores():
    cores = usable_cores()
    assert cap_workers(100, 4) == min(4, cores)
    assert cap_workers(100, 1) == 1
    assert cap_workers(1, 50) == 1
    assert cap_workers(3, 0) == 1  # nothing to compute: no cluster is started anyway
    assert cap_workers(10**6, 10**6) == cores


# --------------------------------------------------------------------------- errors in estimator workers


def test_worker_errors_travel_as_plain_values_and_an_input_error_stays_one():
    from experiments.pipeline import EstimatorWorkerError, raise_worker_error, worker_error

    try:
        raise InputError("/x/cfg.toml", "lc.eta_threshold", "must be > 0")
    except InputError as exc:
        payload = pickle.loads(pickle.dumps(worker_error(exc)))
    with pytest.raises(InputError) as err:
        raise_worker_error("estimator worker 0 (icp_da_lc)", payload)
    assert (err.value.path, err.value.field, err.value.message) == ("/x/cfg.toml", "lc.eta_threshold", "must be > 0")
    try:
        raise ValueError("two\nlines")
    except ValueError as exc:
        payload = pickle.loads(pickle.dumps(worker_error(exc)))
    with pytest.raises(EstimatorWorkerError) as err:
        raise_worker_error("estimator worker 1 (icp_da_pf)", payload)
    assert str(err.value) == "estimator worker 1 (icp_da_pf) failed: ValueError: two lines"
    assert "Traceback" in err.value.worker_traceback and "ValueError: two" in err.value.worker_traceback


def _pool_params():
    from experiments.config import load_config
    from experiments.runner import method_params

    cfg = load_config(Path(__file__).resolve().parents[2] / "experiments" / "single_road.toml")
    return method_params(cfg)


def test_a_worker_that_failed_is_reported_by_its_error_not_by_the_broken_pipe():
    """rsu_bp without [infra]: its worker fails building it and ends; the runner learns why when it waits
    for the worker, and when it sends it the next batch (the pipe is broken by then)."""
    from experiments.pipeline import EstimatorPool, EstimatorWorkerError

    params = dataclasses.replace(_pool_params(), infra=None)
    expected = ("estimator worker 0 (rsu_bp) failed: ValueError: an infrastructure method needs "
                "MethodParams.infra (config [infra])")
    with EstimatorPool(["rsu_bp"], params, 1) as pool:
        with pytest.raises(EstimatorWorkerError) as err:
            pool.wait_ready()
        assert str(err.value) == expected
    with EstimatorPool(["rsu_bp"], params, 1) as pool:
        pool._procs[0].join(timeout=60)  # the worker has sent its error and ended
        assert not pool._procs[0].is_alive()
        with pytest.raises(EstimatorWorkerError) as err:
            for _ in range(100):  # the first sends may still fit in the pipe's buffer
                pool._send(0, [b"x" * 65536])
                time.sleep(0.01)
        assert str(err.value) == expected


def _run_with_a_failing_worker(tmp_path, monkeypatch, capsys, debug: str | None):
    """``coloc run --workers 1`` where the icp_known_da worker gets no [icp] parameters: it builds, then
    fails at its first step (an AttributeError in the worker process)."""
    import experiments.runner as runner

    original = runner.method_params
    monkeypatch.setattr(runner, "method_params", lambda cfg: dataclasses.replace(original(cfg), icp=None))
    if debug is None:
        monkeypatch.delenv("COLOC_DEBUG", raising=False)
    else:
        monkeypatch.setenv("COLOC_DEBUG", debug)
    (tmp_path / "base.toml").write_text(BASE.format(headway=20.0).replace(
        'methods = ["gnss"]', 'methods = ["gnss", "icp_known_da"]').replace("12.0", "120.0"))
    capsys.readouterr()
    rc = main(["run", str(tmp_path / "base.toml"), "--out", str(tmp_path / "o"), "--quiet", "--workers", "1"])
    return rc, capsys.readouterr().err


def test_a_worker_error_is_one_line_with_its_type_and_message(tmp_path, monkeypatch, capsys):
    rc, err = _run_with_a_failing_worker(tmp_path, monkeypatch, capsys, None)
    assert rc == 1
    lines = err.strip().splitlines()
    assert lines == ["coloc: error: estimator worker 0 (icp_known_da) failed: AttributeError: 'NoneType' object "
                     "has no attribute 'motion'"], err
    assert not (tmp_path / "o").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_coloc_debug_adds_the_workers_traceback(tmp_path, monkeypatch, capsys):
    rc, err = _run_with_a_failing_worker(tmp_path, monkeypatch, capsys, "1")
    assert rc == 1
    assert err.startswith("coloc: error: estimator worker 0 (icp_known_da) failed: AttributeError")
    assert "Traceback (most recent call last)" in err and "icp_known_da_step" in err


# --------------------------------------------------------------------------- net check on what is not a net folder


@pytest.mark.parametrize("what, needle", [("file", "is a file, not a net folder"),
                                          ("folder", "is not a net folder: it has no scenario.toml")])
def test_net_check_says_what_is_there(tmp_path, capsys, what, needle):
    target = tmp_path / "thing"
    if what == "file":
        target.write_text("x\n")
    else:
        target.mkdir()
        (target / "readme.txt").write_text("x\n")
    capsys.readouterr()
    assert main(["net", "check", str(target)]) == 1
    out = capsys.readouterr().out
    assert out.strip() == f"{target}: {needle}" + (" (a folder with a scenario.toml)" if what == "file" else "")
