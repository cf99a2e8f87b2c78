"""Every numeric config key has a physical range (experiments/ranges.py), every shipped config lies inside,
and a run whose estimates turn non-finite publishes nothing."""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path

import numpy as np
import pytest

from couplers.errors import InputError, read_toml
from experiments import configdoc, ranges
from experiments.config import OPTIONAL_SECTIONS, SECTIONS, config_from_dict, load_config
from experiments.studies import is_study
from experiments.studies import ranges as study_ranges

PROJECT = Path(__file__).resolve().parents[2]


def _numeric(annotation) -> bool:
    if annotation in (int, float):
        return True
    if typing.get_origin(annotation) in (tuple, typing.Union, types.UnionType):
        return any(_numeric(a) for a in typing.get_args(annotation) if a is not Ellipsis)
    return False


def numeric_fields(sections: dict[str, type]) -> list[tuple[str, object, object]]:
    """(dotted key, annotation, default) of every int/float field of every table, nested tables
    (``[[perception.sensors]]``) included."""
    out = []

    def walk(cls, prefix):
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            a = hints[f.name]
            args = typing.get_args(a)
            if typing.get_origin(a) is tuple and args and dataclasses.is_dataclass(args[0]):
                walk(args[0], f"{prefix}.{f.name}")
            elif _numeric(a):
                default = f.default if f.default is not dataclasses.MISSING else (
                    f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
                out.append((f"{prefix}.{f.name}", a, default))

    for name, cls in sections.items():
        walk(cls, name)
    return out


def test_every_numeric_field_of_every_table_has_a_range():
    fields = numeric_fields({**SECTIONS, **OPTIONAL_SECTIONS})
    missing = [k for k, _, _ in fields if k not in ranges.RANGES]
    assert missing == [], f"numeric config keys without a range in experiments/ranges.py: {missing}"
    stale = sorted(set(ranges.RANGES) - {k for k, _, _ in fields})
    assert stale == [], f"ranges of keys the loader does not have: {stale}"
    assert len(fields) == len(ranges.RANGES) >= 130


def test_a_new_numeric_field_without_a_range_is_caught(monkeypatch):
    @dataclasses.dataclass(frozen=True)
    class Motion(SECTIONS["motion"]):
        jerk_sigma: float = 1.0

    monkeypatch.setitem(SECTIONS, "motion", Motion)
    assert "motion.jerk_sigma" in [k for k, _, _ in numeric_fields(SECTIONS)]
    assert "motion.jerk_sigma" not in ranges.RANGES
    monkeypatch.setitem(configdoc.KEY_DOCS["motion"], "jerk_sigma", ("m/s^3", "a new key"))
    assert "motion.jerk_sigma" in configdoc.undocumented()  # and so the generated page cannot be rendered


def test_every_default_lies_in_its_range_and_units_match_the_page():
    for key, _, default in numeric_fields({**SECTIONS, **OPTIONAL_SECTIONS}):
        r = ranges.RANGES[key]
        values = default if isinstance(default, tuple) else (default,)
        for v in values:
            if v is None or isinstance(v, str):
                continue
            assert r.contains(v), (key, v, r)
        table, name = key.rsplit(".", 1)
        assert configdoc.KEY_DOCS[table][name][0] == r.unit, key
        assert r.why and r.low <= r.high and not math.isnan(r.low)
        assert not math.isinf(r.high), f"{key}: an infinite bound accepts everything; use inf_ok"


def test_seeds_durations_and_counts_are_capped():
    R = ranges.RANGES
    assert (R["run.seed"].low, R["run.seed"].high) == (0, 2**31 - 1)
    assert R["run.duration_s"].high == 7 * 86400
    assert R["pf.vehicle_particles"].high <= 10**5 and R["perception.sensors.clutter_per_scan"].high <= 1000
    assert all(r.high <= 1e3 for k, r in R.items() if r.unit == "m" and "sigma" in k)
    assert {k for k, r in R.items() if r.inf_ok} == {"single_road.v2f_range_m", "single_road.v2v_range_m",
                                                      "crossroad.v2f_range_m", "crossroad.v2v_range_m",
                                                      "sensors.v2f_range_m", "sensors.v2v_range_m",
                                                      "lc.sensing_range_m"}


def _shipped_run_configs() -> list[Path]:
    return [p for p in sorted((PROJECT / "experiments").glob("*.toml")) if not is_study(read_toml(p))]


def test_every_shipped_config_loads_inside_the_ranges():
    files = _shipped_run_configs()
    assert len(files) >= 12
    for path in files:
        cfg = load_config(path)
        for name in [*SECTIONS, *OPTIONAL_SECTIONS]:
            obj = getattr(cfg, name)
            if obj is not None:
                ranges.check_ranges_of(obj, name, path)  # the resolved (derived) values too


@pytest.mark.parametrize("dotted,value,words", [
    ("motion.sigma_along", 1e308, "motion.sigma_along: 1e+308 m/s^2 is outside [0, 50] m/s^2 (5 g"),
    ("motion.sigma_cross", float("inf"), "motion.sigma_cross: must be finite"),
    ("sensors.v2f_sigma_p", -1.0, "sensors.v2f_sigma_p: -1 m is outside [0, 1000] m: must be >= 0"),
    ("lc.bp_iterations", 10**20, "lc.bp_iterations: 100000000000000000000 is outside [0, 100000] ("),
    ("pf.feature_particles", 0, "pf.feature_particles: 0 is outside [1, 100000]: must be >= 1"),
    ("icp.pedestrian_sigma_par", 0.0, "icp.pedestrian_sigma_par: 0 m/s is outside (0, 100] m/s: must be positive"),
    ("run.seed", 2**32, "run.seed: 4294967296 is outside [0, 2147483647]"),
    ("gnss_error.nlos_rate_per_min", [0.25, 1e9], "gnss_error.nlos_rate_per_min[1]: 1e+09 1/min is outside"),
    ("v2x.rounds_per_step", 10**9, "v2x.rounds_per_step: 1000000000 is outside [1, 1000000]"),
])
def test_a_value_outside_its_range_is_one_line_naming_file_field_value_and_range(tmp_path, dotted, value, words):
    sec, key = dotted.split(".")
    data = {"run": {"name": "x"}, sec: {key: value}} if sec != "run" else {"run": {"name": "x", key: value}}
    with pytest.raises(InputError) as exc:
        config_from_dict(data, tmp_path / "exp.toml")
    line = exc.value.describe()
    assert line.startswith(str(tmp_path / "exp.toml")) and "\n" not in line
    assert words in line, line


def test_infinity_only_where_it_means_always_in_range(tmp_path):
    cfg = config_from_dict({"run": {"name": "x"}, "scenario": {"kind": "single_road"},
                            "single_road": {"v2v_range_m": float("inf")}}, tmp_path / "c.toml")
    assert math.isinf(cfg.single_road.v2v_range_m)
    with pytest.raises(InputError, match="perception.sensors.0..range_m"):
        config_from_dict({"run": {"name": "x"}, "perception": {"sensors": [{"range_m": float("inf")}]}},
                         tmp_path / "c.toml")


def test_overrides_go_through_the_ranges(tmp_path):
    base = {"run": {"name": "x"}, "scenario": {"kind": "single_road"}}
    with pytest.raises(InputError, match="run.duration_s: 1e\\+09 s is outside"):
        config_from_dict(base, tmp_path / "c.toml", {"run.duration_s": 1e9})
    assert config_from_dict(base, tmp_path / "c.toml", {"run.duration_s": 60.0}).run.duration_s == 60.0


def _nan_after(monkeypatch, t_bad: float):
    """Make every estimator's mean NaN for one vehicle from step time ``t_bad`` on."""
    from experiments import pipeline

    real = pipeline.step_result

    def step_result(est, known, blind, association):
        res = real(est, known, blind, association)
        if blind.t >= t_bad and res.estimate.mean.shape[0]:
            res.estimate.mean[-1, 0] = np.nan
        return res

    monkeypatch.setattr(pipeline, "step_result", step_result)


def test_a_run_with_non_finite_estimates_publishes_nothing(tmp_path, monkeypatch, capsys):
    from experiments.cli import main

    _nan_after(monkeypatch, 3.0)
    out = tmp_path / "run"
    rc = main(["run", str(PROJECT / "experiments" / "single_road.toml"), "--out", str(out), "--duration", "8",
               "--methods", "gnss", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("coloc: error: "), err
    assert "single_road.toml" in err and "method gnss" in err and "non-finite estimate mean at step t = 3 s" in err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_a_sweep_run_with_non_finite_estimates_fails_instead_of_writing_rows(tmp_path, monkeypatch):
    from experiments.sweep.run import execute_run

    _nan_after(monkeypatch, 2.0)
    cfg = load_config(PROJECT / "experiments" / "single_road.toml",
                      {"run.duration_s": 6.0, "run.methods": ["gnss"]})
    res = execute_run(cfg, str(tmp_path / "r"), 10.0)
    assert res["status"] == "error" and "non-finite estimate" in res["error"], res
    assert not (tmp_path / "r").exists()


def _has_number(v) -> bool:
    if isinstance(v, (list, tuple)):
        return any(_has_number(x) for x in v)
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _study_numeric_keys() -> dict[str, list[tuple[str, object]]]:
    """study kind -> (dotted key, default) of every number its config accepts."""
    from coloc.methods.rsu_bp import RsuBpParams
    from couplers.frohle_scenario import FrohleScenarioParams
    from experiments.studies import fg_topology, rsu_bp, sme

    out = {"rsu_bp": [(k, d) for k, _, d in numeric_fields({
        "study": rsu_bp.StudySection, "study.scenario": FrohleScenarioParams, "study.filter": RsuBpParams,
        "study.sweep": rsu_bp.SweepSection})]}
    for name, mod in (("sme", sme), ("fg_topology", fg_topology)):
        out[name] = [(f"{t}.{k}", key.default) for t, keys in mod.SPEC.items() for k, key in keys.items()
                     if key.kind in ("int", "float", "ints", "floats") or _has_number(key.default)]
    return out


def test_every_numeric_key_of_every_study_has_a_range_and_its_default_is_inside():
    keys = _study_numeric_keys()
    assert set(keys) == set(study_ranges.STUDY_RANGES)
    for kind, pairs in keys.items():
        table = study_ranges.STUDY_RANGES[kind]
        missing = [k for k, _ in pairs if k not in table]
        assert missing == [], f"{kind}: numeric keys without a range: {missing}"
        assert sorted(table) == sorted(k for k, _ in pairs), kind
        for k, default in pairs:
            ranges.check_nested(default, k, Path(f"{kind}.toml"), table)


def test_shipped_study_configs_load_and_a_study_value_out_of_range_is_refused(tmp_path):
    from experiments.studies import fg_topology, rsu_bp, sme
    from experiments.studies.study_config import resolve

    rsu = read_toml(PROJECT / "experiments" / "rsu_bp.toml")
    rsu_bp.load_study(rsu, PROJECT / "experiments" / "rsu_bp.toml")
    for name, mod in (("sme", sme), ("fg_topology", fg_topology)):
        resolve(read_toml(PROJECT / "experiments" / f"{name}.toml"), PROJECT / "experiments" / f"{name}.toml",
                mod.SPEC, study_ranges.STUDY_RANGES[name])
    bad = {**rsu, "study": {**rsu["study"], "filter": {**rsu["study"]["filter"], "n_particles": 10**12}}}
    with pytest.raises(InputError, match=r"study.filter.n_particles: 1000000000000 is outside \[2, 100000\]"):
        rsu_bp.load_study(bad, tmp_path / "r.toml")
    data = read_toml(PROJECT / "experiments" / "sme.toml")
    data["scenario"]["sensor_poses"][1][0] = float("1e300")
    with pytest.raises(InputError, match=r"scenario.sensor_poses\[1\]\[0\]: 1e\+300 m, m, deg is outside"):
        resolve(data, tmp_path / "s.toml", sme.SPEC, study_ranges.STUDY_RANGES["sme"])


def test_every_numeric_command_line_option_has_a_range():
    """Options typed int or float, except --seed (seed_problem) and run --duration (run.duration_s)."""
    import argparse

    from experiments.cli import build_parser

    found = set()

    def walk(parser):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    walk(sub)
            elif action.type in (int, float) and action.dest != "seed":
                func = parser.get_default("func")
                if not (func.__name__ == "cmd_run" and action.dest == "duration"):
                    found.add((func.__name__, action.dest))

    walk(build_parser())
    assert found and found == set(ranges.OPTION_RANGES), found ^ set(ranges.OPTION_RANGES)
