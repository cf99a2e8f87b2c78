"""`coloc run --workers N` (experiments.pipeline): the estimators in worker processes write the same
files, byte for byte, as the serial loop; a failing worker fails the run cleanly."""

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments.cli import main
from experiments.config import load_config
from experiments.pipeline import EstimatorPool, EstimatorWorkerError, assign_methods
from experiments.runner import method_params

PROJECT = Path(__file__).resolve().parents[2]

CONFIG = """
[run]
name = "pipeline_test"
seed = 3
duration_s = 90
methods = ["gnss", "icp_known_da", "icp_da_lc"]

[scenario]
kind = "sumo"
net_dir = "{net}"
control = "tlr"

[report]
figures = false
"""

SAME = ("estimates.parquet", "association.parquet", "features.parquet", "traffic.parquet", "config.toml")


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_methods_go_where_their_cost_balances():
    """Light methods stay beside SUMO; the others go heaviest first to the least loaded process, the
    runner's counting the frame synthesis (FRAME_COST); only workers with a method exist."""
    methods = ["gnss", "icp_known_da", "icp_da_lc"]
    assert assign_methods(methods, 1) == ([0, 1], [[2]])  # LC (1.3) in the worker, known DA beside SUMO
    assert assign_methods(methods, 2) == ([0], [[2], [1]])
    assert assign_methods(methods, 8) == ([0], [[2], [1]])
    assert assign_methods(["gnss"], 3) == ([0], [])
    assert assign_methods(["icp_known_da"], 1) == ([], [[0]])
    assert assign_methods(["icp_known_da", "icp_da_pf", "icp_da_lc"], 1) == ([0, 2], [[1]])
    local, groups = assign_methods(["icp_known_da"] * 7, 3)
    assert sorted(local + [i for g in groups for i in g]) == list(range(7)) and all(groups)


@pytest.mark.parametrize("workers", [1, 3])
def test_workers_write_the_serial_files_byte_for_byte(cross_net, tmp_path, workers):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(CONFIG.format(net=cross_net))
    assert main(["run", str(cfg), "--out", str(tmp_path / "serial"), "--quiet"]) == 0
    assert main(["run", str(cfg), "--out", str(tmp_path / "pooled"), "--quiet", "--workers", str(workers)]) == 0
    for name in SAME:
        assert _digest(tmp_path / "serial" / name) == _digest(tmp_path / "pooled" / name), name
    a = json.loads((tmp_path / "serial" / "summary.json").read_text())
    b = json.loads((tmp_path / "pooled" / "summary.json").read_text())
    for block in (a, b):  # the only fields that may differ: seconds measured
        block.pop("wall_seconds")
        for method in block["methods"].values():
            assert method.pop("seconds") > 0.0
    assert a == b
    # the association is exercised (not an empty run): LC paired rows with tracks
    assert a["association"]["icp_da_lc"]["correct"] > 0


def test_failing_worker_raises_and_ends_every_worker(cross_net, tmp_path):
    cfg_path = tmp_path / "cfg.toml"
    cfg_path.write_text(CONFIG.format(net=cross_net))
    cfg = load_config(cfg_path, {})
    pool = EstimatorPool(["gnss", "no_such_method"], method_params(cfg), 2)
    with pytest.raises(EstimatorWorkerError, match="no_such_method"):
        pool.wait_ready()
    pool.close()
    assert not any(p.is_alive() for p in pool._procs)


def test_light_methods_step_in_the_runners_process(cross_net, tmp_path):
    """GNSS (Method.light) is stepped beside the frame source, the others in the workers when there are
    enough of them; a run of light methods alone starts no worker."""
    cfg_path = tmp_path / "cfg.toml"
    cfg_path.write_text(CONFIG.format(net=cross_net))
    params = method_params(load_config(cfg_path, {}))
    pool = EstimatorPool(["icp_known_da", "gnss", "icp_da_lc"], params, 2)
    try:
        assert pool.local == [1] and pool.groups == [[2], [0]] and len(pool._procs) == 2
    finally:
        pool.close()
    pool = EstimatorPool(["gnss"], params, 3)
    assert pool.groups == [] and pool._procs == [] and pool.local == [0]
    pool.close()


def test_negative_workers_is_one_clear_line(cross_net, tmp_path):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(CONFIG.format(net=cross_net))
    res = subprocess.run([sys.executable, "-m", "experiments.cli", "run", str(cfg), "--out", str(tmp_path / "o"),
                          "--workers", "-1"], cwd=PROJECT, capture_output=True, text=True)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "--workers" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_workers_draw_the_same_figures(cross_net, tmp_path):
    """With --workers the end-of-run report draws its figures in two processes (on two cores): the same PNG bytes."""
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(CONFIG.format(net=cross_net).replace("figures = false", "figures = true")
                   .replace("duration_s = 90", "duration_s = 60"))
    assert main(["run", str(cfg), "--out", str(tmp_path / "serial"), "--quiet", "--methods", "gnss"]) == 0
    assert main(["run", str(cfg), "--out", str(tmp_path / "pooled"), "--quiet", "--methods", "gnss",
                 "--workers", "1"]) == 0
    serial = sorted(p.name for p in (tmp_path / "serial" / "figures").iterdir())
    assert serial and serial == sorted(p.name for p in (tmp_path / "pooled" / "figures").iterdir())
    for name in serial:
        assert _digest(tmp_path / "serial" / "figures" / name) == _digest(tmp_path / "pooled" / "figures" / name), name


def test_a_batch_gives_the_frame_by_frame_estimates(cross_net, tmp_path):
    """step_batch (each estimator through the batch before the next) against the frame-by-frame loop
    (every estimator on a frame before the next frame): the same estimates, bit for bit."""
    from experiments.pipeline import step_batch
    from experiments.runner import build_estimators, frame_source
    from coloc.methods.registry import METHODS

    cfg_path = tmp_path / "cfg.toml"
    cfg_path.write_text(CONFIG.format(net=cross_net).replace("duration_s = 90", "duration_s = 40"))
    cfg = load_config(cfg_path, {})
    with frame_source(cfg) as source:
        pairs = [(f.without_truth(), f.truth.v2f_feature) for f in source.frames()]
    batched, single = build_estimators(cfg), build_estimators(cfg)
    known = [METHODS[e.name].known_association for e in batched]
    out = step_batch(batched, known, pairs)
    assert sum(p[0].v2f_owner.size for p in pairs) > 0
    for f, (blind, association) in enumerate(pairs):
        for j, (est, told) in enumerate(zip(single, known)):
            want = est.step_with_association(blind, association) if told else est.step(blind)
            got = out[f][j].estimate
            for name in ("mean", "cov", "feature_mean", "feature_cov", "feature_track_ids", "v2f_assignment"):
                a, b = getattr(got, name), getattr(want, name)
                assert (a is None and b is None) or np.asarray(a).tobytes() == np.asarray(b).tobytes(), (f, j, name)
