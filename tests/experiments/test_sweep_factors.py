"""One factor at a time (``[sweep.factors]``), per-zone pooled accuracy (zones.parquet), the V2V degree
(summary.json ``v2v``, v2v.parquet) and the study figures of the sweep report."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.sparse as sp

from couplers.errors import InputError
from experiments.sweep.run import expand_runs, load_sweep, run_sweep
from experiments.sweep.zones import ERR_BIN_M, p95_from_histogram, zone_partials

PROJECT = Path(__file__).resolve().parents[2]

BASE = """
[run]
name = "base"
methods = ["gnss", "icp_known_da", "icp_da_lc"]
duration_s = 12.0

[scenario]
kind = "single_road"
"""

SWEEP = """
[sweep]
name = "oat"
base = "base.toml"
seeds = [1, 2]
{grid}

[sweep.factors]
{factors}
"""

FACTORS = """
eta_threshold = [{label = "0.5", preset = true}, {label = "1", set = {"lc.eta_threshold" = 1.0}}]
spacing = [{label = "0.5", set = {"single_road.feature_spacing_m" = 0.5}}, {label = "6", set = {"single_road.feature_spacing_m" = 6.0}}]
"""


def write(tmp: Path, factors: str = FACTORS, grid: str = "") -> Path:
    (tmp / "base.toml").write_text(BASE)
    path = tmp / "sweep.toml"
    path.write_text(SWEEP.format(factors=factors, grid=grid))
    return path


# --------------------------------------------------------------------------- the spec


def test_runs_are_the_preset_plus_every_other_level(tmp_path):
    path = write(tmp_path, grid='[sweep.grid]\n"lc.detection_probability" = [0.9, 0.95]')
    base, runs = expand_runs(load_sweep(path))
    # 2 grid values x (preset + 1 eta level + 2 spacing levels) x 2 seeds
    assert len(runs) == 2 * 4 * 2 and len({r.run_id for r in runs}) == len(runs)
    ids = [r.run_id for r in runs if r.seed == 1][:4]
    assert ids == ["detection_probability=0.9,preset,seed=1", "detection_probability=0.9,eta_threshold=1,seed=1",
                   "detection_probability=0.9,spacing=0.5,seed=1", "detection_probability=0.9,spacing=6,seed=1"]
    by_id = {r.run_id: r.cfg for r in runs}
    preset = by_id["detection_probability=0.9,preset,seed=1"]
    assert preset.lc.eta_threshold == base.lc.eta_threshold
    eta = by_id["detection_probability=0.95,eta_threshold=1,seed=2"]
    assert eta.lc.eta_threshold == 1.0 and eta.lc.detection_probability == 0.95
    assert eta.single_road.feature_spacing_m == preset.single_road.feature_spacing_m  # one factor at a time
    assert by_id["detection_probability=0.9,spacing=6,seed=1"].single_road.feature_spacing_m == 6.0


def test_star_key_sets_every_sensor_and_a_level_may_take_another_base():
    spec = load_sweep(PROJECT / "experiments" / "sweeps" / "arterial_sensing.toml")
    _, runs = expand_runs(spec)
    # controls x (preset + 9 levels) x seeds, and the two pedestrian levels in TLR only, as the file's header says
    assert len(runs) == 2 * 10 * 5 + 2 * 5
    ped = [r for r in runs if "pedestrians=" in r.run_id]
    assert len(ped) == 10 and all(r.cfg.scenario.control == "tlr" for r in ped)
    assert all(r.cfg.features.pedestrians == ("=on," in r.run_id) for r in ped)
    cfg = {r.run_id: r.cfg for r in runs if r.seed == 1}
    pd07 = cfg["control=vsr,detection_probability=0.7,seed=1"]
    assert pd07.scenario.control == "vsr"
    assert [(s.pd_near, s.pd_far) for s in pd07.perception.sensors] == [(0.7, 0.7), (0.7, 0.7)]
    preset = cfg["control=tlr,preset,seed=1"]
    assert [(s.pd_near, s.pd_far) for s in preset.perception.sensors] == [(0.95, 0.7), (0.95, 0.7)]
    clutter = cfg["control=tlr,clutter_per_scan=5,seed=1"]
    assert [s.clutter_per_scan for s in clutter.perception.sensors] == [5.0, 5.0]
    assert clutter.lc.clutter_intensity == pytest.approx(5 * preset.lc.clutter_intensity)
    ideal = cfg["control=vsr,idealised=idealised,seed=1"]
    assert ideal.perception is None and ideal.gnss_error is None and ideal.scenario.control == "vsr"
    assert cfg["control=tlr,gnss_tau_s=0,seed=1"].gnss_error.tau_s == 0.0


@pytest.mark.parametrize("factors, field", [
    ('x = [{label = "a", preset = true}, {label = "b", preset = true}]', "sweep.factors.x"),
    ('x = [{label = "a", preset = true, set = {"lc.eta_threshold" = 1.0}}]', "sweep.factors.x[0]"),
    ('x = [{label = "a"}]', "sweep.factors.x[0]"),
    ('x = [{label = "a", set = {"lc.eta" = 1.0}}]', "sweep.factors.x[0].set.lc.eta"),
    ('x = [{label = "a", set = {"lc.eta_threshold" = 1.0}}, {label = "a", set = {"lc.eta_threshold" = 0.2}}]',
     "sweep.factors.x[1].label"),
    ('x = [{label = "a", set = {"lc.eta_threshold" = 1.0}, colour = "red"}]', "sweep.factors.x[0].colour"),
    ('x = [{label = "a", base = "missing.toml"}]', "sweep.factors.x[0].base"),
    ('x = []', "sweep.factors.x"),
    ('preset = [{label = "a", set = {"lc.eta_threshold" = 1.0}}]', "sweep.factors.preset"),
    ('x = [{label = "a", set = {"perception.sensors[*].pd_far" = 0.5}}]', "sweep.factors.x.set.perception.sensors[*].pd_far"),
    ('x = [{label = "a", set = {"lc.eta_threshold" = 7.0}}]', "sweep.factors.x"),
    ('feature_spacing_m = [{label = "a", set = {"lc.eta_threshold" = 1.0}}]', "sweep.factors.feature_spacing_m"),
    ('x = [{label = "a", set = {"single_road.feature_spacing_m" = 1.0}}]',
     "sweep.factors.x[0].set.single_road.feature_spacing_m"),
])
def test_bad_factors_name_the_field(tmp_path, factors, field):
    path = write(tmp_path, factors=factors, grid='[sweep.grid]\n"single_road.feature_spacing_m" = [0.5, 3.0]')
    with pytest.raises(InputError) as err:
        expand_runs(load_sweep(path))
    assert err.value.path == str(path) and err.value.field == field


# --------------------------------------------------------------------------- zones and degree


def test_pooled_p95_from_histograms_is_the_exact_quantile_to_one_bin():
    rng = np.random.default_rng(7)
    runs = [pd.DataFrame({"method": "m", "zone": rng.choice(["A", "B"], 5000),
                          "err_pos": rng.gamma(2.0, 1.5, 5000) * (1 + 30 * (rng.random(5000) < 0.01))})
            for _ in range(3)]
    parts = [zone_partials(r) for r in runs]
    hist = pd.concat([h for _, h in parts]).groupby(["zone", "bin"])["count"].sum()
    pooled = pd.concat(runs)
    for zone in ("A", "B", "all"):
        err = pooled["err_pos"].to_numpy() if zone == "all" else pooled.loc[pooled["zone"] == zone, "err_pos"].to_numpy()
        h = hist.loc[zone]
        got = p95_from_histogram(h.index.to_numpy(), h.to_numpy(), err.max())
        exact = np.quantile(err, 0.95, method="inverted_cdf")
        assert exact <= got <= exact + ERR_BIN_M + 1e-12
        sums = pd.concat([s for s, _ in parts]).groupby("zone")[["sse_pos", "n"]].sum().loc[zone]
        assert np.sqrt(sums["sse_pos"] / sums["n"]) == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-12)
    # beyond 100 m the exact maximum is reported
    big = pd.DataFrame({"method": "m", "zone": "A", "err_pos": [1.0] * 10 + [150.0, 250.0]})
    s, h = zone_partials(big)
    hh = h[h["zone"] == "A"]
    assert p95_from_histogram(hh["bin"].to_numpy(), hh["count"].to_numpy(), 250.0) == 250.0


def test_v2v_degree_tally_counts_every_vehicle_step():
    from coloc.core.frame import empty_frame
    from experiments.runner import V2vTally

    rng = np.random.default_rng(3)
    tally, direct = V2vTally(), []
    for n in (0, 5, 12, 3):
        a = np.triu(rng.random((n, n)) < 0.3, 1)
        adj = sp.csr_matrix(a | a.T)
        frame = dataclasses.replace(empty_frame(0.0, 0.75), vehicle_ids=np.arange(n).astype(str), neighbors=adj)
        tally.add(frame)
        direct += list(np.asarray(adj.sum(axis=1)).ravel())
    s = tally.summary()
    assert s["vehicle_steps"] == len(direct) == 20
    assert s["degree_counts"] == np.bincount(direct).tolist()
    assert s["mean_degree"] == pytest.approx(np.mean(direct))
    assert s["isolated_share"] == pytest.approx(np.mean(np.asarray(direct) == 0))


# --------------------------------------------------------------------------- a tiny factor sweep


@pytest.fixture(scope="module")
def oat(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("oat")
    path = write(tmp)
    out = tmp / "out"
    res = run_sweep(path, out, workers=2, progress=False)
    assert (res.n_runs, res.computed) == (8, 8)
    return out


def test_factor_sweep_outputs(oat):
    out = oat
    assert sorted(p.name for p in (out / "runs").iterdir())[:2] == ["eta_threshold=1,seed=1", "eta_threshold=1,seed=2"]
    table = pd.read_parquet(out / "sweep.parquet")
    assert list(table.columns[:4]) == ["run_id", "seed", "factor", "level"]
    assert table.groupby(["factor", "level"]).size().to_dict() == {
        ("eta_threshold", "1"): 6, ("preset", "preset"): 6, ("spacing", "0.5"): 6, ("spacing", "6"): 6}
    zones = pd.read_parquet(out / "zones.parquet")
    # the zone rows equal the pooled estimates of the setting's runs
    est = pd.concat(pd.read_parquet(out / "runs" / f"spacing=6,seed={s}" / "estimates.parquet") for s in (1, 2))
    for method, g in est.groupby("method"):
        row = zones[(zones["factor"] == "spacing") & (zones["level"] == "6") & (zones["method"] == method)
                    & (zones["zone"] == "all")]
        assert row["n_samples"].item() == len(g) and row["n_runs"].item() == 2
        assert row["rmse_pos_m"].item() == pytest.approx(np.sqrt(np.mean(g["err_pos"] ** 2)), rel=1e-12)
        exact = np.quantile(g["err_pos"], 0.95, method="inverted_cdf")
        assert exact <= row["p95_pos_m"].item() <= exact + ERR_BIN_M + 1e-12
    v2v = pd.read_parquet(out / "v2v.parquet")
    summary = json.loads((out / "runs" / "preset,seed=1" / "summary.json").read_text())
    pre = v2v[(v2v["factor"] == "preset") & (v2v["level"] == "preset")]
    assert pre["vehicle_steps"].sum() == 2 * summary["v2v"]["vehicle_steps"] > 0  # both seeds: the same 2 vehicles
    html = (out / "report.html").read_text()
    for fig in ("factors_rmse_zone.png", "factors_p95_zone.png", "factors_gap.png", "factors_association.png"):
        assert fig in html and (out / "figures" / fig).is_file()
    assert "rmse_time.png" not in html  # the Sec. V curves would mix the factors' levels


def test_factor_sweep_rerun_writes_identical_files(oat):
    before = {p.name: p.read_bytes() for p in oat.glob("*.parquet")}
    res = run_sweep(oat.parent / "sweep.toml", oat, workers=1, progress=False)
    assert res.computed == 0
    assert {p.name: p.read_bytes() for p in oat.glob("*.parquet")} == before


# --------------------------------------------------------------------------- the penetration figures


def test_penetration_sweep_draws_gain_by_zone_and_the_v2v_degree(cross_net, tmp_path):
    """A SUMO sweep over the equipped share (nested sets) and the control: zones.parquet has the net's
    zones, the V2V links only grow with the share, the report draws the gain by zone, the degree and
    the TLR - VSR table."""
    (tmp_path / "base.toml").write_text(f"""
[run]
name = "pen"
duration_s = 60.0
methods = ["gnss", "icp_known_da", "icp_da_lc"]
[scenario]
kind = "sumo"
net_dir = "{cross_net}"
[motion]
sigma_cross = 0.1
[v2x]
penetration_rate = 0.5
""")
    path = tmp_path / "sweep.toml"
    path.write_text("""
[sweep]
name = "pen"
base = "base.toml"
seeds = [1]
[sweep.grid]
"v2x.penetration_rate" = [0.5, 1.0]
"scenario.control" = ["tlr", "vsr"]
""")
    out = tmp_path / "out"
    assert run_sweep(path, out, workers=2, progress=False).computed == 4
    zones = pd.read_parquet(out / "zones.parquet")
    assert set(zones["zone"]) == {"A", "C", "all"}
    v2v = pd.read_parquet(out / "v2v.parquet")
    links = (v2v["degree"] * v2v["vehicle_steps"]).groupby([v2v["v2x.penetration_rate"], v2v["scenario.control"]]).sum()
    for ctl in ("tlr", "vsr"):  # nested equipped sets on the same traffic: every link at 0.5 is one at 1.0
        assert links[(0.5, ctl)] <= links[(1.0, ctl)]
    html = (out / "report.html").read_text()
    assert "gain_zone.png" in html and "v2v_degree.png" in html and "TLR against VSR" in html
    assert (out / "figures" / "gain_zone.png").is_file() and (out / "figures" / "v2v_degree.png").is_file()


def test_a_level_may_run_with_some_grid_values_only(tmp_path):
    factors = FACTORS + 'wide = [{label = "w", set = {"lc.eta_threshold" = 0.9}, only = {"lc.detection_probability" = [0.95]}}]\n'
    path = write(tmp_path, factors=factors, grid='[sweep.grid]\n"lc.detection_probability" = [0.9, 0.95]')
    _, runs = expand_runs(load_sweep(path))
    wide = [r.run_id for r in runs if r.variant.factor == "wide"]
    assert wide == ["detection_probability=0.95,wide=w,seed=1", "detection_probability=0.95,wide=w,seed=2"]
    assert len(runs) == 2 * 4 * 2 + 2
    for bad, field in (('{"lc.eta_threshold" = [0.5]}', "sweep.factors.wide[0].only.lc.eta_threshold"),
                       ('{"lc.detection_probability" = [0.5]}', "sweep.factors.wide[0].only.lc.detection_probability")):
        path.write_text(path.read_text().replace('only = {"lc.detection_probability" = [0.95]}', f"only = {bad}"))
        with pytest.raises(InputError) as err:
            expand_runs(load_sweep(path))
        assert err.value.field == field
        path = write(tmp_path, factors=factors, grid='[sweep.grid]\n"lc.detection_probability" = [0.9, 0.95]')
